"""SE(3) in the one convention of the library: poses T_world_object, tangent vectors
ξ = (ω, v) in GTSAM's Pose3 order (rotation first), perturbations on the right.

* :func:`hat` ([v]×, batched) and :func:`hat3` (one vector, inside compiled kernels);
* :func:`exp` and :func:`log`: GTSAM's Pose3.Expmap and Logmap, batched: the chart of the
  Laplace covariance (gtsam.Marginals) and of the posterior samples (uncertainty.sampling),
  T = T* · Exp(ξ);
* :func:`retract`: the step every optimizer of ours takes, R' = R Exp(ω), t' = t + R' v,
  the rotation turned first and the translation taken in the turned frame. To first order
  it is T · Exp(ξ) (both move an object-frame point p by p × ω - v), so a Gauss–Newton
  step, a Jacobian and a covariance mean the same in either; the second-order terms differ;
* :func:`inverse` of a rigid transform.

Rotations of a rotation vector come from scipy.spatial.transform; Exp and Log of a
batch are compiled because the sampler calls them for every walker at every step (a test
holds them equal to GTSAM's).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from contactpose.errors import ContactPoseError


def hat(v):
    """[v]×, the matrix of v × ·, for each vector of v (..., 3) -> (..., 3, 3)."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return S - np.swapaxes(S, -1, -2)


@njit(cache=True)
def hat3(v):
    """[v]× of one vector (3,) -> (3, 3), inside compiled kernels (:func:`hat` outside)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def retract(R, t, xi):
    """Poses (R (K, 3, 3), t (K, 3)) moved by right perturbations ξ = (ω, v) (K, 6):
    R Exp(ω), t + R Exp(ω) v. -> (R (K, 3, 3), t (K, 3))"""
    R = R @ Rotation.from_rotvec(xi[:, :3]).as_matrix()
    return R, t + np.einsum("kij,kj->ki", R, xi[:, 3:])


def inverse(T):
    """The inverse of a rigid transform T (4, 4): [Rᵀ, -Rᵀ t]."""
    inv = np.eye(4)
    inv[:3, :3] = T[:3, :3].T
    inv[:3, 3] = -T[:3, 3] @ T[:3, :3]
    return inv


@njit(cache=True)
def _exp_into(w0, w1, w2, v0, v1, v2, T):
    """T[:3, :4] = Exp(ξ) of GTSAM's Pose3: R = exp([ω]×) (Rodrigues), t = J_l(ω) v,
    J_l = I + a [ω]× + b [ω]×², with Taylor series for small |ω|."""
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-10:
        s_, c_ = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0  # sin θ/θ, (1 - cos θ)/θ²
        b = 1.0 / 6.0 - th2 / 120.0  # (θ - sin θ)/θ³
    else:
        th = np.sqrt(th2)
        s_, c_ = np.sin(th) / th, (1.0 - np.cos(th)) / th2
        b = (th - np.sin(th)) / (th2 * th)
    # [ω]× and [ω]×² = ω ωᵀ - θ² I
    K = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    w = (w0, w1, w2)
    v = (v0, v1, v2)
    for i in range(3):
        for j in range(3):
            K2 = w[i] * w[j] - (th2 if i == j else 0.0)
            T[i, j] = (1.0 if i == j else 0.0) + s_ * K[i][j] + c_ * K2
        ti = 0.0
        for j in range(3):
            K2 = w[i] * w[j] - (th2 if i == j else 0.0)
            ti += ((1.0 if i == j else 0.0) + c_ * K[i][j] + b * K2) * v[j]
        T[i, 3] = ti


@njit(cache=True)
def _log_into(T, out):
    """out[:6] = Log(T) of GTSAM's Pose3: ω from the unit quaternion of R (well defined up
    to θ = π), v = J_l(ω)⁻¹ t, J_l⁻¹ = I - ½[ω]× + c [ω]×²."""
    # quaternion (x, y, z, w) of R by the largest-pivot method
    tr = T[0, 0] + T[1, 1] + T[2, 2]
    if tr > 0.0:
        s = 2.0 * np.sqrt(tr + 1.0)
        qw, qx, qy, qz = 0.25 * s, (T[2, 1] - T[1, 2]) / s, (T[0, 2] - T[2, 0]) / s, (T[1, 0] - T[0, 1]) / s
    elif T[0, 0] > T[1, 1] and T[0, 0] > T[2, 2]:
        s = 2.0 * np.sqrt(1.0 + T[0, 0] - T[1, 1] - T[2, 2])
        qw, qx, qy, qz = (T[2, 1] - T[1, 2]) / s, 0.25 * s, (T[0, 1] + T[1, 0]) / s, (T[0, 2] + T[2, 0]) / s
    elif T[1, 1] > T[2, 2]:
        s = 2.0 * np.sqrt(1.0 + T[1, 1] - T[0, 0] - T[2, 2])
        qw, qx, qy, qz = (T[0, 2] - T[2, 0]) / s, (T[0, 1] + T[1, 0]) / s, 0.25 * s, (T[1, 2] + T[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + T[2, 2] - T[0, 0] - T[1, 1])
        qw, qx, qy, qz = (T[1, 0] - T[0, 1]) / s, (T[0, 2] + T[2, 0]) / s, (T[1, 2] + T[2, 1]) / s, 0.25 * s
    if qw < 0.0:
        qw, qx, qy, qz = -qw, -qx, -qy, -qz
    nv = np.sqrt(qx * qx + qy * qy + qz * qz)
    # θ = 2 atan2(|q_v|, q_w); ω = θ q_v / |q_v|
    f = 2.0 * np.arctan2(nv, qw) / nv if nv > 1e-12 else 2.0 / qw
    w0, w1, w2 = f * qx, f * qy, f * qz
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    if th2 < 1e-10:
        c = 1.0 / 12.0 + th2 / 720.0
    else:
        th = np.sqrt(th2)
        c = 1.0 / th2 - (1.0 + np.cos(th)) / (2.0 * th * np.sin(th))
    K = ((0.0, -w2, w1), (w2, 0.0, -w0), (-w1, w0, 0.0))
    w = (w0, w1, w2)
    out[0], out[1], out[2] = w0, w1, w2
    for i in range(3):
        vi = 0.0
        for j in range(3):
            K2 = w[i] * w[j] - (th2 if i == j else 0.0)
            vi += ((1.0 if i == j else 0.0) - 0.5 * K[i][j] + c * K2) * T[j, 3]
        out[3 + i] = vi


@njit(cache=True)
def _exp_batch(xi, out):
    for n in range(xi.shape[0]):
        _exp_into(xi[n, 0], xi[n, 1], xi[n, 2], xi[n, 3], xi[n, 4], xi[n, 5], out[n])
        out[n, 3, 0], out[n, 3, 1], out[n, 3, 2], out[n, 3, 3] = 0.0, 0.0, 0.0, 1.0


@njit(cache=True)
def _log_batch(T, out):
    for n in range(T.shape[0]):
        _log_into(T[n], out[n])


def exp(xi):
    """Exp: GTSAM's Pose3.Expmap, batched. xi : (N, 6) float, (ω, v)  ->  (N, 4, 4)"""
    xi = np.ascontiguousarray(xi, dtype=np.float64)
    if xi.ndim != 2 or xi.shape[1] != 6:
        raise ContactPoseError(f"xi must have shape (N, 6), got {xi.shape}")
    out = np.empty((len(xi), 4, 4))
    _exp_batch(xi, out)
    return out


def log(T):
    """Log: GTSAM's Pose3.Logmap, batched, the inverse of :func:`exp`.
    T : (N, 4, 4) rigid  ->  (N, 6) (ω, v), |ω| ≤ π"""
    T = np.ascontiguousarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ContactPoseError(f"T must have shape (N, 4, 4), got {T.shape}")
    out = np.empty((len(T), 6))
    _log_batch(T, out)
    return out


@njit(cache=True)
def retract3(R, t, xi):
    """:func:`retract` of one pose inside compiled kernels: R Exp(ω), t + R Exp(ω) v.
    R (3, 3), t (3,), xi (6,) -> (R (3, 3), t (3,))"""
    T = np.empty((4, 4))
    _exp_into(xi[0], xi[1], xi[2], 0.0, 0.0, 0.0, T)
    turned = R @ np.ascontiguousarray(T[:3, :3])
    return turned, t + turned @ xi[3:]
