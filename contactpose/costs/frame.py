"""Contacts in the object frame, where every contact cost compares them with the model.

Under a pose T_world_object = (R, t) a contact (world point x̃, finger normal ñ) lies at
p = Rᵀ (x̃ - t) and measures the outward surface normal ν = -Rᵀ ñ (paper eq. (6): the measured
plane moved into the object frame). The compiled forms write the products out, in the order
geometry.kernels' 3-tuple helpers take them.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def object_frame(R, t, points, finger_normals=None):
    """The contacts under one pose (R (3, 3), t (3,)) or many (R (H, 3, 3), t (H, 3)):
    points p (n, 3) or (H, n, 3), and with ``finger_normals`` (n, 3) also the outward normals
    ν, -> (p, ν)."""
    if np.ndim(R) == 2:
        p = (points - t) @ R
        nu = None if finger_normals is None else -(finger_normals @ R)
    else:
        p = np.einsum("hji,hnj->hni", R, points[None, :, :] - t[:, None, :])
        nu = None if finger_normals is None else -np.einsum("hji,nj->hni", R, finger_normals)
    return p if finger_normals is None else (p, nu)


@njit(cache=True)
def object_point(R, t, point):
    """p = Rᵀ (x̃ - t) of one contact inside compiled kernels: R (3, 3), t (3,), point (3,) -> 3-tuple."""
    d0, d1, d2 = float(point[0]) - float(t[0]), float(point[1]) - float(t[1]), float(point[2]) - float(t[2])
    return (R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2,
            R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2,
            R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2)


@njit(cache=True)
def object_normal(R, finger_normal):
    """ν = -Rᵀ ñ of one contact inside compiled kernels: R (3, 3), finger_normal (3,) -> 3-tuple."""
    f0, f1, f2 = float(finger_normal[0]), float(finger_normal[1]), float(finger_normal[2])
    return (-(R[0, 0] * f0 + R[1, 0] * f1 + R[2, 0] * f2),
            -(R[0, 1] * f0 + R[1, 1] * f1 + R[2, 1] * f2),
            -(R[0, 2] * f0 + R[1, 2] * f1 + R[2, 2] * f2))
