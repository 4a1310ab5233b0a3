"""Particle-filter global localization after the Scaling Series (Petrovskaya & Khatib, "Global
localization of objects via touch", IEEE T-RO 2011), in two forms.

:func:`scaling_series_published` runs the algorithm as published: its schedule of
N = log2(Vol(S_δ0)/Vol(S_δ*)) scales, M particles per δ-neighbourhood, no cap on the particle
set, a last cover weighted at τ = 1 (research/baselines.md gives the source of each step and
setting). :func:`scaling_series` is the budgeted variant the baselines were tuned with: particles
in SE(3) are refined over a sequence of shrinking neighbourhoods δ_k = δ_0 · zoom^k; at each
scale, ``per_ball`` samples are drawn uniformly in the δ-ball of every surviving particle,
weighted by the contact likelihood annealed to the scale (σ² inflated by τ = (δ_k/δ*)²), and
pruned by importance resampling to at most ``max_particles``. The scales stop at δ*, the
resolution the measurement noise supports. Both score a pose with the peers' contact likelihood
(peers.surface.contact_cost).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from contactpose.peers.surface import BaselineResult, contact_cost

#: Dimension of the pose space (for the Scaling Series zoom factor 2^(-1/dim)).
POSE_DIM = 6
#: The published zoom: each scale halves the volume of a δ-neighbourhood.
ZOOM = 2.0 ** (-1.0 / POSE_DIM)
#: Particles per δ-neighbourhood of the published form (research/baselines.md: the setting of the
#: reproduction that compared the Memory Unscented Particle Filter with it).
PER_NEIGHBOURHOOD = 3
#: Redraws of a cover sample that falls in the neighbourhood of an earlier particle.
COVER_TRIES = 5
#: The published form stops (and says so) when a cover would exceed this many particles.
MAX_COVER = 200_000


def _ball(rng, count, dim=POSE_DIM):
    """count points uniform in the unit ball of R^dim -> (count, dim)."""
    g = rng.normal(size=(count, dim))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    return g * rng.random((count, 1)) ** (1.0 / dim)


def _perturb(R, c, u, delta, radius):
    """Move particles (R (P, 3, 3), object-centre position c (P, 3)) by u (P, 6) in the unit
    ball scaled to delta: rotation vector δ·u[:3]/radius about the centre (world frame), shift δ·u[3:]."""
    dR = Rotation.from_rotvec(delta * u[:, :3] / radius).as_matrix()
    return np.einsum("pij,pjk->pik", dR, R), c + delta * u[:, 3:]


def _poses(R, c, center):
    """T_world_object of particles given their rotation and the world position of the surface centre."""
    T = np.zeros((len(R), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = c - R @ center
    T[:, 3, 3] = 1.0
    return T


def scaling_series(model, surface, contacts, rng, *, position_noise, normal_noise_deg, prior=None,
                   initial=2000, per_ball=8, max_particles=2000, delta_final=None, zoom=ZOOM):
    """Scaling-Series pose estimate from contacts, with a prior (PosePrior) or globally.

    Pose metric: translation of the surface centre plus rotation angle times the surface
    radius ρ, so a δ-ball moves no surface point by more than about 2δ. Start: ``initial``
    particles from the prior (Gaussian) with δ_0 = 3·max(σ_t, ρ·σ_rot), or uniform rotations
    with the centre uniform in the ρ-ball around the contacts' centroid (every contact lies
    within ρ of the centre) with δ_0 = π·ρ. Each scale: δ ← zoom·δ, τ = max(1, (δ/δ*)²);
    ``per_ball`` uniform samples in the previous δ-ball of each survivor (survivors capped at
    max_particles / per_ball); weights exp(-χ²/(2τ)); importance resampling, duplicates
    removed. δ* (default: max(σ_x, ρ·σ_n)·3) is where the scales stop. The estimate is the
    lowest-χ² particle of the last scale.
    """
    rho = surface.radius
    sigma_n = np.radians(normal_noise_deg)
    if delta_final is None:
        delta_final = 3.0 * max(position_noise, rho * sigma_n)
    # initial particles: rotation R (P, 3, 3) and world position of the surface centre c (P, 3)
    if prior is not None:
        cov = prior.covariance_matrix()
        xi = rng.multivariate_normal(np.zeros(6), cov, size=initial)
        R = Rotation.from_rotvec(xi[:, :3]).as_matrix() @ prior.pose[:3, :3]
        c = (prior.pose[:3, :3] @ surface.center + prior.pose[:3, 3]) + xi[:, 3:]
        delta = 3.0 * max(np.sqrt(np.max(np.diag(cov)[3:])), rho * np.sqrt(np.max(np.diag(cov)[:3])))
    else:
        R = Rotation.random(initial, random_state=rng).as_matrix()
        c = contacts.points.mean(axis=0) + rho * _ball(rng, initial, 3)
        delta = np.pi * rho
    cost = contact_cost(model, surface, contacts, _poses(R, c, surface.center), position_noise, normal_noise_deg)
    evaluations, scales = initial, 0
    R, c, cost = _prune(rng, R, c, cost, max(delta / delta_final, 1.0) ** 2, max_particles // per_ball)
    while delta > delta_final:
        new_delta = max(zoom * delta, delta_final)
        tau = (new_delta / delta_final) ** 2
        # even density cover: per_ball samples in the δ-ball of each survivor
        Rs = np.repeat(R, per_ball, axis=0)
        cs = np.repeat(c, per_ball, axis=0)
        Rs, cs = _perturb(Rs, cs, _ball(rng, len(Rs)), delta, rho)
        cost = contact_cost(model, surface, contacts, _poses(Rs, cs, surface.center), position_noise, normal_noise_deg)
        evaluations += len(Rs)
        scales += 1
        delta = new_delta
        keep = max_particles // per_ball
        if delta <= delta_final:
            R, c = Rs, cs  # the last scale: keep every particle for the estimate
            break
        R, c, cost = _prune(rng, Rs, cs, cost, tau, keep)
    best = int(np.argmin(cost))
    return BaselineResult(_poses(R[best:best + 1], c[best:best + 1], surface.center)[0], float(cost[best]),
                          evaluations, scales)


def _prune(rng, R, c, cost, tau, keep):
    """Importance resampling with weights exp(-cost/(2τ)), duplicates removed; at most keep survivors."""
    logw = -0.5 * (cost - cost.min()) / tau
    w = np.exp(logw)
    w /= w.sum()
    # systematic resampling: keep draws, one uniform offset
    positions = (rng.random() + np.arange(keep)) / keep
    idx = np.unique(np.searchsorted(np.cumsum(w), positions).clip(0, len(w) - 1))
    return R[idx], c[idx], cost[idx]


# --------------------------------------------------------------------------- the published form

def scaling_series_published(model, surface, contacts, rng, *, position_noise, normal_noise_deg,
                             per_neighbourhood=PER_NEIGHBOURHOOD, delta_final=None, seconds=None,
                             max_cover=MAX_COVER):
    """The Scaling Series as published, global (steps and settings: research/baselines.md).

    V_0: every rotation, the surface centre in the ρ-ball around the contacts' centroid; δ_0 = π·ρ
    in the metric of :func:`scaling_series`. δ* (default max(σ_x, ρ·σ_n): at τ = 1 the weights
    are the sensor's own likelihood); zoom = 2^(-1/6); N = round(log2(Vol(S_δ0)/Vol(S_δ*)))
    = round(6·log2(δ_0/δ*)) scales. X_0: ``per_neighbourhood`` particles uniform in V_0. Scale
    n = 1..N: δ_n = zoom·δ_{n-1}, τ_n = (δ_n/δ*)²; from n = 2 an even density cover of X_{n-1}
    (:func:`_cover`, radius δ_{n-1}); weights exp(-χ²/(2τ_n)); prune: systematic resampling of as
    many draws as particles, duplicates removed. Last: a cover of X_N weighted at τ = 1; the
    estimate is its heaviest (lowest-χ²) particle. No cap on the particle set. The series stops
    early, before a scale, when the time spent plus the last scale's time would pass ``seconds``
    (a time budget; the first scale always runs) or when a cover would pass ``max_cover``
    particles (memory), with the heaviest particle so far and ``stopped`` saying why.
    """
    start = time.perf_counter()
    rho, m = surface.radius, per_neighbourhood
    if delta_final is None:
        delta_final = max(position_noise, rho * np.radians(normal_noise_deg))
    delta = np.pi * rho
    planned = max(int(round(POSE_DIM * np.log2(delta / delta_final))), 1)
    R = Rotation.random(m, random_state=rng).as_matrix()
    c = contacts.points.mean(axis=0) + rho * _ball(rng, m, 3)
    evaluations, stopped = 0, ""

    def cost_of(R, c):
        return contact_cost(model, surface, contacts, _poses(R, c, surface.center), position_noise, normal_noise_deg)

    last = 0.0  # seconds the last scale took
    for n in range(1, planned + 1):
        if n > 1:
            if seconds is not None and time.perf_counter() - start + last > seconds:
                stopped = f"time budget {seconds:.3g} s: stopped after scale {n - 1} of {planned}"
                n -= 1
                break
            if len(R) * m > max_cover:
                stopped = f"a cover of {len(R) * m} particles would pass {max_cover}: stopped after scale {n - 1} of {planned}"
                n -= 1
                break
            R, c = _cover(rng, R, c, delta, rho, m)
        began = time.perf_counter()
        delta *= ZOOM
        cost = cost_of(R, c)
        evaluations += len(R)
        R, c, cost = _prune(rng, R, c, cost, (delta / delta_final) ** 2, len(R))
        last = time.perf_counter() - began
    else:
        R, c = _cover(rng, R, c, delta, rho, m)
        cost = cost_of(R, c)
        evaluations += len(R)
    best = int(np.argmin(cost))
    return BaselineResult(_poses(R[best:best + 1], c[best:best + 1], surface.center)[0], float(cost[best]),
                          evaluations, n, planned, stopped)


def _embed(R, c, rho):
    """Particles as points of R^12 whose distance is sqrt(|Δc|² + 2ρ²(1 - cos θ)) ≈ the pose
    metric sqrt(|Δc|² + ρ²θ²) (chordal in the rotation): R (P, 3, 3), c (P, 3) -> (P, 12)."""
    return np.hstack([c, rho / np.sqrt(2.0) * R.reshape(len(R), 9)])


def _cover(rng, R, c, delta, rho, m, tries=COVER_TRIES):
    """Even density cover: m samples uniform in the δ-ball of each particle, in order; a sample
    that falls in the δ-ball of an earlier particle (that region has its m already) is drawn
    again, up to ``tries`` times, then dropped. R (P, 3, 3), c (P, 3) -> (R (K, 3, 3), c (K, 3))."""
    parent = np.repeat(np.arange(len(R)), m)
    tree = cKDTree(_embed(R, c, rho))
    Rs, cs = _perturb(R[parent], c[parent], _ball(rng, len(parent)), delta, rho)
    todo = np.arange(len(parent))
    for attempt in range(tries + 1):
        near = tree.query_ball_point(_embed(Rs[todo], cs[todo], rho), delta, return_sorted=False)
        earlier = np.array([bool(js) and min(js) < p for js, p in zip(near, parent[todo])], dtype=bool)
        todo = todo[earlier]
        if not len(todo) or attempt == tries:
            break
        Rs[todo], cs[todo] = _perturb(R[parent[todo]], c[parent[todo]], _ball(rng, len(todo)), delta, rho)
    keep = np.ones(len(parent), dtype=bool)
    keep[todo] = False
    return Rs[keep], cs[keep]
