"""The BOP challenge's MSSD (geometry.metrics.mssd) against brute force: every symmetry and
every vertex tried in a loop, a continuous axis's turn on a 0.02° grid, and the known answers of
a pure turn, a pure shift and a symmetric twin; its average recall (ar_mssd) by hand."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from contactpose.geometry.metrics import MSSD_THRESHOLDS_FRAC, MSSD_TURN_FRAC, ar_mssd, mssd, symmetry_transforms
from contactpose.model.object_model import ObjectModel
from contactpose.model.symmetry import symmetry
from contactpose.sim import objects


def pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def brute(T_est, T_true, vertices, group):
    """min over the group's elements of max over every vertex of the distance, by loops."""
    best = np.inf
    for G in group:
        worst = 0.0
        for x in vertices:
            a = T_est[:3, :3] @ x + T_est[:3, 3]
            b = T_true[:3, :3] @ (G[:3, :3] @ x + G[:3, 3]) + T_true[:3, 3]
            worst = max(worst, float(np.linalg.norm(a - b)))
        best = min(best, worst)
    return best


def random_poses(rng, k, scale=0.05):
    return [pose(Rotation.random(random_state=rng).as_rotvec(), rng.normal(0, scale, 3)) for _ in range(k)]


def test_discrete_group_against_loops_over_every_vertex():
    """The 53-facet banana (not convex: the hull's vertices must give the same maximum) under
    a made-up group of four elements; random truths and estimates, and estimates near a twin."""
    vertices = objects.load("banana").vertices
    rng = np.random.default_rng(3)
    group = np.stack([np.eye(4), pose([0, 0, np.pi], [0.01, 0, 0]), pose([np.pi / 2, 0, 0], [0, 0.02, 0]),
                      pose([0.3, -0.4, 1.0], [0, 0, -0.01])])
    for T_true, T_est in zip(random_poses(rng, 6), random_poses(rng, 6)):
        for estimate in (T_est, T_true @ group[2] @ pose(rng.normal(0, 0.02, 3), rng.normal(0, 0.002, 3))):
            assert mssd(estimate, T_true, vertices, group) == pytest.approx(brute(estimate, T_true, vertices, group),
                                                                         rel=1e-12, abs=1e-15)


def test_known_answers_of_a_turn_a_shift_and_a_twin():
    """No symmetry: a turn by θ about an axis through a point moves the vertex farthest from
    that axis most, by 2 sin(θ/2) r_max; a shift by d moves every vertex by d. A box's half turn
    about its own axis (its symmetry found from the mesh) leaves MSSD 0."""
    vertices = objects.load("banana").vertices
    identity = np.eye(4)[None]
    axis, point, theta = np.array([0.6, 0.0, 0.8]), np.array([0.01, 0.02, -0.01]), np.radians(7.0)
    turn = pose(theta * axis, np.zeros(3))
    turn[:3, 3] = point - turn[:3, :3] @ point
    offset = vertices - point
    r_max = np.linalg.norm(offset - np.outer(offset @ axis, axis), axis=1).max()
    T_true = pose([0.2, 0.1, -0.3], [0.1, 0.0, 0.3])
    assert mssd(T_true @ turn, T_true, vertices, identity) == pytest.approx(2 * np.sin(theta / 2) * r_max, rel=1e-12)
    shift = pose(np.zeros(3), [0.003, -0.004, 0.0])
    assert mssd(shift @ T_true, T_true, vertices, identity) == pytest.approx(0.005, rel=1e-12)
    model = ObjectModel.from_mesh(trimesh.creation.box(extents=(0.1, 0.06, 0.03)))
    group = symmetry(model)
    assert len(group.rotations) == 4
    twin = T_true @ group.rotations[1]
    assert group.mssd(twin, T_true, model.vertices) == pytest.approx(0.0, abs=1e-12)
    assert mssd(twin, T_true, model.vertices, identity) > 0.03  # the same pose without the group


def test_continuous_axis_against_a_fine_grid():
    """A 24-sided cylinder taken as continuous about z: the sampled minimum lies between the
    minimum over 0.02° turns (less the grid's own slack) and that plus MSSD_TURN_FRAC · D."""
    mesh = trimesh.creation.cylinder(radius=0.03, height=0.12, sections=24)
    vertices = np.asarray(mesh.vertices)
    D = np.sqrt(0.06**2 + 0.12**2)
    step = np.radians(0.02)
    fine = np.stack([pose([0, 0, phi], np.zeros(3)) for phi in np.arange(0, 2 * np.pi, step)])
    rng = np.random.default_rng(5)
    for T_true, T_est in zip(random_poses(rng, 3), random_poses(rng, 3)):
        near = T_true @ pose([0, 0, 1.234], np.zeros(3)) @ pose(rng.normal(0, 0.03, 3), rng.normal(0, 0.002, 3))
        for estimate in (T_est, near):
            got = mssd(estimate, T_true, vertices, np.eye(4)[None], axes=[[0, 0, 1]])
            best = min(_max_distance(estimate, T_true @ G, vertices) for G in fine)
            assert best - 2 * np.sin(step / 2) * 0.03 - 1e-12 <= got <= best + MSSD_TURN_FRAC * D + 1e-12


def test_continuous_axis_turns_are_as_close_as_the_protocol_asks_and_no_closer():
    """Consecutive turns move the vertex farthest from the axis at most MSSD_TURN_FRAC of the
    diameter; one turn fewer would move it farther. Each of the group's rotations gets them."""
    vertices = np.asarray(trimesh.creation.cylinder(radius=0.03, height=0.12, sections=24).vertices)
    D = np.sqrt(0.06**2 + 0.12**2)
    group = np.stack([np.eye(4), pose([np.pi, 0, 0], np.zeros(3))])
    S = symmetry_transforms(vertices, group, axes=[[0, 0, 1]])
    steps = len(S) // 2
    assert len(S) == 2 * steps and np.allclose(S[steps:], group[1] @ S[:steps])
    chord = lambda n: 2 * 0.03 * np.sin(np.pi / n)  # noqa: E731
    assert chord(steps) <= MSSD_TURN_FRAC * D < chord(steps - 1)
    first = Rotation.from_matrix(S[:steps, :3, :3]).as_rotvec()
    assert np.allclose(first[:, :2], 0) and np.allclose(np.sort(np.mod(first[:, 2], 2 * np.pi)),
                                                        2 * np.pi * np.arange(steps) / steps, atol=1e-9)


def _max_distance(T_a, T_b, vertices):
    return float(np.linalg.norm(vertices @ (T_a[:3, :3] - T_b[:3, :3]).T + (T_a[:3, 3] - T_b[:3, 3]), axis=1).max())


def test_sphere_scores_the_centre_displacement_and_batches():
    """Every rotation about the centre a symmetry: MSSD is how far the centre moved, whatever the
    rotations; a batch of estimates gives each one's value."""
    vertices = np.asarray(trimesh.creation.icosphere(2, radius=0.04).vertices) + [0.01, 0.0, 0.0]
    centre = np.array([0.01, 0.0, 0.0])
    rng = np.random.default_rng(8)
    T_true = random_poses(rng, 1)[0]
    estimates = np.stack(random_poses(rng, 4))
    moved = estimates[:, :3, :3] @ centre + estimates[:, :3, 3] - (T_true[:3, :3] @ centre + T_true[:3, 3])
    got = mssd(estimates, T_true, vertices, np.eye(4)[None], axes=np.eye(3), centre=centre)
    assert got == pytest.approx(np.linalg.norm(moved, axis=1), rel=1e-12)
    one = mssd(estimates, T_true, vertices, np.eye(4)[None])
    assert one == pytest.approx([mssd(T, T_true, vertices, np.eye(4)[None]) for T in estimates], rel=1e-12)


def test_average_recall_over_the_ten_thresholds():
    """Errors of 2 %, 12 % and 60 % of D and one missing pose: the first passes all ten
    thresholds (5 %, ..., 50 %), the second eight (15 % up), the others none: 18 of 40."""
    assert MSSD_THRESHOLDS_FRAC == (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5)
    D = 0.2
    assert ar_mssd([0.02 * D, 0.12 * D, 0.6 * D, np.nan], D) == pytest.approx(18 / 40)
    assert ar_mssd([0.05 * D], D) == pytest.approx(0.9)  # a threshold is not passed at equality
