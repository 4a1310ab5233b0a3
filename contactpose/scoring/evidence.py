"""The evidence of refined hypotheses, and a vision prior's agreement with them.

* :func:`laplace_log_evidence`: the Laplace approximation of log ∫ p(z | T, h) p(T) dT,
  ``-½ chi2 + ½ log det(2π Σ) - ½ log det(2π Σ_prior)`` (the last term only with a prior;
  without one the flat prior is a constant). Terms equal for all hypotheses of one call
  (the Gaussian normalisation of the n contacts) are dropped, so only differences matter.
  With a robust kernel exp(-ρ) stands in for the Gaussian likelihood;
* :func:`normalise`: probabilities, the softmax of the log-evidence;
* :func:`prior_gate`, :func:`prior_mahalanobis2`: how far a hypothesis's pose lies from the
  prior's.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

#: χ²₃ quantile at 1 - 1e-9: a hypothesis whose rotation disagrees more with the prior's is
#: not screened when a prior is given (see :func:`prior_gate`).
PRIOR_GATE_CHI2 = 44.841275388361254


def laplace_log_evidence(chi2, covariance, prior_covariance=None):
    """-½ chi2 + ½ log det(2π Σ) [- ½ log det(2π Σ_prior)].  chi2 : (K,), covariance : (K, 6, 6)."""
    sign, logdet = np.linalg.slogdet(2.0 * np.pi * covariance)
    out = -0.5 * chi2 + 0.5 * np.where(sign > 0, logdet, np.nan)
    if prior_covariance is not None:
        out -= 0.5 * np.linalg.slogdet(2.0 * np.pi * prior_covariance)[1]
    return out


def normalise(log_evidence):
    """Softmax over the finite entries; NaN entries get probability 0 (all NaN when no
    entry is finite: a set of pose families has no probabilities). (K,) -> (K,)"""
    ok = np.isfinite(log_evidence)
    p = np.zeros(len(log_evidence)) if ok.any() else np.full(len(log_evidence), np.nan)
    if ok.any():
        z = log_evidence[ok] - log_evidence[ok].max()
        p[ok] = np.exp(z) / np.exp(z).sum()
    return p


def log_evidence(chi2, cov, prior_cov):
    """laplace_log_evidence with NaN for hypotheses without a covariance (pose families)."""
    determined = np.isfinite(cov).all(axis=(1, 2))
    log_ev = laplace_log_evidence(chi2, np.where(determined[:, None, None], cov, np.eye(6)), prior_cov)
    log_ev[~determined] = np.nan
    return log_ev


def prior_mahalanobis2(R, t, prior):
    """Squared Mahalanobis distance of poses from the prior, ξ = (Log(R_pᵀR), R_pᵀ(t - t_p)).

    R : (H, 3, 3), t : (H, 3)  ->  (H,). The translation part is the first-order Pose3 log.
    """
    Rp, tp = prior.pose[:3, :3], prior.pose[:3, 3]
    xi = np.concatenate([Rotation.from_matrix(np.einsum("ji,hjk->hik", Rp, R)).as_rotvec(),
                         (t - tp) @ Rp], axis=1)
    return np.einsum("hi,ij,hj->h", xi, np.linalg.inv(prior.covariance_matrix()), xi)


def prior_gate(model, arrays, tolerance, prior):
    """(H,) bool: hypotheses whose closed-form rotation agrees with the prior's rotation.

    A consistency test of two Gaussian rotation estimates: δ = Log(R_pᵀ R) of the contact-only
    closed form R, whose information (object frame) is Σ_i (I - n_k n_kᵀ) / σ_n², and of the
    prior with covariance C_p. Rows with δᵀ (info⁻¹ + C_p)⁻¹ δ above :data:`PRIOR_GATE_CHI2`
    are dropped before the prior-aware scoring (which costs ~10 µs a row). The form
    info (I + C_p info)⁻¹ needs no inverse of info, so rotations the normals leave free
    (singular info) are never dropped.
    """
    facets = np.asarray(arrays.facets)
    ok = facets >= 0  # unassigned fingers carry no information
    normals = model.planes.normals[np.maximum(facets, 0)] * ok[..., None]
    n = ok.sum(axis=1)[:, None, None]
    info = (n * np.eye(3) - np.einsum("hni,hnj->hij", normals, normals)) / tolerance.normal_noise**2
    Rp = prior.pose[:3, :3]
    delta = Rotation.from_matrix(np.einsum("ji,hjk->hik", Rp, arrays.fit.R)).as_rotvec()
    Cp = prior.covariance_matrix()[:3, :3]
    y = np.linalg.solve(np.eye(3) + np.einsum("ij,hjk->hik", Cp, info), delta[..., None])[..., 0]
    return np.einsum("hi,hij,hj->h", delta, info, y) <= PRIOR_GATE_CHI2


def agrees_with_prior(model, arrays, tolerance, prior):
    """Whether some hypothesis of ``arrays`` passes :func:`prior_gate` (False when there are none)."""
    return len(arrays.cost) > 0 and bool(prior_gate(model, arrays, tolerance, prior).any())
