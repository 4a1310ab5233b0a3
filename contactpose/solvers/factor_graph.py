"""The factor graphs of a pose in GTSAM: contact factors, the vision prior, LM settings, and
the one-pose graph that refines a hypothesis (scoring.refine chooses which, and ranks them).

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

Tracks (tracking.track) take the same contact rows one factor per contact with the kernel as
GTSAM's reweighting (:func:`reweighted_contact_factors`, :func:`reweighted_smooth_factors`)
on one pose variable per hand motion.
"""

from __future__ import annotations

import time
from functools import partial

import gtsam
import numpy as np

from contactpose.costs.facet import contact_rows, factor_dim, kernel_params
from contactpose.costs.robust import reweighted_noise
from contactpose.costs.smooth import smooth_data, smooth_rows

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
    with λ·diag(JᵀJ) it shortens the step and goes on. λ starts at 1e-5 (Gauss-Newton steps
    near the optimum).
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
#: false ones converge only linearly in the kinks of r_l and the robust zones). A hypothesis the
#: screen gives a real probability is then polished with :func:`lm_params` from where the screen
#: stopped (scoring.refine).
SCREEN = dict(max_iterations=15, relative_tol=1e-3, absolute_tol=1e-2)


def optimize(graph, T0, params, spread=None):
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


class PoseGraph:
    """The one-pose graph of a hypothesis, reused for every hypothesis of one call: its contact
    factor reads the packed contacts (costs.facet.pack_contacts) from a buffer that
    :meth:`solve` overwrites (all hypotheses have the same n, so the same factor shape).
    ``graph`` holds the contact factor (point_to_facet rows included) and the prior's factor,
    ``spread`` the same without the point-to-facet rows (the covariance's graph, :func:`optimize`).
    data : (n, 20) packed contacts of a first hypothesis; tolerance : Tolerance; robust : kernel
    name; prior : PosePrior or None."""

    def __init__(self, data, tolerance, robust, point_to_facet, prior):
        self.buffer = data.copy()
        self.graph, self.spread = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
        self.graph.add(contact_factor(self.buffer, kernel_params(tolerance, robust, point_to_facet)))
        self.spread.add(contact_factor(self.buffer, kernel_params(tolerance, robust, point_to_facet=False)))
        if prior is not None:
            self.graph.add(prior_factor(prior))
            self.spread.add(prior_factor(prior))

    def solve(self, data, T0, params):
        """:func:`optimize` of the hypothesis ``data`` (n, 20) from T0 (4, 4) with LM ``params``.
        -> (pose, chi2, covariance, iterations, wall seconds, thread CPU seconds)"""
        clock, cpu = time.perf_counter(), time.thread_time()
        np.copyto(self.buffer, data)
        return optimize(self.graph, T0, params, self.spread) + (time.perf_counter() - clock, time.thread_time() - cpu)
