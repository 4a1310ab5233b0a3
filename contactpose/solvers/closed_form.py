"""Closed-form pose of every hypothesis at once (NOTES.md, "Structure of the problem").

The rotation enters only the normal term of the cost: R solves Wahba's problem,
aligning the facet normals n_k with the measured object normals -ñ_i (SVD with
a determinant fix). Given R, the offset term is linear in t: linear least squares.

* ``cost="invariant"`` (default method): rows (R n_k)ᵀ t = (R n_k)ᵀ x̃_i + d_k,
  the origin-invariant point-to-plane residual.
* ``cost="paper"``: rows ñ_iᵀ t = ñ_iᵀ x̃_i - d_k, eq. (7) corrected. Here R and t
  decouple exactly, so this is the exact minimum of eq. (7).

Directions the normals do not constrain are reported, and t is taken nearest a
reference translation t0 along them.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass
class PoseFit:
    """Poses of H hypotheses with their degenerate directions.

    R : (H, 3, 3); t : (H, 3);
    free_translation : (H, 3, 3) rows are world unit directions, valid where
    free_translation_mask : (H, 3) bool; free_rotation : (H, 3) world axis, valid
    where free_rotation_mask : (H,) bool.
    """

    R: np.ndarray
    t: np.ndarray
    free_translation: np.ndarray
    free_translation_mask: np.ndarray
    free_rotation: np.ndarray
    free_rotation_mask: np.ndarray

    def take(self, idx):
        """The fits of the hypotheses ``idx``."""
        return PoseFit(*(getattr(self, f.name)[idx] for f in fields(self)))

    def concat(self, other):
        """Both sets of fits, self's first."""
        return PoseFit(*(np.concatenate([getattr(self, f.name), getattr(other, f.name)]) for f in fields(self)))

    @property
    def underdetermined(self):
        """(H,) bool: a pose family, not one pose."""
        return self.free_translation_mask.any(axis=1) | self.free_rotation_mask

    def poses(self):
        """(H, 4, 4) T_world_object."""
        T = np.zeros((len(self.R), 4, 4))
        T[:, :3, :3] = self.R
        T[:, :3, 3] = self.t
        T[:, 3, 3] = 1.0
        return T


def fit_poses(obj_normals, obj_offsets, points, finger_normals, *, cost="invariant",
              angle_tol, t0=None, centroids=None):
    """Closed-form poses of H hypotheses.

    obj_normals : (H, n, 3), obj_offsets : (H, n) of the hypothesised facets;
    points, finger_normals : (n, 3) measurements; cost : "invariant" | "paper";
    angle_tol : radians, normals closer than this to a common plane (or line) leave
    a direction free; t0 : (H, 3) reference translation (default: the one that puts
    the facet centroids' mean on the contacts' mean; centroids : (H, n, 3) needed then).
    """
    if cost not in ("invariant", "paper"):
        raise ValueError(f"cost must be 'invariant' or 'paper', got {cost!r}")
    n = obj_normals.shape[1]
    min_eig = n * np.sin(angle_tol) ** 2
    R = wahba(obj_normals, -finger_normals)
    if t0 is None:
        t0 = points.mean(axis=0)[None] - np.einsum("hij,hj->hi", R, centroids.mean(axis=1))
    # Σ n nᵀ in the object frame: its eigenvectors are the (un)determined directions
    lam, V = np.linalg.eigh(np.einsum("hni,hnj->hij", obj_normals, obj_normals))
    world = np.einsum("hij,hjk->hik", R, V)  # columns: world eigenvectors
    if cost == "invariant":
        # rows (R n_k)ᵀ: AᵀA = R (Σ n nᵀ) Rᵀ shares the eigenvalues, eigenvectors R V
        A = np.einsum("hij,hnj->hni", R, obj_normals)
        b = np.einsum("hni,ni->hn", A, points) + obj_offsets
        t = _solve_along(A, b, t0, lam, world, min_eig)
    else:
        A = np.broadcast_to(finger_normals, obj_normals.shape)
        b = np.einsum("ni,ni->n", finger_normals, points)[None] - obj_offsets
        lam_p, V_p = np.linalg.eigh(finger_normals.T @ finger_normals)
        t = _solve_along(A, b, t0, np.broadcast_to(lam_p, lam.shape), np.broadcast_to(V_p, world.shape), min_eig)
    rows = world.transpose(0, 2, 1)
    return PoseFit(R, t, rows, lam <= min_eig, rows[:, 2], lam[:, 1] <= min_eig)


def wahba(obj_vectors, world_vectors):
    """Rotations R minimising Σ_i |R a_i - b_i|² (Wahba's problem, SVD with det fix).

    obj_vectors a : (H, n, 3); world_vectors b : (n, 3)  ->  (H, 3, 3)
    """
    B = np.einsum("ni,hnj->hij", world_vectors, obj_vectors)
    U, _, Vt = np.linalg.svd(B)
    flip = np.linalg.det(U) * np.linalg.det(Vt) < 0
    U[flip, :, 2] *= -1.0
    return U @ Vt


def _solve_along(A, b, t0, lam, V, min_eig):
    """argmin_t |A t - b|² with AᵀA = V diag(lam) Vᵀ, moving from t0 only along
    eigenvectors whose eigenvalue exceeds min_eig. A : (H, n, 3), b : (H, n) -> (H, 3)"""
    residual = np.einsum("hni,hn->hi", A, b - np.einsum("hni,hi->hn", A, t0))
    coef = np.einsum("hji,hj->hi", V, residual)
    coef = np.where(lam > min_eig, coef / np.where(lam > min_eig, lam, 1.0), 0.0)
    return t0 + np.einsum("hij,hj->hi", V, coef)
