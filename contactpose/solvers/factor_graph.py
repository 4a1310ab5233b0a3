"""Factor-graph refinement of ranked hypotheses in GTSAM: contact factors, vision prior,
robust kernels, marginal covariances and hypothesis probabilities.

One ``Pose3`` variable per hypothesis: T_world_object. Its graph holds

* one batched contact factor (a ``gtsam.CustomFactor`` over all n contacts) whose error
  is exactly the residuals of :mod:`contactpose.solvers.residuals`, whitened by the sensor noise:
  ``[r_n / σ_n (3n: x, y, z of contact 0, then 1, ...), r_o / σ_x (n), w / σ_x (2n,
  point_to_facet only)]``, where w is the in-plane offset of the contact from its triangle
  in the facet's in-plane basis, |w| = r_l (two rows per contact, contact-major);
* optionally a ``PriorFactorPose3`` from a :class:`~contactpose.types.PosePrior`.

Jacobians are analytic, in GTSAM's tangent order and convention: rotation first, right
perturbation ``T ⊕ ξ = T · Exp(ξ)``, ``ξ = (ω, v)``, so to first order ``R' = R (I + [ω]×)``
and ``t' = t + R v``. With ``p = Rᵀ(x̃ - t)`` this gives ``dp/dξ = [[p]×, -I]`` and

* ``∂r_n/∂ξ = [-R [n_k]×, 0]``,
* ``∂r_o/∂ξ = [(n_k × p)ᵀ, -n_kᵀ]``,
* ``∂w/∂ξ = P [[p]×, -I]`` with P = u uᵀ beside an edge (u = w/|w|) and I - n_k n_kᵀ beside
  a corner; the rows are zero when the contact lies over its triangle (w = 0, flat). The
  vector w, not its norm r_l, so that Gauss-Newton's model of r_l² keeps all its curvature
  in p (:func:`_lateral_rows`; research/tracking.md, "iSAM2 against batch LM").

Noise: the factor uses a ``Unit`` noise model and whitens inside (divides by σ), because
the robust kernel must act on whitened errors.

Robust kernels act per contact, on the norm s_i of the contact's whitened block (its
4 or 6 rows), not on the whole factor: GTSAM's ``noiseModel.Robust`` reweights a factor's
error as one block, which on a batched factor would down-weight all contacts together.
The factor returns ``ẽ_i = sqrt(2 ρ(s_i)) e_i / s_i``, so that ``½|ẽ_i|² = ρ(s_i)`` exactly
(the "square-rooted" robust residual) with GTSAM's ``mEstimator`` losses
``ρ_Huber(s) = s²/2 (s ≤ k), k s - k²/2`` and ``ρ_Cauchy(s) = k²/2 log(1 + s²/k²)``.
The optimum is the robust M-estimate ``argmin Σ_i ρ(s_i)``; one factor per contact with
``noiseModel.Robust`` (block reweighting) has the same cost and optimum (a test).

Kernel width: an inlier block holds about 3 informative whitened components (2 normal,
1 offset; w is 0 for a contact inside its triangle), so s_i² ~ χ²(3). k = sqrt(χ²₃(0.95))
= 2.80 leaves 95 % of inlier contacts in the quadratic zone (Huber: no efficiency loss
there), and a displaced contact (tens of σ) keeps only a bounded (Huber) or vanishing
(Cauchy) influence. The scalar textbook value 1.345 would down-weight 61 % of the inlier
contacts, whose block norm has median 1.54.

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
from functools import lru_cache, partial

import gtsam
import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from contactpose.contacts import Contacts
from contactpose.errors import ContactPoseError, check_count
from contactpose.geometry.kernels import _axpy, _cross, _dot, _t, closest_point_triangle, fit_cost, normal_misfit, segment_d2
from contactpose.geometry.se3 import hat, hat3
from contactpose.options import DEFAULT_REFINE, check_robust, fit_threshold, outlier_penalty
from contactpose.solvers import residuals as res
from contactpose.solvers.closed_form import wahba
from contactpose.types import HypothesisArrays, PosePrior

log = logging.getLogger(__name__)

#: Kernel width on the norm of a contact's whitened block: sqrt(χ²₃(0.95)).
HUBER_K = 2.7954834829151074
CAUCHY_K = 2.7954834829151074
#: A lateral residual below this fraction of σ_x counts as 0 (rounding of the face projection).
LATERAL_ZERO_REL = 1e-9
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
_KERNEL_CODE = {"none": 0, "huber": 1, "cauchy": 2}


# ------------------------------------------------------------------ kernels ---

@njit(cache=True)
def _robust_scale(s, kernel, k):
    """(f, g') for the square-rooted robust residual ẽ = f e, g(s) = f s = sqrt(2ρ(s))."""
    if kernel == 1:  # Huber
        if s <= k:
            return 1.0, 1.0
        g = np.sqrt(2.0 * k * s - k * k)
        return g / s, k / g
    # Cauchy: ρ = k²/2 log(1 + s²/k²), ρ' = s / (1 + s²/k²)
    q = s * s / (k * k)
    g = k * np.sqrt(np.log1p(q))
    return g / s, s / (1.0 + q) / g


def robust_rho(s, kernel, k):
    """ρ(s) of the kernel (code as in :func:`kernel_params`: 0 none, 1 Huber, 2 Cauchy) for
    whitened residual norms s (array): g(s)²/2 of :func:`_robust_scale`."""
    s = np.asarray(s, dtype=np.float64)
    if kernel == 1:
        return np.where(s <= k, 0.5 * s * s, k * s - 0.5 * k * k)
    if kernel == 2:
        return 0.5 * k * k * np.log1p(s * s / (k * k))
    return 0.5 * s * s


@njit(cache=True)
def _contact_rows(M, data, params, e, J):
    """Whitened (robust) contact residuals and their Jacobian w.r.t. the Pose3.

    M : (4, 4) pose; data : (n, 20) packed contacts; params : from :func:`kernel_params`;
    e : (m,) out; J : (m, 6) out, written unless it has 0 rows. Rows: 3n normal
    (contact-major), n offset, then 2n lateral (:func:`_lateral_rows`, contact-major) when
    point-to-facet is on. The rows of an
    unassigned contact (data[i, 19] == 0) are 0.
    """
    n = data.shape[0]
    inv_sn, inv_sx, k, tiny = params[0], params[1], params[2], params[3]
    lateral = params[4] != 0.0
    kernel = int(params[5])
    want_j = J.shape[0] > 0
    R = M[:3, :3]
    t = M[:3, 3]
    for i in range(n):
        if data[i, 19] == 0.0:  # unassigned finger: no residual
            _zero_rows(e, J, (3 * i, 3 * i + 1, 3 * i + 2, 3 * n + i, 4 * n + 2 * i, 4 * n + 2 * i + 1), lateral, want_j)
            continue
        nk = data[i, 0:3]
        x = data[i, 13:16]
        f = data[i, 16:19]
        # r_n = R n_k + ñ_i; ∂/∂ω = -R [n_k]×
        for a in range(3):
            e[3 * i + a] = (R[a, 0] * nk[0] + R[a, 1] * nk[1] + R[a, 2] * nk[2] + f[a]) * inv_sn
        if want_j:
            for a in range(3):
                # row a of -R [n_k]×
                J[3 * i + a, 0] = -(R[a, 1] * nk[2] - R[a, 2] * nk[1]) * inv_sn
                J[3 * i + a, 1] = -(R[a, 2] * nk[0] - R[a, 0] * nk[2]) * inv_sn
                J[3 * i + a, 2] = -(R[a, 0] * nk[1] - R[a, 1] * nk[0]) * inv_sn
                J[3 * i + a, 3] = 0.0
                J[3 * i + a, 4] = 0.0
                J[3 * i + a, 5] = 0.0
        # p = Rᵀ (x̃ - t)
        d0, d1, d2 = x[0] - t[0], x[1] - t[1], x[2] - t[2]
        p0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
        p1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
        p2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
        # r_o = n_kᵀ p + d_k; ∂/∂ξ = [(n_k × p)ᵀ, -n_kᵀ]
        ro = nk[0] * p0 + nk[1] * p1 + nk[2] * p2 + data[i, 3]
        row = 3 * n + i
        e[row] = ro * inv_sx
        if want_j:
            J[row, 0] = (nk[1] * p2 - nk[2] * p1) * inv_sx
            J[row, 1] = (nk[2] * p0 - nk[0] * p2) * inv_sx
            J[row, 2] = (nk[0] * p1 - nk[1] * p0) * inv_sx
            J[row, 3] = -nk[0] * inv_sx
            J[row, 4] = -nk[1] * inv_sx
            J[row, 5] = -nk[2] * inv_sx
        if lateral:
            _lateral_rows(e, J, 4 * n + 2 * i, nk, (p0, p1, p2), data[i], inv_sx, tiny, want_j)
    if kernel != 0:
        _robust_rows(e, J, n, lateral, kernel, k, want_j)


@njit(cache=True)
def _lateral_rows(e, J, row, nk, p, datum, inv_sx, tiny, want_j):
    """The two lateral rows of one contact, from ``row`` on: w = the in-plane part of
    p - closest(p, V_k), in the facet's in-plane basis (e_1 along its first edge, e_2 = n_k × e_1),
    so that |w| = r_l. w is 0 over the triangle and affine in p on each side of it, so that
    Gauss-Newton's model of r_l² is exact there: ∂w/∂ξ = P [[p]×, -I] with P = I - n_k n_kᵀ
    beside a corner (w = p - corner, in-plane) and P = u uᵀ beside an edge (u = w/|w|).
    The scalar r_l of the same cost bends around each corner (its Hessian holds (I - u uᵀ)/r_l),
    which Gauss-Newton leaves out; that stalled iSAM2's trust region on fine meshes."""
    p0, p1, p2 = p
    c = closest_point_triangle(np.array((p0, p1, p2)), datum[4:7], datum[7:10], datum[10:13])
    w0, w1, w2 = p0 - c[0], p1 - c[1], p2 - c[2]
    h = nk[0] * w0 + nk[1] * w1 + nk[2] * w2
    w0, w1, w2 = w0 - h * nk[0], w1 - h * nk[1], w2 - h * nk[2]
    rl = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    f0, f1, f2 = datum[7] - datum[4], datum[8] - datum[5], datum[9] - datum[6]  # e_1: the first edge
    size = np.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
    f0, f1, f2 = f0 / size, f1 / size, f2 / size
    g0, g1, g2 = nk[1] * f2 - nk[2] * f1, nk[2] * f0 - nk[0] * f2, nk[0] * f1 - nk[1] * f0  # e_2 = n_k × e_1
    outside = rl > tiny
    corner = False
    for s in range(3):  # c is a corner itself (a vertex region), else a point of an edge
        corner = corner or (c[0] == datum[4 + 3 * s] and c[1] == datum[5 + 3 * s] and c[2] == datum[6 + 3 * s])
    for j in range(2):
        x, y, z = (f0, f1, f2) if j == 0 else (g0, g1, g2)
        along = x * w0 + y * w1 + z * w2
        e[row + j] = along * inv_sx if outside else 0.0
        if not want_j:
            continue
        if outside and not corner:  # v = (e_j·u) u
            x, y, z = along / (rl * rl) * w0, along / (rl * rl) * w1, along / (rl * rl) * w2
        if not outside:
            x = y = z = 0.0
        # the row e_jᵀ P [[p]×, -I] = [(v × p)ᵀ, -vᵀ], v = e_j beside a corner, (e_j·u) u beside an edge
        J[row + j, 0] = (y * p2 - z * p1) * inv_sx
        J[row + j, 1] = (z * p0 - x * p2) * inv_sx
        J[row + j, 2] = (x * p1 - y * p0) * inv_sx
        J[row + j, 3] = -x * inv_sx
        J[row + j, 4] = -y * inv_sx
        J[row + j, 5] = -z * inv_sx


@njit(cache=True)
def _robust_rows(e, J, n, lateral, kernel, k, want_j):
    """The per-contact robust kernel on the contact factor's rows, in place:
    ẽ = f e, ∂ẽ = f ∂e + (g' - f) û ûᵀ ∂e (``_robust_scale``)."""
    rows = np.empty(6, np.int64)
    nrow = 6 if lateral else 4
    for i in range(n):
        rows[0], rows[1], rows[2], rows[3] = 3 * i, 3 * i + 1, 3 * i + 2, 3 * n + i
        rows[4], rows[5] = 4 * n + 2 * i, 4 * n + 2 * i + 1
        s2 = 0.0
        for a in range(nrow):
            s2 += e[rows[a]] ** 2
        s = np.sqrt(s2)
        if s == 0.0:
            continue
        fs, gp = _robust_scale(s, kernel, k)
        if want_j and (fs != 1.0 or gp != 1.0):
            for c6 in range(6):
                proj = 0.0
                for a in range(nrow):
                    proj += e[rows[a]] * J[rows[a], c6]
                proj /= s2  # (ûᵀ ∂e) / s
                for a in range(nrow):
                    J[rows[a], c6] = fs * J[rows[a], c6] + (gp - fs) * e[rows[a]] * proj
        for a in range(nrow):
            e[rows[a]] *= fs


@njit(cache=True)
def _zero_rows(e, J, rows, lateral, want_j):
    """Zero the residual rows (and Jacobian rows) of one contact; the lateral rows only if present."""
    for a in range(6 if lateral else 4):
        e[rows[a]] = 0.0
        if want_j:
            for c6 in range(6):
                J[rows[a], c6] = 0.0


def pack_contacts(model, contacts, facets):
    """Per-contact factor data: normal (3), offset, triangle (9), point (3), finger normal (3),
    assigned (1.0, or 0.0 for facet -1: an unassigned finger, whose rows are 0).

    model : ObjectModel; contacts : Contacts; facets : (..., n) int  ->  (..., n, 20) float64
    """
    facets = np.asarray(facets)
    safe = np.maximum(facets, 0)
    data = np.empty(facets.shape + (20,))
    data[..., 0:3] = model.planes.normals[safe]
    data[..., 3] = model.planes.offsets[safe]
    data[..., 4:13] = model.triangles[safe].reshape(facets.shape + (9,))
    data[..., 13:16] = contacts.points
    data[..., 16:19] = contacts.finger_normals
    data[..., 19] = facets >= 0
    return data


def kernel_params(tolerance, robust="none", point_to_facet=True):
    """(6,) float64 factor settings: 1/σ_n, 1/σ_x, kernel width k, the r_l zero, point-to-facet
    (0/1), kernel code (0 none, 1 Huber, 2 Cauchy)."""
    check_robust(robust)
    k = {"huber": HUBER_K, "cauchy": CAUCHY_K, "none": 0.0}[robust]
    return np.array([1.0 / tolerance.normal_noise, 1.0 / tolerance.position_noise, k,
                     LATERAL_ZERO_REL * tolerance.position_noise, float(bool(point_to_facet)),
                     float(_KERNEL_CODE[robust])])


def factor_dim(n, point_to_facet):
    """Rows of the batched contact factor of n contacts."""
    return n * (6 if point_to_facet else 4)


def lateral_norms(e, n):
    """r_l / σ_x of each contact (its two lateral rows' norm) from the error e (6n,) of a
    factor with point-to-facet rows and no robust kernel. -> (n,)"""
    return np.hypot(e[4 * n::2], e[4 * n + 1::2])


def contact_residuals(T, data, params, jacobian=True):
    """The batched factor's error and Jacobian at a pose, outside GTSAM.

    T : (4, 4); data : (n, 20) from :func:`pack_contacts`; params : from :func:`kernel_params`.
    Returns e (m,) and J (m, 6) (None when not ``jacobian``), m = :func:`factor_dim`.
    """
    m = factor_dim(len(data), params[4] != 0.0)
    e = np.empty(m)
    J = np.empty((m if jacobian else 0, 6))
    _contact_rows(np.ascontiguousarray(T, dtype=np.float64), data, params, e, J)
    return e, (J if jacobian else None)


def contact_error(data, params, e, J, key, this, values, H):
    """CustomFactor error function; bind everything before ``this`` with functools.partial.

    data : (n, 20); params : (6,); e : (m,) and J : (m, 6) work buffers (GTSAM copies what
    it is given, so they can be reused); key : the Pose3 key.
    """
    if H is None:
        _contact_rows(values.atPose3(key).matrix(), data, params, e, _NO_JACOBIAN)
        return e
    _contact_rows(values.atPose3(key).matrix(), data, params, e, J)
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


@lru_cache(maxsize=None)
def reweighted_noise(dim, robust):
    """GTSAM's own robust noise model on ``dim`` unit-whitened rows: the same ρ as the batched
    factor's kernel (:func:`robust_rho`), applied by reweighting (each linearization scales the
    rows by √w, w = ρ'(s)/s). robust : "huber" | "cauchy" | "none" (unit noise)."""
    unit = gtsam.noiseModel.Unit.Create(dim)
    if check_robust(robust) == "none":
        return unit
    kernel = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[robust]
    return gtsam.noiseModel.Robust.Create(kernel.Create(HUBER_K if robust == "huber" else CAUCHY_K), unit)


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


#: Columns of :func:`smooth_data`'s per-contact rows.
SMOOTH_COLUMNS = 61


def smooth_data(model, contacts, facets, tolerance):
    """The smooth factor's inputs: (pack_contacts data (..., n, 20), smooth (..., n, 61): per
    contact M (9, row-major), a (3), n_a (3), assigned (1.0 or 0.0), W_f (9, row-major) of
    ObjectModel.normal_whitening, then its facet's three ObjectModel.crease_edges (3 × 12, NaN
    where an edge is no crease)). facets : (..., n) int, as for :func:`pack_contacts`."""
    facets = np.asarray(facets)
    safe = np.maximum(facets, 0)
    M, corner = model.smooth_normals
    smooth = np.empty(facets.shape + (SMOOTH_COLUMNS,))
    smooth[..., 0:9] = M[safe].reshape(facets.shape + (9,))
    smooth[..., 9:12] = model.triangles[safe, 0]
    smooth[..., 12:15] = corner[safe]
    smooth[..., 15] = facets >= 0
    W = model.normal_whitening(tolerance.normal_noise, tolerance.position_noise)
    smooth[..., 16:25] = W[safe].reshape(facets.shape + (9,))
    smooth[..., 25:61] = model.crease_edges[safe].reshape(facets.shape + (36,))
    return pack_contacts(model, contacts, facets), smooth


@njit(cache=True)
def _smooth_rows(T, data, params, smooth, place, e, J):
    """The contact rows (:func:`_contact_rows`, no kernel), their normal rows replaced by the
    smooth ones (:func:`_smooth_normal_rows`), then the kernel of ``params``."""
    plain = params.copy()
    plain[5] = 0.0
    _contact_rows(T, data, plain, e, J)
    _smooth_normal_rows(T, data, smooth, place, params[0], params[1], e, J)
    if params[5] != 0.0:
        _robust_rows(e, J, data.shape[0], params[4] != 0.0, int(params[5]), params[2], True)


@njit(cache=True)
def _smooth_normal_rows(T, data, smooth, place, inv_sn, inv_sx, e, J):
    """Overwrite the 3n normal rows of e and J with each contact's face rows
    r_n = W (n(p) + Rᵀ ñ), n = m/|m|, m = n_a + M (p - a), p = Rᵀ(x̃ - t) (smooth: from
    :func:`smooth_data`): ∂/∂ω = W (Dn [p]× + [Rᵀñ]×), ∂/∂v = -W Dn, Dn = (I - n nᵀ) M / |m|;
    without ``place``, Dn = 0 in the Jacobian. Where a crease edge of the facet costs less
    (:func:`_crease_rows`), its rows instead."""
    R, t = np.ascontiguousarray(T[:3, :3]), T[:3, 3].copy()
    Rt = np.ascontiguousarray(R.T)
    edge_e, edge_J = np.empty(3), np.empty((3, 6))
    for i in range(data.shape[0]):
        rows = slice(3 * i, 3 * i + 3)
        if smooth[i, 15] == 0.0:
            e[rows] = 0.0
            J[rows] = 0.0
            continue
        M = smooth[i, 0:9].copy().reshape((3, 3))
        W = smooth[i, 16:25].copy().reshape((3, 3))
        p = Rt @ (data[i, 13:16] - t)
        w = Rt @ data[i, 16:19].copy()
        m = smooth[i, 12:15] + M @ (p - smooth[i, 9:12])
        size = np.sqrt(m @ m)
        nu = m / size
        e[rows] = W @ (nu + w)
        Dn = (np.eye(3) - np.outer(nu, nu)) @ M / size if place else np.zeros((3, 3))
        J[rows, :3] = W @ (Dn @ hat3(p) + hat3(w))  # Dn, the hats: fresh, contiguous
        J[rows, 3:] = -(W @ Dn)
        best = e[rows] @ e[rows]
        for k in range(3):
            edge = smooth[i, 25 + 12 * k:37 + 12 * k]
            if np.isnan(edge[0]):
                continue
            cost = _crease_rows(p, -w, data[i, 0:3], edge, place, inv_sn, inv_sx, edge_e, edge_J)
            if cost < best:
                best = cost
                e[rows] = edge_e
                J[rows] = edge_J


@njit(cache=True)
def _crease_rows(p, nu, n_f, edge, place, inv_sn, inv_sx, out, J):
    """The rows of a contact on a crease edge (edge: a, e, u, n_g of ObjectModel.crease_edges)
    whose measured outward normal ν (object frame) lies in the edge's arc of normals from n_f
    to n_g: its normal's residual to the arc's nearest direction ν* = Pν/|Pν| (P = I - e eᵀ),
    in the orthonormal axes e, ν* (ν - ν* = (ν·e) e + (|Pν| - 1) ν*), over σ_n, and the contact's
    distance across the edge in f's plane, u·(p - a), over σ_x (zero Jacobian without
    ``place``), written to out (3,) and J (3, 6). ∂ν/∂ω = [ν]×, ∂p/∂ω = [p]×, ∂p/∂v = -I.
    -> the rows' squared norm, or inf where ν lies outside the arc."""
    along, size, star, inside = _arc_nearest(nu, n_f, edge)
    if not inside:
        return np.inf
    a, ax, u = edge[0:3], edge[3:6], edge[6:9]
    out[0] = along * inv_sn
    out[1] = (size - 1.0) * inv_sn
    out[2] = (u @ (p - a)) * inv_sx
    hat_nu = hat3(nu)
    J[0, :3] = (ax @ hat_nu) * inv_sn
    J[1, :3] = (np.array(star) @ hat_nu) * inv_sn
    J[0:2, 3:] = 0.0
    if place:
        J[2, :3] = (u @ hat3(p)) * inv_sx
        J[2, 3:] = -u * inv_sx
    else:
        J[2] = 0.0
    return out @ out


@njit(cache=True)
def _arc_nearest(nu, n_f, edge):
    """The direction ν* = Pν/|Pν| (P = I - e eᵀ) of a crease edge's arc of normals from n_f
    to n_g (edge: a, e, u, n_g of ObjectModel.crease_edges) nearest to the unit ν (object
    frame): (ν·e, |Pν|, ν* (3-tuple), whether ν* lies inside the arc, not beyond its ends)."""
    ax, n_g = _t(edge[3:6]), _t(edge[9:12])
    along = _dot(_t(nu), ax)
    proj = _axpy(-along, ax, _t(nu))
    size = np.sqrt(_dot(proj, proj))
    if size < 1e-12:
        return along, size, proj, False
    star = (proj[0] / size, proj[1] / size, proj[2] / size)
    inside = _dot(_cross(_t(n_f), star), ax) > 0.0 and _dot(_cross(star, n_g), ax) > 0.0
    return along, size, star, inside


def touch_chi2(T, data, params, smooth=None):
    """χ² = Σ_i 2ρ(s_i) of H tracks' touches, each at its own pose, from one compiled pass: the
    kernel's rows of :func:`contact_residuals` (``smooth`` None) or of the smooth factor
    (:func:`_smooth_rows`) squared and summed (each robust row block has norm
    g(s) = √(2ρ(s))). T : (H, 4, 4); data : (H, n, 20); params : :func:`kernel_params` with the
    kernel; smooth : (H, n, SMOOTH_COLUMNS) or None. -> (H,)"""
    T = np.ascontiguousarray(T, dtype=np.float64)
    if smooth is None:
        return _stacked_chi2(T, data, params, np.zeros(data.shape[:2] + (SMOOTH_COLUMNS,)), False)
    return _stacked_chi2(T, data, params, smooth, True)


@njit(cache=True)
def _stacked_chi2(T, data, params, smooth, smooth_on):
    m = data.shape[1] * (6 if params[4] != 0.0 else 4)  # factor_dim
    e, J = np.empty(m), np.empty((m, 6))
    out = np.empty(T.shape[0])
    for h in range(T.shape[0]):
        if smooth_on:
            _smooth_rows(T[h], data[h], params, smooth[h], True, e, J)
        else:
            _contact_rows(T[h], data[h], params, e, J[:0])
        out[h] = e @ e
    return out


def _smooth_error(data, params, smooth, place, e, J, key, this, values, H):
    """CustomFactor error function of the smooth factor, as :func:`contact_error`."""
    _smooth_rows(values.atPose3(key).matrix(), data, params, smooth, place, e, J)
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
    contact_chi2 = _contact_chi2(model, contacts, facets, poses, tolerance, point_to_facet)
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


def fitting_facets(model, contacts, facets, poses, tolerance):
    """Each contact's facet moved to the member of its patch that fits it best under the pose.

    With patches (connected facets searched as one unit) a hypothesis's facet within a patch
    depends on the pose, and the residuals of the wrong member would hold the contact to it.
    The member is the one of least whitened distance² plus normal residual²
    (:func:`residuals.fitting_members`, as in the ranking): on a fine mesh of a curved surface
    neighbouring members differ in normal by more than σ_n, and the nearest member alone
    biased the rotation (research/uncertainty.md, "Fine meshes"). Without patches in the
    model, ``facets`` unchanged.
    facets : (H, n) int (-1: unassigned, kept), poses : (H, 4, 4)  ->  (H, n) int
    """
    patches = getattr(model, "patches", None)
    labels = None if patches is None else patches.labels[np.maximum(facets, 0)]
    if patches is None or not np.any(np.diff(patches.indptr)[labels] > 1):
        return facets  # no patches, or every contact's patch is a single facet
    members = res.fitting_members(model, contacts, np.ascontiguousarray(labels), poses[:, :3, :3], poses[:, :3, 3],
                                  tolerance)
    return np.where(facets >= 0, members, -1)


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
    score = (_contact_chi2(model, contacts, facets, T, tolerance, point_to_facet) + outlier_penalty(facets)
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


def _residuals(model, contacts, facets, poses, point_to_facet):
    """residuals.py's r_n (H, n, 3), r_o (H, n), r_l (H, n) (0 without point_to_facet), each
    0 for an unassigned finger, and ok (H, n) bool: assigned. facets : (H, n) int, -1 unassigned."""
    ok, safe = facets >= 0, np.maximum(facets, 0)
    r_n, r_o, r_l = res.contact_residuals(poses[:, :3, :3], poses[:, :3, 3], model.planes.normals[safe],
                                          model.planes.offsets[safe], model.triangles[safe], contacts.points,
                                          contacts.finger_normals)
    return r_n * ok[..., None], r_o * ok, r_l * (ok & point_to_facet), ok


def agrees_with_prior(model, arrays, tolerance, prior):
    """Whether some hypothesis of ``arrays`` passes :func:`prior_gate` (False when there are none)."""
    return len(arrays.cost) > 0 and bool(prior_gate(model, arrays, tolerance, prior).any())


def _contact_chi2(model, contacts, facets, poses, tolerance, point_to_facet):
    """Whitened χ² of residuals.py over the assigned contacts. -> (H,)"""
    r_n, r_o, r_l, _ = _residuals(model, contacts, facets, poses, point_to_facet)
    return res.whitened_cost(r_n, r_o, r_l, tolerance.normal_noise, tolerance.position_noise)


def nearest_fit_facets(model, contacts, pose, tolerance, pose_covariance=None, creases=False):
    """Each contact's best facet under a pose: least whitened point-to-triangle distance²
    plus normal residual². pose : (4, 4) -> (n,) int, or (H, 4, 4) -> (H, n) int, the poses
    searched together in one pass (valid facets only). pose_covariance : None, or the poses'
    (6, 6) / (H, 6, 6) covariance (rotation first, right perturbation), whose spread of each
    contact's object-frame point and normal joins the sensor's (:func:`association_weights`).
    creases : also score each facet's crease edges (ObjectModel.crease_edges) as the smooth
    contact model reads them, the squared distance to the edge plus the normal's to the
    edge's arc of normals (:func:`_arc_nearest`), a contact on an edge taking that facet.

    The NEAREST_CANDIDATES facets of nearest centroid are scored first. A facet lies at least
    (its centroid's distance - the largest facet radius) from the contact, so one whose centroid
    lies farther than the best candidate's cost, as a distance, plus that radius cannot beat
    it; where the candidates do not reach that far, the contact is scored against every facet
    within it (one ball query for all such contacts). The answer is the brute force's either
    way."""
    poses = np.asarray(pose, dtype=np.float64)
    single = poses.ndim == 2
    poses = poses.reshape(-1, 4, 4)
    H, n = len(poses), contacts.n
    tree, valid, radius = model.centroid_tree
    R = poses[:, :3, :3]  # object-frame points and outward normals, (H·n, 3), pose by pose
    p = np.einsum("hij,hci->hcj", R, contacts.points[None] - poses[:, None, :3, 3]).reshape(-1, 3)
    normals = -np.einsum("hij,ci->hcj", R, contacts.finger_normals).reshape(-1, 3)
    weight = association_weights(p.reshape(H, n, 3), normals.reshape(H, n, 3), tolerance, pose_covariance).reshape(-1)

    def scored(points, outward, candidates, found=None, found_cost=None, weights=weight):
        if found is None:
            found, found_cost = np.full(len(points), -1), np.full(len(points), np.inf)
        return _best_fits(points, outward, candidates, model.triangles, model.planes.normals, model.facet_radii,
                          weights, found, found_cost, edges)

    edges = model.crease_edges if creases else np.full((1, 3, 12), np.nan)

    if len(valid) <= SCORE_ALL_BELOW:  # a coarse mesh: score every facet
        every = np.broadcast_to(valid, (H * n, len(valid)))
        best, _ = scored(p, normals, every)
    else:
        dist, near = tree.query(p, NEAREST_CANDIDATES)
        best, cost = scored(p, normals, valid[near])
        reach = np.sqrt(cost) + radius  # a facet whose centroid lies farther costs more
        short = np.flatnonzero(dist[:, -1] < reach)
        if short.size:
            balls = valid[_padded(tree.query_ball_point(p[short], reach[short]), near[short, 0])]
            best[short] = scored(p[short], normals[short], balls, best[short], cost[short], weight[short])[0]
    return best.reshape(n) if single else best.reshape(H, n)


def association_weights(p, normals, tolerance, pose_covariance=None):
    """Each contact's weight w = σ_p²/σ_r² of its normal misfit in the fit to a facet
    (geometry.kernels.fit_cost): σ_p² = σ_x² plus the mean variance per axis of its object-frame
    point p under the pose's uncertainty, σ_r² = σ_n² plus that of its normal n per tangent
    axis; without a covariance, σ_x²/σ_n². A pose perturbed by ξ = (ω, v) on the right moves
    p by [p]× ω - v and n by [n]× ω, so a predicted pose a slip away, whose point errs by
    millimetres while its normal errs by about a degree, leans on the normal to pick the facet
    (research/tracking.md, "A covariance that carries the association").
    p, normals : (H, n, 3) object frame; pose_covariance : None, (6, 6) or (H, 6, 6). -> (H, n)"""
    base = (tolerance.position_noise / tolerance.normal_noise) ** 2
    if pose_covariance is None:
        return np.full(p.shape[:2], base)
    P = np.broadcast_to(np.asarray(pose_covariance, dtype=np.float64), (len(p), 6, 6))
    Jp = np.concatenate([hat(p), np.broadcast_to(-np.eye(3), p.shape + (3,))], axis=-1)  # (H, n, 3, 6)
    point_var = np.einsum("hcij,hjk,hcik->hc", Jp, P, Jp) / 3.0
    Jn = hat(normals)
    normal_var = np.einsum("hcij,hjk,hcik->hc", Jn, P[:, :3, :3], Jn) / 2.0
    return (tolerance.position_noise ** 2 + point_var) / (tolerance.normal_noise ** 2 + normal_var)


#: nearest_fit_facets scores this many facets of nearest centroid before it looks further (a
#: fine mesh's contacts mostly look further, in one ball query: cheaper than more neighbours).
NEAREST_CANDIDATES = 48
#: ... and scores every facet of a mesh with at most this many valid facets.
SCORE_ALL_BELOW = 1024


def _padded(lists, fill):
    """Ragged index lists -> (m, longest) int, row i padded with fill[i] (an index already
    scored: the least cost is unchanged)."""
    longest = max(1, max(len(a) for a in lists))
    out = np.empty((len(lists), longest), dtype=np.int64)
    for i, a in enumerate(lists):
        out[i, :len(a)] = a
        out[i, len(a):] = fill[i]
    return out


@njit(cache=True)
def _best_fits(p, normals, candidates, triangles, facet_normals, radii, weight, found, found_cost, edges):
    """Each contact's candidate of least fit_cost (the first on a tie), or its ``found`` facet
    of cost ``found_cost`` (m,) when no candidate costs less (-1 and inf: none yet). p, normals
    : (m, 3) object-frame points and outward normals; candidates : (m, K) int; radii : (F,)
    the facets' radii; weight : (m,) each contact's σ_x²/σ_n² (association_weights); edges :
    ObjectModel.crease_edges, whose edges of a candidate compete with its face
    (:func:`_arc_misfits`), or one NaN row: none. A candidate whose normal misfit plus (centroid
    distance - radius)² already reaches the least cost so far is not scored further.
    -> (facets (m,) int, their costs (m,), length²: the whitened cost times σ_x²)"""
    m, K = candidates.shape
    best, cost = np.empty(m, np.int64), np.empty(m)
    creases = len(edges) > 1
    for i in range(m):
        least, pick = found_cost[i], found[i]
        for j in range(K):
            f = candidates[i, j]
            c = normal_misfit(facet_normals[f], normals[i], weight[i])
            arcs = _arc_misfits(normals[i], facet_normals[f], edges[f], weight[i]) if creases else _NO_ARCS
            lower = min(c, arcs[0], arcs[1], arcs[2])
            if lower >= least:
                continue
            gap = 0.0
            for a in range(3):
                gap += (p[i, a] - (triangles[f, 0, a] + triangles[f, 1, a] + triangles[f, 2, a]) / 3.0) ** 2
            gap = max(np.sqrt(gap) - radii[f], 0.0)
            if lower + gap * gap >= least:
                continue
            c = fit_cost(p[i], normals[i], triangles[f], facet_normals[f], weight[i])
            for k in range(3):
                if arcs[k] < least:
                    c = min(c, arcs[k] + segment_d2(p[i], triangles[f, k], triangles[f, (k + 1) % 3]))
            if c < least:
                least, pick = c, f
        best[i], cost[i] = pick, least
    return best, cost


_NO_ARCS = (np.inf, np.inf, np.inf)


@njit(cache=True)
def _arc_misfits(nu, n_f, edges, weight):
    """weight · |ν - ν*|² to the arc of each of a facet's three edges (edges (3, 12) of
    ObjectModel.crease_edges; :func:`_arc_nearest`), inf where the edge is no crease or ν*
    would lie beyond the arc's ends. -> 3-tuple"""
    return (_arc_misfit(nu, n_f, edges[0], weight), _arc_misfit(nu, n_f, edges[1], weight),
            _arc_misfit(nu, n_f, edges[2], weight))


@njit(cache=True)
def _arc_misfit(nu, n_f, edge, weight):
    if np.isnan(edge[0]):
        return np.inf
    along, size, _, inside = _arc_nearest(nu, n_f, edge)
    return weight * (along * along + (size - 1.0) ** 2) if inside else np.inf


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
