"""The refine stage: the factor graph's refinement of the best hypotheses, ranked by evidence.

Which hypotheses, from where (:func:`refine_hypotheses`): without a prior the first k rows
of the closed-form ranking, from their closed-form poses. With a prior, rows whose rotation
contradicts the prior's are dropped (scoring.evidence.prior_gate), the rest are posed in
closed form with the prior as extra observations (solvers.closed_form.prior_closed_form) and
ranked by contact χ² plus prior Mahalanobis distance; the best k are refined from those
poses. When the model has patches (facets searched as one unit), each contact takes the
member facet of its patch that fits it best under the current pose, before and after LM
(costs.association.fitting_facets). Each is solved in its one-pose graph
(solvers.factor_graph.PoseGraph).

LM runs twice: a screening pass (solvers.factor_graph.SCREEN, loose stopping) over all k,
then a polish (solvers.factor_graph.lm_params) of the hypotheses the screen gives
probability >= POLISH_PROBABILITY.

Hypothesis scores:

* ``chi2 = 2 · graph.error(T*)``: the whitened χ² of the contacts (robust: Σ 2ρ(s_i)) plus
  the prior's squared Mahalanobis distance, plus :func:`outlier_penalty` per unassigned
  finger (facet -1, from ``localize(..., max_outliers=...)``: its rows in the factor are 0);
* ``covariance``: ``gtsam.Marginals`` at T*, 6×6, rotation first, in the tangent space
  at T* (right perturbation), of the graph without the point-to-facet rows (a hinge whose
  curvature is no information on the triangle's side; solvers.factor_graph.optimize);
* ``log_evidence``: the Laplace approximation of scoring.evidence;
* ``probability``: softmax of log_evidence over the refined hypotheses.

A hypothesis whose normals leave pose directions free (the closed form's free directions,
and no prior) has no Gaussian posterior: its covariance and log-evidence are NaN and it gets
probability 0 (all NaN when no refined hypothesis is determined), so such rows keep the
closed form's order. This holds even where LM's Hessian is regular: the point-to-facet
residual of a contact outside its triangle pins a free direction at the triangle's edge,
which places one member of the family, not the pose (research/discrimination.md, "The
factor graph on underdetermined hypotheses").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from contactpose.contacts import Contacts
from contactpose.costs import facet
from contactpose.costs.association import fitting_facets
from contactpose.costs.facet import pack_contacts
from contactpose.errors import ContactPoseError, check_count
from contactpose.options import DEFAULT_REFINE, check_robust, fit_threshold, outlier_penalty
from contactpose.scoring.evidence import log_evidence, normalise, prior_gate, prior_mahalanobis2
from contactpose.solvers.closed_form import prior_closed_form
from contactpose.solvers.factor_graph import SCREEN, PoseGraph, lm_params
from contactpose.types import HypothesisArrays, PosePrior

log = logging.getLogger(__name__)

#: After LM, contacts that another member of their patch fits better move to it and LM runs
#: again, at most this many times per hypothesis (see :func:`fitting_facets`).
REASSIGN_ROUNDS = 2


#: With a prior, when no hypothesis agrees with it and fits the contacts within noise,
#: ``localize`` searches again with the pair tolerances widened by this factor (3σ gates
#: become 6σ; research/factor_graph.md, "Rescue").
RESCUE_WIDEN = 2.0


POLISH_PROBABILITY = 1e-3


@dataclass
class Refinement:
    """Refined hypotheses, most probable first.

    index : (K,) int rows of the input HypothesisArrays; facets : (K, n) int, the facets at
    the refined pose (with patches in the model, each contact's nearest member of its patch;
    rows that end on the same facets are merged, so K can be less than asked for);
    poses : (K, 4, 4) refined T_world_object; start : (K, 4, 4) LM initial values;
    chi2 : (K,) 2·graph.error at the optimum (robust contact cost + prior term) plus
    :func:`outlier_penalty` for unassigned fingers;
    contact_chi2 : (K,) plain whitened χ² of the assigned contacts (no kernel, no prior);
    covariance : (K, 6, 6) marginal covariance (rotation first), NaN when undetermined;
    log_evidence : (K,) Laplace log-evidence (NaN when undetermined); probability : (K,);
    iterations : (K,) LM iterations; determined : (K,) bool; seconds, cpu_seconds : (K,) wall
    and thread CPU time of each refinement (graph update, LM, marginals); agreeing : input rows
    that passed scoring.evidence.prior_gate (-1 without a prior; 0 means all were refined regardless).
    """

    index: np.ndarray
    facets: np.ndarray
    poses: np.ndarray
    start: np.ndarray
    chi2: np.ndarray
    contact_chi2: np.ndarray
    covariance: np.ndarray
    log_evidence: np.ndarray
    probability: np.ndarray
    iterations: np.ndarray
    determined: np.ndarray
    seconds: np.ndarray
    cpu_seconds: np.ndarray
    robust: str = "huber"
    has_prior: bool = False
    agreeing: int = -1

    def __len__(self):
        return len(self.index)


def refine_hypotheses(model, contacts, arrays, tolerance, *, prior=None, robust="huber", k=DEFAULT_REFINE,
                      point_to_facet=True, params=None):
    """Refine the best k hypotheses in a GTSAM factor graph and score them.

    model : ObjectModel; contacts : Contacts; arrays : HypothesisArrays ranked by the closed
    form (rows with n facets each, -1 for an unassigned finger); tolerance : Tolerance (σ_x =
    position_noise, σ_n = normal_noise); prior : PosePrior or None; robust : "huber" | "cauchy" | "none"; k : how
    many to refine (0: all); point_to_facet : add the lateral residual; params : optional
    gtsam.LevenbergMarquardtParams for a single pass (default: a SCREEN pass over all
    k, then an lm_params polish of those with probability >= POLISH_PROBABILITY).

    Which k: without a prior the first k rows of ``arrays`` (closed-form ranking), started
    from their closed-form poses. With a prior every row is re-scored by its contact χ² plus
    the prior's Mahalanobis distance at solvers.closed_form.prior_closed_form, the best k are refined
    from those poses (a closed-form ranking blind to the prior can push the true hypothesis
    of a near-symmetric object past k). Returns a :class:`Refinement`, most probable first.
    """
    _check(model, contacts, arrays, tolerance, prior, robust, k)
    facets_all = np.asarray(arrays.facets)
    if len(facets_all) == 0:
        return _empty(contacts.n, robust, prior)
    idx, starts, facets, agreeing = _select(model, contacts, arrays, tolerance, prior, k, point_to_facet)
    screen, polish = (params, None) if params is not None else (lm_params(**SCREEN), lm_params())
    packed = pack_contacts(model, contacts, facets)
    graph = PoseGraph(packed[0], tolerance, robust, point_to_facet, prior)
    prior_cov = None if prior is None else prior.covariance_matrix()
    K = len(idx)
    free = np.asarray(arrays.fit.underdetermined)[idx] if prior is None else np.zeros(K, bool)
    penalty = outlier_penalty(facets)
    poses, chi2, cov = starts.copy(), np.zeros(K), np.zeros((K, 6, 6))
    iters, secs, cpu_secs = np.zeros(K, int), np.zeros(K), np.zeros(K)

    def refine(rows, lm):
        for j in rows:
            for _ in range(1 + REASSIGN_ROUNDS):
                poses[j], chi2[j], cov[j], it, sec, cpu = graph.solve(packed[j], poses[j], lm)
                if free[j]:  # the normals leave directions free: no Gaussian posterior
                    cov[j] = np.nan
                chi2[j] += penalty[j]
                iters[j] += it
                secs[j] += sec
                cpu_secs[j] += cpu
                moved = fitting_facets(model, contacts, facets[j:j + 1], poses[j:j + 1], tolerance)[0]
                if np.array_equal(moved, facets[j]):
                    break
                facets[j] = moved
                packed[j] = pack_contacts(model, contacts, moved)

    refine(range(K), screen)
    if polish is not None:
        refine(np.flatnonzero(normalise(log_evidence(chi2, cov, prior_cov)) >= POLISH_PROBABILITY), polish)
    # rows that ended on the same facets are one hypothesis: keep the most probable
    log_ev = log_evidence(chi2, cov, prior_cov)
    contact_chi2 = facet.contact_chi2(model, contacts, facets, poses, tolerance, point_to_facet)
    # without a prior a pose family has no evidence to rank it by: one that fits within noise
    # (χ² <= fit_threshold) is kept before a determined pose that does not
    fits = prior is not None or contact_chi2 + penalty <= fit_threshold(contacts.n)
    order = np.lexsort((np.arange(K), -np.nan_to_num(log_ev, nan=-np.inf), ~np.broadcast_to(fits, (K,))))
    _, first = np.unique(facets[order], axis=0, return_index=True)
    order = order[np.sort(first)]
    prob = normalise(log_ev[order])
    determined = np.isfinite(cov[order]).all(axis=(1, 2))
    return Refinement(idx[order], facets[order], poses[order], starts[order], chi2[order], contact_chi2[order],
                      cov[order], log_ev[order], prob, iters[order], determined, secs[order],
                      cpu_secs[order], robust, prior is not None, agreeing)


def _select(model, contacts, arrays, tolerance, prior, k, point_to_facet):
    """Rows to refine, their LM start poses and facets: (K,) int, (K, 4, 4), (K, n) int, and
    how many rows passed the prior gate (-1 without a prior)."""
    h = len(arrays.facets)
    if prior is not None:
        return _select_with_prior(model, contacts, arrays, tolerance, prior, k, point_to_facet)
    idx = np.arange(h if k == 0 else min(k, h))
    T = np.asarray(arrays.poses)[idx]
    return idx, T, fitting_facets(model, contacts, np.asarray(arrays.facets)[idx], T, tolerance), -1


def _select_with_prior(model, contacts, arrays, tolerance, prior, k, point_to_facet):
    """_select with a prior: the rows that pass the prior gate (all, when none does), posed in
    closed form with the prior, the best k by contact χ² plus the prior's Mahalanobis distance."""
    h = len(arrays.facets)
    rows = np.flatnonzero(prior_gate(model, arrays, tolerance, prior))
    agreeing = len(rows)
    if len(rows) == 0:  # the prior contradicts every hypothesis: rank them all anyway
        log.warning("vision prior inconsistent with all %d hypotheses' rotations", h)
        rows = np.arange(h)
    facets = np.asarray(arrays.facets)[rows]
    ok, safe = facets >= 0, np.maximum(facets, 0)  # an unassigned finger enters with weight 0
    R, t = prior_closed_form(model.planes.normals[safe] * ok[..., None], model.planes.offsets[safe] * ok,
                             contacts.points, contacts.finger_normals, tolerance, prior)
    T = np.zeros((len(rows), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, t, 1.0
    facets = fitting_facets(model, contacts, facets, T, tolerance)
    score = (facet.contact_chi2(model, contacts, facets, T, tolerance, point_to_facet) + outlier_penalty(facets)
             + prior_mahalanobis2(R, t, prior))
    best = np.argsort(score, kind="stable")[:len(rows) if k == 0 else k]
    return rows[best], T[best], facets[best], agreeing


def _check(model, contacts, arrays, tolerance, prior, robust, k):
    check_robust(robust)
    check_count(k, "k", minimum=0)
    if not isinstance(contacts, Contacts):
        raise ContactPoseError(f"contacts must be a contactpose.Contacts, got {type(contacts).__name__}")
    if not isinstance(arrays, HypothesisArrays):
        raise ContactPoseError(f"arrays must be a HypothesisArrays, got {type(arrays).__name__}")
    if prior is not None and not isinstance(prior, PosePrior):
        raise ContactPoseError(f"prior must be a contactpose.PosePrior or None, got {type(prior).__name__}")
    facets = np.asarray(arrays.facets)
    if facets.ndim != 2 or (len(facets) and facets.shape[1] != contacts.n):
        raise ContactPoseError(f"arrays.facets must have shape (H, {contacts.n}), got {facets.shape}")
    if len(facets) and (facets.min() < -1 or facets.max() >= model.num_facets):
        raise ContactPoseError(f"arrays.facets must index the model's {model.num_facets} facets (-1: unassigned)")


def _empty(n, robust, prior):
    z = np.zeros(0)
    return Refinement(np.zeros(0, int), np.zeros((0, n), int), np.zeros((0, 4, 4)), np.zeros((0, 4, 4)),
                      z, z, np.zeros((0, 6, 6)), z, z, np.zeros(0, int), np.zeros(0, bool), z, z,
                      robust, prior is not None, 0 if prior is not None else -1)
