"""Pose errors modulo a symmetry group (geometry.metrics.symmetric_errors) against brute force:
every element tried in a loop (scipy's rotation angles), a continuous axis's turn searched on
a 0.01° grid, a sphere's error as the centroid's displacement."""

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.geometry.metrics import rotation_error_deg, symmetric_errors, translation_error

CENTRE = np.array([0.01, -0.02, 0.005])


def pose(rotvec, t):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def about_centre(rotvec):
    """(4, 4) the rotation by ``rotvec`` about CENTRE."""
    T = pose(rotvec, np.zeros(3))
    T[:3, 3] = CENTRE - T[:3, :3] @ CENTRE
    return T


def brute(T_est, T_true, group):
    """(rotation °, translation) against the element of least rotation error, by a loop."""
    best = None
    for G in group:
        C = T_true @ G
        angle = np.degrees(Rotation.from_matrix(T_est[:3, :3].T @ C[:3, :3]).magnitude())
        if best is None or angle < best[0]:
            best = (angle, np.linalg.norm(T_est[:3, 3] - C[:3, 3]))
    return best


def test_discrete_group_against_a_loop():
    """A 6-fold axis and a half turn across it (12 elements); random truths and estimates, and
    estimates near a twin T G Δ, whose error is Δ's."""
    rng = np.random.default_rng(0)
    z, x = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    group = [about_centre(z * 2 * np.pi * k / 6) for k in range(6)]
    group += [G @ about_centre(x * np.pi) for G in group]
    group = np.stack(group)
    for _ in range(50):
        T_true = pose(rng.normal(size=3), rng.normal(size=3))
        T_est = pose(rng.normal(size=3), rng.normal(size=3))
        rot, trans = symmetric_errors(T_est, T_true, group)
        want = brute(T_est, T_true, group)
        assert np.isclose(rot, want[0], atol=1e-6) and np.isclose(trans, want[1], atol=1e-12)
        delta = pose(0.01 * rng.normal(size=3), 0.001 * rng.normal(size=3))
        rot, trans = symmetric_errors(T_true @ group[rng.integers(12)] @ delta, T_true, group)
        assert np.isclose(rot, np.degrees(np.linalg.norm(Rotation.from_matrix(delta[:3, :3]).as_rotvec())), atol=1e-6)
        assert np.isclose(trans, np.linalg.norm(delta[:3, 3]), atol=1e-12)


def test_continuous_axis_against_a_grid():
    """With a continuous axis (and a half turn across it), the closed-form best turn is no
    worse than the best of 36,000 turns on a 0.01° grid, and within the grid's step of it."""
    rng = np.random.default_rng(1)
    axis = np.array([0.3, -0.4, 0.866])
    axis /= np.linalg.norm(axis)
    across = np.cross(axis, [1.0, 0.0, 0.0])
    across /= np.linalg.norm(across)
    reps = np.stack([np.eye(4), about_centre(across * np.pi)])
    grid = np.radians(np.arange(0.0, 360.0, 0.01))
    turned = np.stack([G @ T for G in reps for T in (about_centre(axis * phi) for phi in grid)])
    for _ in range(5):
        T_true = pose(rng.normal(size=3), rng.normal(size=3))
        T_est = T_true @ turned[rng.integers(len(turned))] @ pose(0.05 * rng.normal(size=3), 0.01 * rng.normal(size=3))
        rot, trans = symmetric_errors(T_est, T_true, reps, axes=[axis], centre=CENTRE)
        errors = rotation_error_deg(T_est, T_true @ turned)
        assert errors.min() - 0.01 <= rot <= errors.min() + 1e-9
        assert np.isclose(trans, translation_error(T_est, T_true @ turned[np.argmin(errors)]), atol=1e-4)


def test_sphere_leaves_the_centroid_displacement():
    rng = np.random.default_rng(2)
    T_true, T_est = pose(rng.normal(size=3), rng.normal(size=3)), pose(rng.normal(size=3), rng.normal(size=3))
    rot, trans = symmetric_errors(T_est, T_true, np.eye(4)[None], axes=np.eye(3), centre=CENTRE)
    moved = lambda T: T[:3, :3] @ CENTRE + T[:3, 3]  # noqa: E731
    assert rot == 0.0 and np.isclose(trans, np.linalg.norm(moved(T_est) - moved(T_true)), atol=1e-12)


def test_no_symmetry_gives_the_raw_errors_and_broadcasts():
    """The identity alone: the raw errors; poses (H, 1, 4, 4) against (1, H, 4, 4) give (H, H)."""
    rng = np.random.default_rng(3)
    poses = np.stack([pose(rng.normal(size=3), rng.normal(size=3)) for _ in range(5)])
    rot, trans = symmetric_errors(poses[:, None], poses[None], np.eye(4)[None])
    assert rot.shape == (5, 5)
    assert np.allclose(rot, rotation_error_deg(poses[:, None], poses[None]), atol=1e-9)
    assert np.allclose(trans, translation_error(poses[:, None], poses[None]))
