"""Random points on triangles and random tilts of unit normals. Every function takes ``rng``."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.errors import ContactPoseError


def barycentric_uniform(rng, count):
    """(u, v), each (count,): weights of edges 1 and 2 of a point uniform in a triangle
    (the unit square folded onto the triangle u + v <= 1)."""
    u, v = rng.random((2, count))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    return u, v


def points_in_triangles(triangles, u, v):
    """Points a + u (b - a) + v (c - a). triangles : (n, 3, 3), u, v : (n,) -> (n, 3)"""
    return triangles[:, 0] + u[:, None] * (triangles[:, 1] - triangles[:, 0]) + v[:, None] * (triangles[:, 2] - triangles[:, 0])


def uniform_in_triangles(triangles, rng):
    """One point uniform inside each triangle. triangles : (n, 3, 3) -> (n, 3)"""
    return points_in_triangles(triangles, *barycentric_uniform(rng, len(triangles)))


def tangent_basis(normals):
    """Two unit vectors orthogonal to each normal. normals : (n, 3) -> (n, 2, 3)"""
    helper = np.where(np.abs(normals[:, [0]]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(normals, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.stack([e1, np.cross(normals, e1)], axis=1)


def bounded_gaussian(rng, n, dim, sigma, bound):
    """n Gaussian vectors of per-axis σ, each redrawn until its norm is within bound."""
    out = rng.normal(0.0, sigma, (n, dim)) if sigma > 0 else np.zeros((n, dim))
    for _ in range(1000):
        bad = np.linalg.norm(out, axis=1) > bound
        if not bad.any():
            return out
        out[bad] = rng.normal(0.0, sigma, (bad.sum(), dim))
    raise ContactPoseError(f"cannot draw noise of sigma {sigma} within bound {bound}")


def perturb_normals(normals, sigma, rng, bound=np.inf):
    """Rotate each unit normal by a tangent-plane Gaussian angle of per-axis σ (radians),
    redrawing any whose angle exceeds ``bound``. normals : (n, 3) -> (n, 3)"""
    angles = bounded_gaussian(rng, len(normals), 2, sigma, bound)
    axis_vec = np.einsum("nk,nkj->nj", angles, tangent_basis(normals))
    return Rotation.from_rotvec(np.cross(normals, axis_vec)).apply(normals)
