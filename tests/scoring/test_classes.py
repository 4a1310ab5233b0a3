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



@pytest.fixture(scope="module")
def symmetric_models():
    """An exact box (its 4 rotations) and an exact 64-sided cylinder (rotation about its axis
    and half turns across it)."""
    import trimesh

    from contactpose.model.object_model import ObjectModel
    return {"box": ObjectModel.from_mesh(trimesh.creation.box([0.1, 0.06, 0.04])),
            "cylinder": ObjectModel.from_mesh(trimesh.creation.cylinder(0.03, 0.1, sections=64))}


def _twin_moves(group, rng, k):
    """k random members of the group as object-frame transforms (a turn about the axis, if any,
    after a discrete rotation)."""
    from scipy.spatial.transform import Rotation
    moves = []
    for _ in range(k):
        G = group.rotations[rng.integers(len(group.rotations))].copy()
        if len(group.axes):
            turn = np.eye(4)
            turn[:3, :3] = Rotation.from_rotvec(rng.uniform(-np.pi, np.pi) * group.axes[0]).as_matrix()
            turn[:3, 3] = group.centre - turn[:3, :3] @ group.centre
            G = G @ turn
        moves.append(G)
    return moves


@pytest.mark.parametrize("name", ["box", "cylinder"])
def test_canonical_twin_is_one_pose_per_placement(symmetric_models, name):
    """Every twin T G of a pose has the same canonical twin, and that twin places the surface as
    T does: T⁻¹ times it moves the surface points onto the surface (trimesh's nearest point on
    the mesh; near 0 on the box, within FINE_FRAC on the 64-sided prism that counts as a body
    of revolution)."""
    import trimesh

    from contactpose.model.symmetry import FINE_FRAC, symmetry
    model = symmetric_models[name]
    mesh = trimesh.Trimesh(model.vertices, model.faces, process=False)
    group = symmetry(model)
    assert group.exact and not group.trivial and len(group.axes) == (name == "cylinder")
    rng = np.random.default_rng(8)
    for _ in range(10):
        T = simulate.random_pose(rng, max_translation=0.05)
        twins = np.stack([T @ G for G in _twin_moves(group, rng, 6)])
        canonical = group.canonical(np.concatenate([T[None], twins]))
        assert np.allclose(canonical, canonical[0], atol=1e-9)
        move = np.linalg.solve(T, canonical[0])
        moved = model.surface_points @ move[:3, :3].T + move[:3, 3]
        limit = (FINE_FRAC if len(group.axes) else 1e-6) * model.diameter
        assert mesh.nearest.on_surface(moved)[1].max() < limit


@pytest.mark.parametrize("name, points, normals", [
    ("box", [[0.0, 0.0, 0.02], [0.05, 0.01, 0.0], [0.01, 0.03, 0.005], [-0.05, 0.0, 0.01]],
     [[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0]]),
    ("cylinder", [[0.03 * np.cos(a), 0.03 * np.sin(a), z] for a, z in zip(np.radians([0, 100, 200, 290]),
                                                                          [0.01, -0.02, 0.03, 0.0])],
     [[np.cos(a), np.sin(a), 0.0] for a in np.radians([0, 100, 200, 290])]),
])
def test_twins_of_a_placement_are_listed_once(symmetric_models, name, points, normals):
    """On a symmetric object every assignment's twins count as one distinct pose: no two kept
    poses place the surface alike (ADD-S on the surface points, by brute force over all pairs),
    every dropped pose places it as a kept one does, and the pose the contacts were taken at is
    still listed modulo the symmetry, within the near-copy radius (the cylinder's grasp leaves
    a slide along its axis free). Without twins (a vision prior picks among them) the twins
    stay apart."""
    from contactpose.contacts import Contacts
    from contactpose.geometry.metrics import adds_many
    from contactpose.scoring.classes import distinct_radius
    model = symmetric_models[name]
    contacts = Contacts(np.asarray(points, float), object_normals=np.asarray(normals, float))
    every = localize(model, contacts, distinct=False, keep="all", diagnose=False, **NOISE).hypotheses.arrays
    same, radius = 0.01 * model.diameter, distinct_radius(model, NOISE["position_noise"])
    kept, _ = distinct_poses(model, every, NOISE["position_noise"], merge_twins=True)
    apart, _ = distinct_poses(model, every, NOISE["position_noise"], merge_twins=False)
    adds = lambda A, B: np.array([adds_many(A, b, model.surface_points, model.surface_tree) for b in B])  # noqa: E731
    between = adds(kept.poses, kept.poses)
    assert np.all(between[~np.eye(len(kept.cost), dtype=bool)] > same)
    assert np.all(adds(every.poses, kept.poses).min(axis=0) <= radius)
    assert adds(kept.poses, np.eye(4)[None]).min() <= radius
    assert len(apart.cost) > len(kept.cost)
    listed = localize(model, contacts, diagnose=False, **NOISE)
    assert len(listed.hypotheses) == len(kept.cost)
    if name == "box":  # a determined grasp: a prior keeps the twins apart, as twins=True does
        from contactpose.types import PosePrior
        with_prior = localize(model, contacts, diagnose=False, prior=PosePrior(np.eye(4), 10.0, 0.01), **NOISE)
        assert with_prior.num_hypotheses == localize(model, contacts, diagnose=False, twins=True,
                                                     **NOISE).num_hypotheses > listed.num_hypotheses
