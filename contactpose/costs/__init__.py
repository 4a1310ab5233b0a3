"""Contact costs: each measurement model of a contact written once, with its residual rows,
Jacobians, whitening and robust weight. Every optimizer, the ranking, the in-facet bound,
the sampler and the tracks call these; nothing else writes a contact residual.

* :mod:`.frame`: contacts in the object frame, p = Rᵀ(x̃ − t), ν = −Rᵀñ;
* :mod:`.facet`: the facet plane (r_n, r_o: eq. (7)'s normal term and the origin-invariant
  offset) and the facet triangle (the lateral residual r_l), batched and as packed rows;
* :mod:`.smooth`: the smooth normal interpolated over a facet, and crease edges;
* :mod:`.surface`: the surface feature (face, edge, vertex) with its normal cone;
* :mod:`.paper`: the paper's eq. (7), corrected (erratum 3);
* :mod:`.robust`: the per-contact robust kernels and their widths;
* :mod:`.association`: which facet explains a contact under a pose (the facet model's cost
  of each candidate).

Paper equations: eq. (7) -> :func:`paper.eq7_residuals`, :func:`paper.paper_cost` (and its
normal term, :func:`facet.normal_residuals`).
"""

from contactpose.costs.association import fitting_facets, fitting_members, nearest_fit_facets, nearest_members
from contactpose.costs.facet import (
    contact_chi2,
    contact_residuals,
    factor_rows,
    kernel_params,
    lateral_residuals,
    normal_residuals,
    offset_residuals,
    pack_contacts,
    whitened_cost,
)
from contactpose.costs.frame import object_frame
from contactpose.costs.paper import eq7_residuals, paper_cost, paper_offset_residuals
from contactpose.costs.robust import robust_rho
from contactpose.costs.smooth import smooth_data, touch_chi2
from contactpose.costs.surface import land, landing

__all__ = ["contact_chi2", "contact_residuals", "eq7_residuals", "factor_rows", "fitting_facets", "fitting_members",
           "kernel_params", "land", "landing", "lateral_residuals", "nearest_fit_facets", "nearest_members",
           "normal_residuals", "object_frame", "offset_residuals", "pack_contacts", "paper_cost",
           "paper_offset_residuals", "robust_rho", "smooth_data", "touch_chi2", "whitened_cost"]
