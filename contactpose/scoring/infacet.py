"""The in-facet check: can some pose within noise put every contact on its facet *triangle*?

The closed form poses a hypothesis on the facet *planes*; the lateral residual r_l (how far a
contact lies outside its triangle, costs.facet) is measured at that pose. Testing the full χ²
there drops true hypotheses: the best pose for planes and triangles together slides a contact
near an edge back inside (research/discrimination.md). So the test bounds the best full χ²
from below instead (solvers.polish.lowest_chi2_bound, which says how), and rejects a
hypothesis only when that bound exceeds the fit threshold.
"""

from __future__ import annotations

import numpy as np

from contactpose.solvers.polish import lowest_chi2_bound

#: Hypotheses checked at a time by within_noise(..., enough=...).
CHUNK = 64


def within_noise(model, contacts, arrays, tolerance, threshold, enough=None, deadline=None):
    """(H,) bool: the hypotheses whose best full χ² (triangles included) may be within
    ``threshold``, by the lower bound above. arrays : HypothesisArrays.

    enough : check in rank order, CHUNK at a time, and stop once this many hypotheses are
    known to fit: the first ``enough`` fitting ones are exact, the rest may be left False.
    deadline : a progress.Deadline; once passed (after the first chunk), the rest are left False.
    """
    ok = arrays.chi2 <= threshold
    # no pre-test on the plane χ² at the closed form: the closed form is not the minimiser of
    # the whitened plane χ², which may lie well below it (research/discrimination.md)
    check = np.flatnonzero(~ok)
    chunk = max(len(check), 1) if enough is None else CHUNK
    for lo in range(0, len(check), chunk):
        if enough is not None and np.count_nonzero(ok[:check[lo]]) >= enough:
            ok[check[lo]:] = False
            break
        if lo and deadline is not None and deadline.passed:
            ok[check[lo:]] = False
            break
        rows = check[lo:lo + chunk]
        ok[rows] = lowest_chi2_bound(model, contacts, arrays, rows, tolerance, threshold) <= threshold
    return ok

