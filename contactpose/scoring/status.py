"""The one status rule: what the ranked hypotheses and their pose classes say.

In this order:

* ``no_hypothesis``: nothing matched (the hint says why it may be: units, flipped normals,
  tolerances);
* ``time_limit``: the search stopped at its time limit; the hypotheses found so far are
  returned, best first, but the true one may be missing;
* ``poor_fit``: the best hypothesis does not fit the contacts within noise (its best χ²,
  triangles included, exceeds the FIT_CONFIDENCE quantile): the pose is a guess;
* ``underdetermined``: the best hypothesis's normals leave pose directions free (and no
  covariance from a prior pins them);
* ``ambiguous``: another distinct placement holds a real share of the probability (more
  than AMBIGUOUS_PROBABILITY, 5 %); the hint lists exactly the placements above it;
* ``ok`` otherwise.

Placements that differ by a symmetry of the object are one pose class (ADD-S), and the
hint says when the object has such symmetries (model.symmetry).

The hint of an empty or poor answer (DIAGNOSED) ends in the likely reasons (:func:`reason`);
contactpose.diagnosis tests them and puts the cause that holds in their place.
"""

from __future__ import annotations

import numpy as np

from contactpose.model.symmetry import symmetries
from contactpose.options import AMBIGUOUS_PROBABILITY, LISTED_PROBABILITY, fit_threshold

#: The statuses of an empty or poor answer, whose cause localize diagnoses.
DIAGNOSED = ("no_hypothesis", "poor_fit")
#: The reasons a hint gives for an empty answer when no likely mistake stands out.
NO_HYPOTHESIS_REASONS = "noise too small, wrong units, or a finger off the object?"
#: The reasons a hint gives for a best hypothesis that does not fit within noise.
POOR_FIT_REASONS = "more noise than stated, a finger off the object, or a model that differs from the object"
#: Contacts spread up to this many times the diameter may be one finger off the object.
FINGER_OFF_RATIO = 2.0


def status(model, contacts, arrays, classes, tolerance, fits=None, truncated=False, *, placements=(),
           confidence=None, ok_probability=None):
    """Status and hint from the ranked hypotheses and their pose classes.

    fits : (H,) bool, the hypotheses that fit within noise (default: those in a class);
    truncated : the search stopped at its time limit; placements, confidence : the
    distinct placements weighed by evidence and the probability that the best pose is
    strictly right (scoring.placements); with ok_probability, "ok" needs that confidence
    (:func:`sure`), else the class probabilities decide (:func:`ambiguous`).
    """
    if len(arrays.cost) == 0:
        if truncated:
            return "time_limit", "the search stopped at its time limit before any hypothesis was complete"
        return "no_hypothesis", no_hypothesis_hint(model, contacts, tolerance)
    if truncated:
        return "time_limit", ("the search stopped at its time limit: the hypotheses found so far are returned, "
                              "but the true one may be missing; raise time_limit or narrow the tolerances")
    best_fits = bool(fits[0]) if fits is not None else any(0 in c.members for c in classes)
    if not best_fits:
        return "poor_fit", (f"the best hypothesis does not fit within noise (chi2 {arrays.chi2[0]:.3g} > "
                            f"{fit_threshold(contacts.n):.3g}): {POOR_FIT_REASONS}")
    if arrays.fit.underdetermined[0] and (arrays.covariance is None or not np.isfinite(arrays.covariance[0]).all()):
        return "underdetermined", ("the hypothesised facet normals leave pose directions free; see "
                                   "free_translation / free_rotation")
    symmetric = symmetry_note(model)
    if ok_probability is not None:
        status, hint = sure(model, placements, confidence, ok_probability)
        return status, "; ".join(h for h in (hint, symmetric) if h)
    if ambiguous(classes):
        shown = [c for c in classes if c.probability > AMBIGUOUS_PROBABILITY]
        hint = (f"{len(shown)} distinct placements fit within noise with probabilities "
                f"{', '.join(f'{c.probability:.2f}' for c in shown)}; add a prior or a touch")
        return "ambiguous", f"{hint}; {symmetric}" if symmetric else hint
    return "ok", symmetric


def sure(model, placements, confidence, ok_probability):
    """("ok", "") when the best pose is strictly right with probability ``confidence`` of at
    least ``ok_probability``; else ("ambiguous", the placements of LISTED_PROBABILITY or
    more with their probabilities) when others share the probability, or
    ("underdetermined", how loosely the contacts pin the best pose) when it has it alone."""
    if confidence >= ok_probability:
        return "ok", ""
    shown = [p for p in placements if p.probability >= LISTED_PROBABILITY]
    if len(shown) > 1:
        return "ambiguous", (f"{len(shown)} distinct placements fit within noise with probabilities "
                             f"{', '.join(f'{p.probability:.2f}' for p in shown)} (the best pose is strictly right "
                             f"with probability {confidence:.2f}, below {ok_probability:g}); add a prior or a touch")
    spread = _spread(placements[0].covariance, model.diameter) if placements else "not at all"
    return "underdetermined", (f"the contacts pin the best pose {spread}: it is strictly right (within 5 degrees "
                               f"and 5 % of the diameter) with probability {confidence:.2f}, below {ok_probability:g}; "
                               "add a touch")


def _spread(covariance, diameter):
    """How loosely a Laplace covariance (6, 6) or None pins a pose, in words (1 σ)."""
    if covariance is None:
        return "only up to a family of poses"
    rot = np.degrees(np.sqrt(np.linalg.eigvalsh(covariance[:3, :3])[-1]))
    trans = np.sqrt(np.linalg.eigvalsh(covariance[3:, 3:])[-1]) / diameter
    return f"to {rot:.2g} degrees and {100 * trans:.2g} % of the diameter (1 sigma, widest directions)"


def ambiguous(classes, threshold=AMBIGUOUS_PROBABILITY):
    """Whether a pose class other than the best holds more than ``threshold`` of the
    probability (symmetric twins of the best are in its class)."""
    return any(c.probability > threshold for c in classes[1:])


def symmetry_note(model):
    """A hint naming the object's symmetries, or "" when it has none."""
    found = symmetries(model)
    if not found:
        return ""
    return (f"the object is symmetric ({'; '.join(s.describe() for s in found)}): placements that differ by "
            "it fit the contacts equally and are reported as one placement")


def no_hypothesis_hint(model, contacts, tolerance):
    """Why nothing may have matched: contacts in other units, flipped normals, or tolerances."""
    why = reason("no_hypothesis", model, contacts, tolerance)
    if why != NO_HYPOTHESIS_REASONS:
        return why
    return (f"no facet tuple matches within tolerance (distance ±{tolerance.distance:.3g}, "
            f"angle ±{np.degrees(tolerance.angle):.3g}°): {why}")


def reason(status, model, contacts, tolerance):
    """The likely reasons that the hint of an empty or poor answer (``status`` in DIAGNOSED)
    ends in: contacts spread wider than the object, normals that all point away from the
    contacts, or the generic ones."""
    if status == "poor_fit":
        return POOR_FIT_REASONS
    spread = contacts.spread
    if spread > model.diameter + tolerance.distance:
        return units_message(spread, model.diameter)
    if normals_flipped(contacts):
        return ("all normals point away from the contacts' centroid: finger_normal points into the object "
                "(give object_normal for outward normals)")
    return NO_HYPOTHESIS_REASONS


def units_message(spread, diameter):
    """One line for contacts spread wider than the object can be."""
    ratio = spread / diameter
    guess = " millimetres vs metres?" if 100 <= ratio < 10_000 else " same units?"
    if ratio < FINGER_OFF_RATIO:
        guess += " (or a finger off the object)"
    return f"contacts span {spread:.4g} but the model is {diameter:.4g} across ({ratio:.3g} times):{guess}"


def normals_flipped(contacts):
    """Whether every finger normal points away from the contacts' centroid (n >= 3): a
    grasp's fingers press toward the object, so at least one must point inward."""
    if contacts.n < 3:
        return False
    to_centre = contacts.points.mean(axis=0) - contacts.points
    return bool(np.all(np.einsum("ij,ij->i", contacts.finger_normals, to_centre) < 0))
