"""Pose error metrics: rotation and translation error, raw and modulo a symmetry group, ADD-S,
the benchmark's MSSD and its average recall, top-1 success."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError
from scipy.spatial.distance import pdist
from scipy.spatial.transform import Rotation

from contactpose.geometry.se3 import hat

#: Default top-1 success thresholds: rotation error in degrees, translation error
#: as a fraction of the object diameter.
SUCCESS_ROT_DEG = 5.0
SUCCESS_TRANS_FRAC = 0.05
#: Poses whose ADD-S is below this fraction of the diameter place the surface the same way.
SAME_CLASS_ADDS_FRAC = 0.05
#: The MSSD thresholds whose recalls AR_MSSD averages: 5 %, 10 %, ..., 50 % of the diameter
#: (the BOP challenge's protocol).
MSSD_THRESHOLDS_FRAC = tuple(round(0.05 * k, 2) for k in range(1, 11))
#: A continuous symmetry enters the MSSD as turns so close that the point farthest from the
#: axis moves at most this fraction of the diameter from one to the next (as in BOP).
MSSD_TURN_FRAC = 0.01


def rotation_error_deg(T_est, T_true):
    """Angle of R_estᵀ R_true in degrees. T_* : (..., 4, 4) -> (...)"""
    R = np.einsum("...ji,...jk->...ik", T_est[..., :3, :3], T_true[..., :3, :3])
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def translation_error(T_est, T_true):
    """|t_est - t_true| in length units. T_* : (..., 4, 4) -> (...)"""
    return np.linalg.norm(T_est[..., :3, 3] - T_true[..., :3, 3], axis=-1)


def symmetric_errors(T_est, T_true, rotations, axes=(), centre=None):
    """Rotation error (degrees) and translation error (length units) of T_est against the
    nearest of the poses that place the surface as T_true does (:func:`nearest_twins`).

    T_est, T_true : (..., 4, 4), broadcast; rotations, axes, centre : the symmetry group, as
    for :func:`nearest_twins`. -> (rotation (...), translation (...))
    """
    twin = nearest_twins(T_est, T_true, rotations, axes, centre)
    return rotation_error_deg(T_est, twin), translation_error(T_est, twin)


def nearest_twins(T_ref, T, rotations, axes=(), centre=None):
    """Of the poses that place the surface as T does, T G over the object's symmetries G, the
    one of least rotation error to T_ref.

    T_ref, T : (..., 4, 4), broadcast; rotations : (K, 4, 4) the symmetries G = [Q, c - Q c]
    in the object frame (the identity among them); axes : (C, 3) unit axes through ``centre``
    (3,; default the origin) about which every turn is a symmetry: C = 0 none; 1 an axis, each
    G then followed by the turn about it that fits best (in closed form: the angle φ maximising
    tr(A Rot(a, φ)), A = R_refᵀ R Q, is atan2(tr(A [a]×), tr A - aᵀ A a)); 2 or more, every
    rotation (the twin then has T_ref's rotation). -> (..., 4, 4)
    """
    T_ref, T = np.broadcast_arrays(np.asarray(T_ref, dtype=np.float64), np.asarray(T, dtype=np.float64))
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    rotations = np.asarray(rotations, dtype=np.float64)
    centre = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    if len(axes) == 0 and len(rotations) == 1 and np.array_equal(rotations[0], np.eye(4)):  # no symmetry
        return T.copy()
    if len(axes) >= 2:
        Q = np.einsum("...ji,...jk->...ik", T[..., :3, :3], T_ref[..., :3, :3])
        return T @ _about(Q, centre)
    candidates = T[..., None, :, :] @ rotations  # (..., K, 4, 4)
    if len(axes) == 1:
        a = axes[0]
        A = np.einsum("...ji,...kjl->...kil", T_ref[..., :3, :3], candidates[..., :3, :3])
        phi = np.arctan2(np.einsum("...ij,ji->...", A, hat(a)),
                         np.trace(A, axis1=-2, axis2=-1) - np.einsum("i,...ij,j->...", a, A, a))
        turn = Rotation.from_rotvec(phi.reshape(-1, 1) * a).as_matrix().reshape(phi.shape + (3, 3))
        candidates = candidates @ _about(turn, centre)
    best = np.argmin(rotation_error_deg(T_ref[..., None, :, :], candidates), axis=-1)
    return np.take_along_axis(candidates, best[..., None, None, None], axis=-3)[..., 0, :, :]


def mssd(T_est, T_true, points, rotations, axes=(), centre=None):
    """Maximum symmetry-aware surface distance (the BOP challenge's MSSD) of each estimate:
    min over the symmetries S of max over the points x of |T_est x - T_true S x|.

    T_est : (K, 4, 4) or (4, 4); T_true : (4, 4); points : (N, 3) object-frame model vertices;
    rotations, axes, centre : the symmetry group, as for :func:`nearest_twins` (a continuous
    axis sampled at MSSD_TURN_FRAC of the diameter; every rotation, a sphere: the centre's
    displacement, exactly). -> (K,) or a float, in length units. The max over the points is
    taken over their convex hull's vertices, where a convex function of x attains it.
    """
    T_est = np.asarray(T_est, dtype=np.float64)
    single = T_est.ndim == 2
    T_est, T_true = T_est.reshape(-1, 4, 4), np.asarray(T_true, dtype=np.float64)
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    centre = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    if len(axes) >= 2:
        moved = T_est[:, :3, :3] @ centre + T_est[:, :3, 3] - (T_true[:3, :3] @ centre + T_true[:3, 3])
        out = np.linalg.norm(moved, axis=1)
        return float(out[0]) if single else out
    hull = hull_points(points)
    S = symmetry_transforms(hull, rotations, axes, centre)
    TS = T_true @ S  # (M, 4, 4)
    out = np.empty(len(T_est))
    for k, T in enumerate(T_est):
        A = T[:3, :3] - TS[:, :3, :3]  # (M, 3, 3)
        b = T[:3, 3] - TS[:, :3, 3]
        gap = np.einsum("mij,nj->mni", A, hull) + b[:, None, :]
        out[k] = np.sqrt(np.einsum("mni,mni->mn", gap, gap).max(axis=1).min())
    return float(out[0]) if single else out


def hull_points(points):
    """The points (N, 3) on their convex hull (all of them when they span no volume)."""
    points = np.asarray(points, dtype=np.float64)
    try:
        return points[ConvexHull(points).vertices]
    except (QhullError, ValueError):
        return points


def symmetry_transforms(points, rotations, axes=(), centre=None):
    """The symmetries an MSSD minimises over, (M, 4, 4): the group's rotations, each followed
    by turns about a continuous axis (through ``centre``) spaced so that no point of
    ``points`` (N, 3) moves more than MSSD_TURN_FRAC of their diameter between two."""
    rotations = np.asarray(rotations, dtype=np.float64)
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    if len(axes) == 0:
        return rotations
    centre = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    a = axes[0]
    offset = points - centre
    radius = np.linalg.norm(offset - np.outer(offset @ a, a), axis=1).max()
    chord = MSSD_TURN_FRAC * (pdist(points).max() if len(points) > 1 else 0.0)
    steps = 1 if radius <= chord / 2 else int(np.ceil(2 * np.pi / (2 * np.arcsin(chord / (2 * radius)))))
    phis = 2 * np.pi * np.arange(steps) / steps
    turns = _about(Rotation.from_rotvec(phis[:, None] * a).as_matrix(), centre)
    return (rotations[:, None] @ turns[None]).reshape(-1, 4, 4)


def ar_mssd(errors, diameter, thresholds=MSSD_THRESHOLDS_FRAC):
    """Average recall of MSSD errors (K,) over thresholds (fractions of ``diameter``): the
    mean over thresholds θ of the share of errors below θ · diameter. A missing error (NaN:
    no pose) counts as a miss at every threshold."""
    errors = np.asarray(errors, dtype=np.float64)
    if errors.size == 0:
        return float("nan")
    below = np.nan_to_num(errors, nan=np.inf)[:, None] < np.asarray(thresholds)[None] * diameter
    return float(below.mean())


def _about(Q, centre):
    """(..., 4, 4) [Q, c - Q c]: rotations Q (..., 3, 3) about ``centre`` (3,)."""
    T = np.zeros(Q.shape[:-2] + (4, 4))
    T[..., :3, :3] = Q
    T[..., :3, 3] = centre - Q @ centre
    T[..., 3, 3] = 1.0
    return T


def pose_success(T_est, T_true, diameter, rot_deg=SUCCESS_ROT_DEG, trans_frac=SUCCESS_TRANS_FRAC):
    """Rotation error < rot_deg and translation error < trans_frac · diameter."""
    return (rotation_error_deg(T_est, T_true) < rot_deg) & (translation_error(T_est, T_true) < trans_frac * diameter)


def relative_points(T_a, T_b, points):
    """Object points under T_a, expressed in T_b's object frame: T_b⁻¹ T_a p. points : (N, 3)."""
    T = np.linalg.solve(T_b, T_a)
    return points @ T[:3, :3].T + T[:3, 3]


def rms_displacement(T_a, T_b, mean, second):
    """Root-mean-square distance each surface point moves between poses T_a (K of them) and
    T_b, from the points' moments: an upper bound on ADD and hence on ADD-S (Jensen).

    T_a : (K, 4, 4), T_b : (4, 4); mean : (3,) and second : (3, 3) = E[p pᵀ] of the
    object-frame surface points  ->  (K,). With M = R - I and t of T_b⁻¹ T_a,
    E|M p + t|² = tr(M E[ppᵀ] Mᵀ) + 2 tᵀ M E[p] + |t|².
    """
    Rb_t = T_b[:3, :3].T
    M = Rb_t @ T_a[:, :3, :3] - np.eye(3)
    t = (T_a[:, :3, 3] - T_b[:3, 3]) @ Rb_t.T
    msq = (np.einsum("kij,jl,kil->k", M, second, M) + 2.0 * np.einsum("ki,kij,j->k", t, M, mean)
           + np.einsum("ki,ki->k", t, t))
    return np.sqrt(np.maximum(msq, 0.0))


def pose_embedding(poses, mean, second):
    """Poses (..., 4, 4) as 12-vectors [R L, R μ + t] whose Euclidean distances are the RMS
    displacements of :func:`rms_displacement` (L Lᵀ the points' covariance E[ppᵀ] - μμᵀ),
    so near poses can be found with a k-d tree. mean : (3,), second : (3, 3)  ->  (..., 12)"""
    w, V = np.linalg.eigh(second - np.outer(mean, mean))
    root = V * np.sqrt(np.maximum(w, 0.0))
    R = poses[..., :3, :3]
    RL = np.einsum("...ij,jk->...ik", R, root).reshape(*poses.shape[:-2], 9)
    return np.concatenate([RL, np.einsum("...ij,j->...i", R, mean) + poses[..., :3, 3]], axis=-1)


def adds_many(T_a, T_b, points, tree):
    """ADD-S of K poses T_a (K, 4, 4) against one pose T_b (4, 4)  ->  (K,); see :func:`adds`."""
    T = np.linalg.solve(T_b[None], T_a)
    moved = np.einsum("kij,nj->kni", T[:, :3, :3], points) + T[:, None, :3, 3]
    dist, _ = tree.query(moved.reshape(-1, 3))
    return dist.reshape(len(T_a), len(points)).mean(axis=1)


def adds(T_a, T_b, points, tree):
    """ADD-S: mean distance from each surface point under T_a to the surface under T_b.

    points : (N, 3) object-frame surface samples; tree : scipy cKDTree over ``points``.
    Symmetric placements of a symmetric object have ADD-S near 0.
    """
    dist, _ = tree.query(relative_points(T_a, T_b, points))
    return float(np.mean(dist))
