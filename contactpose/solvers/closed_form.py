"""Closed-form pose of every hypothesis at once (research/design.md, "Poses").

The rotation enters only the normal term of the cost: R solves Wahba's problem,
aligning the facet normals n_k with the measured object normals -ñ_i (SVD with
a determinant fix). Given R, the offset term is linear in t: linear least squares.

* ``cost="invariant"`` (default method): rows (R n_k)ᵀ t = (R n_k)ᵀ x̃_i + d_k,
  the origin-invariant point-to-plane residual.
* ``cost="paper"``: rows ñ_iᵀ t = ñ_iᵀ x̃_i - d_k, eq. (7) corrected. Here R and t
  decouple exactly, so this is the exact minimum of eq. (7).

Directions the normals do not constrain are reported, and t is taken nearest a
reference translation t0 along them. With a vision prior (:func:`prior_closed_form`) the
prior's axes and translation join the observations, and the pose is always unique.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.types import PoseFit


def fit_poses(obj_normals, obj_offsets, points, finger_normals, *, cost="invariant",
              angle_tol, t0=None, centroids=None):
    """Closed-form poses of H hypotheses.

    obj_normals : (H, n, 3), obj_offsets : (H, n) of the hypothesised facets;
    points, finger_normals : (n, 3) measurements; cost : "invariant" | "paper";
    angle_tol : radians, normals closer than this to a common plane (or line) leave
    a direction free; t0 : (H, 3) reference translation (default: the one that puts
    the facet centroids' mean on the contacts' mean); centroids : (H, n, 3), needed
    without t0, and used to fix a free rotation (see :func:`free_angles`).
    """
    if cost not in ("invariant", "paper"):
        raise ValueError(f"cost must be 'invariant' or 'paper', got {cost!r}")
    obj_normals = _c(obj_normals)
    n = obj_normals.shape[1]
    min_eig = n * np.sin(angle_tol) ** 2
    R = wahba(obj_normals, -finger_normals)
    lam, V = _spread(obj_normals)
    free_rotation = lam[:, 1] <= min_eig
    if centroids is not None and free_rotation.any():
        axis = V[free_rotation, :, 2]
        turn = free_angles(axis, R[free_rotation], centroids[free_rotation], points)
        axis = np.einsum("fij,fj->fi", R[free_rotation], axis)
        R[free_rotation] = Rotation.from_rotvec(axis * turn[:, None]).as_matrix() @ R[free_rotation]
    world = R @ V  # columns: world eigenvectors
    if t0 is None:
        t0 = points.sum(axis=0) / n - (R @ centroids.sum(axis=1)[..., None])[..., 0] / n
    t = np.empty((len(R), 3))
    _translations(R, world, lam, obj_normals, _c(obj_offsets),
                  _c(points), _c(finger_normals), _c(t0 if np.shape(t0) == t.shape else np.broadcast_to(t0, t.shape)),
                  cost == "paper", min_eig, t)
    rows = world.transpose(0, 2, 1)
    return PoseFit(R, t, rows, lam <= min_eig, rows[:, 2], free_rotation)


def _spread(obj_normals):
    """Eigenvalues (ascending) and eigenvectors of Σ n nᵀ in the object frame, the
    (un)determined directions of normals (H, n, 3)."""
    return np.linalg.eigh(obj_normals.transpose(0, 2, 1) @ obj_normals)


def free_directions(R, obj_normals, angle_tol):
    """What normals leave free, as fit_poses reports it, for poses R (H, 3, 3) whose contacts
    hold object-frame normals (H, n, 3) (zero rows: contacts that hold none): (free_translation
    (H, 3, 3) world rows, free_translation_mask (H, 3), free_rotation (H, 3) world axis,
    free_rotation_mask (H,)), a direction free where Σ n nᵀ's eigenvalue is at most
    (contacts) sin²(angle_tol)."""
    lam, V = _spread(_c(obj_normals))
    min_eig = (np.linalg.norm(obj_normals, axis=2) > 0).sum(axis=1)[:, None] * np.sin(angle_tol) ** 2
    rows = (R @ V).transpose(0, 2, 1)
    return rows, lam <= min_eig, rows[:, 2], lam[:, 1] <= min_eig[:, 0]


def _c(a):
    return np.ascontiguousarray(a, dtype=np.float64)


def free_angles(axis_obj, R, centroids, points):
    """Angle to turn R about the free axis R·axis_obj, picked from the geometry, not the frame.

    When the normals fix only one axis, Wahba's rotation about it is arbitrary and depends
    on the world frame. θ minimises Σ_i |Rot(axis, θ) R (c_i - c̄) - (x̃_i - x̄)|²: it turns
    the facet centroids' spread onto the contacts'. Where the centroids lie on the axis
    (the centres of two opposite faces, say), a fixed object direction off the axis is
    turned onto the first contact that lies off it instead, so the choice stays the same
    under any rigid motion of the contacts.
    axis_obj : (F, 3) object-frame unit axes, R : (F, 3, 3), centroids : (F, n, 3),
    points : (n, 3)  ->  (F,) radians
    """
    axis = np.einsum("fij,fj->fi", R, axis_obj)
    u = np.einsum("fij,fnj->fni", R, centroids - centroids.mean(axis=1, keepdims=True))
    v = np.broadcast_to(points - points.mean(axis=0), u.shape)
    theta, fixed = _turn(axis, u, v)
    if not fixed.all():
        loose = ~fixed
        ref = np.eye(3)[np.argmin(np.abs(axis_obj[loose]), axis=1)]  # least aligned object axis
        ref -= np.einsum("fi,fi->f", ref, axis_obj[loose])[:, None] * axis_obj[loose]
        off = v[loose] - np.einsum("fni,fi->fn", v[loose], axis[loose])[..., None] * axis[loose][:, None]
        size = np.linalg.norm(off, axis=2)
        first = np.argmax(size > 1e-6 * size.max(axis=1, keepdims=True), axis=1)
        theta[loose] = _turn(axis[loose], np.einsum("fij,fj->fi", R[loose], ref)[:, None],
                             off[np.arange(len(first)), first][:, None])[0]
    return theta


def _turn(axis, u, v):
    """θ maximising Σ_i v_i·Rot(axis, θ) u_i: atan2(Σ axis·(u_i × v_i), Σ u_i⊥·v_i).
    axis : (F, 3), u, v : (F, k, 3) -> (θ (F,), whether u and v fix it (F,) bool; θ = 0 if not)."""
    sin = np.einsum("fi,fni->f", axis, np.cross(u, v))
    cos = np.einsum("fni,fni->f", u, v) - np.einsum("fni,fi,fnj,fj->f", u, axis, v, axis)
    fixed = np.hypot(sin, cos) > 1e-9 * np.linalg.norm(u, axis=2).sum(axis=1) * np.linalg.norm(v, axis=2).sum(axis=1)
    return np.where(fixed, np.arctan2(sin, cos), 0.0), fixed


def wahba(obj_vectors, world_vectors):
    """Rotations R minimising Σ_i |R a_i - b_i|² (Wahba's problem, SVD with det fix).

    obj_vectors a : (H, n, 3); world_vectors b : (n, 3)  ->  (H, 3, 3)
    """
    U, _, Vt = np.linalg.svd(world_vectors.T @ obj_vectors)  # B = Σ_i b_i a_iᵀ
    R = U @ Vt
    flip = np.linalg.det(R) < 0
    if flip.any():
        U[flip, :, 2] *= -1.0
        R[flip] = U[flip] @ Vt[flip]
    return R


@numba.njit(cache=True)
def _translations(R, world, lam, normals, offsets, points, finger_normals, t0, paper, min_eig, t):
    """argmin_t |A t - b|², moving from t0 only along eigenvectors of AᵀA whose eigenvalue
    exceeds min_eig. Invariant cost: rows (R n_k)ᵀ t = (R n_k)ᵀ x̃_i + d_k (AᵀA = R ΣnnᵀRᵀ,
    eigenvectors ``world``); paper: ñ_iᵀ t = ñ_iᵀ x̃_i - d_k."""
    lam_p, V_p = np.linalg.eigh(finger_normals.T @ finger_normals)
    for h in range(R.shape[0]):
        if paper:
            A, b = finger_normals, np.sum(finger_normals * points, axis=1) - offsets[h]
            E, w = V_p, lam_p
        else:
            A = np.ascontiguousarray(normals[h] @ R[h].T)  # rows (R n_k)ᵀ
            b = np.sum(A * points, axis=1) + offsets[h]
            E, w = world[h], lam[h]
        resid = A.T @ (b - A @ t0[h])
        t[h] = t0[h]
        for j in range(3):
            if w[j] > min_eig:
                coef = (E[0, j] * resid[0] + E[1, j] * resid[1] + E[2, j] * resid[2]) / w[j]
                for r in range(3):
                    t[h, r] += E[r, j] * coef


def prior_closed_form(obj_normals, obj_offsets, points, finger_normals, tolerance, prior):
    """Closed-form poses of H hypotheses with the vision prior as extra observations.

    Rotation: Wahba on the whitened normals plus the prior's axes, Σ_i |R n_k + ñ_i|²/σ_n²
    + |R - R_p|_F² / (2 σ_r²) (σ_r² the mean rotation variance of the prior). Translation:
    exact least squares of Σ_i r_o²/σ_x² + (t - t_p)ᵀ Σ_t⁻¹ (t - t_p) given R, with the prior's
    translation covariance rotated into the world. Always a unique pose (the prior fills any
    direction the normals leave free), so it serves as LM start and for screening.

    obj_normals : (H, n, 3), obj_offsets : (H, n), points, finger_normals : (n, 3)
    -> R (H, 3, 3), t (H, 3)
    """
    h, n, _ = obj_normals.shape
    cov = prior.covariance_matrix()
    Rp, tp = prior.pose[:3, :3], prior.pose[:3, 3]
    w_r = 1.0 / np.sqrt(2.0 * np.trace(cov[:3, :3]) / 3.0)
    w_n = 1.0 / tolerance.normal_noise
    obj = np.concatenate([obj_normals * w_n, np.broadcast_to(np.eye(3) * w_r, (h, 3, 3))], axis=1)
    world = np.concatenate([-finger_normals * w_n, Rp.T * w_r], axis=0)  # rows R_p e_j
    R = wahba(obj, world)
    A = np.einsum("hij,hnj->hni", R, obj_normals)  # rows (R n_k)ᵀ
    b = np.einsum("hni,ni->hn", A, points) + obj_offsets
    info_t = np.linalg.inv(Rp @ cov[3:, 3:] @ Rp.T)
    lhs = np.einsum("hni,hnj->hij", A, A) / tolerance.position_noise**2 + info_t
    rhs = np.einsum("hni,hn->hi", A, b) / tolerance.position_noise**2 + info_t @ tp
    return R, np.linalg.solve(lhs, rhs[..., None])[..., 0]
