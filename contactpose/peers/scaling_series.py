"""A particle-filter global localization in the style of the Scaling Series
(Petrovskaya & Khatib, "Global localization of objects via touch", IEEE T-RO 2011).

Particles in SE(3) are refined over a sequence of shrinking neighbourhoods δ_k = δ_0 · zoom^k;
at each scale, ``per_ball`` samples are drawn uniformly in the δ-ball of every surviving
particle (Even Density Cover), weighted by the contact likelihood annealed to the scale (σ²
inflated by τ = (δ_k/δ*)²), and pruned by importance resampling. The scales stop at δ*, the
resolution the measurement noise supports. It scores a pose with the peers' contact
likelihood (peers.surface.contact_cost); research/baselines.md says how it was tuned.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.peers.surface import BaselineResult, contact_cost

#: Dimension of the pose space (for the Scaling Series zoom factor 2^(-1/dim)).
POSE_DIM = 6



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
                   initial=2000, per_ball=8, max_particles=2000, delta_final=None, zoom=2.0 ** (-1.0 / POSE_DIM)):
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
