"""Robust kernels on a contact's whitened residual block, with their widths.

A contact's rows are whitened by the sensor noise; s is the norm of its block (4 or 6 rows
of the facet model, 3 of the smooth one). The kernels are GTSAM's ``mEstimator`` losses,

    ρ_Huber(s) = s²/2 (s ≤ k), k s - k²/2;   ρ_Cauchy(s) = k²/2 log(1 + s²/k²);   ρ_none = s²/2,

applied two ways: as the square-rooted residual ẽ = sqrt(2 ρ(s)) e / s, so that ½|ẽ|² = ρ(s)
exactly (:func:`robust_scale`, the batched factors of costs.facet), or as GTSAM's own
reweighting (:func:`reweighted_noise`, one factor per contact: the iteratively reweighted
least-squares step, whose Gauss–Newton steps do not overshoot).

Kernel width: an inlier block holds about 3 informative whitened components (2 normal,
1 offset; the lateral rows are 0 for a contact inside its triangle), so s² ~ χ²(3).
k = sqrt(χ²₃(0.95)) = 2.80 leaves 95 % of inlier contacts in the quadratic zone (Huber: no
efficiency loss there), and a displaced contact (tens of σ) keeps only a bounded (Huber) or
vanishing (Cauchy) influence. The scalar textbook value 1.345 would down-weight 61 % of the
inlier contacts, whose block norm has median 1.54.
"""

from __future__ import annotations

from functools import lru_cache

import gtsam
import numpy as np
from numba import njit

from contactpose.options import check_robust

#: Kernel width on the norm of a contact's whitened block: sqrt(χ²₃(0.95)).
HUBER_K = 2.7954834829151074
CAUCHY_K = 2.7954834829151074
#: The compiled kernels' codes.
KERNEL_CODE = {"none": 0, "huber": 1, "cauchy": 2}


def kernel_width(robust):
    """The width k of the kernel named ``robust`` (0 for "none")."""
    return {"huber": HUBER_K, "cauchy": CAUCHY_K, "none": 0.0}[check_robust(robust)]


@njit(cache=True)
def robust_scale(s, kernel, k):
    """(f, g') for the square-rooted robust residual ẽ = f e, g(s) = f s = sqrt(2ρ(s)); kernel
    : KERNEL_CODE of Huber (1) or Cauchy (2), k its width."""
    if kernel == 1:  # Huber
        if s <= k:
            return 1.0, 1.0
        g = np.sqrt(2.0 * k * s - k * k)
        return g / s, k / g
    # Cauchy: ρ = k²/2 log(1 + s²/k²), ρ' = s / (1 + s²/k²)
    q = s * s / (k * k)
    g = k * np.sqrt(np.log1p(q))
    return g / s, s / (1.0 + q) / g


def robust_rho(s, robust):
    """ρ(s) of the kernel named ``robust`` for whitened residual norms s (array): g(s)²/2 of
    :func:`robust_scale`."""
    s = np.asarray(s, dtype=np.float64)
    k = kernel_width(robust)
    if robust == "huber":
        return np.where(s <= k, 0.5 * s * s, k * s - 0.5 * k * k)
    if robust == "cauchy":
        return 0.5 * k * k * np.log1p(s * s / (k * k))
    return 0.5 * s * s


@lru_cache(maxsize=None)
def reweighted_noise(dim, robust):
    """GTSAM's own robust noise model on ``dim`` unit-whitened rows: the same ρ as the batched
    factors' kernel (:func:`robust_rho`), applied by reweighting (each linearization scales the
    rows by √w, w = ρ'(s)/s). robust : "huber" | "cauchy" | "none" (unit noise)."""
    unit = gtsam.noiseModel.Unit.Create(dim)
    if check_robust(robust) == "none":
        return unit
    kernel = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[robust]
    return gtsam.noiseModel.Robust.Create(kernel.Create(kernel_width(robust)), unit)
