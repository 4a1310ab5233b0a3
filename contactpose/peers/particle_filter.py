"""A particle filter for an object held in a moving hand, in the spirit of the memory
unscented particle filter (Vezzani et al., 2017): particles move with the hand and a sampled
slip, and each touch weights them by the contact likelihood of the last ``memory`` contacts.
It scores a pose with the peers' contact likelihood (peers.surface.contact_cost).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.errors import ContactPoseError
from contactpose.peers.surface import contact_cost


class MemoryParticleFilter:
    """The pose of an object held in a moving hand, as particles.

    model : ObjectModel; surface : its Surface (:func:`sample_surface`); starts : (S, 4, 4)
    poses to start from (for example localize's distinct poses of a first grasp), the
    particles split evenly among them and spread by N(0, spread_deg²) of rotation and
    N(0, spread²) of translation per axis (default 1 % of the diameter); contacts : the first
    grasp's Contacts; rng : numpy Generator; position_noise, normal_noise_deg : the contact
    likelihood's σ (:func:`contact_cost`); memory : contacts kept for the likelihood.

    Each :meth:`add` moves the particles with the hand, X ← ΔT X S, with a slip S drawn from
    the slip's sigmas (rotation vector and translation in the object frame), moves the
    remembered contacts with the hand (x ← ΔT x), weights every particle by exp(-χ²/2) of
    the last ``memory`` contacts (recomputed each touch, not multiplied over touches: the
    memory stands for the history), and resamples (systematic). The estimate is the weighted
    mean of the particles within ESTIMATE_DEG and ESTIMATE_FRAC of the diameter of the most
    probable one. A bootstrap filter: the proposal is the motion model, not an unscented one.
    """

    #: The estimate averages the particles this close to the most probable one.
    ESTIMATE_DEG = 10.0
    ESTIMATE_FRAC = 0.1

    def __init__(self, model, surface, starts, contacts, rng, *, position_noise, normal_noise_deg, particles=1000,
                 spread_deg=2.0, spread=None, memory=4):
        starts = np.asarray(starts, dtype=np.float64).reshape(-1, 4, 4)
        if len(starts) == 0:
            raise ContactPoseError("a particle filter needs at least one start pose")
        self.model, self.surface, self.rng, self.memory = model, surface, rng, memory
        self.noise = (position_noise, normal_noise_deg)
        spread = 0.01 * model.diameter if spread is None else spread
        X = starts[np.arange(particles) % len(starts)]
        self.X = X @ _slips(rng, particles, spread_deg, spread)
        self.remembered = contacts
        self._weigh_and_resample()

    def add(self, contacts, hand_motion):
        """One touch after the hand moved: hand_motion (ΔT (4, 4), σ_rot in degrees, σ_trans).
        -> the estimate (4, 4)"""
        delta, sigma_rot_deg, sigma_trans = hand_motion
        self.X = delta @ self.X @ _slips(self.rng, len(self.X), sigma_rot_deg, sigma_trans)
        joined = self.remembered.transformed(delta).joined(contacts)
        self.remembered = joined.permuted(np.arange(max(0, joined.n - self.memory), joined.n))
        return self._weigh_and_resample()

    def _weigh_and_resample(self):
        chi2 = contact_cost(self.model, self.surface, self.remembered, self.X, *self.noise)
        w = np.exp(-0.5 * (chi2 - chi2.min()))
        w /= w.sum()
        self.pose = _local_mean(self.X, w, self.X[np.argmax(w)], self.ESTIMATE_DEG,
                                self.ESTIMATE_FRAC * self.model.diameter)
        positions = (self.rng.random() + np.arange(len(w))) / len(w)
        self.X = self.X[np.searchsorted(np.cumsum(w), positions).clip(0, len(w) - 1)]
        return self.pose


def _slips(rng, count, sigma_rot_deg, sigma_trans):
    """count random rigid transforms: rotation vector N(0, σ_r²), translation N(0, σ_t²) per
    axis. -> (count, 4, 4)"""
    S = np.zeros((count, 4, 4))
    S[:, :3, :3] = Rotation.from_rotvec(np.radians(sigma_rot_deg) * rng.normal(size=(count, 3))).as_matrix()
    S[:, :3, 3] = sigma_trans * rng.normal(size=(count, 3))
    S[:, 3, 3] = 1.0
    return S


def _local_mean(X, w, best, max_deg, max_trans):
    """Weighted mean pose of the particles X (P, 4, 4) within max_deg and max_trans of
    ``best`` (rotations by scipy's weighted mean). -> (4, 4)"""
    rel = Rotation.from_matrix(np.einsum("ji,pjk->pik", best[:3, :3], X[:, :3, :3]))
    near = (np.degrees(rel.magnitude()) <= max_deg) & (np.linalg.norm(X[:, :3, 3] - best[:3, 3], axis=1) <= max_trans)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_matrix(X[near, :3, :3]).mean(weights=w[near]).as_matrix()
    T[:3, 3] = np.average(X[near, :3, 3], axis=0, weights=w[near])
    return T
