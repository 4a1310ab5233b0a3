"""Ranking: the one constructor of ranked hypotheses, and the polish of their poses.

Every ranked set of hypotheses (:class:`~contactpose.types.HypothesisArrays`) is built by
:func:`hypothesis_arrays`: the residuals of the facet model (costs.facet; eq. (7) from costs.paper) at each
pose, the whitened χ² (research/errata.md, "Further decisions"), and the ranking cost (χ² for
the default method, eq. (7) ℒ for the paper's). Fingers left unassigned (facet -1,
``max_outliers``) have NaN residuals and add OUTLIER_PENALTY to χ² and cost.
"""

from __future__ import annotations

import numpy as np

from contactpose.costs import paper
from contactpose.costs.association import fitting_members
from contactpose.costs.facet import contact_residuals, normal_residuals, whitened_cost
from contactpose.options import fit_threshold, outlier_penalty
from contactpose.scoring.infacet import polished_poses
from contactpose.solvers.closed_form import fit_poses
from contactpose.solvers.surface import needs_surface, surface_fit
from contactpose.types import HypothesisArrays

#: localize(..., surface=True) fits this many of its best hypotheses on the surface (solvers.surface).
SURFACE_REFINE = 8
#: The default method moves the poses of at most this many hypotheses toward the least
#: full χ² (:func:`polish`), those whose plane χ² is at least POLISH_GAIN below the best.
POLISH = 256
POLISH_GAIN = 0.5


def hypothesis_arrays(model, contacts, facets, fit, tolerance, *, method="fast", paper_cost=None,
                      cost=None, covariance=None, probability=None, order=True, surface=None):
    """Hypotheses with their residuals and costs, ranked best first (unless ``order=False``).

    facets : (H, n) int (-1: unassigned); fit : PoseFit of the H poses; method : "fast"
    (cost = χ², residual column 3 the point-to-plane offset) or "paper" (cost = eq. (7)
    ℒ, ``paper_cost`` when LM computed it, column 3 the eq. (7) offset); cost : (H,) an
    explicit ranking cost (the factor graph's -log evidence); covariance : (H, 6, 6) and
    probability : (H,) from the factor graph. residuals : (H, n, 5). surface : the contact
    model's landing (cone (H, n, 3) object-frame normals ν*, gap (H, n) distances |p − q|,
    solvers.surface): r_n compares the contact with ν* instead of its facet's normal, and
    r_l is what of the gap the plane offset leaves, so that χ² is χ²_S.
    """
    facets = np.asarray(facets, dtype=np.int64)
    ok, safe = facets >= 0, np.maximum(facets, 0)
    offsets = model.planes.offsets[safe]
    r_n, r_o, r_l = contact_residuals(fit.R, fit.t, model.planes.normals[safe], offsets,
                                      model.triangles[safe], contacts.points, contacts.finger_normals)
    if surface is not None:
        r_n = normal_residuals(fit.R, np.nan_to_num(surface[0]), contacts.finger_normals)
        r_l = np.sqrt(np.maximum(np.nan_to_num(surface[1]) ** 2 - r_o**2, 0.0))
    if not ok.all():
        r_n, r_o, r_l = r_n * ok[..., None], r_o * ok, r_l * ok
    chi2 = whitened_cost(r_n, r_o, r_l, tolerance.normal_noise, tolerance.position_noise) + outlier_penalty(facets)
    offset_col = r_o
    if method == "paper":
        offset_col = paper.paper_offset_residuals(fit.t, contacts.points, contacts.finger_normals, offsets)
        cost = paper.paper_cost(r_n, offset_col) if paper_cost is None else paper_cost
    elif cost is None:
        cost = chi2
    residual = np.concatenate([r_n, offset_col[..., None], r_l[..., None]], axis=2)
    if not ok.all():
        residual[~ok] = np.nan
    arrays = HypothesisArrays(facets, fit.poses(), cost, chi2, residual, fit, covariance, probability)
    if not order or np.all(cost[1:] >= cost[:-1]):
        return arrays
    return arrays.take(np.argsort(cost, kind="stable"))


def closed_form_arrays(model, contacts, facets, tolerance, *, prior=None, angle_tol=None):
    """Given facet tuples posed in closed form and ranked as the default method ranks them:
    for tuples found some other way (the true tuple, a rescue, one tuple to sample).

    facets : (H, n) int -> HypothesisArrays, best χ² first. angle_tol : the closed form's
    threshold for parallel normals (default: the normal noise); prior : its translation
    picks the member of a translation family.
    """
    facets = np.asarray(facets, dtype=np.int64).reshape(-1, contacts.n)
    t0 = None if prior is None else np.broadcast_to(prior.pose[:3, 3], (len(facets), 3))
    fit = fit_poses(model.planes.normals[facets], model.planes.offsets[facets], contacts.points,
                    contacts.finger_normals, cost="invariant",
                    angle_tol=tolerance.normal_noise if angle_tol is None else angle_tol,
                    t0=t0, centroids=model.centroids[facets])
    return hypothesis_arrays(model, contacts, facets, fit, tolerance)


def refined_arrays(model, contacts, refinement, fit, tolerance):
    """A factor-graph Refinement as ranked hypotheses, in its order (most probable first).

    fit : PoseFit of the refined rows (its free directions are kept; R, t become the
    refined poses); cost = -log evidence (+inf when undetermined).
    """
    fit.R, fit.t = refinement.poses[:, :3, :3], refinement.poses[:, :3, 3]
    cost = -np.nan_to_num(refinement.log_evidence, nan=-np.inf)
    return hypothesis_arrays(model, contacts, refinement.facets, fit, tolerance, cost=cost,
                             covariance=refinement.covariance, probability=refinement.probability, order=False)


def polish(model, contacts, arrays, tolerance):
    """The ranked hypotheses with the poses of those that could beat the best moved toward
    the least full χ² (infacet.polished_poses), where that lowers it.

    The closed form fits the planes only, the ranking cost includes the triangles: a
    hypothesis whose plane χ² is at least POLISH_GAIN below the best full χ² (the best
    itself, when a contact lies outside its triangle) is moved, up to POLISH of them, best
    plane fit first. With patches, each moved contact gets the member facet nearest to it again.
    """
    lateral = arrays.residuals[..., 4]
    if not lateral.any():  # every contact inside its triangle: the plane χ² is the full χ²
        return arrays
    plane = arrays.chi2 - np.sum(lateral**2, axis=1) / tolerance.position_noise**2
    rows = np.flatnonzero(plane <= arrays.chi2.min() - POLISH_GAIN)
    rows = rows[np.argsort(plane[rows], kind="stable")[:POLISH]]
    if not len(rows):
        return arrays
    R, t = polished_poses(model, contacts, arrays, rows, tolerance, fit_threshold(contacts.n))
    facets = arrays.facets[rows]
    if model.patch_table is not None:
        facets = fitting_members(model, contacts, np.ascontiguousarray(model.patches.labels[facets]), R, t, tolerance)
    fit = arrays.fit.take(rows)
    fit.R, fit.t = R, t
    moved = hypothesis_arrays(model, contacts, facets, fit, tolerance, order=False)
    better = moved.chi2 < arrays.chi2[rows]
    if not better.any():
        return arrays
    return _replaced(arrays, rows[better], moved.take(np.flatnonzero(better)))


def surface_refined(model, contacts, arrays, tolerance, k=SURFACE_REFINE):
    """The ranked hypotheses with the best ``k`` determined ones posed on the surface
    (solvers.surface.surface_fit) where the contact model differs from their facets and the
    surface pose lowers χ²: their facets become those the contacts land on, their residuals
    those of the contact model. Re-ranked."""
    rows = np.flatnonzero(~arrays.fit.underdetermined)[:k]
    fits = []
    for r in rows:
        R, t, f = arrays.fit.R[r], arrays.fit.t[r], arrays.facets[r]
        if needs_surface(model, contacts, R, t, f, tolerance):
            fits.append((r, surface_fit(model, contacts, R, t, f, tolerance)))
    fits = [(r, got) for r, got in fits if got[5] + outlier_penalty(arrays.facets[r:r + 1])[0] < arrays.chi2[r]]
    if not fits:
        return arrays
    rows = np.array([r for r, _ in fits])
    fit = arrays.fit.take(rows)
    fit.R, fit.t = np.stack([got[0] for _, got in fits]), np.stack([got[1] for _, got in fits])
    facets = np.stack([np.where(arrays.facets[r] >= 0, got[2], -1) for r, got in fits])
    surface = np.stack([got[3] for _, got in fits]), np.stack([got[4] for _, got in fits])
    moved = hypothesis_arrays(model, contacts, facets, fit, tolerance, order=False, surface=surface)
    arrays = _replaced(arrays, rows, moved)
    _, first = np.unique(arrays.facets, axis=0, return_index=True)  # two fits may land alike: keep the better
    return arrays if len(first) == len(arrays.cost) else arrays.take(np.sort(first))


def _replaced(arrays, rows, moved):
    """A copy of the ranked hypotheses with rows ``rows`` replaced by ``moved`` (their
    new facets, poses, costs and residuals), re-ranked."""
    arrays = arrays.take(np.arange(len(arrays.cost)))
    for name in ("facets", "poses", "cost", "chi2", "residuals"):
        getattr(arrays, name)[rows] = getattr(moved, name)
    arrays.fit.R[rows], arrays.fit.t[rows] = moved.fit.R, moved.fit.t
    return arrays.take(np.argsort(arrays.cost, kind="stable"))
