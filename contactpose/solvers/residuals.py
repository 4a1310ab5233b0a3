"""Contact residuals: the one definition shared by ranking, solvers and sampling.

For contact i (world point x̃_i, finger normal ñ_i) assigned to facet k
(unit outward normal n_k, offset d_k, triangle V_k) under the pose
``T_world_object = (R, t)``:

* normal residual (eq. 7, first term):     r_n = R n_k + ñ_i             (3,)
  Its norm is 2 sin(θ/2) for the angle θ between -ñ_i and R n_k.
* origin-invariant offset (errata.md):     r_o = n_kᵀ Rᵀ (x̃_i - t) + d_k
  The signed distance of the contact from facet k's plane, in length units.
* the paper's offset (eq. 7 corrected):    r_p = ñ_iᵀ t + d̃_i + d_k,  d̃_i = -ñ_iᵀ x̃_i
* lateral residual:                        r_l = sqrt(dist(p_i, V_k)² - r_o²)
  How far the contact lies outside its facet *triangle*, in the plane,
  with p_i = Rᵀ (x̃_i - t) the contact in the object frame.

All functions are batched over H hypotheses with n contacts each.
:func:`contact_residuals` computes r_n, r_o and r_l together in one compiled pass, for
ranking thousands of hypotheses; the per-term functions are its readable reference (a test
holds them equal).
"""

from __future__ import annotations

import numba
import numpy as np

from contactpose.geometry.kernels import (  # 3-tuple kernels
    _add,
    _dot,
    _point_triangle_d2,
    _r_apply,
    _rt_apply,
    _sub,
    _t,
    point_triangle_distance,
)
from contactpose.model.patches import nearest_members


def to_object_frame(R, t, points):
    """Map world points into the object frame: p = Rᵀ (x - t).

    R : (H, 3, 3), t : (H, 3), points : (n, 3)  ->  (H, n, 3)
    """
    return np.einsum("hji,hnj->hni", R, points[None, :, :] - t[:, None, :])


def contact_residuals(R, t, obj_normals, obj_offsets, triangles, points, finger_normals):
    """r_n, r_o and r_l of every contact under every hypothesis, in one compiled pass.

    R : (H, 3, 3), t : (H, 3); obj_normals : (H, n, 3), obj_offsets : (H, n), triangles :
    (H, n, 3, 3) of the hypothesised facets; points, finger_normals : (n, 3)
    ->  r_n (H, n, 3), r_o (H, n), r_l (H, n)
    """
    h, n = np.shape(obj_offsets)
    r_n, r_o, r_l = np.empty((h, n, 3)), np.empty((h, n)), np.empty((h, n))
    _residuals(*(np.ascontiguousarray(a, dtype=np.float64) for a in
                 (R, t, obj_normals, obj_offsets, triangles, points, finger_normals)), r_n, r_o, r_l)
    return r_n, r_o, r_l


@numba.njit(cache=True)
def _residuals(R, t, normals, offsets, triangles, points, finger_normals, r_n, r_o, r_l):
    for h in range(R.shape[0]):
        for i in range(points.shape[0]):
            p = _rt_apply(R[h], _sub(_t(points[i]), _t(t[h])))  # the contact in the object frame
            nrm = _t(normals[h, i])
            rn = _add(_r_apply(R[h], nrm), _t(finger_normals[i]))
            r_n[h, i, 0], r_n[h, i, 1], r_n[h, i, 2] = rn
            r_o[h, i] = _dot(nrm, p) + offsets[h, i]
            tri = triangles[h, i]
            dist2 = _point_triangle_d2(p, _t(tri[0]), _t(tri[1]), _t(tri[2]))
            r_l[h, i] = np.sqrt(max(dist2 - r_o[h, i] ** 2, 0.0))


def normal_residuals(R, obj_normals, finger_normals):
    """r_n = R n_k + ñ_i.

    R : (H, 3, 3), obj_normals : (H, n, 3), finger_normals : (n, 3)  ->  (H, n, 3)
    """
    return np.einsum("hij,hnj->hni", R, obj_normals) + finger_normals[None]


def offset_residuals(p_obj, obj_normals, obj_offsets):
    """r_o = n_kᵀ p_i + d_k, the signed point-to-plane distance (origin-invariant).

    p_obj : (H, n, 3) contacts in the object frame, obj_normals : (H, n, 3),
    obj_offsets : (H, n)  ->  (H, n)
    """
    return np.einsum("hni,hni->hn", obj_normals, p_obj) + obj_offsets


def paper_offset_residuals(t, points, finger_normals, obj_offsets):
    """r_p = ñ_iᵀ t - ñ_iᵀ x̃_i + d_k (eq. 7 with erratum 3). Depends on the origin.

    t : (H, 3), points : (n, 3), finger_normals : (n, 3), obj_offsets : (H, n)  ->  (H, n)
    """
    d_meas = -np.einsum("ni,ni->n", finger_normals, points)
    return t @ finger_normals.T + d_meas[None] + obj_offsets


def lateral_residuals(p_obj, triangles, r_offset):
    """r_l = sqrt(max(dist(p, triangle)² - r_o², 0)): distance outside the triangle, in-plane.

    p_obj : (H, n, 3), triangles : (H, n, 3, 3), r_offset : (H, n)  ->  (H, n)
    """
    h, n = r_offset.shape
    dist = point_triangle_distance(p_obj.reshape(-1, 3), triangles.reshape(-1, 3, 3))
    return np.sqrt(np.maximum(dist.reshape(h, n) ** 2 - r_offset**2, 0.0))


def whitened_cost(r_normal, r_offset, r_lateral, sigma_normal, sigma_position):
    """χ² of the default method: Σ_i |r_n|²/σ_n² + (r_o² + r_l²)/σ_x².

    r_normal : (H, n, 3), r_offset, r_lateral : (H, n)  ->  (H,)
    sigma_normal in radians, sigma_position in length units (per-axis standard deviations).
    """
    normal = np.einsum("hni,hni->h", r_normal, r_normal) / sigma_normal**2
    position = (np.sum(r_offset**2, axis=1) + np.sum(r_lateral**2, axis=1)) / sigma_position**2
    return normal + position


def paper_cost(r_normal, r_paper_offset):
    """ℒ of eq. (7): Σ_i |Rᵀñ_i + n_k|² + r_p², unweighted as in the paper.

    r_normal : (H, n, 3), r_paper_offset : (H, n)  ->  (H,)
    """
    return np.einsum("hni,hni->h", r_normal, r_normal) + np.sum(r_paper_offset**2, axis=1)


def fitting_members(model, contacts, tuples, R, t, tolerance):
    """The member facet of each hypothesised patch that fits its contact best under the pose
    (R (H, 3, 3), t (H, 3)): least whitened distance and normal residual
    (model.patches.nearest_members): the ranking's and the factor graph's choice of member.
    tuples : (H, n) patch indices  ->  (H, n) facets"""
    normals = -np.einsum("hji,nj->hni", R, contacts.finger_normals)
    weight = (tolerance.position_noise / tolerance.normal_noise) ** 2
    return nearest_members(model.member_groups, model.triangles, tuples, to_object_frame(R, t, contacts.points),
                           (model.planes.normals, normals, weight), (model.centroids, model.facet_radii))
