"""Cramér–Rao bounds of the pose from contacts: how well any unbiased estimator can do.

A contact measures its point p̃ = R x + t + e (σ_x per axis) and its outward normal ν
(σ_n per tangent axis). In the right perturbation ξ = (ω, v) of T_world_object (rotation
first), in the object frame, the point moves by ω × x + v and the normal by ω × ν. Two
models of what is known about where the contact lies (research/regions.md, "How accurate
can four contacts be?"):

* *facet known*: the contact lies on a known plane; its offset along ν and its normal are
  measured, its slide in the plane is irrelevant: F = Σ j_o j_oᵀ/σ_x² + J_nᵀJ_n/σ_n², with
  j_o = (x × ν, ν) and J_n = Tᵀ[-[ν]×, 0] (T (3, 2) a tangent basis);
* *location unknown*: the contact sits at x(u) on a smooth surface, x(u) = x + T u +
  ν (½ uᵀ H u) to second order, its normal turning by dν/du = -T H; the slides u (2 per
  contact) are nuisance parameters, removed by the Schur complement of F over (ξ, u).
"""

from __future__ import annotations

import numpy as np

from contactpose.geometry.se3 import hat

__all__ = ["local_quadric", "pose_information", "rotation_bound_deg", "tangent_basis"]

#: rotation_bound_deg fits each contact's quadric to the vertices within this share of the diameter.
QUADRIC_RADIUS_FRAC = 0.03


def tangent_basis(normal):
    """(3, 2) orthonormal columns perpendicular to the unit ``normal`` (3,)."""
    return np.linalg.svd(np.eye(3) - np.outer(normal, normal))[0][:, :2]


#: local_quadric fits to at least this many vertices (the nearest, where few lie within the radius).
QUADRIC_POINTS = 12


def local_quadric(vertices, tree, point, normal, radius):
    """The surface near ``point`` as a height over its tangent plane, h(u) = c + bᵀu + ½uᵀHu,
    fitted by least squares to the mesh vertices within ``radius`` (at least the
    QUADRIC_POINTS nearest: large flat facets leave few). vertices : (V, 3); tree : scipy
    cKDTree over them  ->  T (3, 2) tangent basis, H (2, 2)"""
    T = tangent_basis(normal)
    near = tree.query_ball_point(point, radius)
    if len(near) < QUADRIC_POINTS:
        near = tree.query(point, k=min(QUADRIC_POINTS, len(vertices)))[1]
    q = vertices[near] - point
    u, h = q @ T, q @ normal
    A = np.column_stack([np.ones(len(u)), u, 0.5 * u[:, 0] ** 2, u[:, 0] * u[:, 1], 0.5 * u[:, 1] ** 2])
    c = np.linalg.lstsq(A, h, rcond=None)[0]
    return T, np.array([[c[3], c[4]], [c[4], c[5]]])


def pose_information(points, normals, position_noise, normal_noise, hessians=None, tangents=None):
    """Fisher information (6, 6) of the pose ξ (rotation first) from contacts at object-frame
    points (n, 3) with unit outward normals (n, 3); position_noise σ_x (length), normal_noise
    σ_n (radians). hessians : None (facet known), or (n, 2, 2) the surface's H at each contact
    in the bases tangents (n, 3, 2) (location unknown: the slides are marginalised out)."""
    n = len(points)
    slides = 0 if hessians is None else 2 * n
    info = np.zeros((6 + slides, 6 + slides))
    for i, (x, nu) in enumerate(zip(points, normals)):
        T = tangent_basis(nu) if tangents is None else tangents[i]
        J_n = np.zeros((2, 6 + slides))
        J_n[:, :3] = -T.T @ hat(nu)
        if hessians is None:
            j_o = np.concatenate([np.cross(x, nu), nu])
            info[:6, :6] += np.outer(j_o, j_o) / position_noise**2
        else:
            J_p = np.zeros((3, 6 + slides))
            J_p[:, :3], J_p[:, 3:6], J_p[:, 6 + 2 * i:8 + 2 * i] = -hat(x), np.eye(3), T
            J_n[:, 6 + 2 * i:8 + 2 * i] = -hessians[i]
            info += J_p.T @ J_p / position_noise**2
        info += J_n.T @ J_n / normal_noise**2
    if hessians is None:
        return info
    A, B, C = info[:6, :6], info[:6, 6:], info[6:, 6:]
    return A - B @ np.linalg.solve(C, B.T)




def rotation_bound_deg(vertices, tree, diameter, points, normals, position_noise, normal_noise):
    """RMS rotation error (degrees) of an efficient estimator from contacts at object-frame
    points (n, 3) with outward unit normals (n, 3), each contact's location unknown on the
    quadric fitted within QUADRIC_RADIUS_FRAC of the diameter (:func:`local_quadric`;
    vertices (V, 3) and their cKDTree ``tree``); σ_x a length, σ_n radians: √trace of the
    rotation block of the inverse information (:func:`pose_information`)."""
    fits = [local_quadric(vertices, tree, x, nu, QUADRIC_RADIUS_FRAC * diameter) for x, nu in zip(points, normals)]
    info = pose_information(points, normals, position_noise, normal_noise, hessians=np.stack([H for _, H in fits]),
                            tangents=np.stack([T for T, _ in fits]))
    return float(np.degrees(np.sqrt(np.trace(np.linalg.pinv(info)[:3, :3]))))
