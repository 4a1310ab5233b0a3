"""The search by hypothesize and verify (search.verify, stages.verified_hypotheses):
completeness measured against the truth on fingertip contacts of the sphere-sweep simulator
(rounded fingertips on faces, edges and vertices, noisy), the closed-form pair pose against a
known motion, and localize(search="samples") against the truth end to end."""

import warnings

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from contactpose import localize
from contactpose.contacts import Contacts, FreeSpace, Tolerance
from contactpose.errors import ContactPoseError
from contactpose.geometry import metrics
from contactpose.geometry.raycast import raycaster
from contactpose.model.object_model import ObjectModel
from contactpose.search.verify import _pair_pose, candidate_poses, posed_pairs
from contactpose.sim import fingertip, objects
from contactpose.sim import grasps as simulate

NOISE_FRAC, NORMAL_DEG = 0.0025, 1.0


@pytest.fixture(scope="module")
def ycb_banana():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObjectModel.from_mesh(objects.load("ycb:011_banana"), max_span=1e-9, patch_tol_deg=None,
                                     facet_pairs=True)


def _grasp(model, rng, frac):
    """A random pose and 4 noisy fingertip contacts of radius frac x diameter. -> (pose, Contacts)"""
    D = model.diameter
    pose = simulate.random_pose(rng, max_translation=0.5 * D)
    got = fingertip.approach(model.vertices, model.faces, rng, 4, frac * D)
    while not got.hit.all():
        got = fingertip.approach(model.vertices, model.faces, rng, 4, frac * D)
    R, t = pose[:3, :3], pose[:3, 3]
    world = got.points @ R.T + t + rng.normal(0, NOISE_FRAC * D, got.points.shape)
    finger = Rotation.from_rotvec(rng.normal(0, np.radians(NORMAL_DEG), (4, 3))).apply(-(got.normals @ R.T))
    return pose, Contacts(world, finger_normals=finger)


def _near(model, R, t, pose, rot_deg, trans_frac):
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, t
    return (metrics.rotation_error_deg(T, pose) < rot_deg) & (metrics.translation_error(T, pose) < trans_frac * model.diameter)


def test_pair_pose_recovers_a_known_motion():
    """Two oriented points moved by a known pose: the pair pose is that pose exactly."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=(2, 3))
        m = Rotation.random(2, random_state=rng).apply([0.0, 0.0, 1.0])
        R0, t0 = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)
        p, nu = q @ R0.T + t0, m @ R0.T
        R, t = np.empty((3, 3)), np.empty(3)
        _pair_pose(q, m, 0, 1, p, nu, 0, 1, np.empty((3, 3)), np.empty((3, 3)), R, t)
        np.testing.assert_allclose(R, R0, atol=1e-9)
        np.testing.assert_allclose(t, t0, atol=1e-9)


@pytest.mark.parametrize("frac", [0.0, 0.02, 0.05])
def test_some_candidate_lies_near_the_truth(ycb_banana, frac):
    """On the YCB banana (16,384 facets), fingertips of radius 0, 2 and 5 % of the diameter:
    a candidate within 10° and 5 % of the diameter of the truth in every grasp (measured:
    30 of 30 at each radius, seed 7; here 12)."""
    model = ycb_banana
    tol = Tolerance.from_noise(NOISE_FRAC * model.diameter, NORMAL_DEG)
    rng = np.random.default_rng(11)
    missed = []
    for g in range(12):
        pose, contacts = _grasp(model, rng, frac)
        found = candidate_poses(model.oriented, contacts, tol, model.diameter)
        if not _near(model, found.R, found.t, pose, 10.0, 0.05).any():
            missed.append(g)
    assert not missed


def test_candidates_are_clustered_and_ordered(ycb_banana):
    model = ycb_banana
    tol = Tolerance.from_noise(NOISE_FRAC * model.diameter, NORMAL_DEG)
    _, contacts = _grasp(model, np.random.default_rng(3), 0.02)
    found = candidate_poses(model.oriented, contacts, tol, model.diameter)
    assert len(found) > 1
    assert np.all(np.diff(found.cost) >= 0)
    # the pose hash: R's first two columns in 5° steps, the translation in steps of 5 % D
    key = np.concatenate([np.floor(found.R[:, :, :2].reshape(-1, 6) / np.radians(5.0)),
                          np.floor(found.t / (0.05 * model.diameter))], axis=1)
    assert len(np.unique(key, axis=0)) == len(found)


def test_localize_by_samples_finds_the_truth(ycb_banana):
    """End to end, rounded fingertips of 5 % D: the best pose strictly right (5°, 5 % D) in at
    least 4 of 6 grasps and the truth among the listed poses in 5 (measured: 5 and 5)."""
    model = ycb_banana
    rng = np.random.default_rng(5)
    top, listed = 0, 0
    for _ in range(6):
        pose, contacts = _grasp(model, rng, 0.05)
        r = localize(model, contacts, search="samples", finger_radius=0.05 * model.diameter, diagnose=False)
        poses = np.stack([h.pose for h in r.hypotheses])
        strict = _near(model, poses[:, :3, :3], poses[:, :3, 3], pose, 5.0, 0.05)
        top += bool(strict[0])
        listed += bool(strict.any())
    assert top >= 4 and listed >= 5


def test_unknown_search_is_refused(ycb_banana):
    _, contacts = _grasp(ycb_banana, np.random.default_rng(0), 0.0)
    with pytest.raises(ContactPoseError, match="search must be one of"):
        localize(ycb_banana, contacts, search="voxels")


def test_paper_method_refuses_another_search(ycb_banana):
    _, contacts = _grasp(ycb_banana, np.random.default_rng(0), 0.0)
    with pytest.raises(ContactPoseError, match="method='paper' searches its facet table"):
        localize(ycb_banana, contacts, method="paper", search="samples")


def test_the_time_limit_bounds_the_search(ycb_banana):
    """A time limit that has passed before the first chunk: nothing is checked, and the answer
    says the search stopped there."""
    _, contacts = _grasp(ycb_banana, np.random.default_rng(1), 0.02)
    r = localize(ycb_banana, contacts, search="samples", time_limit=1e-9, diagnose=False)
    assert r.status == "time_limit" and len(r.hypotheses) == 0


def test_max_outliers_is_refused_by_the_samples_search(ycb_banana):
    _, contacts = _grasp(ycb_banana, np.random.default_rng(0), 0.0)
    with pytest.raises(ContactPoseError, match="max_outliers=1 needs search='auto'"):
        localize(ycb_banana, contacts, search="samples", max_outliers=1)


def test_pairs_are_posed_longest_first():
    points = np.random.default_rng(4).normal(size=(5, 3))
    pairs = posed_pairs(points)
    length = [np.linalg.norm(points[j] - points[i]) for i, j in pairs]
    assert sorted(pairs) == [(i, j) for i in range(5) for j in range(i + 1, 5)]
    assert np.all(np.diff(length) <= 0)


@pytest.fixture(scope="module")
def rock_regions():
    return ObjectModel.from_mesh(objects.load("rock1k"), patch_tol_deg=10.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_check_before_ok_finds_a_truth_the_region_search_lost(rock_regions, seed):
    """stages.checked_by_samples: an answer whose hypotheses lost every pose strictly alike the
    truth (by construction: those rows removed) gets it back from the search by hypothesize
    and verify, fitted on the surface (χ² within noise), and keeps every pose it had that
    fits, or a near-copy that fits better."""
    from contactpose import stages
    from contactpose.options import fit_threshold

    model = rock_regions
    pose, contacts = _grasp(model, np.random.default_rng(seed), 0.02)
    noise = dict(position_noise=NOISE_FRAC * model.diameter, normal_noise_deg=NORMAL_DEG)
    r = localize(model, contacts, **noise, keep="all", diagnose=False)
    arrays = r.hypotheses.arrays
    right = _near(model, arrays.poses[:, :3, :3], arrays.poses[:, :3, 3], pose, 5.0, 0.05)
    assert right.any()
    lost = arrays.take(np.flatnonzero(~right))
    timing = {"tree": 0.0, "pose": 0.0}
    checked = stages.checked_by_samples(model, contacts, lost, r.tolerance, timing)
    back = _near(model, checked.poses[:, :3, :3], checked.poses[:, :3, 3], pose, 5.0, 0.05)
    assert back.any() and checked.chi2[back].min() <= fit_threshold(contacts.n)
    assert timing["tree"] > 0 and timing["pose"] > 0
    for k in np.flatnonzero(lost.chi2 <= fit_threshold(contacts.n)):  # each pose it had that fits stays, or a
        near = _near(model, checked.poses[:, :3, :3], checked.poses[:, :3, 3], lost.poses[k], 10.0, 0.1)
        assert near.any() and checked.chi2[near].min() <= lost.chi2[k] + 1e-9  # near-copy of a lower χ² takes it
    inside = model.centroids - 0.05 * model.diameter * model.planes.normals  # a ball the truth's object holds:
    held = inside[raycaster(model).inside(inside)][:1] @ pose[:3, :3].T + pose[:3, 3]  # told free, the truth
    checked = stages.checked_by_samples(model, contacts, lost, r.tolerance, timing,  # cannot come back
                                        free_space=FreeSpace(points=held))
    assert not _near(model, checked.poses[:, :3, :3], checked.poses[:, :3, 3], pose, 5.0, 0.05).any()
