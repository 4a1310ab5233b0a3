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

from dataclasses import dataclass

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


def wahba(obj_vectors, world_vectors):
    """Rotations R minimising Σ_i |R a_i - b_i|² (Wahba's problem, SVD with det fix).

    obj_vectors a : (H, n, 3); world_vectors b : (H, n, 3) or (n, 3)  ->  (H, 3, 3)
    """
    B = np.einsum("...ni,hnj->hij", world_vectors, obj_vectors)
    U, _, Vt = np.linalg.svd(B)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def least_squares_translation(A, b, t0, min_eig):
    """argmin_t |A t - b|², taken nearest t0 along weakly determined directions.

    A : (H, n, 3) or (n, 3); b : (H, n); t0 : (H, 3); min_eig : eigenvalues of AᵀA
    at or below it count as undetermined.  ->  t (H, 3)
    """
    A = np.broadcast_to(A, b.shape + (3,))
    M = np.einsum("hni,hnj->hij", A, A)
    g = np.einsum("hni,hn->hi", A, b)
    lam, V = np.linalg.eigh(M)
    ok = lam > min_eig
    residual = g - np.einsum("hij,hj->hi", M, t0)
    coef = np.einsum("hji,hj->hi", V, residual) / np.where(ok, lam, 1.0) * ok
    return t0 + np.einsum("hij,hj->hi", V, coef)


def fit_poses(obj_normals, obj_offsets, points, finger_normals, *, cost="invariant",
              angle_tol, t0=None, centroids=None):
    """Closed-form poses of H hypotheses.

    obj_normals : (H, n, 3), obj_offsets : (H, n) of the hypothesised facets;
    points, finger_normals : (n, 3) measurements; cost : "invariant" | "paper";
    angle_tol : radians, normals closer than this to a common plane (or line) leave
    a direction free; t0 : (H, 3) reference translation (default: the one that puts
    the facet centroids' mean on the contacts' mean; centroids : (H, n, 3) needed then).
    """
    h, n, _ = obj_normals.shape
    R = wahba(obj_normals, -finger_normals)
    if t0 is None:
        t0 = points.mean(axis=0)[None] - np.einsum("hij,hj->hi", R, centroids.mean(axis=1))
    min_eig = n * np.sin(angle_tol) ** 2
    if cost == "invariant":
        A = np.einsum("hij,hnj->hni", R, obj_normals)
        b = np.einsum("hni,ni->hn", A, points) + obj_offsets
    elif cost == "paper":
        A = finger_normals
        b = np.einsum("ni,ni->n", finger_normals, points)[None] - obj_offsets
    else:
        raise ValueError(f"cost must be 'invariant' or 'paper', got {cost!r}")
    t = least_squares_translation(A, b, t0, min_eig)
    return PoseFit(R, t, *free_directions(R, obj_normals, min_eig))


def free_directions(R, obj_normals, min_eig):
    """Directions the hypothesised normals leave undetermined, in the world frame.

    R : (H, 3, 3); obj_normals : (H, n, 3).
    Returns translation dirs (H, 3, 3) rows, their mask (H, 3), rotation axis (H, 3), its mask (H,).
    The translation is free along eigenvectors of Σ n nᵀ with small eigenvalue; the
    rotation is free when all normals are (nearly) parallel, about their common axis.
    """
    N = np.einsum("hni,hnj->hij", obj_normals, obj_normals)
    lam, V = np.linalg.eigh(N)  # ascending
    world = np.einsum("hij,hjk->hki", R, V)  # rows: world eigenvectors
    trans_mask = lam <= min_eig
    rot_mask = lam[:, 1] <= min_eig
    return world, trans_mask, world[:, 2], rot_mask
