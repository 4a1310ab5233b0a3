"""Pose solvers: a pose per hypothesis, and poses moved where the contacts fit better.

* :mod:`.closed_form`: every hypothesis at once, Wahba's rotation then linear translation
  (the default method's origin-invariant cost, or eq. (7) exactly), with or without a prior;
* :mod:`.lm`: the paper's Levenberg–Marquardt on eq. (7) (§4);
* :mod:`.polish`: the full χ² (planes and triangles) linearised about a pose: its
  minimisation (polished poses) and its lower bound (the in-facet test);
* :mod:`.surface`: poses on the surface contact model;
* :mod:`.factor_graph`: GTSAM graphs of a pose (contact factors, prior, one-pose graph).

Paper equations: eq. (6), the measured plane moved into the object frame, and eq. (7), its
comparison with the facet's -> :func:`lm.fit_lm` (minimised as published) and
:func:`closed_form.fit_poses` with ``cost="paper"`` (its exact minimum); the cost itself is
costs.paper.
"""

from contactpose.solvers.closed_form import fit_poses, prior_closed_form, wahba
from contactpose.solvers.factor_graph import (
    PoseGraph,
    contact_factor,
    lm_params,
    optimize,
    prior_factor,
    reweighted_contact_factors,
    reweighted_smooth_factors,
    smooth_contact_factor,
)
from contactpose.solvers.lm import fit_lm, fit_lm_all
from contactpose.solvers.polish import lowest_chi2_bound, polished, polished_poses
from contactpose.solvers.surface import needs_surface, surface_factor, surface_fit, surface_poses

__all__ = ["PoseGraph", "contact_factor", "fit_lm", "fit_lm_all", "fit_poses", "lm_params", "lowest_chi2_bound",
           "needs_surface", "optimize", "polished", "polished_poses", "prior_closed_form", "prior_factor",
           "reweighted_contact_factors", "reweighted_smooth_factors", "smooth_contact_factor", "surface_factor",
           "surface_fit", "surface_poses", "wahba"]
