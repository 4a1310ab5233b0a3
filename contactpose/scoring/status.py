"""The one status rule: what the ranked hypotheses and their pose classes say.

* ``no_hypothesis``: nothing matched (the hint says why it may be);
* ``underdetermined``: the best hypothesis's normals leave pose directions free (and no
  covariance from a prior pins them);
* ``ambiguous``: more than one distinct placement fits within noise (with the factor
  graph's probabilities: the classes other than the best hold more than
  AMBIGUOUS_PROBABILITY);
* ``ok`` otherwise.
"""

from __future__ import annotations

import numpy as np

from contactpose.types import AMBIGUOUS_PROBABILITY, fit_threshold


def status(model, contacts, arrays, classes, tolerance):
    """Status and hint from the ranked hypotheses and their pose classes."""
    if len(arrays.cost) == 0:
        return "no_hypothesis", no_hypothesis_hint(model, contacts, tolerance)
    if arrays.fit.underdetermined[0] and (arrays.covariance is None or not np.isfinite(arrays.covariance[0]).all()):
        return "underdetermined", "the hypothesised facet normals leave pose directions free; see free_translation / free_rotation"
    if len(classes) > 1 and (arrays.probability is None or ambiguous(classes)):
        return "ambiguous", (f"{len(classes)} distinct placements fit within noise (probabilities "
                             f"{', '.join(f'{c.probability:.2f}' for c in classes[:4])}); add a prior or a touch")
    if not classes:
        return "ok", f"the best hypothesis does not fit within noise (chi2 {arrays.chi2[0]:.3g} > {fit_threshold(contacts.n):.3g})"
    return "ok", ""


def ambiguous(classes, threshold=AMBIGUOUS_PROBABILITY):
    """Whether the pose classes other than the best hold more than ``threshold`` of the
    probability together (symmetric twins of the best are in its class)."""
    return len(classes) > 1 and 1.0 - classes[0].probability > threshold


def no_hypothesis_hint(model, contacts, tolerance):
    spread = contacts.spread
    if spread > model.diameter + tolerance.distance:
        return (f"contacts are {spread:.4g} apart but the object is only {model.diameter:.4g} across: "
                "wrong units?")
    return (f"no facet tuple matches within tolerance (distance ±{tolerance.distance:.3g}, "
            f"angle ±{np.degrees(tolerance.angle):.3g}°): noise too small, wrong units, or a finger off the object?")
