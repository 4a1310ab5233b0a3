"""The paper's contact cost: eq. (7), corrected (research/errata.md, erratum 3).

For contact i (world point x̃_i, finger normal ñ_i) on facet k (outward normal n_k, offset d_k)
under the pose (R, t):

    ℒ(R, t) = Σ_i |Rᵀ ñ_i + n_k|² + (ñ_iᵀ t + d̃_i + d_k)²,   d̃_i = -ñ_iᵀ x̃_i,

unweighted as published. Its offset term compares plane offsets through the measured normal,
so it depends on where the object frame's origin is; the default method's point-to-plane
offset (costs.facet) does not. The first term equals |r_n|² of costs.facet (a rotation keeps
norms), so the batched form takes r_n from there.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def eq7_residuals(x, obj_normals, obj_offsets, points, finger_normals):
    """Residual vector of eq. (7) for x = (rotation vector, t). -> (4n,)"""
    R = Rotation.from_rotvec(x[:3]).as_matrix()
    normal = finger_normals @ R + obj_normals  # rows: Rᵀ ñ_i + n_k
    offset = finger_normals @ x[3:] - np.einsum("ni,ni->n", finger_normals, points) + obj_offsets
    return np.concatenate([normal.ravel(), offset])


def paper_offset_residuals(t, points, finger_normals, obj_offsets):
    """r_p = ñ_iᵀ t - ñ_iᵀ x̃_i + d_k (eq. 7 with erratum 3). Depends on the origin.

    t : (H, 3), points : (n, 3), finger_normals : (n, 3), obj_offsets : (H, n)  ->  (H, n)
    """
    d_meas = -np.einsum("ni,ni->n", finger_normals, points)
    return t @ finger_normals.T + d_meas[None] + obj_offsets


def paper_cost(r_normal, r_paper_offset):
    """ℒ of eq. (7): Σ_i |Rᵀñ_i + n_k|² + r_p², unweighted as in the paper.

    r_normal : (H, n, 3), r_paper_offset : (H, n)  ->  (H,)
    """
    return np.einsum("hni,hni->h", r_normal, r_normal) + np.sum(r_paper_offset**2, axis=1)
