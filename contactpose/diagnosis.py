"""Why an answer came back empty or poor: each likely cause tested, the one that holds named.

:func:`diagnose` runs once the status of the default method's answer is known, and only for
an empty or poor one (scoring.status.DIAGNOSED): a good grasp pays nothing. It tests, in
order (the names are types.CAUSES):

1. ``units``: contacts that span far less than the object (under PLAUSIBLE_SPREAD[0] of its
   diameter) or more than it, scaled by the ratio of two common units (UNIT_SIZES) into a
   plausible span (the noise as stated, then scaled alike): do they fit?
2. ``model_normals_inward`` / ``contact_normals_flipped``: do the contacts fit with their
   normals reversed? The model's face winding, recorded when it was built
   (ObjectModel.winding), tells which of the two normals are at fault; without a record the
   contacts are (their normals all point away from their centroid) or the model is.
3. ``finger_off``: with n >= 4 contacts and no outlier allowed, does localize fit with
   max_outliers=1, and which finger does it leave out?
4. ``noise_too_small``: at what larger noise (both sigmas scaled together, from the best
   hypothesis's χ² when there is one, up to MAX_NOISE_FACTOR times) does localize fit?

Each test localizes again with the default method's stages (contactpose.stages) on the
changed input, and a cause holds when that answer fits with a determined pose (status in
FITTING); its suggestion
is that very input, so localize given it fits. The tests share what is left of the caller's
time limit, and their own warnings are not shown.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from itertools import permutations

import numpy as np

from contactpose import stages
from contactpose.contacts import Contacts, Tolerance
from contactpose.options import fit_threshold
from contactpose.progress import Deadline
from contactpose.scoring.status import DIAGNOSED, normals_flipped, reason
from contactpose.tol import CONFIDENCE_SIGMA
from contactpose.types import (
    CAUSE_CONTACT_NORMALS,
    CAUSE_FINGER_OFF,
    CAUSE_MODEL_NORMALS,
    CAUSE_NOISE,
    CAUSE_UNEXPLAINED,
    CAUSE_UNITS,
    Diagnosis,
)

#: Statuses of an answer whose best hypothesis fits the contacts with a determined pose (an
#: underdetermined fit, a pose family, proves little: two contacts fit almost anything).
FITTING = ("ok", "ambiguous")
#: Length units that contacts and meshes come in, in metres.
UNIT_SIZES = {"metres": 1.0, "centimetres": 0.01, "millimetres": 0.001, "inches": 0.0254}
#: The span of a grasp's contacts as a fraction of the object's diameter: below the first
#: (or beyond the object) units are tested, and a unit ratio is tried when it brings the
#: span within these bounds.
PLAUSIBLE_SPREAD = (0.1, 1.0)
#: Unit ratios tried at most, those that bring the span nearest half the diameter first.
MAX_UNIT_TRIES = 3
#: The noise test scales the stated noise by at most this factor ...
MAX_NOISE_FACTOR = 10.0
#: ... and to at most this normal noise (degrees) and position noise (fraction of the diameter).
MAX_NORMAL_NOISE_DEG = 5.0
MAX_POSITION_NOISE_FRAC = 0.01
#: Without a hypothesis to scale from, the noise test starts at this factor (the search has
#: widened the pair tolerances 2x already) and grows it threefold.
NOISE_START = 3.0
#: Margin on the factor that brings the best χ² to the fit threshold.
NOISE_MARGIN = 1.05

__all__ = ["FITTING", "diagnose"]


def diagnose(model, contacts, tolerance, status, hint, arrays, *, method="fast", max_outliers=0, prior=None,
             deadline=None, timing=None):
    """The cause of an empty or poor answer, and the hint that names it.

    status, hint, arrays : the answer's status, hint and ranked HypothesisArrays; method,
    max_outliers, prior : its localize options; deadline : the caller's progress.Deadline,
    whose remaining time the tests share; timing : the answer's seconds per stage, which gets
    ``"diagnose"`` when the tests run. Returns (hint, Diagnosis), or (hint, None) unchanged for
    a status outside DIAGNOSED or a method other than "fast".
    """
    if status not in DIAGNOSED or method != "fast":
        return hint, None
    start = time.perf_counter()
    trial = _Trials(model, contacts, tolerance, prior, Deadline(None if deadline is None else deadline.remaining()))
    tested, found = [], None
    for causes, test in (((CAUSE_UNITS,), _units), ((CAUSE_MODEL_NORMALS, CAUSE_CONTACT_NORMALS), _normals),
                         ((CAUSE_FINGER_OFF,), _finger_off), ((CAUSE_NOISE,), _noise)):
        if trial.budget.passed:
            break
        applies, found = test(trial, arrays=arrays, max_outliers=max_outliers)
        tested += causes if applies else ()
        if found is not None:
            break
    if found is None:
        found = Diagnosis(CAUSE_UNEXPLAINED, _unexplained(trial, tested))
    diagnosis = dataclasses.replace(found, tested=tuple(tested))
    if timing is not None:
        timing["diagnose"] = time.perf_counter() - start
    return _named(hint, diagnosis, reason(status, model, contacts, tolerance)), diagnosis


class _Trials:
    """localize again on a changed input, within the diagnosis's budget."""

    def __init__(self, model, contacts, tolerance, prior, budget):
        self.model, self.contacts, self.tolerance, self.prior, self.budget = model, contacts, tolerance, prior, budget
        self.model_error = max(0.0, tolerance.distance - CONFIDENCE_SIGMA * np.sqrt(2.0) * tolerance.position_noise)

    def run(self, contacts=None, tolerance=None, max_outliers=0):
        """(status, ranked HypothesisArrays) of the default method on these contacts and
        tolerances (default: the answer's), or None when the budget ran out first."""
        contacts = self.contacts if contacts is None else contacts
        tolerance = self.tolerance if tolerance is None else tolerance
        deadline = Deadline(self.budget.remaining())
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arrays = stages.find_hypotheses(self.model, contacts, tolerance, prior=self.prior,
                                            max_outliers=max_outliers, deadline=deadline, progress=False)[0]
            if deadline.hit:  # a cut answer proves nothing: spend no grace on it
                self.budget.hit = True
                return None
            arrays = stages.distinct(self.model, arrays, tolerance, deadline, merge_twins=self.prior is None)
            status = stages.classify(self.model, contacts, arrays, tolerance, deadline=deadline)[1]
        if deadline.hit:
            self.budget.hit = True
            return None
        return status, arrays

    def noise(self, factor_position, factor_normal=None):
        """Tolerance of the stated noise scaled (position, normal; model_error kept)."""
        factor_normal = factor_position if factor_normal is None else factor_normal
        return Tolerance.from_noise(self.tolerance.position_noise * factor_position,
                                    np.degrees(self.tolerance.normal_noise) * factor_normal, self.model_error)


def _fits(result):
    return result is not None and result[0] in FITTING


# ------------------------------------------------------------------- tests ---

def _units(trial, **_):
    """Contacts in other units: (whether tested, Diagnosis or None)."""
    model, contacts = trial.model, trial.contacts
    ratio = contacts.spread / model.diameter
    if PLAUSIBLE_SPREAD[0] <= ratio and contacts.spread <= model.diameter + trial.tolerance.distance:
        return False, None
    for scale, given, mesh in _unit_ratios(ratio)[:MAX_UNIT_TRIES]:
        scaled = Contacts(contacts.points * scale, finger_normals=contacts.finger_normals)
        for noise_too in (False, True):
            result = trial.run(scaled, trial.noise(scale, 1.0) if noise_too else None)
            if _fits(result):
                share = f"1/{1 / ratio:,.0f} of it" if ratio < 0.1 else f"{ratio:.2g} times that"
                also = " (position_noise too)" if noise_too else ""
                return True, Diagnosis(CAUSE_UNITS, (
                    f"contacts span {contacts.spread:.4g} but the model is {model.diameter:.4g} across ({share}): "
                    f"contacts in {given} for a mesh in {mesh}? Multiplied by {scale:.6g}{also}, they fit "
                    f"(status {result[0]}); give the contacts in the mesh's units"), scale=float(scale))
            if result is None:
                return True, None
    return True, None


def _unit_ratios(ratio):
    """[(scale, contact unit, mesh unit)] that bring a span of ``ratio`` diameters within
    PLAUSIBLE_SPREAD, nearest half the diameter first."""
    found = {}
    for given, mesh in permutations(UNIT_SIZES, 2):
        scale = UNIT_SIZES[given] / UNIT_SIZES[mesh]
        if PLAUSIBLE_SPREAD[0] <= scale * ratio <= PLAUSIBLE_SPREAD[1]:
            found.setdefault(round(scale, 9), (scale, given, mesh))
    return sorted(found.values(), key=lambda r: abs(math.log(r[0] * ratio / 0.5)))


def _normals(trial, **_):
    """Normals reversed, in the model or in the contacts: (True, Diagnosis or None)."""
    contacts = trial.contacts
    result = trial.run(Contacts(contacts.points, finger_normals=-contacts.finger_normals))
    if not _fits(result):
        return True, None
    fits = f"the contacts fit with their normals reversed (status {result[0]})"
    winding = getattr(trial.model, "winding", None)
    rebuild = "rebuild the model with fix_normals=True (build-model --fix-normals)"
    if winding in ("inward", "inconsistent"):
        how = "point inward" if winding == "inward" else "are wound inconsistently"
        return True, Diagnosis(CAUSE_MODEL_NORMALS, f"the model's facet normals {how} (found when it was built): {fits}; "
                                                    f"{rebuild}")
    if winding == "outward" or normals_flipped(contacts):
        return True, Diagnosis(CAUSE_CONTACT_NORMALS, f"{fits}: finger_normal points into the object; give outward "
                                                      "normals as object_normal, or flip them")
    unknown = "its mesh is not closed" if winding == "open" else "it was not recorded in the model file"
    return True, Diagnosis(CAUSE_MODEL_NORMALS, (
        f"{fits}, and they press into the object as a grasp's do: the model's facet normals likely point inward "
        f"(its winding is unknown: {unknown}); {rebuild}, or reverse the contact normals"))


def _finger_off(trial, *, max_outliers, **_):
    """All fingers but one fit: (whether tested, Diagnosis or None)."""
    n = trial.contacts.n
    if max_outliers or n < 4:
        return False, None
    result = trial.run(max_outliers=1)
    if not _fits(result) or not (result[1].facets[0] < 0).any():
        return True, None
    finger = int(np.flatnonzero(result[1].facets[0] < 0)[0])
    others = [k for k in range(n) if k != finger]
    return True, Diagnosis(CAUSE_FINGER_OFF, (
        f"finger {finger} is off the object: the other {n - 1} (fingers {others}) fit (status {result[0]}, chi2 "
        f"{result[1].chi2[0]:.3g} with the outlier's penalty); localize with max_outliers=1 (--max-outliers 1) "
        "leaves it out"), finger=finger, max_outliers=1)


def _noise(trial, *, arrays, **_):
    """Noise stated smaller than the fit needs: (whether tested, Diagnosis or None)."""
    sx, sn = trial.tolerance.position_noise, np.degrees(trial.tolerance.normal_noise)
    limit = min(MAX_NOISE_FACTOR, MAX_POSITION_NOISE_FRAC * trial.model.diameter / sx, MAX_NORMAL_NOISE_DEG / sn)
    if limit <= 1.0:
        return False, None
    threshold = fit_threshold(trial.contacts.n)
    factor = min(limit, _factor(arrays, threshold, 1.0) or NOISE_START)
    while True:
        position, normal = _round_up(factor * sx), _round_up(factor * sn)
        result = trial.run(tolerance=trial.noise(position / sx, normal / sn))
        if _fits(result):
            return True, Diagnosis(CAUSE_NOISE, (
                f"the contacts fit at about {factor:.2g} times the stated noise: position_noise {position:.2g} "
                f"(length units), normal_noise_deg {normal:.2g} (status {result[0]}); state the sensor's noise "
                f"(--position-noise {position:.2g} --normal-noise-deg {normal:.2g})"),
                position_noise=position, normal_noise_deg=normal)
        if result is None or factor >= limit:
            return True, None
        grown = _factor(result[1], threshold, factor)
        factor = min(limit, max(1.5 * factor, grown) if grown else NOISE_START * factor)


def _factor(arrays, threshold, factor):
    """The factor on the noise that brings the best χ² (at ``factor`` times the stated
    noise) to the fit threshold, with NOISE_MARGIN, at least 1.5; None without a hypothesis."""
    if not len(arrays.cost) or not np.isfinite(arrays.chi2[0]):
        return None
    return max(1.5, factor * math.sqrt(arrays.chi2[0] / threshold) * NOISE_MARGIN)


def _round_up(x):
    """x rounded up to two significant digits."""
    step = 10.0 ** (math.floor(math.log10(x)) - 1)
    return float(f"{math.ceil(x / step - 1e-9) * step:.2g}")


# ----------------------------------------------------------------- message ---

def _unexplained(trial, tested):
    """The message when no tested cause holds, or the budget ran out."""
    done = ", ".join(tested) if tested else "nothing"
    if trial.budget.hit:
        return f"the diagnosis reached the time limit after testing {done}"
    return (f"none of the causes tested holds ({done}): the model may differ from the object (model_error), "
            "or more than one finger is off the object")


def _named(hint, diagnosis, reasons):
    """The hint with the likely reasons it ends in replaced by the diagnosis's message (or,
    for an unexplained answer, followed by it)."""
    if diagnosis.cause != CAUSE_UNEXPLAINED and reasons in hint:
        return hint.replace(reasons, diagnosis.message, 1)
    return f"{hint}; {diagnosis.message}" if hint else diagnosis.message
