"""Contacts in the object frame, where every contact cost compares them with the model.

Under a pose T_world_object = (R, t) a contact (world point x̃, finger normal ñ) lies at
p = Rᵀ (x̃ - t) and measures the outward surface normal ν = -Rᵀ ñ.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from contactpose.geometry.kernels import _rt_apply, _sub, _t


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
    return _rt_apply(R, _sub(_t(point), _t(t)))


@njit(cache=True)
def object_normal(R, finger_normal):
    """ν = -Rᵀ ñ of one contact inside compiled kernels: R (3, 3), finger_normal (3,) -> 3-tuple."""
    f = _rt_apply(R, _t(finger_normal))
    return (-f[0], -f[1], -f[2])
