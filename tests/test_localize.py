"""The online phase: contacts and tolerances, the closed-form pose against
references (scipy's Wahba solver, Levenberg–Marquardt on eq. 7, exact data), degenerate
geometry, ``localize`` statuses and options, invariances, priors, and the recall of the
true facet tuple.
"""

import itertools
import json

import numpy as np
import pytest
import trimesh
from conftest import NORMAL_NOISE_DEG, POSITION_NOISE
from scipy.spatial.transform import Rotation

from contactpose.contacts import Contacts, Tolerance
from contactpose.costs import facet, frame
from contactpose.errors import ContactPoseError, ContactsError, PriorError
from contactpose.geometry.metrics import (
    SAME_CLASS_ADDS_FRAC,
    adds,
    adds_many,
    relative_points,
    rms_displacement,
    rotation_error_deg,
)
from contactpose.localize import localize
from contactpose.options import fit_threshold
from contactpose.scoring.classes import MAX_CLASS_HYPOTHESES, pose_classes
from contactpose.search.pairs import admissible_pairs, pair_conditions
from contactpose.search.tree import TripleTest, join_tuples, sorted_rows
from contactpose.sim import grasps as simulate
from contactpose.solvers.closed_form import fit_poses, wahba
from contactpose.solvers.lm import eq7_residuals, fit_lm
from contactpose.types import PosePrior

NOISE = dict(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)


def rigid(rng, max_translation=0.1):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-max_translation, max_translation, 3)
    return T


def spanning_grasp(model, rng, **kwargs):
    """A grasp whose true facet normals span 3-D well (smallest eigenvalue of Σnnᵀ > 0.2)."""
    for _ in range(200):
        g = simulate.grasp(model, rng, **kwargs)
        n = model.planes.normals[g.facets]
        if np.linalg.eigvalsh(n.T @ n)[0] > 0.2:
            return g
    raise AssertionError("no well-spanning grasp found")


def facet_set(result):
    return set(map(tuple, result.hypotheses.arrays.facets.tolist()))


def has_row(tuples, row):
    """Whether (H, n) int tuples contain row (n,)."""
    return bool((tuples == np.asarray(row)).all(axis=1).any())


def same_rows(a, b):
    """Whether two (H, n) int arrays hold the same rows (as sets; rows are unique)."""
    return a.shape == b.shape and np.array_equal(sorted_rows(a), sorted_rows(b))


# -------------------------------------------------------------- contacts

def test_pair_conditions_match_direct_computation():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(5, 3))
    nf = rng.normal(size=(5, 3))
    nf /= np.linalg.norm(nf, axis=1, keepdims=True)
    c = pair_conditions(Contacts(pts, finger_normals=nf))
    assert c.pairs == list(itertools.combinations(range(5), 2))
    for e, (i, j) in enumerate(c.pairs):
        assert c.distance[e] == pytest.approx(np.linalg.norm(pts[j] - pts[i]), rel=1e-14)
        assert c.angle[e] == pytest.approx(np.arccos(nf[i] @ nf[j]), abs=1e-12)
        assert c.h_ij[e] == pytest.approx(-nf[i] @ (pts[j] - pts[i]), abs=1e-14)
        assert c.h_ji[e] == pytest.approx(-nf[j] @ (pts[i] - pts[j]), abs=1e-14)


def test_contacts_validation():
    pts = np.eye(3)
    n = np.array([[0, 0, 1.0]] * 3)
    with pytest.raises(ContactsError, match="exactly one"):
        Contacts(pts, finger_normals=n, object_normals=n)
    with pytest.raises(ContactsError, match="exactly one"):
        Contacts(pts)
    with pytest.raises(ContactsError, match="at least 1 contact"):
        Contacts(pts[:0], finger_normals=n[:0])
    assert Contacts(pts[:1], finger_normals=n[:1]).n == 1  # a touch may bring one contact
    with pytest.raises(ContactsError, match="shape"):
        Contacts(pts, finger_normals=n[:2])
    with pytest.raises(ContactsError, match="NaN"):
        Contacts(np.array([[0, 0, np.nan], [1, 0, 0]]), finger_normals=n[:2])
    with pytest.raises(ContactsError, match="zero"):
        Contacts(pts, finger_normals=np.zeros((3, 3)))
    with pytest.raises(ContactsError, match="same point"):
        Contacts(np.array([[0, 0, 0], [0, 0, 0.0]]), finger_normals=n[:2])
    with pytest.warns(UserWarning, match="non-unit"):
        c = Contacts(pts, object_normals=3 * n)
    assert np.allclose(c.finger_normals, -n) and np.allclose(c.object_normals, n)


def test_tolerance_covers_about_3_sigma_of_pair_errors():
    """Gaussian noise of per-axis σ: pair distance and angle errors stay within the
    tolerance in ≈ 99.7 % of pairs (3σ of the pair's difference), not far fewer or all."""
    rng = np.random.default_rng(1)
    sx, sn = 0.0005, 1.0
    tol = Tolerance.from_noise(sx, sn)
    assert tol.distance == pytest.approx(3 * np.sqrt(2) * sx)
    assert tol.angle == pytest.approx(3 * np.sqrt(2) * np.radians(sn))
    m = 40_000
    p = rng.normal(size=(m, 2, 3)) * 0.05
    noisy = p + rng.normal(0, sx, p.shape)
    d_err = np.linalg.norm(noisy[:, 1] - noisy[:, 0], axis=1) - np.linalg.norm(p[:, 1] - p[:, 0], axis=1)
    n = rng.normal(size=(2 * m, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    nn = simulate.perturb_normals(n, np.radians(sn), rng).reshape(m, 2, 3)
    n = n.reshape(m, 2, 3)
    angle = lambda a: np.arccos(np.clip(np.einsum("ij,ij->i", a[:, 0], a[:, 1]), -1, 1))
    a_err = angle(nn) - angle(n)
    assert 0.995 <= np.mean(np.abs(d_err) <= tol.distance) <= 0.999
    assert 0.99 <= np.mean(np.abs(a_err) <= tol.angle) <= 0.9995


# ---------------------------------------------------------- closed form

def test_wahba_equals_scipy_align_vectors():
    rng = np.random.default_rng(2)
    for n in (2, 3, 4, 7):
        a = rng.normal(size=(6, n, 3))
        R_true = Rotation.random(6, random_state=rng).as_matrix()
        b = np.einsum("hij,hnj->hni", R_true, a) + 0.3 * rng.normal(size=(6, n, 3))
        for h in range(6):
            R = wahba(a[h][None], b[h])[0]
            ref = Rotation.align_vectors(b[h], a[h])[0].as_matrix()
            assert np.allclose(R, ref, atol=1e-9)
    # where the best orthogonal map is a reflection, wahba still returns the best rotation
    a = rng.normal(size=(5, 3))
    b = a * [1.0, 1.0, -1.0]
    R = wahba(a[None], b)[0]
    assert np.linalg.det(R) == pytest.approx(1.0)
    cost = lambda Q: np.sum((a @ Q.T - b) ** 2)
    assert cost(R) == pytest.approx(cost(Rotation.align_vectors(b, a)[0].as_matrix()), rel=1e-9)


def hypothesis_arrays(model, g):
    normals = model.planes.normals[g.facets][None]
    offsets = model.planes.offsets[g.facets][None]
    return normals, offsets, model.centroids[g.facets][None]


def eq7_cost(T, normals, offsets, contacts):
    x = np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])
    r = eq7_residuals(x, normals, offsets, contacts.points, contacts.finger_normals)
    return float(r @ r)


def test_closed_form_paper_cost_equals_lm_optimum(rock_model):
    model = rock_model
    rng = np.random.default_rng(3)
    for _ in range(8):
        g = spanning_grasp(model, rng, n=4, position_noise=0.001, normal_noise_deg=2.0)
        normals, offsets, centroids = hypothesis_arrays(model, g)
        c = g.contacts
        fit = fit_poses(normals, offsets, c.points, c.finger_normals, cost="paper",
                        angle_tol=np.radians(1.0), centroids=centroids)
        T_cf = fit.poses()[0]
        start = g.pose @ simulate.pose_from(rng.normal(0, np.radians(3), 3), rng.normal(0, 0.003, 3))
        T_lm, cost_lm, ok = fit_lm(normals[0], offsets[0], c.points, c.finger_normals, start)
        assert ok
        cost_cf = eq7_cost(T_cf, normals[0], offsets[0], c)
        assert cost_cf > 1e-6                       # a real optimum, not an exact fit
        assert abs(cost_cf - cost_lm) <= 1e-6 * cost_cf
        assert np.abs(T_cf - T_lm).max() <= 1e-6
        # the closed form is the global minimum: LM from far starts never beats it
        T_far, cost_far, _ = fit_lm(normals[0], offsets[0], c.points, c.finger_normals, np.eye(4))
        assert cost_cf <= cost_far + 1e-12


def test_closed_form_invariant_cost_is_stationary_and_origin_free(rock_model):
    """The default cost Σ (n_kᵀRᵀ(x̃_i - t) + d_k)²: t is its minimiser (finite differences),
    and moving the object frame's origin by c moves t by R c; eq. 7's t does not follow."""
    model = rock_model
    rng = np.random.default_rng(4)
    g = spanning_grasp(model, rng, n=4, position_noise=0.001, normal_noise_deg=2.0)
    normals, offsets, centroids = hypothesis_arrays(model, g)
    c = g.contacts
    fit = fit_poses(normals, offsets, c.points, c.finger_normals, angle_tol=np.radians(1.0), centroids=centroids)
    R, t = fit.R[0], fit.t[0]

    def F(t):
        return np.sum((np.einsum("nj,nj->n", normals[0] @ R.T, c.points - t) + offsets[0]) ** 2)

    h = 1e-6
    grad = np.array([(F(t + h * e) - F(t - h * e)) / (2 * h) for e in np.eye(3)])
    assert np.abs(grad).max() < 1e-9
    # the rotation is Wahba's: aligning R n_k with -ñ_i
    assert np.allclose(R, wahba(normals, c.finger_normals * -1)[0], atol=1e-12)

    shift = np.array([0.03, -0.02, 0.05])
    offsets_shifted = offsets + np.einsum("hnj,j->hn", normals, shift)   # vertices v - shift
    for cost, follows in (("invariant", True), ("paper", False)):
        a = fit_poses(normals, offsets, c.points, c.finger_normals, cost=cost, angle_tol=np.radians(1.0),
                      centroids=centroids)
        b = fit_poses(normals, offsets_shifted, c.points, c.finger_normals, cost=cost,
                      angle_tol=np.radians(1.0), centroids=centroids - shift)
        assert np.allclose(a.R, b.R, atol=1e-12)
        moved = np.allclose(b.t[0], a.t[0] + a.R[0] @ shift, atol=1e-9)
        assert moved == follows, cost


@pytest.mark.parametrize("cost", ["invariant", "paper"])
def test_closed_form_recovers_true_pose_from_exact_data(models, cost):
    rng = np.random.default_rng(5)
    for model in models.values():
        for _ in range(5):
            g = spanning_grasp(model, rng, n=4)
            normals, offsets, centroids = hypothesis_arrays(model, g)
            fit = fit_poses(normals, offsets, g.contacts.points, g.contacts.finger_normals, cost=cost,
                            angle_tol=np.radians(1.0), centroids=centroids)
            assert not fit.underdetermined[0]
            assert np.abs(fit.poses()[0] - g.pose).max() < 1e-9


def test_fused_residuals_equal_the_per_term_definitions(rock_model):
    """contact_residuals (one compiled pass) against normal_, offset_ and lateral_residuals,
    on random poses and facets, so contacts land both inside and outside their triangles."""
    model = rock_model
    rng = np.random.default_rng(8)
    facets = rng.integers(0, model.num_facets, size=(50, 4))
    R = Rotation.random(50, random_state=9).as_matrix()
    t = rng.normal(scale=0.02, size=(50, 3))
    points, fn = rng.normal(scale=0.03, size=(4, 3)), Rotation.random(4, random_state=3).apply([0, 0, 1.0])
    normals, offsets, tri = model.planes.normals[facets], model.planes.offsets[facets], model.triangles[facets]
    r_n, r_o, r_l = facet.contact_residuals(R, t, normals, offsets, tri, points, fn)
    p = frame.object_frame(R, t, points)
    want_o = facet.offset_residuals(p, normals, offsets)
    assert np.allclose(r_n, facet.normal_residuals(R, normals, fn), atol=1e-14)
    assert np.allclose(r_o, want_o, atol=1e-14)
    assert np.allclose(r_l, facet.lateral_residuals(p, tri, want_o), atol=1e-9)
    assert (r_l > 0).any() and (r_l == 0).any()


def test_free_rotation_is_chosen_from_the_geometry_not_the_frame(carton_model):
    """Contacts on one flat side leave the rotation about its normal free; the closed form
    turns the facet centroids' spread onto the contacts' spread, so a rigid motion of the
    contacts moves the fitted pose by exactly that motion."""
    model = carton_model
    rng = np.random.default_rng(11)
    k = int(np.argmax(model.planes.areas))
    side = np.flatnonzero(model.planes.normals @ model.planes.normals[k] > 1 - 1e-9)[:3]
    g = simulate.grasp(model, rng, n=3, facets=side, position_noise=0.0005, normal_noise_deg=0.5)
    normals, offsets, centroids = (a[side][None] for a in (model.planes.normals, model.planes.offsets,
                                                           model.centroids))
    c = g.contacts
    T = simulate.random_pose(rng, max_translation=0.5)
    moved = c.transformed(T)
    a = fit_poses(normals, offsets, c.points, c.finger_normals, angle_tol=np.radians(1.0), centroids=centroids)
    b = fit_poses(normals, offsets, moved.points, moved.finger_normals, angle_tol=np.radians(1.0),
                  centroids=centroids)
    assert a.free_rotation_mask[0]
    assert np.allclose(T @ a.poses()[0], b.poses()[0], atol=1e-9)


def test_two_contacts_leave_one_translation_free(rock_model):
    model = rock_model
    rng = np.random.default_rng(6)
    for _ in range(5):
        g = simulate.grasp(model, rng, n=2)
        normals, offsets, centroids = hypothesis_arrays(model, g)
        if abs(normals[0, 0] @ normals[0, 1]) > 0.9:
            continue
        c = g.contacts
        fit = fit_poses(normals, offsets, c.points, c.finger_normals, angle_tol=np.radians(1.0),
                        centroids=centroids)
        assert fit.underdetermined[0] and not fit.free_rotation_mask[0]
        free = fit.free_translation[0][fit.free_translation_mask[0]]
        assert free.shape == (1, 3)
        axis = np.cross(c.finger_normals[0], c.finger_normals[1])
        assert abs(free[0] @ axis) / np.linalg.norm(axis) == pytest.approx(1.0, abs=1e-9)
        # with exact data the rotation is the true one, and t differs from truth only along the axis
        assert np.allclose(fit.R[0], g.pose[:3, :3], atol=1e-9)
        off = fit.t[0] - g.pose[:3, 3]
        assert np.linalg.norm(off - (off @ free[0]) * free[0]) < 1e-9


def test_parallel_normals_leave_rotation_about_them_free(carton_model):
    """Three contacts on one flat side: rotation about its normal and two translations free."""
    model = carton_model
    rng = np.random.default_rng(7)
    k = int(np.argmax(model.planes.areas))
    g = simulate.grasp(model, rng, n=3, facets=[k, k, k])
    normals, offsets, centroids = hypothesis_arrays(model, g)
    c = g.contacts
    for cost in ("invariant", "paper"):
        fit = fit_poses(normals, offsets, c.points, c.finger_normals, cost=cost, angle_tol=np.radians(1.0),
                        centroids=centroids)
        assert fit.free_rotation_mask[0]
        world_normal = g.pose[:3, :3] @ model.planes.normals[k]
        assert abs(fit.free_rotation[0] @ world_normal) == pytest.approx(1.0, abs=1e-9)
        free = fit.free_translation[0][fit.free_translation_mask[0]]
        assert free.shape == (2, 3)
        assert np.abs(free @ world_normal).max() < 1e-9


# ------------------------------------------------------------- localize

def test_status_ok_means_the_truth_is_the_only_fitting_pose_class(banana_model, rock_model):
    """Whenever the true tuple fits within noise and the status is ok, the best hypothesis
    places the object like the truth (ADD-S below 5 % of the diameter)."""
    rng = np.random.default_rng(8)
    ok = 0
    for model in (banana_model, rock_model):
        limit = SAME_CLASS_ADDS_FRAC * model.diameter
        for _ in range(15):
            g = simulate.grasp(model, rng, n=4, noise="bounded", **NOISE)
            r = localize(model, g.contacts, **NOISE, distinct=False)
            a = r.hypotheses.arrays
            truth = np.flatnonzero((a.facets == g.facets).all(axis=1))
            assert len(truth) == 1
            if r.status == "ok" and a.chi2[truth[0]] <= fit_threshold(4):
                ok += 1
                assert adds(r.best.pose, g.pose, model.surface_points, model.surface_tree) < limit
    assert ok >= 15


def naive_pose_classes(model, poses):
    """Reference twin of pose_classes' grouping: each pose joins the first class whose best
    pose is within ADD-S (on class_points, against all surface points), else opens one."""
    limit = SAME_CLASS_ADDS_FRAC * model.diameter
    reps, labels = [], []
    for T in poses:
        c = next((c for c, r in enumerate(reps)
                  if adds(T, poses[r], model.class_points, model.surface_tree) <= limit), None)
        if c is None:
            c = len(reps)
            reps.append(len(labels))
        labels.append(c)
    return labels


def test_pose_classes_equal_the_naive_grouping(rock_model, box_model):
    """The bounds that spare nearest-point queries (RMS displacement, anchors) never change a
    class: hypotheses of real grasps and random poses grouped both ways agree."""
    rng = np.random.default_rng(31)
    checked = 0
    for model in (rock_model, box_model):
        for _ in range(6):
            g = simulate.grasp(model, rng, n=4, noise="bounded", **NOISE)
            a = localize(model, g.contacts, **NOISE).hypotheses.arrays
            fits = np.ones(len(a.cost), dtype=bool)
            classes = pose_classes(model, a, fits)
            labels = np.empty(min(len(a.cost), MAX_CLASS_HYPOTHESES), dtype=int)
            for c, cls in enumerate(classes):
                labels[cls.members] = c
            assert labels.tolist() == naive_pose_classes(model, a.poses[:len(labels)])
            checked += len(classes) > 1
    assert checked >= 2


def test_rms_displacement_bounds_adds(rock_model):
    """RMS displacement from the moments equals the direct mean over the points, and bounds
    ADD-S from above; adds_many equals adds pose by pose."""
    rng = np.random.default_rng(32)
    base = rigid(rng)
    poses = np.array([base @ rigid(rng, 0.01) for _ in range(20)])
    pts = rock_model.class_points
    rms = rms_displacement(poses, base, *rock_model.class_moments)
    moved = [relative_points(T, base, pts) for T in poses]
    direct = [np.sqrt(np.mean(np.sum((q - pts) ** 2, axis=1))) for q in moved]
    assert np.allclose(rms, direct, rtol=1e-9, atol=1e-12)
    many = adds_many(poses, base, pts, rock_model.surface_tree)
    assert np.allclose(many, [adds(T, base, pts, rock_model.surface_tree) for T in poses], rtol=1e-12)
    assert np.all(many <= rms + 1e-12)


def test_status_no_hypothesis_for_wrong_units(rock_model):
    rng = np.random.default_rng(9)
    g = simulate.grasp(rock_model, rng, n=4, noise="bounded", **NOISE)
    mm = Contacts(g.contacts.points * 1000.0, finger_normals=g.contacts.finger_normals)
    with pytest.raises(ContactsError, match="millimetres vs metres"):
        localize(rock_model, mm, **NOISE)
    wide = Contacts(g.contacts.points * 3.0, finger_normals=g.contacts.finger_normals)
    if wide.spread > rock_model.diameter * 1.1:
        with pytest.warns(UserWarning, match="same units"):
            r = localize(rock_model, wide, **NOISE)
        assert r.status == "no_hypothesis" and "same units" in r.hint
        assert len(r.hypotheses) == 0 and r.best is None and r.num_hypotheses == 0
        assert json.loads(json.dumps(r.to_dict(), allow_nan=False))["status"] == "no_hypothesis"


def test_flipped_finger_normals_get_a_hint_about_the_sign(rock_model):
    rng = np.random.default_rng(9)
    g = simulate.grasp(rock_model, rng, n=4, noise="bounded", **NOISE)
    flipped = Contacts(g.contacts.points, finger_normals=-g.contacts.finger_normals)
    r = localize(rock_model, flipped, **NOISE)
    assert r.status == "no_hypothesis" and "finger_normal points into the object" in r.hint


def test_status_underdetermined_for_two_contacts(rock_model):
    rng = np.random.default_rng(10)
    g = simulate.grasp(rock_model, rng, n=2, noise="bounded", **NOISE)
    r = localize(rock_model, g.contacts, **NOISE)
    assert r.status == "underdetermined"
    assert all(h.underdetermined for h in r.hypotheses)
    best = r.best
    assert best.free_translation.shape == (1, 3)
    axis = np.cross(g.contacts.finger_normals[0], g.contacts.finger_normals[1])
    assert abs(best.free_translation[0] @ axis) / np.linalg.norm(axis) > np.cos(np.radians(5))


def test_status_ambiguous_for_symmetric_box_grasp(box_model):
    """Box 0.10 × 0.06 × 0.04 (origin at its centre). Contacts on +x, +y, top and bottom near
    the (+x, +y) edge fit the box as it is and the box turned 90° about that edge: two
    placements of the surface that are not symmetric twins."""
    pts = np.array([[0.05, 0.007, 0.005], [0.02, 0.03, -0.005], [0.01, -0.01, 0.02], [0.015, 0.005, -0.02]])
    normals = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    r = localize(box_model, Contacts(pts, object_normals=normals), twins=True, **NOISE)
    assert r.status == "ambiguous"
    mesh = trimesh.Trimesh(box_model.vertices, box_model.faces, process=False)
    fitting = []
    for h in r.hypotheses[:50]:
        R, t = h.pose[:3, :3], h.pose[:3, 3]
        local = (pts - t) @ R                      # contacts in the object frame
        _, dist, tri = trimesh.proximity.closest_point(mesh, local)
        if dist.max() < 1e-6 and np.allclose(box_model.planes.normals[tri], normals @ R, atol=1e-6):
            fitting.append(h.pose)
    rot = [rotation_error_deg(T, np.eye(4)) for T in fitting]
    limit = SAME_CLASS_ADDS_FRAC * box_model.diameter
    distinct = [T for T in fitting
                if adds(T, np.eye(4), box_model.surface_points, box_model.surface_tree) > limit]
    assert min(rot) < 1e-6                          # the truth fits ...
    assert any(abs(a - 90.0) < 1e-6 for a in rot)   # ... and so does the box turned by 90°
    assert distinct                                 # which is a different placement


def test_result_to_dict_round_trips_through_json(models, box_model):
    rng = np.random.default_rng(11)
    results = [localize(models["rock"], simulate.grasp(models["rock"], rng, n=n, noise="bounded",
                                                        **NOISE).contacts, **NOISE) for n in (2, 4)]
    results.append(localize(box_model, simulate.grasp(box_model, rng, n=4, noise="bounded",
                                                      **NOISE).contacts, method="paper",
                            solver="closed-form", top=100, **NOISE))
    for r in results:
        d = r.to_dict()
        text = json.dumps(d, allow_nan=False)
        back = json.loads(text)
        assert back == d
        assert back["status"] == r.status and back["num_hypotheses"] == r.num_hypotheses
        assert len(back["hypotheses"]) == len(r.hypotheses)
        for hd, h in zip(back["hypotheses"][:20], r.hypotheses[:20]):
            assert hd["facets"] == h.facets.tolist()
            assert np.array_equal(np.array(hd["pose"]), h.pose)
            assert hd["cost"] == h.cost
        assert set(back["timing_ms"]) >= {"pairs", "tree", "pose", "rank", "total"}
        assert back["num_returned"] == len(r.hypotheses) and back["best"] == (back["hypotheses"] or [None])[0]


def test_top_truncates_the_ranked_list(rock_model):
    rng = np.random.default_rng(12)
    g = simulate.grasp(rock_model, rng, n=4, noise="bounded", **NOISE)
    full = localize(rock_model, g.contacts, **NOISE, keep="all")
    assert len(full.hypotheses) > 5
    costs = [h.cost for h in full.hypotheses]
    assert costs == sorted(costs)
    for k in (1, 3, len(full.hypotheses) + 10):
        r = localize(rock_model, g.contacts, top=k, **NOISE, keep="all")
        assert len(r.hypotheses) == min(k, len(full.hypotheses))
        assert r.num_hypotheses == full.num_hypotheses and r.status == full.status
        for a, b in zip(r.hypotheses, full.hypotheses):
            assert np.array_equal(a.facets, b.facets) and a.cost == b.cost


@pytest.mark.parametrize("kwargs", [
    dict(method="slow"), dict(method=None), dict(solver="newton"), dict(top=0), dict(top=-2),
    dict(top=2.5), dict(top="3"), dict(prior={"pose": np.eye(4)}),
    dict(position_noise=-1.0), dict(normal_noise_deg=0.0), dict(position_noise=float("nan")),
])
def test_invalid_options_raise(banana_model, kwargs):
    rng = np.random.default_rng(13)
    g = simulate.grasp(banana_model, rng, n=3)
    with pytest.raises(ContactPoseError):
        localize(banana_model, g.contacts, **{**NOISE, **kwargs})


def test_contacts_must_be_contacts(banana_model):
    with pytest.raises(ContactPoseError, match="Contacts"):
        localize(banana_model, np.zeros((3, 3)), **NOISE)


def test_rigid_motion_equivariance(models):
    rng = np.random.default_rng(14)
    for name in ("banana", "rock"):
        model = models[name]
        for _ in range(3):
            g = spanning_grasp(model, rng, n=4, noise="bounded", **NOISE)
            M = rigid(rng)
            a = localize(model, g.contacts, **NOISE)
            b = localize(model, g.contacts.transformed(M), **NOISE)
            assert facet_set(a) == facet_set(b)
            assert a.status == b.status
            poses_b = {tuple(f): (T, c) for f, T, c in zip(b.hypotheses.arrays.facets.tolist(),
                                                           b.hypotheses.arrays.poses, b.hypotheses.arrays.cost)}
            for f, T, c in zip(a.hypotheses.arrays.facets.tolist(), a.hypotheses.arrays.poses,
                               a.hypotheses.arrays.cost):
                Tb, cb = poses_b[tuple(f)]
                assert np.abs(M @ T - Tb).max() < 1e-8
                assert cb == pytest.approx(c, rel=1e-6, abs=1e-9)


def test_finger_permutation_permutes_facets(models):
    rng = np.random.default_rng(15)
    for name in ("banana", "rock"):
        model = models[name]
        g = spanning_grasp(model, rng, n=4, noise="bounded", **NOISE)
        a = localize(model, g.contacts, **NOISE)
        poses_a = dict(zip(map(tuple, a.hypotheses.arrays.facets.tolist()), a.hypotheses.arrays.poses))
        for perm in ([1, 0, 2, 3], [3, 2, 1, 0], [2, 0, 3, 1]):
            b = localize(model, g.contacts.permuted(perm), **NOISE)
            expected = {tuple(np.array(f)[perm]) for f in poses_a}
            assert facet_set(b) == expected
            assert np.array_equal(b.best.facets, a.best.facets[perm])
            for f, T in zip(b.hypotheses.arrays.facets, b.hypotheses.arrays.poses):
                orig = np.empty(4, dtype=int)
                orig[perm] = f
                # the surface fit is iterative (finite-difference Jacobians): equal to ~1e-9
                assert np.abs(poses_a[tuple(orig)] - T).max() < 1e-8


def test_paper_lm_from_prior_matches_paper_closed_form(banana_model):
    """method="paper": LM (the paper's solver, started at the prior) and the closed form
    reach the same eq. (7) optimum for every hypothesis."""
    rng = np.random.default_rng(16)
    g = spanning_grasp(banana_model, rng, n=4, noise="bounded", **NOISE)
    prior = PosePrior(g.pose @ simulate.pose_from([0.02, -0.01, 0.03], [0.002, 0.0, -0.001]), 5.0, 0.01)
    lm = localize(banana_model, g.contacts, method="paper", solver="lm", prior=prior, **NOISE)
    cf = localize(banana_model, g.contacts, method="paper", solver="closed-form", prior=prior, **NOISE)
    assert lm.num_hypotheses == cf.num_hypotheses > 0
    assert np.array_equal(lm.best.facets, g.facets)
    assert np.array_equal(lm.best.facets, cf.best.facets)
    assert np.abs(lm.best.pose - cf.best.pose).max() < 1e-6
    assert lm.best.cost == pytest.approx(cf.best.cost, rel=1e-6)


@pytest.mark.parametrize("pose", [
    np.diag([1.1, 1.0, 1.0, 1.0]),                                   # scale
    np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]),  # shear
    np.diag([1.0, 1.0, -1.0, 1.0]),                                  # reflection
    np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1.0]]),  # bad last row
    np.full((4, 4), np.nan),
    np.eye(3),
    "identity",
])
def test_prior_rejects_non_rigid_pose(pose):
    with pytest.raises(PriorError):
        PosePrior(pose, 5.0, 0.01)


@pytest.mark.parametrize("sigmas", [(-1.0, 0.01), (5.0, -0.01), (0.0, 0.01), (5.0, np.nan),
                                    (np.inf, 0.01), (None, 0.01)])
def test_prior_rejects_bad_sigmas(sigmas):
    with pytest.raises(PriorError):
        PosePrior(np.eye(4), *sigmas)


def test_prior_accepts_rigid_pose_and_covariance():
    T = simulate.pose_from([0.1, 0.2, 0.3], [1.0, 2.0, 3.0])
    p = PosePrior(T, 5.0, 0.01)
    assert np.allclose(np.diag(p.covariance_matrix()), [np.radians(5) ** 2] * 3 + [1e-4] * 3)
    assert PosePrior(T, covariance=np.eye(6) * 1e-4).covariance.shape == (6, 6)
    with pytest.raises(PriorError):
        PosePrior(T, covariance=-np.eye(6))
    with pytest.raises(PriorError):
        PosePrior(T, covariance=np.eye(6) + np.triu(np.ones((6, 6)), 1))


# ---------------------------------------------------------------- recall

RECALL_GRASPS = 100


def fast_hypotheses(model, contacts, tolerance):
    """The facet tuples of method="fast", assembled from the public stages as localize does."""
    S = admissible_pairs(model, pair_conditions(contacts), tolerance, "exact", direction=True)
    triple = TripleTest(model.planes.normals, contacts.object_normals, tolerance.per_contact_bounds()[1])
    return join_tuples(S, contacts.n, triple)


def recall_grasps(model, seed):
    rng = np.random.default_rng(seed)
    return [simulate.grasp(model, rng, n=4, where="area", noise="bounded", **NOISE)
            for _ in range(RECALL_GRASPS)]


# The carton is searched by patches: which coplanar member a contact sits on cannot be
# observed, so its recall is judged on patch tuples (test_recall_patch_level_carton).
@pytest.mark.parametrize("name", ["banana", "rock"])
def test_recall_of_true_tuple_fast_is_complete(models, name):
    """Recall (quick version), models searched by facets: bounded noise inside the
    tolerance, random poses, area-weighted contacts: the true facet tuple is always found."""
    assert models[name].patch_table is None
    model = models[name]
    missed = [i for i, g in enumerate(recall_grasps(model, 300))
              if not has_row(localize(model, g.contacts, **NOISE, distinct=False).hypotheses.arrays.facets, g.facets)]
    assert missed == [], f"{len(missed)} of {RECALL_GRASPS} grasps miss the true tuple"


@pytest.mark.parametrize("name", ["banana", "rock"])
def test_localize_hypotheses_equal_the_facet_level_stages(models, name):
    """Without patches, localize's hypothesis set is exactly the public stages' set
    (S_ij with the direction test, the tree with the handedness test)."""
    model = models[name]
    assert model.patch_table is None
    tolerance = Tolerance.from_noise(POSITION_NOISE, NORMAL_NOISE_DEG)
    for g in recall_grasps(model, 302)[:30]:
        r = localize(model, g.contacts, **NOISE, distinct=False)
        assert same_rows(r.hypotheses.arrays.facets, fast_hypotheses(model, g.contacts, tolerance))


def test_recall_patch_level_carton(carton_model):
    """On the carton the patch search always finds the true patch tuple."""
    model = carton_model
    labels = model.patches.labels
    assert model.patch_table is not None
    missed = [i for i, g in enumerate(recall_grasps(model, 300))
              if not has_row(labels[localize(model, g.contacts, twins=True, **NOISE).hypotheses.arrays.facets],
                             labels[g.facets])]
    assert missed == []


def test_recall_facet_level_search_carton(carton_model):
    """The facet-level search (the public stages, no patches) keeps the true facet tuple."""
    model = carton_model
    tolerance = Tolerance.from_noise(POSITION_NOISE, NORMAL_NOISE_DEG)
    missed = [i for i, g in enumerate(recall_grasps(model, 300))
              if not has_row(fast_hypotheses(model, g.contacts, tolerance), g.facets)]
    assert missed == []


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_keep_fitting_lists_the_best_and_the_hypotheses_that_fit(rock_model, seed):
    """keep="fitting" (the default) lists, of keep="all"'s distinct poses, the best and
    exactly those the fit test passes (scoring.infacet.within_noise on keep="all"'s list), in
    rank order; its pose classes point at the same poses, and the counts stay those of all."""
    from contactpose.scoring.infacet import within_noise

    model = rock_model
    g = simulate.grasp(model, np.random.default_rng(seed), n=4, position_noise=0.0008, normal_noise_deg=2.0)
    noise = dict(position_noise=0.0008, normal_noise_deg=2.0)
    every = localize(model, g.contacts, **noise, keep="all")
    fitting = localize(model, g.contacts, **noise)
    tol = Tolerance.from_noise(0.0008, 2.0)
    fits = within_noise(model, g.contacts, every.hypotheses.arrays, tol, fit_threshold(4))
    rows = np.union1d([0], np.flatnonzero(fits))
    assert len(every.hypotheses) > len(rows) >= 1                      # something is left out
    assert np.array_equal(fitting.hypotheses.arrays.facets, every.hypotheses.arrays.facets[rows])
    assert fitting.num_hypotheses == every.num_hypotheses and fitting.status == every.status
    for mine, theirs in zip(fitting.classes, every.classes, strict=True):
        assert np.array_equal(fitting.hypotheses.arrays.poses[mine.members], every.hypotheses.arrays.poses[theirs.members])
        assert np.array_equal(fitting.hypotheses[mine.best].pose, mine.pose)


def test_keep_fitting_lists_the_best_few_when_nothing_fits(rock_model):
    """Contacts three times noisier than stated: the best does not fit (poor_fit). When no
    hypothesis fits at all, the best POOR_FIT_LISTED of all distinct poses are listed."""
    from contactpose.stages import POOR_FIT_LISTED

    empty = 0
    for seed in (2, 4, 7, 8):
        g = simulate.grasp(rock_model, np.random.default_rng(seed), n=4, position_noise=3 * POSITION_NOISE,
                           normal_noise_deg=3 * NORMAL_NOISE_DEG)
        every = localize(rock_model, g.contacts, **NOISE, keep="all")
        fitting = localize(rock_model, g.contacts, **NOISE)
        assert fitting.status == every.status == "poor_fit" and len(every.hypotheses) > POOR_FIT_LISTED
        if fitting.classes:
            rows = np.union1d([0], np.concatenate([c.members for c in every.classes]))
        else:
            rows, empty = np.arange(POOR_FIT_LISTED), empty + 1
        assert np.array_equal(fitting.hypotheses.arrays.facets, every.hypotheses.arrays.facets[rows])
    assert empty


def test_keep_is_checked(rock_model):
    g = simulate.grasp(rock_model, np.random.default_rng(1), n=4, **NOISE)
    with pytest.raises(ContactPoseError, match="keep must be one of"):
        localize(rock_model, g.contacts, **NOISE, keep="some")


def test_localize_needs_two_contacts(banana_model):
    """One contact is a Contacts (a touch of a tracked object), not a grasp localize can answer."""
    with pytest.raises(ContactsError, match="need at least 2 contacts, got 1"):
        localize(banana_model, Contacts(np.zeros((1, 3)), finger_normals=[[0, 0, 1.0]]))
