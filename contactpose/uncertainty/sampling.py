"""Pose uncertainty of a hypothesis: posterior samples with emcee, and their summaries.

The posterior of one hypothesis (a finger-to-facet assignment) is written in the tangent
space at its factor-graph optimum T*: ``ξ = (ω, v) ∈ R⁶`` (rotation first) and
``T = T* · Exp(ξ)``, GTSAM's right perturbation and Pose3 exponential, the chart in which
:mod:`contactpose.solvers.factor_graph` reports its Laplace covariance. Then

    log p(ξ | z) = -Σ_i ρ(s_i(T)) - ½ Log(T_p⁻¹ T)ᵀ Σ_p⁻¹ Log(T_p⁻¹ T) + const,

with s_i the norm of contact i's whitened residual block and ρ the factor graph's kernel
(``s²/2`` for "none", GTSAM's Huber or Cauchy loss), evaluated by the factor graph's own
residual rows (costs.facet.factor_rows returns the square-rooted robust residual ẽ with
``½|ẽ|² = Σ_i ρ(s_i)``), so ``log p(0) = -½ chi2`` of the refinement.
The prior term is GTSAM's ``PriorFactorPose3`` error. The prior on ξ is otherwise flat
(Lebesgue in the chart; the Haar density differs from it by 1 + O(|ω|²)).

Sampling (:func:`run_ensemble`): emcee's ``EnsembleSampler`` with the vectorized log-prob
(``vectorize=True``). Moves: 80 % :class:`IndependenceMove` (each walker proposes a fresh
draw from a Gaussian fitted to the posterior) and 20 % emcee's ``DEMove``. A pilot of
PILOT_STEPS, started from N(0, INIT_SCALE² Σ_Laplace) and proposing from 1.2² Σ_Laplace,
is the burn-in; its sample mean and covariance then shape the proposal of the main chain.
The main chain runs in chunks until it is TAU_CHAIN (50) integrated autocorrelation times
long (emcee's own reliability rule, ``get_autocorr_time(tol=0)``) and holds the requested
samples after discarding BURN_TAU·τ steps and thinning by at least THIN_TAU·τ; at
``max_steps`` it stops and warns (:class:`SamplingWarning`). Where the posterior is near
Gaussian τ is 2-4 steps and 200 steps suffice; where it is not (few contacts, contacts at
a triangle's edge) the independence proposals are rejected more often, the DE moves carry
the chain, τ grows and the chain with it. All randomness comes from the ``rng`` passed in
(the walkers, and a seed for emcee's own RandomState).
"""

from __future__ import annotations

import logging
import sys
import time
import warnings
from dataclasses import KW_ONLY, dataclass

import emcee
import numpy as np

from contactpose.costs import surface
from contactpose.costs.facet import factor_rows, kernel_params, pack_contacts
from contactpose.errors import ContactPoseError, check_count
from contactpose.geometry import se3
from contactpose.model.memory import check_fits
from contactpose.schema import json_array, json_number
from contactpose.scoring import refine
from contactpose.scoring.rank import closed_form_arrays

log = logging.getLogger(__name__)

#: Posterior samples returned by default (per hypothesis).
DEFAULT_SAMPLES = 2000
#: Walkers of the ensemble (emcee asks for at least 2 · dim = 12).
DEFAULT_WALKERS = 32
#: Walkers start from N(0, INIT_SCALE² Σ): inside the posterior's bulk, spread enough
#: that the ensemble is not degenerate.
INIT_SCALE = 0.5
#: The chain must be this many autocorrelation times long (emcee's ``tol`` default).
TAU_CHAIN = 50
#: Burn-in and thinning, in autocorrelation times.
BURN_TAU = 3.0
THIN_TAU = 0.5
#: Steps of the first chunk, and the most steps of one chain.
FIRST_STEPS = 200
MAX_STEPS = 20000
#: Central credible intervals stored with the samples.
LEVELS = (0.68, 0.95)
#: Fraction of IndependenceMove steps (the rest are DEMove), and the proposal's scale on Σ.
INDEPENDENCE_FRACTION = 0.8
INDEPENDENCE_SCALE = 1.2
#: Pilot steps (burn-in, and the covariance of the main chain's proposal).
PILOT_STEPS = 200
#: |ω| at or beyond this is outside the chart (Exp is not one-to-one past π).
MAX_ANGLE = np.pi - 1e-6


class SamplingWarning(UserWarning):
    """The chain is too short to estimate its autocorrelation time reliably."""


# ----------------------------------------------------------- log-posterior ---

class PosePosterior:
    """log p(ξ | contacts) of one hypothesis in the tangent space at T*, vectorized.

    model : ObjectModel; contacts : Contacts (n contacts); facets : (n,) int, one facet per
    contact; T_opt : (4, 4) the chart's centre (the factor-graph optimum); tolerance :
    Tolerance (σ_x, σ_n); prior : PosePrior or None; robust : "huber" | "cauchy" | "none";
    point_to_facet : the lateral term, as in the factor graph; surface : the likelihood of the
    surface contact model instead (solvers.surface: a contact may land on a neighbouring
    facet, an edge or a vertex, its cost Σ_i ρ(√c_i) with c_i its whitened landing cost).

    Calling it with ξ : (W, 6) returns (W,) log-posteriors (-inf outside the chart).
    """

    def __init__(self, model, contacts, facets, T_opt, tolerance, *, prior=None, robust="huber",
                 point_to_facet=True, surface=False):
        facets = np.asarray(facets)
        if facets.shape != (contacts.n,):
            raise ContactPoseError(f"facets must have shape ({contacts.n},), got {facets.shape}")
        if facets.min() < 0 or facets.max() >= model.num_facets:
            raise ContactPoseError(f"facets must index the model's {model.num_facets} facets, got {facets.tolist()}")
        self.T_opt = _check_pose(T_opt, "T_opt")
        self.facets = facets
        self.data = pack_contacts(model, contacts, facets)
        self.params = kernel_params(tolerance, robust, point_to_facet)
        self.robust = robust
        self.prior = prior
        # surface: the contact model of solvers.surface, each contact landing near its facet
        self.surface = (model, contacts, tolerance) if surface else None
        if prior is not None:
            self._prior_inv_pose = np.linalg.inv(prior.pose)
            self._prior_info = np.linalg.inv(prior.covariance_matrix())

    def poses(self, xi):
        """T* · Exp(ξ). xi : (W, 6) -> (W, 4, 4)"""
        return self.T_opt @ se3.exp(xi)

    def tangent(self, T):
        """ξ = Log(T*⁻¹ T), the chart coordinates of poses. T : (W, 4, 4) or (4, 4) -> (W, 6)"""
        T = np.asanyarray(T, dtype=np.float64).reshape(-1, 4, 4)
        return se3.log(np.linalg.inv(self.T_opt) @ T)

    def log_likelihood(self, xi):
        """-Σ_i ρ(s_i) of the contacts at T* · Exp(ξ) (-inf outside the chart). xi : (W, 6) -> (W,)"""
        xi = _check_xi(xi)
        out = np.full(len(xi), -np.inf)
        inside = _in_chart(xi)
        if self.surface is not None:
            model, contacts, tolerance = self.surface
            out[inside] = -surface.robust_cost(model, contacts, self.poses(xi[inside]), self.facets, tolerance,
                                               self.robust)
            return out
        for w, T in zip(np.flatnonzero(inside), self.poses(xi[inside])):
            # the factor graph's own error: ½|ẽ|² = Σ_i ρ(s_i)
            e, _ = factor_rows(T, self.data, self.params, jacobian=False)
            out[w] = -0.5 * (e @ e)
        return out

    def log_prior(self, xi):
        """-½ Mahalanobis² of Log(T_p⁻¹ T), GTSAM's PriorFactorPose3 error (0 without a prior).
        xi : (W, 6) -> (W,)"""
        xi = _check_xi(xi)
        if self.prior is None:
            return np.where(_in_chart(xi), 0.0, -np.inf)
        out = np.full(len(xi), -np.inf)
        inside = _in_chart(xi)
        d = se3.log(self._prior_inv_pose @ self.poses(xi[inside]))
        out[inside] = -0.5 * np.einsum("wi,ij,wj->w", d, self._prior_info, d)
        return out

    def __call__(self, xi):
        xi = _check_xi(xi)
        out = self.log_likelihood(xi)
        if self.prior is not None:
            ok = np.isfinite(out)
            out[ok] += self.log_prior(xi[ok])
        return out


def _in_chart(xi):
    """(W,) bool: finite rows with |ω| < MAX_ANGLE (Exp is one-to-one there)."""
    return np.isfinite(xi).all(axis=1) & (np.einsum("wi,wi->w", xi[:, :3], xi[:, :3]) < MAX_ANGLE**2)


def _check_xi(xi):
    xi = np.ascontiguousarray(xi, dtype=np.float64)
    if xi.ndim == 1:
        xi = xi[None]
    if xi.ndim != 2 or xi.shape[1] != 6:
        raise ContactPoseError(f"xi must have shape (W, 6), got {xi.shape}")
    return xi


# ----------------------------------------------------------------- sampling ---

@dataclass
class EnsembleRun:
    """What :func:`run_ensemble` returns.

    xi : (N, 6) thinned samples after burn-in; log_prob : (N,); tau : (6,) integrated
    autocorrelation time per coordinate (steps); acceptance : mean acceptance fraction;
    steps, burn, thin, n_walkers : chain bookkeeping; converged : steps ≥ TAU_CHAIN · max τ;
    seconds : wall time.
    """

    xi: np.ndarray
    log_prob: np.ndarray
    tau: np.ndarray
    acceptance: float
    steps: int
    burn: int
    thin: int
    n_walkers: int
    converged: bool
    seconds: float


class IndependenceMove(emcee.moves.MHMove):
    """Independence Metropolis-Hastings: every walker proposes a fresh draw from
    N(mean, scale² Σ), whatever its position.

    With Σ the Laplace covariance (pilot) or the pilot's sample covariance (main chain),
    most proposals are accepted where the posterior is near Gaussian, and successive states
    are nearly independent (τ of a few steps); where it is not, the ensemble's DE moves
    carry the chain and τ grows, and the chain length follows τ. The Hastings factor is
    log q(x) - log q(x') = ½|z'|² - ½|z|², z = (scale L)⁻¹ (x - mean).
    """

    def __init__(self, mean, covariance, scale=INDEPENDENCE_SCALE):
        self.mean = np.asanyarray(mean, dtype=np.float64)
        self.L = scale * _sqrt_cov(np.asanyarray(covariance, dtype=np.float64))
        self.L_inv = np.linalg.inv(self.L)
        super().__init__(self._propose)

    def _propose(self, x, random):
        z_new = random.randn(*x.shape)
        z_old = (x - self.mean) @ self.L_inv.T
        factors = 0.5 * np.einsum("wi,wi->w", z_new, z_new) - 0.5 * np.einsum("wi,wi->w", z_old, z_old)
        return self.mean + z_new @ self.L.T, factors


def default_moves(mean, covariance):
    """emcee moves for a posterior near a Gaussian N(mean, covariance): IndependenceMove
    (INDEPENDENCE_FRACTION of the steps) and differential evolution (DEMove, the rest)."""
    return [(IndependenceMove(mean, covariance), INDEPENDENCE_FRACTION),
            (emcee.moves.DEMove(), 1.0 - INDEPENDENCE_FRACTION)]


def run_ensemble(log_prob, covariance, n_samples, rng, *, n_walkers=DEFAULT_WALKERS, init_scale=INIT_SCALE,
                 max_steps=MAX_STEPS, moves=None, progress=None):
    """Sample a vectorized log-density on R^d with emcee, sized by its autocorrelation time.

    log_prob : callable (W, d) -> (W,); covariance : (d, d) positive definite, an estimate of
    the target's covariance (the Laplace one); n_samples : samples wanted; rng : numpy
    Generator (seeds the walkers and emcee's own RandomState); moves : emcee moves of the
    main chain (default: :func:`default_moves` on the pilot's mean and covariance);
    progress : tqdm bar (default: when stderr is a terminal).

    Two stages. The pilot (PILOT_STEPS, discarded as burn-in) starts the walkers from
    N(0, init_scale² covariance) and moves them with :func:`default_moves` on ``covariance``.
    The main chain continues from the pilot's last state, its independence proposal now on
    the pilot's sample mean and covariance, and runs in chunks until it is TAU_CHAIN times
    its largest autocorrelation time τ (``get_autocorr_time(tol=0)``) and holds n_samples
    after discarding BURN_TAU·τ steps and thinning by THIN_TAU·τ, or until ``max_steps``
    (then a :class:`SamplingWarning`). -> :class:`EnsembleRun` with the last
    min(n_samples, available) samples.
    """
    clock = time.perf_counter()
    cov = np.asanyarray(covariance, dtype=np.float64)
    dim = cov.shape[0] if cov.ndim == 2 else 0
    if cov.shape != (dim, dim) or dim == 0 or not np.isfinite(cov).all():
        raise ContactPoseError(f"covariance must be a finite square matrix, got shape {cov.shape}")
    n_samples = check_count(n_samples, "n_samples")
    if check_count(n_walkers, "n_walkers", minimum=2 * dim) % 2:
        raise ContactPoseError(f"n_walkers must be an even integer >= {2 * dim}, got {n_walkers!r}")
    max_steps = check_count(max_steps, "max_steps")
    # emcee keeps (steps, walkers, d + 1) float64 and copies it as the chain grows
    check_fits(16 * n_walkers * (dim + 1) * (max_steps + PILOT_STEPS), f"sampling {n_walkers} walkers for up to "
               f"{max_steps:,} steps", "lower n_walkers or max_steps")
    if not isinstance(rng, np.random.Generator):
        raise ContactPoseError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    from tqdm.auto import tqdm

    x0, lp0 = _initial_walkers(log_prob, _sqrt_cov(cov), n_walkers, init_scale, rng)
    # emcee draws from its own RandomState: seed it from rng, never from the global state
    state = emcee.State(x0, log_prob=lp0, random_state=np.random.RandomState(rng.integers(2**32)).get_state())
    show = sys.stderr.isatty() if progress is None else bool(progress)
    with tqdm(total=PILOT_STEPS + FIRST_STEPS, desc="sampling", unit="step", disable=not show, leave=False) as bar:
        pilot = emcee.EnsembleSampler(n_walkers, dim, log_prob, vectorize=True,
                                      moves=default_moves(np.zeros(dim), cov))
        for state in pilot.sample(state, iterations=PILOT_STEPS):
            bar.update(1)
        warm = pilot.get_chain(discard=PILOT_STEPS // 2, flat=True)
        if moves is None:
            moves = default_moves(warm.mean(axis=0), np.cov(warm, rowvar=False))
        sampler = emcee.EnsembleSampler(n_walkers, dim, log_prob, vectorize=True, moves=moves)
        target, done = min(FIRST_STEPS, max_steps), 0
        while True:
            for state in sampler.sample(state, iterations=target - done):
                bar.update(1)
            done = target
            tau = np.asarray(sampler.get_autocorr_time(tol=0), dtype=np.float64)
            tau_max = float(np.nanmax(tau)) if np.isfinite(tau).any() else float(done)
            burn, thin = _burn_thin(tau_max, done)
            available = (done - burn) // thin * n_walkers
            need = int(np.ceil(TAU_CHAIN * tau_max))
            if (done >= need and available >= n_samples) or done >= max_steps:
                break
            more = int(np.ceil((n_samples - available) / n_walkers)) * thin if available < n_samples else 0
            # 10 % beyond the current estimate: τ tends to grow as the chain gets longer
            target = min(max_steps, int(1.1 * max(need, done + more)) + 1)
            bar.total = PILOT_STEPS + target
            bar.refresh()
    converged = done >= TAU_CHAIN * tau_max
    if not converged:
        warnings.warn(f"chain of {done} steps is shorter than {TAU_CHAIN} autocorrelation times "
                      f"({TAU_CHAIN} x {tau_max:.1f}): tau and the samples are not reliable; "
                      f"raise max_steps (now {max_steps})", SamplingWarning, stacklevel=2)
    # thin further when the chain holds more than asked: the samples then span all of it
    thin = max(thin, (done - burn) // int(np.ceil(n_samples / n_walkers)))
    xi = sampler.get_chain(discard=burn, thin=thin, flat=True)[-n_samples:]
    lp = sampler.get_log_prob(discard=burn, thin=thin, flat=True)[-n_samples:]
    if len(xi) < n_samples:
        warnings.warn(f"only {len(xi)} of {n_samples} samples after burn-in {burn} and thinning {thin} "
                      f"within max_steps={max_steps}", SamplingWarning, stacklevel=2)
    return EnsembleRun(xi, lp, tau, float(np.mean(sampler.acceptance_fraction)), done, PILOT_STEPS + burn, thin,
                       n_walkers, bool(converged), time.perf_counter() - clock)


def _burn_thin(tau_max, steps):
    """Burn-in and thinning (steps) from the largest autocorrelation time."""
    burn = min(int(np.ceil(BURN_TAU * tau_max)), steps // 2)
    return burn, max(1, int(THIN_TAU * tau_max))


def _sqrt_cov(cov):
    """A square root L (L Lᵀ = cov) of a symmetric PSD matrix, eigenvalues floored."""
    cov = 0.5 * (cov + cov.T)
    vals, vecs = np.linalg.eigh(cov)
    if vals.max() <= 0:
        raise ContactPoseError("covariance must have a positive eigenvalue")
    return vecs * np.sqrt(np.maximum(vals, 1e-12 * vals.max()))


def _initial_walkers(log_prob, L, n_walkers, scale, rng, tries=30):
    """Walkers from N(0, scale² L Lᵀ) with finite log-prob; shrink the draws that are not."""
    x = scale * rng.standard_normal((n_walkers, L.shape[0])) @ L.T
    lp = np.asarray(log_prob(x), dtype=np.float64)
    for _ in range(tries):
        bad = ~np.isfinite(lp)
        if not bad.any():
            return x, lp
        scale *= 0.5
        x[bad] = scale * rng.standard_normal((bad.sum(), L.shape[0])) @ L.T
        lp[bad] = log_prob(x[bad])
    raise ContactPoseError(f"{int(bad.sum())} of {n_walkers} starting walkers have log-prob -inf or NaN "
                           "near the optimum: is T_opt a pose this hypothesis supports?")


# --------------------------------------------------------------- summaries ---

@dataclass
class PoseSamples(EnsembleRun):
    """Posterior samples of one hypothesis's pose: the :class:`EnsembleRun` that drew them
    (xi : (N, 6) tangent coordinates at T_opt, rotation first, radians; translation in the
    object frame at T_opt, length units; log_prob : (N,) log-posterior up to a constant; the
    chain's tau, acceptance, steps, ...) and, keyword-only:

    poses : (N, 4, 4) T_world_object; T_opt : (4, 4) chart centre; facets : (n,) int;
    mean : (6,); covariance : (6, 6) sample covariance of xi (rotation first);
    intervals : {level: (6, 2)} central credible intervals per axis of xi, rotation rows in
    degrees, translation rows in length units;
    laplace_covariance : (6, 6) the covariance the walkers started from, for comparison.
    """

    _: KW_ONLY
    poses: np.ndarray
    T_opt: np.ndarray
    facets: np.ndarray
    mean: np.ndarray
    covariance: np.ndarray
    intervals: dict
    laplace_covariance: np.ndarray | None = None

    def credible_interval(self, level):
        """(6, 2) central interval holding ``level`` of the samples per axis; rotation in degrees."""
        if not (0.0 < level < 1.0):
            raise ContactPoseError(f"level must be in (0, 1), got {level!r}")
        q = np.quantile(self.xi, [0.5 - level / 2, 0.5 + level / 2], axis=0).T
        q[:3] = np.degrees(q[:3])
        return q

    def mahalanobis2(self, xi):
        """Squared Mahalanobis distance from the sample mean under the sample covariance.
        xi : (K, 6) -> (K,)"""
        d = np.atleast_2d(xi) - self.mean
        return np.einsum("ki,ki->k", d, np.linalg.solve(self.covariance, d.T).T)

    def hpd_credibility(self, log_prob):
        """Smallest HPD level whose region holds a point of this log-posterior: the fraction
        of samples with a higher log-posterior. log_prob : (K,) -> (K,) in [0, 1]"""
        lp = np.sort(self.log_prob)
        return 1.0 - np.searchsorted(lp, np.atleast_1d(log_prob), side="left") / len(lp)

    def summary(self):
        """A JSON-ready summary (no samples; ``$defs/samples`` of contactpose/data/result.schema.json).

        mean (6,) and covariance (6, 6) of ξ in radians and length units; intervals
        {"0.68", "0.95": (6, 2)} with rotation rows in degrees; tau in chain steps; time_ms in
        milliseconds; NaN as null.
        """
        return {
            "n_samples": int(len(self.xi)), "mean": json_array(self.mean), "covariance": json_array(self.covariance),
            "intervals": {f"{k:g}": json_array(v) for k, v in self.intervals.items()},
            "tau": json_array(self.tau), "acceptance": json_number(self.acceptance), "steps": int(self.steps),
            "burn": int(self.burn), "thin": int(self.thin), "n_walkers": int(self.n_walkers),
            "converged": bool(self.converged), "time_ms": 1000.0 * float(self.seconds),
        }


def summarize(run, posterior, laplace_covariance=None):
    """PoseSamples of an :class:`EnsembleRun` on a :class:`PosePosterior`."""
    xi = run.xi
    mean = xi.mean(axis=0)
    cov = np.cov(xi, rowvar=False) if len(xi) > 1 else np.full((xi.shape[1],) * 2, np.nan)
    out = PoseSamples(**vars(run), poses=posterior.poses(xi), T_opt=posterior.T_opt, facets=posterior.facets,
                      mean=mean, covariance=cov, intervals={}, laplace_covariance=laplace_covariance)
    out.intervals = {level: out.credible_interval(level) for level in LEVELS}
    return out


def sample_pose(model, contacts, hypothesis_facets, T_opt, covariance, tolerance, *, prior=None, robust="huber",
                n_samples=DEFAULT_SAMPLES, rng, n_walkers=DEFAULT_WALKERS, progress=None, point_to_facet=True,
                max_steps=MAX_STEPS, surface=False):
    """Posterior samples of one hypothesis's pose.

    model : ObjectModel; contacts : Contacts; hypothesis_facets : (n,) int; T_opt : (4, 4)
    factor-graph optimum; covariance : (6, 6) its Laplace covariance (walker start; if not
    finite, a regularised Gauss-Newton one is used); tolerance : Tolerance; prior, robust,
    point_to_facet : as given to the factor graph; rng : numpy Generator; surface : sample the
    surface contact model's posterior (:class:`PosePosterior`). -> PoseSamples
    """
    post = PosePosterior(model, contacts, hypothesis_facets, T_opt, tolerance, prior=prior, robust=robust,
                         point_to_facet=point_to_facet, surface=surface)
    cov = start_covariance(post, covariance, model.diameter)
    run = run_ensemble(post, cov, n_samples, rng, n_walkers=n_walkers, progress=progress, max_steps=max_steps)
    return summarize(run, post, cov)


def start_covariance(posterior, covariance, diameter):
    """The walkers' spread: the Laplace covariance when it is finite and positive definite,
    else the inverse Gauss-Newton Hessian at T* with each direction's variance capped at
    (5°)² and (1 % of the diameter)² (directions the contacts leave free)."""
    cov = None if covariance is None else np.asanyarray(covariance, dtype=np.float64)
    if cov is not None and cov.shape == (6, 6) and np.isfinite(cov).all() and np.linalg.eigvalsh(cov).min() > 0:
        return cov
    e, J = factor_rows(posterior.T_opt, posterior.data, posterior.params)
    H = J.T @ J
    if posterior.prior is not None:
        H = H + posterior._prior_info  # Gauss-Newton of the prior at its centre
    cap = np.diag(1.0 / np.square([np.radians(5.0)] * 3 + [0.01 * diameter] * 3))
    log.info("no Laplace covariance: walkers start from the capped Gauss-Newton covariance")
    return np.linalg.inv(H + cap)


# ----------------------------------------------------------------- mixture ---

@dataclass
class MixtureSamples:
    """Samples from the mixture of hypotheses' posteriors, weighted by their probabilities.

    poses : (N, 4, 4); component : (N,) int, which hypothesis each sample came from;
    weights : (K,) the mixture weights; components : K PoseSamples (None for a component
    that drew no samples).
    """

    poses: np.ndarray
    component: np.ndarray
    weights: np.ndarray
    components: list


def sample_mixture(model, contacts, facets, poses, covariances, probabilities, tolerance, *, prior=None,
                   robust="huber", n_samples=DEFAULT_SAMPLES, rng, n_walkers=DEFAULT_WALKERS, progress=None,
                   point_to_facet=True):
    """Samples of the pose under the mixture Σ_k p_k · posterior_k of K hypotheses.

    facets : (K, n) int; poses : (K, 4, 4) optima; covariances : (K, 6, 6) Laplace;
    probabilities : (K,) (renormalised; NaN counts as 0). Each component gets a multinomial
    share of n_samples. -> MixtureSamples
    """
    facets = np.asarray(facets)
    p = np.nan_to_num(np.asarray(probabilities, dtype=np.float64), nan=0.0)
    if facets.ndim != 2 or len(p) != len(facets) or p.sum() <= 0 or (p < 0).any():
        raise ContactPoseError(f"need (K, n) facets and K non-negative probabilities with a positive sum, "
                               f"got facets {facets.shape} and probabilities {p.tolist()}")
    p = p / p.sum()
    counts = rng.multinomial(n_samples, p)
    components, all_poses, labels = [], [], []
    for k, count in enumerate(counts):
        if count == 0:
            components.append(None)
            continue
        s = sample_pose(model, contacts, facets[k], poses[k], covariances[k], tolerance, prior=prior,
                        robust=robust, n_samples=int(count), rng=rng, n_walkers=n_walkers, progress=progress,
                        point_to_facet=point_to_facet)
        components.append(s)
        all_poses.append(s.poses)
        labels.append(np.full(len(s.poses), k))
    return MixtureSamples(np.concatenate(all_poses), np.concatenate(labels), p, components)


# ------------------------------------------------------- ranked hypotheses ---

def sample_hypotheses(model, contacts, hypotheses, tolerance, n_samples, rng, *, prior=None, robust="huber",
                      top=1, progress=None, surface=False):
    """Posterior samples of the best ``top`` hypotheses: dict rank -> PoseSamples.

    hypotheses : a ranked sequence of Hypothesis (``Result.hypotheses``). Hypotheses that
    carry a finite factor-graph ``covariance`` are sampled around their ``pose``; the others
    are first refined with :func:`scoring.refine.refine_hypotheses` (same prior and kernel) on
    their facets. Fingers left unassigned (facet -1) are left out. The caller attaches the
    samples (``localize`` puts them on ``.samples`` and ``.sample_covariance``).
    """
    top = check_count(top, "top")
    n_samples = check_count(n_samples, "samples")
    out = {}
    for rank, h in enumerate(hypotheses[:top]):
        keep = np.flatnonzero(np.asarray(h.facets) >= 0)
        sub = contacts if len(keep) == contacts.n else contacts.permuted(keep)
        facets = np.asarray(h.facets)[keep]
        T, cov = h.pose, h.covariance
        if cov is None or not np.isfinite(cov).all():
            T, cov, facets = refine_one(model, sub, facets, tolerance, prior=prior, robust=robust)
        out[rank] = sample_pose(model, sub, facets, T, cov, tolerance, prior=prior, robust=robust,
                                n_samples=n_samples, rng=rng, progress=progress, surface=surface)
    return out


def refine_one(model, contacts, facets, tolerance, *, prior=None, robust="huber", point_to_facet=True):
    """Factor-graph optimum, Laplace covariance and (possibly patch-moved) facets of one
    facet tuple. facets : (n,) int -> (4, 4), (6, 6), (n,) int"""
    arrays = closed_form_arrays(model, contacts, np.asarray(facets)[None], tolerance, angle_tol=tolerance.angle)
    ref = refine.refine_hypotheses(model, contacts, arrays, tolerance, prior=prior, robust=robust, k=1,
                               point_to_facet=point_to_facet)
    return ref.poses[0], ref.covariance[0], ref.facets[0]


def _check_pose(T, name):
    T = np.asanyarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ContactPoseError(f"{name} must be a finite (4, 4) pose, got shape {T.shape}")
    return T
