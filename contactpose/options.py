"""The options of the online phase and the thresholds behind its decisions, declared once.

Methods, solvers, robust kernels, what ``keep`` lists, every status a Result can carry, and
the policy constants (the fit test's confidence, the outlier penalty, the default noise)
with the small functions that apply them.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from contactpose.errors import ContactPoseError

METHODS = ("fast", "paper")
SOLVERS = ("closed-form", "lm", "factor-graph")
ROBUST = ("huber", "cauchy", "none")


#: localize(..., keep=...): list the hypotheses that fit within noise, or every distinct pose.
KEEP = ("fitting", "all")
#: solver="factor-graph" refines this many of the best closed-form hypotheses (0: all).
DEFAULT_REFINE = 20
#: Probability that a correct hypothesis passes the fit test (χ² quantile, 3 dof per contact).
FIT_CONFIDENCE = 0.9973
#: With evidence-based probabilities (factor graph), "ambiguous" needs the classes other
#: than the best to hold more than this probability together.
AMBIGUOUS_PROBABILITY = 0.05
#: "ok" needs the best pose strictly right (rotation within 5°, translation within 5 % of the
#: diameter, modulo symmetry) with at least this probability (localize(ok_probability=)).
OK_PROBABILITY = 0.99
#: The hint of an answer short of it lists the placements of at least this probability.
LISTED_PROBABILITY = 0.01
#: χ² charged per unassigned finger (max_outliers): the FIT_CONFIDENCE quantile of one
#: contact's 3 dof, so dropping a finger never beats assigning it within noise.
OUTLIER_PENALTY = 14.16
#: Default position noise when none is given: this fraction of the object diameter.
DEFAULT_POSITION_NOISE_FRAC = 0.0025
#: Every status a Result can carry, in the order of the benchmark's tables (scoring.status
#: decides them: no_hypothesis, time_limit, poor_fit, underdetermined, ambiguous, else ok).
STATUSES = ("ok", "poor_fit", "no_hypothesis", "underdetermined", "ambiguous", "time_limit")


def check_robust(robust):
    """The robust kernel's name, checked against ROBUST. -> robust"""
    if robust not in ROBUST:
        raise ContactPoseError(f"robust must be one of {ROBUST}, got {robust!r}")
    return robust


def chi2_quantile(p, dof):
    """The χ² distribution's p-quantile with ``dof`` degrees of freedom (scipy.special, which
    imports in a fraction of scipy.stats' quarter second)."""
    from scipy.special import chdtri

    return float(chdtri(dof, 1.0 - p))


@lru_cache(maxsize=64)
def fit_threshold(n):
    """χ² bound that a correct hypothesis of n contacts passes with FIT_CONFIDENCE."""
    return chi2_quantile(FIT_CONFIDENCE, 3 * n)


def outlier_penalty(facets):
    """χ² charged for the unassigned fingers (facet -1) of each row: OUTLIER_PENALTY each, so
    that leaving a finger out never beats assigning it within noise. (H, n) -> (H,)"""
    return OUTLIER_PENALTY * np.sum(np.asarray(facets) < 0, axis=-1)
