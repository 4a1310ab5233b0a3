"""Tests of contactpose.uncertainty.sampling against independent references.

References: GTSAM's Pose3 Expmap/Logmap, PriorFactorPose3 error and mEstimator losses; the
factor graph's χ² at its optimum; a known Gaussian sampled with the same driver (emcee
style: fixed seeds and tolerance bands, never equality of random output); the Laplace
covariance where the posterior is Gaussian to first order.
"""

import gtsam
import numpy as np
import pytest

from contactpose.contacts import Contacts, Tolerance
from contactpose.costs import facet
from contactpose.costs import robust as kernels
from contactpose.errors import ContactPoseError
from contactpose.geometry import se3
from contactpose.localize import localize
from contactpose.options import ROBUST
from contactpose.scoring import refine
from contactpose.scoring.rank import closed_form_arrays
from contactpose.sim import grasps as simulate
from contactpose.solvers import factor_graph as fg
from contactpose.types import PosePrior
from contactpose.uncertainty import sampling as unc


def _tolerance(model, position_frac=0.0025, normal_deg=1.0):
    return Tolerance.from_noise(position_frac * model.diameter, normal_deg)


def _grasp(model, seed, n=4, where="area"):
    rng = np.random.default_rng(seed)
    tol = _tolerance(model)
    g = simulate.grasp(model, rng, n=n, where=where, position_noise=tol.position_noise,
                       normal_noise_deg=np.degrees(tol.normal_noise))
    return g, tol


def _refined(model, g, tol, **kw):
    arrays = closed_form_arrays(model, g.contacts, g.facets[None], tol)
    return refine.refine_hypotheses(model, g.contacts, arrays, tol, k=1, **kw)


# ---------------------------------------------------------- log-posterior ---

@pytest.mark.parametrize("robust", ["none", "huber", "cauchy"])
def test_log_prob_at_optimum_is_minus_half_factor_graph_chi2(rock_model, robust):
    g, tol = _grasp(rock_model, 1)
    prior = PosePrior(gtsam.Pose3(g.pose).retract(np.r_[0.05, -0.03, 0.02, 0.002, 0.001, -0.003]).matrix(),
                      sigma_rot_deg=5.0, sigma_trans=0.01)
    for p in (None, prior):
        ref = _refined(rock_model, g, tol, robust=robust, prior=p)
        post = unc.PosePosterior(rock_model, g.contacts, ref.facets[0], ref.poses[0], tol, prior=p, robust=robust)
        assert post(np.zeros((1, 6)))[0] == pytest.approx(-0.5 * ref.chi2[0], rel=1e-10, abs=1e-10)


def test_log_prior_is_gtsam_prior_factor_error(rock_model):
    g, tol = _grasp(rock_model, 2)
    cov = np.diag([0.01, 0.02, 0.015, 1e-4, 2e-4, 1.5e-4])
    cov[0, 4] = cov[4, 0] = 5e-4
    prior = PosePrior(gtsam.Pose3(g.pose).retract([0.1, 0.0, -0.05, 0.01, 0.0, 0.0]).matrix(), covariance=cov)
    post = unc.PosePosterior(rock_model, g.contacts, g.facets, g.pose, tol, prior=prior)
    xi = np.random.default_rng(3).normal(size=(8, 6)) * 0.05
    factor = fg.prior_factor(prior)
    for x, lp in zip(xi, post.log_prior(xi)):
        values = gtsam.Values()
        values.insert(fg.POSE_KEY, gtsam.Pose3(g.pose).retract(x))
        assert lp == pytest.approx(-factor.error(values), rel=1e-9)
    np.testing.assert_allclose(post(xi), post.log_likelihood(xi) + post.log_prior(xi))


def test_robust_kernel_bounds_the_penalty_of_a_far_contact(rock_model):
    g, tol = _grasp(rock_model, 4, where="centroid")
    points = g.contacts.points.copy()
    points[0] += 40 * tol.position_noise * g.contacts.object_normals[0]  # 40 σ off its plane
    bad = Contacts(points, object_normals=g.contacts.object_normals)
    lik = {r: unc.PosePosterior(rock_model, bad, g.facets, g.pose, tol, robust=r).log_likelihood(np.zeros((1, 6)))[0]
           for r in ROBUST}
    assert lik["none"] < lik["huber"] < lik["cauchy"] < 0
    # reference: GTSAM's mEstimator losses on each contact's whitened block norm s_i
    e, _ = facet.factor_rows(g.pose, facet.pack_contacts(rock_model, bad, g.facets), facet.kernel_params(tol))
    n = bad.n
    blocks = np.stack([e[3 * i:3 * i + 3].tolist() + [e[3 * n + i], e[4 * n + 2 * i], e[4 * n + 2 * i + 1]]
                       for i in range(n)])
    s = np.linalg.norm(blocks, axis=1)
    assert s[0] > 35 and lik["none"] == pytest.approx(-0.5 * np.sum(s**2), rel=1e-12)
    huber = gtsam.noiseModel.mEstimator.Huber.Create(kernels.HUBER_K)
    cauchy = gtsam.noiseModel.mEstimator.Cauchy.Create(kernels.CAUCHY_K)
    assert lik["huber"] == pytest.approx(-sum(huber.loss(x) for x in s), rel=1e-9)
    assert lik["cauchy"] == pytest.approx(-sum(cauchy.loss(x) for x in s), rel=1e-9)


def test_log_prob_outside_chart_or_nan_is_minus_inf(banana_model):
    g, tol = _grasp(banana_model, 5)
    post = unc.PosePosterior(banana_model, g.contacts, g.facets, g.pose, tol)
    out = post(np.array([[4.0, 0, 0, 0, 0, 0], [np.nan, 0, 0, 0, 0, 0], [0.0] * 6]))
    assert out[0] == -np.inf and out[1] == -np.inf and np.isfinite(out[2])
    with pytest.raises(ContactPoseError, match="facets must have shape"):
        unc.PosePosterior(banana_model, g.contacts, g.facets[:2], g.pose, tol)


# -------------------------------------------------------------- sampling ---

def _gaussian(dim=6, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(dim, dim))
    cov = A @ A.T / dim + 0.1 * np.eye(dim)
    scales = np.r_[[0.01] * 3, [0.001] * 3]  # radians and metres, as in a pose posterior
    cov = cov * np.outer(scales, scales)
    mean = 0.3 * scales * rng.normal(size=dim)
    info = np.linalg.inv(cov)

    def log_prob(x):
        d = x - mean
        return -0.5 * np.einsum("wi,ij,wj->w", d, info, d)
    return mean, cov, log_prob


def test_known_gaussian_mean_and_covariance_within_bands():
    mean, cov, log_prob = _gaussian()
    # start from a wrong guess: twice too wide, no correlations
    guess = 4.0 * np.diag(np.diag(cov))
    run = unc.run_ensemble(log_prob, guess, 4000, np.random.default_rng(1), progress=False)
    assert run.converged and run.steps >= unc.TAU_CHAIN * run.tau.max()
    assert len(run.xi) == 4000 and 0.2 < run.acceptance < 0.95
    sd = np.sqrt(np.diag(cov))
    ess = run.steps * run.n_walkers / run.tau.max()
    # mean within 5 Monte-Carlo standard errors; covariance within 15 % (correlations 0.1)
    assert np.all(np.abs(run.xi.mean(axis=0) - mean) < 5 * sd / np.sqrt(ess))
    sample = np.cov(run.xi, rowvar=False)
    np.testing.assert_allclose(np.diag(sample) / np.diag(cov), 1.0, atol=0.15)
    corr = sample / np.outer(np.sqrt(np.diag(sample)), np.sqrt(np.diag(sample)))
    np.testing.assert_allclose(corr, cov / np.outer(sd, sd), atol=0.1)
    # 68 % and 95 % of the samples inside the Gaussian's regions (χ²₆ quantiles)
    d2 = np.einsum("wi,ij,wj->w", run.xi - mean, np.linalg.inv(cov), run.xi - mean)
    assert np.mean(d2 <= 7.0406) == pytest.approx(0.68, abs=0.04)
    assert np.mean(d2 <= 12.5916) == pytest.approx(0.95, abs=0.02)


def test_pose_posterior_matches_laplace_where_linear(banana_model):
    """Contacts at facet centroids (lateral term flat), no kernel, small noise: the posterior
    is Gaussian to first order, and the samples reproduce the factor graph's covariance."""
    rng = np.random.default_rng(6)
    tol = _tolerance(banana_model, 0.0005, 0.2)
    g = simulate.grasp(banana_model, rng, n=5, where="centroid", position_noise=tol.position_noise,
                       normal_noise_deg=0.2)
    ref = _refined(banana_model, g, tol, robust="none")
    s = unc.sample_pose(banana_model, g.contacts, ref.facets[0], ref.poses[0], ref.covariance[0], tol,
                        robust="none", n_samples=3000, rng=rng, progress=False)
    lap = ref.covariance[0]
    np.testing.assert_allclose(np.diag(s.covariance) / np.diag(lap), 1.0, atol=0.2)
    assert np.all(np.abs(s.mean) < 4 * np.sqrt(np.diag(lap) * s.tau.max() / (s.steps * s.n_walkers)))
    assert s.poses.shape == (3000, 4, 4) and s.xi.shape == (3000, 6)
    np.testing.assert_allclose(s.poses, ref.poses[0] @ se3.exp(s.xi))
    # 95 % intervals about ±1.96 σ of the Laplace marginals; rotation rows in degrees
    half = np.diff(s.intervals[0.95], axis=1)[:, 0] / 2
    sd = np.sqrt(np.diag(lap))
    sd[:3] = np.degrees(sd[:3])
    np.testing.assert_allclose(half / (1.96 * sd), 1.0, atol=0.2)
    assert s.seconds < 10.0


def test_fixed_seed_repeats_and_other_seed_differs(banana_model):
    g, tol = _grasp(banana_model, 7)
    ref = _refined(banana_model, g, tol)
    args = (banana_model, g.contacts, ref.facets[0], ref.poses[0], ref.covariance[0], tol)
    a = unc.sample_pose(*args, n_samples=500, rng=np.random.default_rng(11), progress=False)
    b = unc.sample_pose(*args, n_samples=500, rng=np.random.default_rng(11), progress=False)
    c = unc.sample_pose(*args, n_samples=500, rng=np.random.default_rng(12), progress=False)
    np.testing.assert_array_equal(a.xi, b.xi)
    np.testing.assert_array_equal(a.tau, b.tau)
    assert not np.array_equal(a.xi, c.xi)


def test_short_chain_warns():
    mean, cov, log_prob = _gaussian()
    with pytest.warns(unc.SamplingWarning, match="autocorrelation times"):
        run = unc.run_ensemble(log_prob, cov, 100, np.random.default_rng(2), max_steps=20, progress=False)
    assert not run.converged and run.steps == 20


def test_hpd_and_mahalanobis_helpers():
    mean, cov, log_prob = _gaussian()
    run = unc.run_ensemble(log_prob, cov, 2000, np.random.default_rng(3), progress=False)
    s = unc.PoseSamples(**vars(run), poses=se3.exp(run.xi), T_opt=np.eye(4), facets=np.zeros(4, int),
                        mean=run.xi.mean(0), covariance=np.cov(run.xi, rowvar=False), intervals={})
    # a point at the mode has credibility ~0, one far out ~1; HPD and Mahalanobis agree for a Gaussian
    cred = s.hpd_credibility(log_prob(np.stack([mean, mean + 10 * np.sqrt(np.diag(cov))])))
    assert cred[0] < 0.01 and cred[1] == 1.0
    probe = mean + np.random.default_rng(4).multivariate_normal(np.zeros(6), cov, 200)
    inside_hpd = s.hpd_credibility(log_prob(probe)) <= 0.68
    inside_mah = s.mahalanobis2(probe) <= 7.0406
    assert np.mean(inside_hpd == inside_mah) > 0.9


def test_input_errors():
    mean, cov, log_prob = _gaussian()
    rng = np.random.default_rng(0)
    with pytest.raises(ContactPoseError, match="n_walkers"):
        unc.run_ensemble(log_prob, cov, 10, rng, n_walkers=7)
    with pytest.raises(ContactPoseError, match="n_samples"):
        unc.run_ensemble(log_prob, cov, 0, rng)
    with pytest.raises(ContactPoseError, match="Generator"):
        unc.run_ensemble(log_prob, cov, 10, 3)
    with pytest.raises(ContactPoseError, match="log-prob -inf"):
        unc.run_ensemble(lambda x: np.full(len(x), -np.inf), cov, 10, rng)


# ------------------------------------------------------ localize and mixture ---

def test_sample_hypotheses_of_closed_form_result(banana_model):
    g, tol = _grasp(banana_model, 8)
    result = localize(banana_model, g.contacts, position_noise=tol.position_noise,
                      normal_noise_deg=np.degrees(tol.normal_noise), distinct=False)
    samples = unc.sample_hypotheses(banana_model, g.contacts, result.hypotheses, result.tolerance, 300,
                                    np.random.default_rng(0), top=2)
    assert sorted(samples) == list(range(min(2, len(result.hypotheses))))
    for rank, s in samples.items():
        assert s.poses.shape == (300, 4, 4) and s.covariance.shape == (6, 6)
        # the chart's centre is the refined pose, close to the closed form's
        pose = result.hypotheses[rank].pose
        assert np.linalg.norm(s.T_opt[:3, 3] - pose[:3, 3]) < 0.05 * banana_model.diameter


def test_sample_hypotheses_uses_factor_graph_covariance(banana_model):
    g, tol = _grasp(banana_model, 8)
    result = localize(banana_model, g.contacts, position_noise=tol.position_noise,
                      normal_noise_deg=np.degrees(tol.normal_noise), solver="factor-graph")
    best = result.hypotheses[0]
    assert best.covariance is not None and np.isfinite(best.covariance).all()
    s = unc.sample_hypotheses(banana_model, g.contacts, result.hypotheses, result.tolerance, 300,
                              np.random.default_rng(0), top=1)[0]
    # sampled around the factor graph's own optimum, started from its covariance
    np.testing.assert_array_equal(s.T_opt, best.pose)
    np.testing.assert_array_equal(s.laplace_covariance, best.covariance)
    assert s.covariance.shape == (6, 6)


def test_mixture_splits_samples_by_probability(banana_model):
    g, tol = _grasp(banana_model, 9)
    result = localize(banana_model, g.contacts, position_noise=tol.position_noise,
                      normal_noise_deg=np.degrees(tol.normal_noise))
    ref = refine.refine_hypotheses(banana_model, g.contacts, result.hypotheses.arrays, tol, k=3)
    ok = ref.determined
    m = unc.sample_mixture(banana_model, g.contacts, ref.facets[ok], ref.poses[ok], ref.covariance[ok],
                           ref.probability[ok], tol, n_samples=400, rng=np.random.default_rng(1), progress=False)
    assert len(m.poses) == 400 and m.weights.sum() == pytest.approx(1.0)
    counts = np.bincount(m.component, minlength=len(m.weights))
    assert counts.sum() == 400
    # multinomial counts within 5 binomial standard deviations of the weights
    assert np.all(np.abs(counts - 400 * m.weights) <= 5 * np.sqrt(400 * m.weights * (1 - m.weights)) + 1)


# ------------------------------------------------------ surface posterior ---

@pytest.mark.parametrize("robust", ["none", "huber", "cauchy"])
def test_robust_rho_is_the_gtsam_loss(robust):
    s = np.linspace(0.0, 12.0, 97)
    got = kernels.robust_rho(s, robust)
    if robust == "none":
        ref = 0.5 * s**2
    else:
        est = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}[robust]
        ref = np.array([est.Create(kernels.kernel_width(robust)).loss(x) for x in s])
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("robust", ["none", "huber"])
def test_surface_posterior_is_the_facet_posterior_where_contacts_stay_on_their_faces(rock_model, robust):
    """Near a pose where every contact lands on its own face, the surface contact model's
    likelihood is the factor graph's (normal, offset and lateral terms of those facets); where
    a contact lands elsewhere it is lower in cost, never higher (the facet is one feature)."""
    from contactpose.costs.surface import landing

    g, tol = _grasp(rock_model, 3)
    ref = _refined(rock_model, g, tol, robust=robust)
    T, facets = ref.poses[0], ref.facets[0]
    facet = unc.PosePosterior(rock_model, g.contacts, facets, T, tol, robust=robust)
    surface = unc.PosePosterior(rock_model, g.contacts, facets, T, tol, robust=robust, surface=True)
    xi = np.random.default_rng(4).normal(size=(200, 6)) * np.r_[[0.01] * 3, [0.002] * 3]
    a, b = facet.log_likelihood(xi), surface.log_likelihood(xi)
    own = np.array([np.array_equal(landing(rock_model, g.contacts, P[:3, :3], P[:3, 3], facets, tol).facet, facets)
                    and (landing(rock_model, g.contacts, P[:3, :3], P[:3, 3], facets, tol).kind == 0).all()
                    for P in facet.poses(xi)])
    assert 20 < own.sum() < len(xi)
    np.testing.assert_allclose(b[own], a[own], rtol=1e-9, atol=1e-9)
    assert np.all(b >= a - 1e-9)
