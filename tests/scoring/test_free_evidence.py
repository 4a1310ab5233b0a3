"""Swept free space as evidence (contacts.FreeSpace, scoring.freespace.drop_intersecting,
localize(free_space=...)): input checks, the inside test against trimesh's exact signed
distance, and a carton grasp whose two placements only the free space tells apart."""

import numpy as np
import pytest
import trimesh
from conftest import NORMAL_NOISE_DEG, POSITION_NOISE

import contactpose as cp
from contactpose import stages
from contactpose.contacts import Tolerance
from contactpose.errors import ContactPoseError
from contactpose.geometry import metrics
from contactpose.model.object_model import merged_mesh
from contactpose.model.symmetry import symmetry
from contactpose.progress import Deadline
from contactpose.scoring import freespace
from contactpose.scoring.classes import distinct_radius
from contactpose.sim import fingertip, objects
from contactpose.sim.grasps import pose_from

NOISE = dict(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)
TAU = Tolerance.from_noise(POSITION_NOISE, NORMAL_NOISE_DEG).distance
# the carton (objects.make_carton): square body 0.07 m wide, 0.17 m high, gabled roof 0.03 m
# high along y; a 90° turn about z maps the body onto itself but not the roof
HALF, BODY, ROOF = 0.035, 0.17, 0.03


# --------------------------------------------------------------------- input ---

@pytest.mark.parametrize("kwargs, name", [
    (dict(points=np.zeros((4, 2))), "free_space points"),
    (dict(points=[[0.0, np.nan, 0.0]]), "free_space points"),
    (dict(spheres=np.zeros((2, 4))), "free_space spheres"),
    (dict(spheres=(np.zeros((2, 3)),)), "free_space spheres"),
    (dict(spheres=(np.zeros((2, 3)), [0.01])), "free_space sphere radii"),
    (dict(spheres=(np.zeros((1, 3)), [-0.01])), "free_space sphere radii"),
    (dict(spheres=(np.zeros((2, 2)), [0.01, 0.01])), "free_space sphere centres"),
    (dict(capsules=(np.zeros((2, 3)), np.ones((3, 3)), [0.01, 0.01])), "free_space capsule ends b"),
    (dict(capsules=(np.zeros((1, 3)), np.ones((1, 3)), [np.inf])), "free_space capsule radii"),
    (dict(capsules=(np.zeros((1, 3)), np.ones((1, 3)))), "free_space capsules"),
])
def test_bad_free_space_names_the_value_and_shape(kwargs, name):
    with pytest.raises(ContactPoseError, match=name) as err:
        cp.FreeSpace(**kwargs)
    assert "\n" not in str(err.value)


def test_free_space_holds_read_only_float64_arrays_of_the_stated_shapes():
    free = cp.FreeSpace(points=[[0, 0, 1]], spheres=([[1, 2, 3], [4, 5, 6]], [0.1, 0.2]),
                        capsules=([[0, 0, 0]], [[1, 0, 0]], [0.05]))
    assert free.points.shape == (1, 3) and free.spheres[0].shape == (2, 3) and free.spheres[1].shape == (2,)
    assert [a.shape for a in free.capsules] == [(1, 3), (1, 3), (1,)]
    every = (free.points, *free.spheres, *free.capsules)
    assert all(a.dtype == np.float64 and not a.flags.writeable for a in every)
    assert free.size == 4
    empty = cp.FreeSpace()
    assert empty.size == 0 and empty.points.shape == (0, 3) and empty.capsules[2].shape == (0,)


def test_localize_takes_only_a_free_space(carton_model):
    contacts = cp.Contacts([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], object_normals=np.eye(3))
    with pytest.raises(ContactPoseError, match="free_space must be a contactpose.FreeSpace"):
        cp.localize(carton_model, contacts, free_space=np.zeros((3, 3)))


def test_a_capsule_becomes_balls_of_its_radius_along_its_segment():
    a, b, r = np.array([0.0, 0.0, 0.0]), np.array([0.1, 0.0, 0.0]), 0.007
    centres, radii = freespace.free_balls(cp.FreeSpace(points=[[1.0, 1.0, 1.0]], capsules=([a], [b], [r])), 0.001)
    balls = centres[1:]
    assert np.allclose(centres[0], 1.0) and radii[0] == 0.0
    assert np.allclose(radii[1:], r)
    assert np.allclose(balls[:, 1:], 0.0) and np.isclose(balls[0, 0], 0.0) and np.isclose(balls[-1, 0], 0.1)
    assert np.max(np.diff(balls[:, 0])) <= r + 1e-12


# ----------------------------------------------------------- the inside test ---

def test_ball_margins_agree_with_trimesh_signed_distance(rock_model):
    """Random poses and balls around the posed rock: a ball meets the object (margin > 0)
    exactly when trimesh's signed distance of its centre is below radius - τ, and the margin
    is that difference wherever it is computed exactly."""
    rng = np.random.default_rng(7)
    mesh = objects.load("rock")
    poses = np.stack([pose_from(rng.normal(size=3), rng.uniform(-0.05, 0.05, 3)) for _ in range(40)])
    local = rng.uniform(mesh.bounds[0] - 0.01, mesh.bounds[1] + 0.01, (60, 3))
    radii = rng.uniform(0.0, 0.006, len(local))
    slack = radii - TAU
    for pose in poses[:3]:       # balls given in the world frame of each pose in turn
        centres = local @ pose[:3, :3].T + pose[:3, 3]
        sd = np.stack([-trimesh.proximity.signed_distance(moved(mesh, T), centres) for T in poses])  # (H, E)
        want = slack[None] - sd
        clear = np.abs(want) > 1e-5                       # away from the float32 threshold
        got = np.stack([freespace.ball_margins(rock_model, poses, centres[e:e + 1], slack[e:e + 1])[0]
                        for e in range(len(centres))], axis=1)
        assert np.array_equal((got > 0)[clear], (want > 0)[clear])
        exact = clear & np.isfinite(got) & ((sd < 0) != (slack[None] > 0))   # the side does not settle it
        np.testing.assert_allclose(got[exact], want[exact], atol=1e-5)
        margin, ball = freespace.ball_margins(rock_model, poses, centres, slack)
        assert np.array_equal(margin > 0, (want > 0).any(axis=1))
        hit = margin > 0
        assert np.all(want[np.flatnonzero(hit), ball[hit]] > 0)


def moved(mesh, T):
    out = mesh.copy()
    out.apply_transform(T)
    return out


# ------------------------------------------------- two placements, one free ---

@pytest.fixture(scope="module")
def carton_grasp(carton_model):
    """Four contacts on the carton's body (bottom, both x walls, the -y wall), which fit the
    true pose and the pose turned 90° about the carton's axis alike, and points of the free
    space inside the turned carton's roof (by more than 2 mm) and outside the true carton
    (by more than τ + 2 mm), by trimesh."""
    T = pose_from((0.3, -0.2, 0.5), (0.1, 0.02, -0.05))
    local = np.array([[0.01, -0.012, 0.0], [HALF, 0.01, 0.06], [-HALF, -0.015, 0.11], [0.012, -HALF, 0.08]])
    normals = np.array([[0, 0, -1.0], [1, 0, 0], [-1, 0, 0], [0, -1, 0]])
    contacts = cp.Contacts(local @ T[:3, :3].T + T[:3, 3], object_normals=normals @ T[:3, :3].T)
    before = cp.localize(carton_model, contacts, **NOISE, keep="all", diagnose=False)
    right = strictly_right(carton_model, before.hypotheses.arrays.poses, T)
    wrong = before.hypotheses.arrays.poses[np.flatnonzero(~right)[0]]
    rng = np.random.default_rng(3)
    mesh = objects.load("carton")
    roof = rng.uniform([-HALF, -HALF, BODY], [HALF, HALF, BODY + ROOF], (3000, 3)) @ wrong[:3, :3].T + wrong[:3, 3]
    in_wrong = trimesh.proximity.signed_distance(moved(mesh, wrong), roof)
    in_true = trimesh.proximity.signed_distance(moved(mesh, T), roof)
    free = roof[(in_wrong > 0.002) & (in_true < -(TAU + 0.002))]
    return {"pose": T, "wrong": wrong, "contacts": contacts, "before": before, "free": free,
            "clearance": -trimesh.proximity.signed_distance(moved(mesh, T), free)}


def strictly_right(model, poses, truth):
    rot, trans = symmetry(model).errors(np.asarray(poses), truth)
    return (rot < metrics.SUCCESS_ROT_DEG) & (trans < metrics.SUCCESS_TRANS_FRAC * model.diameter)


def test_without_free_space_both_placements_fit(carton_model, carton_grasp):
    before = carton_grasp["before"]
    assert before.status == "ambiguous" and len(before.placements) == 2
    assert strictly_right(carton_model, [p.pose for p in before.placements], carton_grasp["pose"]).sum() == 1
    assert len(carton_grasp["free"]) > 50


def assert_only_the_truth_left(model, result, grasp):
    assert result.status == "ok", result.hint
    assert strictly_right(model, result.hypotheses.arrays.poses, grasp["pose"]).all()
    assert "free space ruled out 1 placement" in result.hint


def test_free_points_in_the_wrong_placement_rule_it_out(carton_model, carton_grasp):
    free = cp.FreeSpace(points=carton_grasp["free"])
    after = cp.localize(carton_model, carton_grasp["contacts"], **NOISE, keep="all", diagnose=False, free_space=free)
    assert_only_the_truth_left(carton_model, after, carton_grasp)
    assert "free_space" in after.timing


def test_free_spheres_and_capsules_rule_it_out_too(carton_model, carton_grasp):
    pts, clearance = carton_grasp["free"], carton_grasp["clearance"]
    r = 0.001
    spheres = cp.FreeSpace(spheres=(pts, np.full(len(pts), r)))
    after = cp.localize(carton_model, carton_grasp["contacts"], **NOISE, keep="all", diagnose=False, free_space=spheres)
    assert_only_the_truth_left(carton_model, after, carton_grasp)
    # capsules of zero length and radius r at the free points, clear of the truth by construction
    assert np.all(clearance > r + TAU)
    capsules = cp.FreeSpace(capsules=(pts, pts, np.full(len(pts), r)))
    after = cp.localize(carton_model, carton_grasp["contacts"], **NOISE, keep="all", diagnose=False, free_space=capsules)
    assert_only_the_truth_left(carton_model, after, carton_grasp)


def test_free_space_clear_of_both_placements_changes_nothing(carton_model, carton_grasp):
    far = carton_grasp["pose"][:3, 3] + np.array([[1.0, 0, 0], [0, 1.0, 0]])
    after = cp.localize(carton_model, carton_grasp["contacts"], **NOISE, keep="all", diagnose=False,
                        free_space=cp.FreeSpace(points=far))
    before = carton_grasp["before"]
    assert after.status == before.status and len(after.placements) == 2
    assert "free space" not in after.hint


def test_past_the_budget_hypotheses_are_kept_and_counted(carton_model, carton_grasp, monkeypatch):
    monkeypatch.setattr(freespace, "MAX_FREE_PAIRS", 0)
    after = cp.localize(carton_model, carton_grasp["contacts"], **NOISE, keep="all", diagnose=False,
                        free_space=cp.FreeSpace(points=carton_grasp["free"]))
    assert after.status == "ambiguous" and len(after.placements) == 2
    assert "left untested against free space" in after.hint


# --------------------------------------------- the rule on simulated fingertips ---

@pytest.mark.parametrize("seed", range(4))
def test_swept_fingertips_never_rule_out_the_truth(rock_model, seed):
    """Fingertips of radius 2 % of the diameter sweep to the rock (sim.fingertip); the points
    they swept rule out only hypotheses that are shown to meet them (against every posed
    hypothesis, exactly), and never the placement the contacts came from."""
    rng = np.random.default_rng(100 + seed)
    mesh = merged_mesh(rock_model.vertices, rock_model.faces)
    touch = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 4,
                               0.02 * rock_model.diameter)
    hit = touch.hit
    T = pose_from(rng.normal(size=3), rng.uniform(-0.03, 0.03, 3))
    R, t = T[:3, :3], T[:3, 3]
    points = touch.points[hit] @ R.T + t + rng.normal(0.0, POSITION_NOISE, (hit.sum(), 3))
    contacts = cp.Contacts(points, object_normals=touch.normals[hit] @ R.T)
    free = fingertip.swept_free_points(touch, 0.02 * rock_model.diameter) @ R.T + t
    before = cp.localize(rock_model, contacts, **NOISE, keep="all", diagnose=False)
    after = cp.localize(rock_model, contacts, **NOISE, keep="all", diagnose=False,
                        free_space=cp.FreeSpace(points=free))
    if strictly_right(rock_model, before.hypotheses.arrays.poses, T).any():
        assert strictly_right(rock_model, after.hypotheses.arrays.poses, T).any()
    assert len(after.placements) <= len(before.placements)
    # soundness of the bounded rule on the search's own hypotheses
    tolerance = Tolerance.from_noise(POSITION_NOISE, NORMAL_NOISE_DEG)
    arrays, *_ = stages.find_hypotheses(rock_model, contacts, tolerance, solver="closed-form", prior=None,
                                        max_outliers=0, deadline=Deadline(60), progress=False, tree=None,
                                        finger_radius=None)
    centres, radii = freespace.free_balls(cp.FreeSpace(points=free), tolerance.distance)
    bad, untested = freespace.intersecting_best_first(rock_model, contacts, arrays, centres, radii - tolerance.distance,
                                                      distinct_radius(rock_model, POSITION_NOISE))
    exact, _ = freespace.ball_margins(rock_model, arrays.poses, centres, radii - tolerance.distance)
    assert untested == 0
    assert not np.any(bad & ~(exact > 0)) and not np.any(bad & arrays.fit.underdetermined)
