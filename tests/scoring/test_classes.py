"""Distinct poses: one hypothesis per pose, checked against brute-force pairwise displacements."""

from __future__ import annotations

import numpy as np
import pytest

from contactpose.geometry.metrics import pose_embedding, rms_displacement
from contactpose.localize import localize
from contactpose.progress import Deadline
from contactpose.scoring.classes import DISTINCT_RMS_FRAC, DISTINCT_RMS_SIGMA, _leaders, distinct_poses
from contactpose.sim import grasps as simulate

NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)


def test_embedding_distances_are_rms_displacements(rock_model):
    """|e(A) - e(B)| equals the RMS displacement of the class points, computed point by point."""
    rng = np.random.default_rng(4)
    poses = np.stack([simulate.random_pose(rng, max_translation=0.05) for _ in range(6)])
    e = pose_embedding(poses, *rock_model.class_moments)
    p = rock_model.class_points
    for a in range(6):
        moved = p @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3]
        direct = np.sqrt(np.mean(np.sum((moved - moved[a]) ** 2, axis=2), axis=1))
        assert np.allclose(np.linalg.norm(e - e[a], axis=1), direct, atol=1e-12)
        assert np.allclose(rms_displacement(poses, poses[a], *rock_model.class_moments), direct, atol=1e-9)


def plain_greedy(v, r2):
    """The grouping by its definition: rows in order, each free one leads and takes every
    later free row within sqrt(r2)."""
    owner = -np.ones(len(v), dtype=np.int64)
    for lead in range(len(v)):
        if owner[lead] < 0:
            near = (owner < 0) & (np.sum((v - v[lead]) ** 2, axis=1) <= r2)
            owner[near] = lead
    return owner


@pytest.mark.parametrize("spread", [0.02, 1.0])
def test_leaders_equal_plain_greedy(spread):
    """The k-d tree search of _leaders groups exactly as the definition does: clustered 13-D
    rows (near-copies around a few centres) and scattered ones, some exactly on the radius."""
    rng = np.random.default_rng(5)
    centres = rng.normal(size=(40, 13))
    v = centres[rng.integers(0, 40, 3000)] + spread * rng.normal(size=(3000, 13))
    v[1] = v[0] + np.r_[0.3, np.zeros(12)]        # at the radius exactly
    for r in (0.05, 0.3, 2.0):
        assert np.array_equal(_leaders(v, r * r), plain_greedy(v, r * r))


def test_leaders_stop_at_a_passed_deadline():
    """Past the deadline only the first leader's group is formed: every other row leads
    itself, and the deadline records the cut."""
    rng = np.random.default_rng(6)
    v = rng.normal(size=(500, 13)) * 0.1
    passed = Deadline(1e-9)
    while not passed.passed:
        pass
    owner, full = _leaders(v, 0.09, passed), plain_greedy(v, 0.09)
    first = full == 0
    assert first.sum() > 1 and passed.hit
    assert np.array_equal(owner[first], full[first]) and np.array_equal(owner[~first], np.flatnonzero(~first))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_distinct_poses_keep_one_per_pose(banana_model, seed):
    """Brute force over all pairs: no two kept hypotheses are near-copies, every dropped one
    is a near-copy of a better kept one, and the copies add up to every assignment."""
    model = banana_model
    g = simulate.grasp(model, np.random.default_rng(seed), n=4, noise="bounded", **NOISE)
    every = localize(model, g.contacts, **NOISE, distinct=False)
    a = every.hypotheses.arrays
    kept, copies = distinct_poses(model, a, NOISE["position_noise"])
    radius = max(DISTINCT_RMS_FRAC * model.diameter, DISTINCT_RMS_SIGMA * NOISE["position_noise"])
    index = [int(np.flatnonzero((a.poses == pose).all(axis=(1, 2)))[0]) for pose in kept.poses]
    assert index == sorted(index) and index[0] == 0 and copies.sum() == len(a.cost)
    free = a.fit.underdetermined
    for i in range(len(a.cost)):
        d = rms_displacement(a.poses[index], a.poses[i], *model.class_moments)
        near = (d < radius) & (free[index] == free[i])
        if i in index:
            assert np.flatnonzero(near).tolist() == [index.index(i)]
        else:
            assert any(k < i for k, n in zip(index, near) if n)
    r = localize(model, g.contacts, **NOISE, surface=False)  # the listing as grouped, not re-posed on the surface
    assert r.num_assignments == len(a.cost) and r.num_hypotheses == len(kept.cost)
    assert np.allclose(r.hypotheses.arrays.poses, kept.poses)

