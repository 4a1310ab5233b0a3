"""Ranking: the one constructor of ranked hypotheses, and their rows replaced by better ones.

Every ranked set of hypotheses (:class:`~contactpose.types.HypothesisArrays`) is built by
:func:`hypothesis_arrays`: the residuals of the facet model (costs.facet; eq. (7) from costs.paper) at each
pose, the whitened χ² (research/errata.md, "Further decisions"), and the ranking cost (χ² for
the default method, eq. (7) ℒ for the paper's: contactpose.paper passes it). Fingers left unassigned (facet -1,
``max_outliers``) have NaN residuals and add OUTLIER_PENALTY to χ² and cost.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from contactpose.costs.facet import contact_residuals, normal_residuals, whitened_cost
from contactpose.options import outlier_penalty
from contactpose.solvers.closed_form import fit_poses
from contactpose.types import HypothesisArrays


def hypothesis_arrays(model, contacts, facets, fit, tolerance, *, cost=None, offset=None, covariance=None,
                      probability=None, order=True, surface=None):
    """Hypotheses with their residuals and costs, ranked best first (unless ``order=False``).

    facets : (H, n) int (-1: unassigned); fit : PoseFit of the H poses; cost : (H,) the
    ranking cost (default: χ²; the factor graph's -log evidence, eq. (7)'s ℒ for the paper's
    method); offset : (H, n) residual column 3 instead of the point-to-plane offset (eq. (7)'s
    offset, for the paper's method); covariance : (H, 6, 6) and
    probability : (H,) from the factor graph. residuals : (H, n, 5). surface : the contact
    model's landing (cone (H, n, 3) object-frame normals ν*, gap (H, n) distances |p − q|,
    solvers.surface): r_n compares the contact with ν* instead of its facet's normal, and
    r_l is what of the gap the plane offset leaves, so that χ² is χ²_S.
    """
    facets = np.asarray(facets, dtype=np.int64)
    ok, safe = facets >= 0, np.maximum(facets, 0)
    cone = None if surface is None else normal_residuals(fit.R, np.nan_to_num(surface[0]), contacts.finger_normals)
    r_n, r_o, r_l = contact_residuals(fit.R, fit.t, model.planes.normals[safe], model.planes.offsets[safe],
                                      model.triangles[safe], contacts.points, contacts.finger_normals)
    if surface is not None:  # r_n to the cone's direction ν*, r_l what of the gap r_o leaves
        r_n, r_l = cone, np.sqrt(np.maximum(np.nan_to_num(surface[1]) ** 2 - r_o**2, 0.0))
    if not ok.all():
        r_n, r_o, r_l = r_n * ok[..., None], r_o * ok, r_l * ok
    chi2 = whitened_cost(r_n, r_o, r_l, tolerance.normal_noise, tolerance.position_noise) + outlier_penalty(facets)
    residual = np.concatenate([r_n, (r_o if offset is None else offset)[..., None], r_l[..., None]], axis=2)
    if not ok.all():
        residual[~ok] = np.nan
    arrays = HypothesisArrays(facets, fit.poses(), chi2 if cost is None else cost, chi2, residual, fit, covariance,
                              probability)
    return ranked(arrays) if order else arrays


def ranked(arrays, cost=None):
    """The hypotheses in order of ``cost`` (H,) (default: their own), the first on a tie first;
    ``cost`` becomes theirs."""
    if cost is not None:
        arrays = dataclasses.replace(arrays, cost=np.asarray(cost))
    if np.all(arrays.cost[1:] >= arrays.cost[:-1]):
        return arrays
    return arrays.take(np.argsort(arrays.cost, kind="stable"))


def closed_form_arrays(model, contacts, facets, tolerance, *, prior=None, angle_tol=None, order=True):
    """Given facet tuples posed in closed form and ranked as the default method ranks them:
    for tuples found some other way (the true tuple, a rescue, one tuple to sample).

    facets : (H, n) int -> HypothesisArrays, best χ² first. angle_tol : the closed form's
    threshold for parallel normals (default: the normal noise); prior : its translation
    picks the member of a translation family; order=False keeps the tuples' order.
    """
    facets = np.asarray(facets, dtype=np.int64).reshape(-1, contacts.n)
    t0 = None if prior is None else np.broadcast_to(prior.pose[:3, 3], (len(facets), 3))
    fit = fit_poses(model.planes.normals[facets], model.planes.offsets[facets], contacts.points,
                    contacts.finger_normals, cost="invariant",
                    angle_tol=tolerance.normal_noise if angle_tol is None else angle_tol,
                    t0=t0, centroids=model.centroids[facets])
    return hypothesis_arrays(model, contacts, facets, fit, tolerance, order=order)


def refined_arrays(model, contacts, refinement, fit, tolerance):
    """A factor-graph Refinement as ranked hypotheses, in its order (most probable first).

    fit : PoseFit of the refined rows (its free directions are kept; R, t become the
    refined poses); cost = -log evidence (+inf when undetermined).
    """
    fit.R, fit.t = refinement.poses[:, :3, :3], refinement.poses[:, :3, 3]
    cost = -np.nan_to_num(refinement.log_evidence, nan=-np.inf)
    return hypothesis_arrays(model, contacts, refinement.facets, fit, tolerance, cost=cost,
                             covariance=refinement.covariance, probability=refinement.probability, order=False)


def replaced(arrays, rows, moved):
    """A copy of the ranked hypotheses with rows ``rows`` replaced by ``moved`` (their
    new facets, poses, costs, residuals and fits: what each pose leaves free too), re-ranked."""
    arrays = arrays.take(np.arange(len(arrays.cost)))
    for name in ("facets", "poses", "cost", "chi2", "residuals"):
        getattr(arrays, name)[rows] = getattr(moved, name)
    for f in dataclasses.fields(arrays.fit):
        getattr(arrays.fit, f.name)[rows] = getattr(moved.fit, f.name)
    return arrays.take(np.argsort(arrays.cost, kind="stable"))
