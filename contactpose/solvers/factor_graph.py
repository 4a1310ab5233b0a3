"""Factor-graph refinement of ranked hypotheses in GTSAM: contact factors, vision prior,
robust kernels, marginal covariances and hypothesis probabilities.

One ``Pose3`` variable per hypothesis: T_world_object. Its graph holds

* one batched contact factor (a ``gtsam.CustomFactor`` over all n contacts) whose error
  and analytic Jacobian are the facet model's whitened rows (costs.facet.contact_rows:
  normal, offset and, with point_to_facet, lateral rows; rotation first, right perturbation),
  each contact's block under the robust kernel (costs.robust);
* optionally a ``PriorFactorPose3`` from a :class:`~contactpose.types.PosePrior`.

Noise: the factor uses a ``Unit`` noise model and whitens inside (divides by σ), because
the robust kernel must act on whitened errors. Robust kernels act per contact, on the norm
s_i of the contact's whitened block, not on the whole factor: GTSAM's ``noiseModel.Robust``
reweights a factor's error as one block, which on a batched factor would down-weight all
contacts together. The optimum is the robust M-estimate ``argmin Σ_i ρ(s_i)``; one factor per
contact with ``noiseModel.Robust`` (block reweighting, :func:`reweighted_contact_factors`)
has the same cost and optimum (a test).

Which hypotheses, from where (:func:`refine_hypotheses`): without a prior the first k rows
of the closed-form ranking, from their closed-form poses. With a prior, rows whose rotation
contradicts the prior's are dropped (:func:`prior_gate`), the rest are posed in closed form
with the prior as extra observations (:func:`prior_closed_form`) and ranked by contact χ²
plus prior Mahalanobis distance; the best k are refined from those poses. When the model
has patches (facets searched as one unit), each contact takes the member facet of its patch
that fits it best under the current pose, before and after LM (:func:`fitting_facets`).

LM runs twice: a screening pass (:data:`SCREEN`, loose stopping) over all k, then a polish
(:func:`lm_params`) of the hypotheses the screen gives probability >= POLISH_PROBABILITY.

Hypothesis scores:

* ``chi2 = 2 · graph.error(T*)``: the whitened χ² of the contacts (robust: Σ 2ρ(s_i)) plus
  the prior's squared Mahalanobis distance, plus :func:`outlier_penalty` per unassigned
  finger (facet -1, from ``localize(..., max_outliers=...)``: its rows in the factor are 0);
* ``covariance``: ``gtsam.Marginals`` at T*, 6×6, rotation first, in the tangent space
  at T* (right perturbation), of the graph without the point-to-facet rows (a hinge whose
  curvature is no information on the triangle's side; :func:`_optimize`);
* ``log_evidence``: Laplace approximation of log ∫ p(z | T, h) p(T) dT,
  ``-½ chi2 + ½ log det(2π Σ) - ½ log det(2π Σ_prior)`` (the last term only with a prior;
  without one the flat prior is a constant). Terms equal for all hypotheses of one call
  (the Gaussian normalisation of the n contacts) are dropped, so only differences matter.
  With a robust kernel exp(-ρ) stands in for the Gaussian likelihood;
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
import time
from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.contacts import Contacts
from contactpose.costs import facet
from contactpose.costs.association import fitting_facets
from contactpose.costs.facet import contact_rows, factor_dim, kernel_params, pack_contacts
from contactpose.costs.robust import reweighted_noise
from contactpose.costs.smooth import smooth_data, smooth_rows
from contactpose.errors import ContactPoseError, check_count
from contactpose.options import DEFAULT_REFINE, check_robust, fit_threshold, outlier_penalty
from contactpose.solvers.closed_form import wahba
from contactpose.types import HypothesisArrays, PosePrior

log = logging.getLogger(__name__)

#: χ²₃ quantile at 1 - 1e-9: a hypothesis whose rotation disagrees more with the prior's is
#: not screened when a prior is given (see :func:`prior_gate`).
PRIOR_GATE_CHI2 = 44.841275388361254
#: After LM, contacts that another member of their patch fits better move to it and LM runs
#: again, at most this many times per hypothesis (see :func:`fitting_facets`).
REASSIGN_ROUNDS = 2
#: With a prior, when no hypothesis agrees with it and fits the contacts within noise,
#: ``localize`` searches again with the pair tolerances widened by this factor (3σ gates
#: become 6σ; research/factor_graph.md, "Rescue").
RESCUE_WIDEN = 2.0
#: The one variable of every graph.
POSE_KEY = 0


# ---------------------------------------------------------------- factors ---

def contact_error(data, params, e, J, key, this, values, H):
    """CustomFactor error function of costs.facet.contact_rows; bind everything before ``this``
    with functools.partial.

    data : (n, 20); params : (6,); e : (m,) and J : (m, 6) work buffers (GTSAM copies what
    it is given, so they can be reused); key : the Pose3 key.
    """
    if H is None:
        contact_rows(values.atPose3(key).matrix(), data, params, e, _NO_JACOBIAN)
        return e
    contact_rows(values.atPose3(key).matrix(), data, params, e, J)
    H[0] = J
    return e


_NO_JACOBIAN = np.empty((0, 6))


def contact_factor(data, params, key=POSE_KEY, noise=None):
    """The batched contact factor of one hypothesis: a gtsam.CustomFactor on ``key``.

    data : (n, 20) from :func:`pack_contacts`; params : from :func:`kernel_params`; noise :
    the factor's noise model on its whitened rows (default: unit).
    """
    m = factor_dim(len(data), params[4] != 0.0)
    fn = partial(contact_error, data, params, np.empty(m), np.empty((m, 6)), key)
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(m) if noise is None else noise, [key], fn)


def reweighted_contact_factors(data, tolerance, robust, point_to_facet, key=POSE_KEY):
    """The contact factor split into one gtsam.CustomFactor per contact, each with the kernel
    as GTSAM's reweighting (:func:`reweighted_noise`) instead of the batched factor's square
    root. The cost is the same, contact by contact; the linearization differs. The square
    root's Jacobian holds the kernel's exact slope, and a full Gauss–Newton step on it
    overshoots a contact in the kernel's linear part about twofold: iSAM2's Gauss–Newton
    steps then cycle. Reweighting is the iteratively reweighted least squares step, which
    does not (research/tracking.md, "Gauss–Newton steps"). data : (n, 20) from
    :func:`pack_contacts`. -> [gtsam.CustomFactor] (n)"""
    params = kernel_params(tolerance, "none", point_to_facet)
    noise = reweighted_noise(factor_dim(1, point_to_facet), robust)
    return [contact_factor(np.ascontiguousarray(data[i:i + 1]), params, key, noise) for i in range(len(data))]


def smooth_contact_factor(model, contacts, facets, tolerance, key=POSE_KEY, point_to_facet=True, robust="huber"):
    """The batched contact factor with each contact's normal residual taken against the
    normal interpolated over its facet from its corners' normals (ObjectModel.smooth_normals)
    at the contact's place, n(p) = m(p)/|m(p)|, p = Rᵀ(x̃ - t), instead of the facet's own
    normal: on a fine tessellation of a smooth surface the normal then changes continuously
    from facet to facet. The normal rows, in the object frame, are r_n = W_f (n(p) + Rᵀ ñ)
    (|r_n| is that of R n(p) + ñ whitened in the world), W_f = C_f^(-1/2) with C_f = σ_n² I +
    S_f + σ_x² Dn Dnᵀ: the sensor's normal noise; the mesh's own normals straying from n(p)
    (S_f, ObjectModel.normal_scatter); and the contact's position noise along the surface,
    which moves the place where n is read (Dn at the facet's centroid, ObjectModel.normal_whitening).
    The offset and lateral rows are the contact factor's, and so is the per-contact robust
    kernel. A gtsam.CustomFactor on ``key``."""
    data, smooth = smooth_data(model, contacts, facets, tolerance)
    return _smooth_factor(data, smooth, kernel_params(tolerance, robust, point_to_facet), True, key,
                          gtsam.noiseModel.Unit.Create(factor_dim(len(data), point_to_facet)))


def reweighted_smooth_factors(data, smooth, tolerance, robust, point_to_facet, key=POSE_KEY, place=True):
    """:func:`smooth_contact_factor` split into one factor per contact, the kernel as GTSAM's
    reweighting, as :func:`reweighted_contact_factors`. data, smooth : from :func:`smooth_data`;
    place : False drops n(p)'s change with the contact's place from the normal rows' Jacobian
    (∂/∂ω = W [Rᵀñ]×, ∂/∂v = 0), as for the covariance of a faceted surface, whose normal is
    constant over a facet (research/tracking.md, "Smooth normals by default on fine meshes").
    -> [gtsam.CustomFactor] (n)"""
    params = kernel_params(tolerance, "none", point_to_facet)
    noise = reweighted_noise(factor_dim(1, point_to_facet), robust)
    return [_smooth_factor(data[i:i + 1].copy(), smooth[i:i + 1].copy(), params, place, key, noise)
            for i in range(len(data))]


def _smooth_factor(data, smooth, params, place, key, noise):
    m = factor_dim(len(data), params[4] != 0.0)
    fn = partial(_smooth_error, data, params, smooth, place, np.empty(m), np.empty((m, 6)), key)
    return gtsam.CustomFactor(noise, [key], fn)


def _smooth_error(data, params, smooth, place, e, J, key, this, values, H):
    """CustomFactor error function of the smooth factor, as :func:`contact_error`."""
    smooth_rows(values.atPose3(key).matrix(), data, params, smooth, place, e, J)
    if H is not None:
        H[0] = J
    return e


def prior_factor(prior, key=POSE_KEY):
    """PriorFactorPose3 of a PosePrior, Gaussian with its (6, 6) covariance (rotation first)."""
    noise = gtsam.noiseModel.Gaussian.Covariance(prior.covariance_matrix())
    return gtsam.PriorFactorPose3(key, gtsam.Pose3(prior.pose), noise)


def lm_params(max_iterations=30, relative_tol=1e-5, absolute_tol=1e-6):
    """LM settings for one 6-dof pose started near its optimum.

    Diagonal (Marquardt) damping: the whitened Hessian's eigenvalues span ~1e3..1e8
    (radians vs. metres over σ_x), so GTSAM's default λ·I barely shortens a step, and a
    Gauss-Newton step that carries a contact across its triangle's edge (where r_l sets
    in) made LM give up at λ_max short of the optimum on 67 of 200 banana hypotheses;
    with λ·diag(JᵀJ) it shortens the step and goes on. λ starts at 1e-5 (Gauss-Newton steps near the optimum).
    Stops when ½χ² decreases by less than ``relative_tol`` of itself or ``absolute_tol``.
    The defaults (polish) move the pose by ~1e-2 σ or less; :data:`SCREEN` is looser.
    """
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setDiagonalDamping(True)
    params.setlambdaInitial(1e-5)
    params.setRelativeErrorTol(relative_tol)
    params.setAbsoluteErrorTol(absolute_tol)
    return params


#: Screening pass over all k hypotheses: stop when ½χ² falls by < 1e-3 relative or 1e-2
#: absolute (median 5 instead of 8 LM iterations on the banana's top-20 hypotheses, whose
#: false ones converge only linearly in the kinks of r_l and the robust zones). A hypothesis the screen gives at least
#: POLISH_PROBABILITY is then polished with :func:`lm_params` from where the screen stopped.
SCREEN = dict(max_iterations=15, relative_tol=1e-3, absolute_tol=1e-2)
POLISH_PROBABILITY = 1e-3


# ----------------------------------------------------- prior-aware start ---

def prior_closed_form(obj_normals, obj_offsets, points, finger_normals, tolerance, prior):
    """Closed-form poses of H hypotheses with the vision prior as extra observations.

    Rotation: Wahba on the whitened normals plus the prior's axes, Σ_i |R n_k + ñ_i|²/σ_n²
    + |R - R_p|_F² / (2 σ_r²) (σ_r² the mean rotation variance of the prior). Translation:
    exact least squares of Σ_i r_o²/σ_x² + (t - t_p)ᵀ Σ_t⁻¹ (t - t_p) given R, with the prior's
    translation covariance rotated into the world. Always a unique pose (the prior fills any
    direction the normals leave free), so it serves as LM start and for screening.

    obj_normals : (H, n, 3), obj_offsets : (H, n), points, finger_normals : (n, 3)
    -> R (H, 3, 3), t (H, 3)
    """
    h, n, _ = obj_normals.shape
    cov = prior.covariance_matrix()
    Rp, tp = prior.pose[:3, :3], prior.pose[:3, 3]
    w_r = 1.0 / np.sqrt(2.0 * np.trace(cov[:3, :3]) / 3.0)
    w_n = 1.0 / tolerance.normal_noise
    obj = np.concatenate([obj_normals * w_n, np.broadcast_to(np.eye(3) * w_r, (h, 3, 3))], axis=1)
    world = np.concatenate([-finger_normals * w_n, Rp.T * w_r], axis=0)  # rows R_p e_j
    R = wahba(obj, world)
    A = np.einsum("hij,hnj->hni", R, obj_normals)  # rows (R n_k)ᵀ
    b = np.einsum("hni,ni->hn", A, points) + obj_offsets
    info_t = np.linalg.inv(Rp @ cov[3:, 3:] @ Rp.T)
    lhs = np.einsum("hni,hnj->hij", A, A) / tolerance.position_noise**2 + info_t
    rhs = np.einsum("hni,hn->hi", A, b) / tolerance.position_noise**2 + info_t @ tp
    return R, np.linalg.solve(lhs, rhs[..., None])[..., 0]


def prior_mahalanobis2(R, t, prior):
    """Squared Mahalanobis distance of poses from the prior, ξ = (Log(R_pᵀR), R_pᵀ(t - t_p)).

    R : (H, 3, 3), t : (H, 3)  ->  (H,). The translation part is the first-order Pose3 log.
    """
    Rp, tp = prior.pose[:3, :3], prior.pose[:3, 3]
    xi = np.concatenate([Rotation.from_matrix(np.einsum("ji,hjk->hik", Rp, R)).as_rotvec(),
                         (t - tp) @ Rp], axis=1)
    return np.einsum("hi,ij,hj->h", xi, np.linalg.inv(prior.covariance_matrix()), xi)


# ------------------------------------------------------------- refinement ---

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
    that passed :func:`prior_gate` (-1 without a prior; 0 means all were refined regardless).
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


def laplace_log_evidence(chi2, covariance, prior_covariance=None):
    """-½ chi2 + ½ log det(2π Σ) [- ½ log det(2π Σ_prior)].  chi2 : (K,), covariance : (K, 6, 6)."""
    sign, logdet = np.linalg.slogdet(2.0 * np.pi * covariance)
    out = -0.5 * chi2 + 0.5 * np.where(sign > 0, logdet, np.nan)
    if prior_covariance is not None:
        out -= 0.5 * np.linalg.slogdet(2.0 * np.pi * prior_covariance)[1]
    return out


def normalise(log_evidence):
    """Softmax over the finite entries; NaN entries get probability 0 (all NaN when no
    entry is finite: a set of pose families has no probabilities). (K,) -> (K,)"""
    ok = np.isfinite(log_evidence)
    p = np.zeros(len(log_evidence)) if ok.any() else np.full(len(log_evidence), np.nan)
    if ok.any():
        z = log_evidence[ok] - log_evidence[ok].max()
        p[ok] = np.exp(z) / np.exp(z).sum()
    return p


def refine_hypotheses(model, contacts, arrays, tolerance, *, prior=None, robust="huber", k=DEFAULT_REFINE,
                      point_to_facet=True, params=None):
    """Refine the best k hypotheses in a GTSAM factor graph and score them.

    model : ObjectModel; contacts : Contacts; arrays : HypothesisArrays ranked by the closed
    form (rows with n facets each, -1 for an unassigned finger); tolerance : Tolerance (σ_x =
    position_noise, σ_n = normal_noise); prior : PosePrior or None; robust : "huber" | "cauchy" | "none"; k : how
    many to refine (0: all); point_to_facet : add the lateral residual; params : optional
    gtsam.LevenbergMarquardtParams for a single pass (default: a :data:`SCREEN` pass over all
    k, then a :func:`lm_params` polish of those with probability >= POLISH_PROBABILITY).

    Which k: without a prior the first k rows of ``arrays`` (closed-form ranking), started
    from their closed-form poses. With a prior every row is re-scored by its contact χ² plus
    the prior's Mahalanobis distance at :func:`prior_closed_form`, the best k are refined
    from those poses (a closed-form ranking blind to the prior can push the true hypothesis
    of a near-symmetric object past k). Returns a :class:`Refinement`, most probable first.
    """
    _check(model, contacts, arrays, tolerance, prior, robust, k)
    facets_all = np.asarray(arrays.facets)
    if len(facets_all) == 0:
        return _empty(contacts.n, robust, prior)
    idx, starts, facets, agreeing = _select(model, contacts, arrays, tolerance, prior, k, point_to_facet)
    screen, polish = (params, None) if params is not None else (lm_params(**SCREEN), lm_params())
    # One graph for all hypotheses: the contact factor reads its data from ``buffer``,
    # which is overwritten per hypothesis (all have the same n, so the same factor shape).
    packed = pack_contacts(model, contacts, facets)
    buffer = packed[0].copy()
    graph, spread = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    graph.add(contact_factor(buffer, kernel_params(tolerance, robust, point_to_facet)))
    spread.add(contact_factor(buffer, kernel_params(tolerance, robust, point_to_facet=False)))
    if prior is not None:
        graph.add(prior_factor(prior))
        spread.add(prior_factor(prior))
    prior_cov = None if prior is None else prior.covariance_matrix()
    K = len(idx)
    free = np.asarray(arrays.fit.underdetermined)[idx] if prior is None else np.zeros(K, bool)
    penalty = outlier_penalty(facets)
    poses, chi2, cov = starts.copy(), np.zeros(K), np.zeros((K, 6, 6))
    iters, secs, cpu_secs = np.zeros(K, int), np.zeros(K), np.zeros(K)

    def refine(rows, lm):
        for j in rows:
            for _ in range(1 + REASSIGN_ROUNDS):
                poses[j], chi2[j], cov[j], it, sec, cpu = _timed(graph, spread, buffer, packed[j], poses[j], lm)
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
        refine(np.flatnonzero(normalise(_log_evidence(chi2, cov, prior_cov)) >= POLISH_PROBABILITY), polish)
    # rows that ended on the same facets are one hypothesis: keep the most probable
    log_ev = _log_evidence(chi2, cov, prior_cov)
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


def _log_evidence(chi2, cov, prior_cov):
    """laplace_log_evidence with NaN for hypotheses without a covariance (pose families)."""
    determined = np.isfinite(cov).all(axis=(1, 2))
    log_ev = laplace_log_evidence(chi2, np.where(determined[:, None, None], cov, np.eye(6)), prior_cov)
    log_ev[~determined] = np.nan
    return log_ev


def _timed(graph, spread, buffer, data, T0, params):
    """_optimize on the hypothesis ``data`` (copied into the factors' buffer), with wall and CPU time."""
    clock, cpu = time.perf_counter(), time.thread_time()
    np.copyto(buffer, data)
    return _optimize(graph, T0, params, spread) + (time.perf_counter() - clock, time.thread_time() - cpu)


def _optimize(graph, T0, params, spread=None):
    """LM from T0 on a one-pose graph. -> pose (4, 4), chi2 = 2·error, covariance (6, 6), iterations

    The covariance is the marginal of ``spread`` (default: ``graph``) at the optimum: the
    contact factor without its point-to-facet rows. That residual is a hinge, zero over the
    contact's triangle and growing outside it, so its curvature at a contact just outside says
    nothing of the spread on the triangle's side; counted as Gaussian information, it made the
    95 % Laplace region cover the truth in 65–86 % of grasps on the rock (research/uncertainty.md,
    "The lateral term and the Laplace covariance"). Where ``spread`` leaves directions free,
    ``graph``'s marginal is taken; where both do, NaN."""
    values = gtsam.Values()
    values.insert(POSE_KEY, gtsam.Pose3(T0))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = optimizer.optimize()
    cov = np.full((6, 6), np.nan)
    for g in ([graph] if spread is None else [spread, graph]):
        try:
            cov = gtsam.Marginals(g, result).marginalCovariance(POSE_KEY)
            break
        except RuntimeError:  # indeterminant system: a pose family, not a pose
            continue
    return result.atPose3(POSE_KEY).matrix(), 2.0 * optimizer.error(), cov, optimizer.iterations()


def _select(model, contacts, arrays, tolerance, prior, k, point_to_facet):
    """Rows to refine, their LM start poses and facets: (K,) int, (K, 4, 4), (K, n) int, and
    how many rows passed the prior gate (-1 without a prior)."""
    h = len(arrays.facets)
    if prior is None:
        idx = np.arange(h if k == 0 else min(k, h))
        T = np.asarray(arrays.poses)[idx]
        return idx, T, fitting_facets(model, contacts, np.asarray(arrays.facets)[idx], T, tolerance), -1
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


def prior_gate(model, arrays, tolerance, prior):
    """(H,) bool: hypotheses whose closed-form rotation agrees with the prior's rotation.

    A consistency test of two Gaussian rotation estimates: δ = Log(R_pᵀ R) of the contact-only
    closed form R, whose information (object frame) is Σ_i (I - n_k n_kᵀ) / σ_n², and of the
    prior with covariance C_p. Rows with δᵀ (info⁻¹ + C_p)⁻¹ δ above :data:`PRIOR_GATE_CHI2`
    are dropped before the prior-aware scoring (which costs ~10 µs a row). The form
    info (I + C_p info)⁻¹ needs no inverse of info, so rotations the normals leave free
    (singular info) are never dropped.
    """
    facets = np.asarray(arrays.facets)
    ok = facets >= 0  # unassigned fingers carry no information
    normals = model.planes.normals[np.maximum(facets, 0)] * ok[..., None]
    n = ok.sum(axis=1)[:, None, None]
    info = (n * np.eye(3) - np.einsum("hni,hnj->hij", normals, normals)) / tolerance.normal_noise**2
    Rp = prior.pose[:3, :3]
    delta = Rotation.from_matrix(np.einsum("ji,hjk->hik", Rp, arrays.fit.R)).as_rotvec()
    Cp = prior.covariance_matrix()[:3, :3]
    y = np.linalg.solve(np.eye(3) + np.einsum("ij,hjk->hik", Cp, info), delta[..., None])[..., 0]
    return np.einsum("hi,hij,hj->h", delta, info, y) <= PRIOR_GATE_CHI2


def agrees_with_prior(model, arrays, tolerance, prior):
    """Whether some hypothesis of ``arrays`` passes :func:`prior_gate` (False when there are none)."""
    return len(arrays.cost) > 0 and bool(prior_gate(model, arrays, tolerance, prior).any())


def _empty(n, robust, prior):
    z = np.zeros(0)
    return Refinement(np.zeros(0, int), np.zeros((0, n), int), np.zeros((0, 4, 4)), np.zeros((0, 4, 4)),
                      z, z, np.zeros((0, 6, 6)), z, z, np.zeros(0, int), np.zeros(0, bool), z, z,
                      robust, prior is not None, 0 if prior is not None else -1)


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
