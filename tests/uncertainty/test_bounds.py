"""Cramér–Rao bounds (uncertainty.bounds): the information against finite differences of the
measurement model, and the geometric answers of a sphere."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from contactpose.uncertainty.bounds import local_quadric, pose_information, tangent_basis

SX, SN = 0.0005, np.radians(1.0)


def contacts(rng, n=4):
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return 0.05 * rng.normal(size=(n, 3)), normals


def surface(x0, nu, T, H, u):
    """The quadric x(u) = x0 + T u + ν ½uᵀHu and its unit normal (on ν's side)."""
    x = x0 + T @ u + nu * (0.5 * u @ H @ u)
    du = T + np.outer(nu, H @ u)             # columns ∂x/∂u_j
    n = np.cross(du[:, 0], du[:, 1])
    n *= np.sign(n @ nu) / np.linalg.norm(n)
    return x, n


def measured(xi, points, normals, tangents, hessians, slides):
    """Object-frame predictions under the right perturbation ξ: each contact's point (3) and
    its normal's tangent components (2), the contact slid by u on its quadric."""
    rot = Rotation.from_rotvec(xi[:3]).as_matrix()
    out = []
    for i, (x0, nu) in enumerate(zip(points, normals)):
        x, n = surface(x0, nu, tangents[i], hessians[i], slides[2 * i:2 * i + 2])
        out += [rot @ x + xi[3:], tangents[i].T @ (rot @ n)]
    return np.concatenate(out)


def numeric_jacobian(f, z, h=1e-7):
    return np.stack([(f(z + h * e) - f(z - h * e)) / (2 * h) for e in np.eye(len(z))], axis=1)


def test_information_with_slides_matches_finite_differences():
    """Location unknown: JᵀWJ of the finite-difference Jacobian over (ξ, slides), with the
    slides marginalised by brute force (inverse of the full information), equals the
    function's Schur complement."""
    rng = np.random.default_rng(3)
    points, normals = contacts(rng)
    tangents = np.stack([tangent_basis(nu) for nu in normals])
    hessians = np.stack([(lambda a: a + a.T)(rng.normal(scale=10.0, size=(2, 2))) for _ in normals])
    f = (lambda z: measured(z[:6], points, normals, tangents, hessians, z[6:]))
    J = numeric_jacobian(f, np.zeros(6 + 2 * len(points)))
    w = np.tile(np.r_[np.full(3, SX ** -2), np.full(2, SN ** -2)], len(points))
    full = J.T @ (w[:, None] * J)
    want = np.linalg.inv(np.linalg.inv(full)[:6, :6])
    got = pose_information(points, normals, SX, SN, hessians=hessians, tangents=tangents)
    assert np.allclose(got, want, rtol=1e-5, atol=1e-6 * np.abs(want).max())


def test_facet_information_matches_finite_differences():
    """Facet known: the offset along the normal and the normal's tangent components."""
    rng = np.random.default_rng(4)
    points, normals = contacts(rng)

    def f(xi):
        rot = Rotation.from_rotvec(xi[:3]).as_matrix()
        return np.concatenate([np.r_[nu @ (rot @ x + xi[3:]), tangent_basis(nu).T @ (rot @ nu)]
                               for x, nu in zip(points, normals)])
    J = numeric_jacobian(f, np.zeros(6))
    w = np.tile(np.r_[SX ** -2, SN ** -2, SN ** -2], len(points))
    want = J.T @ (w[:, None] * J)
    assert np.allclose(pose_information(points, normals, SX, SN), want, rtol=1e-5, atol=1e-6 * np.abs(want).max())


def test_sphere_quadric_and_unobservable_rotation():
    """On a sphere of radius ρ the fitted height has H = -I/ρ, and with the contacts' location
    unknown no rotation about the centre is observable, while the translation is."""
    rho = 0.05
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=rho)
    vertices = np.asarray(mesh.vertices)
    tree = cKDTree(vertices)
    rng = np.random.default_rng(5)
    normals = rng.normal(size=(4, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    fits = [local_quadric(vertices, tree, rho * nu, nu, 0.2 * rho) for nu in normals]
    for _, H in fits:
        assert np.allclose(H, -np.eye(2) / rho, atol=0.03 / rho)
    exact = np.stack([-np.eye(2) / rho] * 4)
    info = pose_information(rho * normals, normals, SX, SN, hessians=exact,
                            tangents=np.stack([T for T, _ in fits]))
    scale = np.abs(info).max()
    assert np.abs(info[:3]).max() < 1e-9 * scale        # rotations about the centre: no information
    assert np.linalg.eigvalsh(info[3:, 3:]).min() > 1e-3 * scale
