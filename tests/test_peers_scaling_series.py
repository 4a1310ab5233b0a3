"""The Scaling Series in its published form (contactpose.peers.scaling_series): the even density
cover against known geometric answers, and its stopping rules."""

import importlib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from contactpose import peers
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

ss = importlib.import_module("contactpose.peers.scaling_series")  # the package re-exports a function of that name

RHO, DELTA, M = 0.1, 0.02, 7


def metric(R1, c1, R2, c2, rho=RHO):
    """The pose metric sqrt(|Δc|² + ρ²θ²), θ the geodesic rotation angle."""
    theta = Rotation.from_matrix(np.einsum("pji,pjk->pik", R1, R2)).magnitude()
    return np.sqrt(np.sum((c1 - c2) ** 2, axis=1) + (rho * theta) ** 2)


def parents(offsets):
    """Particles with the identity rotation at the given centre offsets (P, 3)."""
    offsets = np.asarray(offsets, dtype=np.float64)
    return np.repeat(np.eye(3)[None], len(offsets), axis=0), offsets


def test_cover_samples_stay_in_their_parents_ball():
    rng = np.random.default_rng(0)
    R, c = parents([[0, 0, 0], [1, 0, 0], [0, 1, 0]])  # far apart: nothing rejected
    Rs, cs = ss._cover(rng, R, c, DELTA, RHO, M)
    assert len(Rs) == 3 * M
    owner = np.repeat(np.arange(3), M)
    assert np.all(metric(Rs, cs, R[owner], c[owner]) <= DELTA * (1 + 1e-9))
    # the rotation part is used: some samples turn by more than a tenth of the ball
    assert np.max(Rotation.from_matrix(Rs).magnitude()) * RHO > 0.1 * DELTA


def test_cover_of_coincident_particles_keeps_one_neighbourhood():
    """Ten copies of one particle: the region is covered once, with M particles (even density)."""
    R, c = parents(np.zeros((10, 3)))
    Rs, _ = ss._cover(np.random.default_rng(1), R, c, DELTA, RHO, M)
    assert len(Rs) == M


def test_cover_of_overlapping_neighbourhoods_keeps_between_one_and_two_covers():
    """Two particles half a radius apart: the second keeps only samples outside the first's ball."""
    R, c = parents([[0, 0, 0], [DELTA / 2, 0, 0]])
    counts = [len(ss._cover(np.random.default_rng(s), R, c, DELTA, RHO, M)[0]) for s in range(20)]
    assert min(counts) >= M and max(counts) <= 2 * M and max(counts) > M


def test_prune_keeps_a_dominant_particle_alone():
    R, c = parents(np.arange(15).reshape(5, 3))
    cost = np.array([500.0, 1.0, 500.0, 500.0, 500.0])
    R2, c2, cost2 = ss._prune(np.random.default_rng(2), R, c, cost, 1.0, 5)
    assert np.array_equal(c2, c[1:2]) and np.array_equal(cost2, [1.0])


@pytest.fixture(scope="module")
def banana():
    model = ObjectModel.from_mesh(objects.load("banana"))
    return model, peers.sample_surface(model)


NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)


def test_published_series_runs_its_schedule_and_returns_its_lowest_cost_particle(banana):
    model, surface = banana
    rng = np.random.default_rng(3)
    g = simulate.grasp(model, rng, n=4, **NOISE)
    r = ss.scaling_series_published(model, surface, g.contacts, rng, **NOISE)
    delta_final = max(0.0005, surface.radius * np.radians(1.0))
    # N scales take δ_0 = πρ to within half a zoom step of δ*
    assert abs(np.log2(np.pi * surface.radius * ss.ZOOM ** r.planned / delta_final)) <= 1 / 12 + 1e-12
    assert r.iterations == r.planned and r.stopped == ""
    assert r.cost == pytest.approx(peers.contact_cost(model, surface, g.contacts, r.pose[None], **NOISE)[0])


def test_published_series_stops_at_its_budgets_and_says_so(banana):
    model, surface = banana
    g = simulate.grasp(model, np.random.default_rng(4), n=4, **NOISE)
    r = ss.scaling_series_published(model, surface, g.contacts, np.random.default_rng(5), seconds=0.0, **NOISE)
    assert (r.iterations, r.evaluations) == (1, ss.PER_NEIGHBOURHOOD) and "time budget" in r.stopped
    r = ss.scaling_series_published(model, surface, g.contacts, np.random.default_rng(5), per_neighbourhood=30,
                                    max_cover=100, **NOISE)
    assert r.iterations < r.planned and "would pass 100" in r.stopped


def test_contact_cost_in_blocks_equals_pose_by_pose(banana, monkeypatch):
    """Scored in blocks smaller than one pose's contacts, the χ² of many poses equals each
    pose's χ² scored alone: the blocks bound memory and change nothing."""
    model, surface = banana
    rng = np.random.default_rng(6)
    g = simulate.grasp(model, rng, n=4, **NOISE)
    poses = np.repeat(g.pose[None], 9, axis=0)
    poses[1:, :3, :3] = Rotation.random(8, random_state=rng).as_matrix() @ g.pose[:3, :3]
    poses[1:, :3, 3] += rng.normal(0.0, 0.01, (8, 3))
    alone = [peers.contact_cost(model, surface, g.contacts, pose[None], **NOISE)[0] for pose in poses]
    monkeypatch.setattr(peers.surface, "PAIRS_PER_BLOCK", 3 * surface.neighbours.shape[1])  # 3 contacts a block
    assert np.allclose(peers.contact_cost(model, surface, g.contacts, poses, **NOISE), alone, rtol=1e-12, atol=0)
    assert peers.contact_cost(model, surface, g.contacts, poses[:0], **NOISE).shape == (0,)
