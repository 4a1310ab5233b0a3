"""TouchSession: touches added one by one against localize of all contacts at once
(static object); for a held object against a TrackSet driven by hand, against the truth and
against batch LM on the same graph; and its suggested touch against trimesh's ray cast."""

import json

import numpy as np
import pytest
import trimesh

from contactpose import ContactPoseError, Contacts, ObjectModel, TouchSession, localize
from contactpose.geometry.metrics import rotation_error_deg, translation_error
from contactpose.sim import grasps as simulate
from contactpose.tracking.session import relocalizer
from contactpose.tracking.track import TrackSet
from tests.conftest import random_icosahedron
from tests.test_schema import validate
from tests.tracking.test_track import _motion

NOISE = 0.0025  # of the diameter


def _noise(model):
    return dict(position_noise=NOISE * model.diameter, normal_noise_deg=1.0)


def _same(a, b):
    """Whether two Results list the same hypotheses (facets, poses, χ², order) and status."""
    x, y = a.hypotheses.arrays, b.hypotheses.arrays
    return (a.status == b.status and a.num_hypotheses == b.num_hypotheses and len(a.classes) == len(b.classes)
            and np.array_equal(x.facets, y.facets) and np.allclose(x.poses, y.poses, rtol=0, atol=1e-12)
            and np.allclose(x.chi2, y.chi2, rtol=1e-12, atol=1e-12))


def _static_sequences(model, rng, count, n=5):
    """``count`` sequences of n noisy contacts on the model, added one per touch; after each
    touch from the second on, the session's Result against localize of all contacts so far.
    -> number of (sequence, touch) comparisons, mismatches"""
    compared, bad = 0, []
    for q in range(count):
        g = simulate.grasp(model, rng, n=n, position_noise=NOISE * model.diameter, normal_noise_deg=1.0)
        session = TouchSession(model, **_noise(model))
        for k in range(n):
            got = session.add(Contacts(g.contacts.points[k:k + 1], finger_normals=g.contacts.finger_normals[k:k + 1]))
            if k == 0:
                continue
            want = localize(model, session.contacts, **_noise(model))
            compared += 1
            if not _same(got, want) or not np.array_equal(got.tree.tuples, want.tree.tuples):
                bad.append((q, k))
    return compared, bad


def test_static_session_equals_localize_of_all_contacts(rock_model, carton_model):
    """62 random sequences of 5 contacts, added one at a time, on 40 irregular 20-facet meshes
    (facets), the carton (patches, 16) and the rock (320 facets, 6): after every touch the
    session lists exactly what localize lists for all the contacts at once, from the same tree
    (the rock's sequences take 2.3 s each: the pose classes and placements of hundreds of
    hypotheses)."""
    assert carton_model.patch_table is not None  # the patch path is exercised
    rng = np.random.default_rng(18)
    compared, bad = 0, []
    for seed in range(40):
        c, b = _static_sequences(ObjectModel.from_mesh(random_icosahedron(seed)), rng, 1)
        compared, bad = compared + c, bad + b
    for model, count in ((carton_model, 16), (rock_model, 6)):
        c, b = _static_sequences(model, rng, count)
        compared, bad = compared + c, bad + b
    assert compared == 62 * 4
    assert bad == []


def test_one_contact_is_every_unit(rock_model):
    """One contact: no search yet, status underdetermined, every facet counted, and a tree
    that the second contact grows into the full search's."""
    session = TouchSession(rock_model)
    g = simulate.grasp(rock_model, np.random.default_rng(3), n=2)
    r = session.add(Contacts(g.contacts.points[:1], finger_normals=g.contacts.finger_normals[:1]))
    assert r.status == "underdetermined" and len(r.hypotheses) == 0 and r.num_hypotheses == rock_model.num_facets
    assert "one contact" in r.hint
    r2 = session.add(Contacts(g.contacts.points[1:], finger_normals=g.contacts.finger_normals[1:]))
    assert _same(r2, localize(rock_model, g.contacts))


def test_tree_of_other_contacts_or_noise_is_refused(rock_model):
    g = simulate.grasp(rock_model, np.random.default_rng(4), n=4)
    first = localize(rock_model, Contacts(g.contacts.points[:3], finger_normals=g.contacts.finger_normals[:3]))
    with pytest.raises(ContactPoseError, match="same noise"):
        localize(rock_model, g.contacts, tree=first.tree, position_noise=0.01)
    moved = g.contacts.transformed(_motion(np.random.default_rng(0), 5.0, 0.01))
    with pytest.raises(ContactPoseError, match="not the first 3"):
        localize(rock_model, moved, tree=first.tree)
    with pytest.raises(ContactPoseError, match="SearchTree"):
        localize(rock_model, g.contacts, tree="tree")


def test_session_refuses_options_it_sets(rock_model):
    with pytest.raises(ContactPoseError, match="tree"):
        TouchSession(rock_model, tree=None)
    with pytest.raises(ContactPoseError, match="association_samples"):
        TouchSession(rock_model, association_samples=-1)
    with pytest.raises(ContactPoseError, match="needs rng"):
        TouchSession(rock_model, association_samples=5, rng=0)


def test_held_session_is_the_track_set(rock_model):
    """A held object: after a static first grasp, touches with hand motions give the poses of a
    TrackSet driven by hand with the same touches, track for track; the best track's association
    covariance (drawn from the same stream) is its sample_covariance, which exceeds the
    covariance by a positive semidefinite term."""
    rng = np.random.default_rng(9)
    d = rock_model.diameter
    g = simulate.grasp(rock_model, rng, n=4, position_noise=NOISE * d, normal_noise_deg=1.0)
    session = TouchSession(rock_model, association_samples=4, rng=np.random.default_rng(5), **_noise(rock_model))
    first = session.add(g.contacts)
    tracks = TrackSet(rock_model, g.contacts, [(h.facets, h.pose) for h in first.hypotheses], session.tolerance,
                      seeder=relocalizer(rock_model, session.tolerance))
    draws = np.random.default_rng(5)
    X = g.pose
    for _ in range(6):
        delta = _motion(rng, 10.0, 0.05 * d)
        X = delta @ X @ _motion(rng, 1.0, 0.01 * d)
        touch = simulate.grasp(rock_model, rng, n=2, pose=X, position_noise=NOISE * d, normal_noise_deg=1.0).contacts
        motion = (delta, 1.0, 0.01 * d)
        r = session.add(touch, hand_motion=motion)
        tracks.add(touch, hand_motion=motion)
        assert len(r.hypotheses) == len(tracks.tracks)
        for h, t in zip(r.hypotheses, tracks.tracks):
            np.testing.assert_allclose(h.pose, t.pose, atol=1e-12)
            assert h.cost == pytest.approx(t.score)
        spread = tracks.best.association_covariance(draws, 4)
        np.testing.assert_allclose(r.best.sample_covariance, spread, rtol=1e-9, atol=1e-20)
        assert np.linalg.eigvalsh(spread - r.best.covariance).min() >= -1e-9 * np.abs(spread).max()
        assert all(h.sample_covariance is None for h in r.hypotheses[1:])
    assert r.status in ("ok", "ambiguous") and r.best.facets.shape == (4 + 12,)
    assert np.degrees(np.arccos(np.clip((np.trace(r.best.pose[:3, :3].T @ X[:3, :3]) - 1) / 2, -1, 1))) < 5.0
    data = json.loads(json.dumps(r.to_dict()))  # the JSON a user writes: validates, holds the covariance
    validate(data, "result")
    assert data["timing_ms"]["track"] > 0 and data["timing_ms"]["total"] >= data["timing_ms"]["track"]
    np.testing.assert_allclose(data["hypotheses"][0]["sample_covariance"], r.best.sample_covariance, rtol=1e-15)
    assert all("sample_covariance" not in h for h in data["hypotheses"][1:])
    with pytest.raises(ContactPoseError, match="static"):
        session.suggest_touch(rng=rng)


def test_held_session_reseeds_unless_told_not_to(rock_model):
    """A held session's tracks reseed on a touch that no track explains, and not with
    reseed=False; the seeder localizes with the session's noise: its best on a grasp is the truth."""
    g = simulate.grasp(rock_model, np.random.default_rng(2), n=4, position_noise=NOISE * rock_model.diameter,
                       normal_noise_deg=1.0)
    motion = (np.eye(4), 1.0, 0.01 * rock_model.diameter)
    for reseed in (True, False):
        session = TouchSession(rock_model, reseed=reseed, **_noise(rock_model))
        session.add(g.contacts)
        session.add(g.contacts.permuted([0, 1]), hand_motion=motion)
        assert (session.tracks.seeder is not None) == reseed
    facets, pose = relocalizer(rock_model, session.tolerance)(g.contacts)[0]
    assert rotation_error_deg(pose, g.pose) < 5.0 and facets.shape == (4,)


def test_held_object_needs_a_determined_pose_first(carton_model):
    """Two contacts on the carton leave the pose free: the hand may not move yet."""
    g = simulate.grasp(carton_model, np.random.default_rng(2), n=2)
    session = TouchSession(carton_model)
    session.add(g.contacts)
    with pytest.raises(ContactPoseError, match="leave the pose free"):
        session.add(g.contacts.transformed(np.eye(4)), hand_motion=(np.eye(4), 1.0, 0.001))


def test_held_session_follows_the_truth_and_batch_lm(rock_model):
    """Three held sequences on the rock (a first grasp of 4 contacts, then 10 hand motions of
    about 10° and 5 % of the diameter with a slip of 1° and 1 %, 2 contacts each). After every
    touch the session's best pose is near the truth, and as near as Levenberg–Marquardt on the
    best track's whole graph (PoseTrack.batch) gets; every track listed carries its covariance;
    iterated to convergence the track is that batch solution. (The session takes one or two
    Gauss–Newton steps per touch, so it may trail the batch optimum a little.)"""
    d = rock_model.diameter
    for seed in range(3):
        rng = np.random.default_rng(seed)
        g = simulate.grasp(rock_model, rng, n=4, **_noise(rock_model))
        session = TouchSession(rock_model, **_noise(rock_model))
        session.add(g.contacts)
        X, errors = g.pose, []
        for _ in range(10):
            delta = _motion(rng, 10.0, 0.05 * d)
            X = delta @ X @ _motion(rng, 1.0, 0.01 * d)
            touch = simulate.grasp(rock_model, rng, n=2, pose=X, **_noise(rock_model)).contacts
            r = session.add(touch, hand_motion=(delta, 1.0, 0.01 * d))
            assert all(h.covariance is not None and h.covariance.shape == (6, 6) for h in r.hypotheses)
            batch = session.tracks.best.batch()[-1]
            errors.append((rotation_error_deg(r.best.pose, X), translation_error(r.best.pose, X),
                           rotation_error_deg(batch, X), translation_error(batch, X)))
        e = np.array(errors)
        median = np.median(e, axis=0)
        assert e[:, 0].max() < 5.0 and median[0] < 2.0 and median[1] < 0.015 * d, (seed, e)
        assert median[0] < 1.5 * median[2] + 0.1 and median[1] < 1.5 * median[3] + 0.001 * d, (seed, median)
        track = session.tracks.best
        converged, batch = track.relinearize(), track.batch()
        assert np.abs(converged[:, :3, :3] - batch[:, :3, :3]).max() < 1e-6
        assert np.abs(converged[:, :3, 3] - batch[:, :3, 3]).max() < 1e-6 * d


def test_suggest_touch_separates_the_classes(rock_model):
    """Three contacts on the rock leave several placements. The probe the session suggests
    predicts, under each placement's pose, the contact trimesh's ray cast finds there; touching the
    object at its true pose along that probe (trimesh again) leaves fewer classes, the best at
    the truth."""
    noise = dict(position_noise=0.001, normal_noise_deg=2.0)
    g = simulate.grasp(rock_model, np.random.default_rng(3), n=3, position_noise=0.0005, normal_noise_deg=1.0)
    session = TouchSession(rock_model, **noise)
    for k in range(3):
        before = session.add(g.contacts.permuted([k]))
    assert before.status == "ambiguous" and len(before.placements) > 2
    touch = session.suggest_touch(rng=np.random.default_rng(0), n_candidates=50)
    mesh = trimesh.Trimesh(rock_model.vertices, rock_model.faces, process=False)
    for c, cls in enumerate(before.placements):  # the probe tells the weighed placements apart
        if touch.outcomes[c]["kind"] == "contact":
            hit = _first_hit(mesh, cls.pose, touch.start, touch.direction)
            np.testing.assert_allclose(hit[0], touch.outcomes[c]["point"], atol=1e-6)
    point, normal = _first_hit(mesh, g.pose, touch.start, touch.direction)
    after = session.add(Contacts(point[None], object_normals=normal[None]))
    held = (lambda r: sum(p.probability >= 0.01 for p in r.placements))  # the count is capped (MAX_PLACEMENTS)
    assert held(after) < held(before) and after.placements[0].probability > before.placements[0].probability
    assert rotation_error_deg(after.placements[0].pose, g.pose) < 5.0


def _first_hit(mesh, pose, start, direction):
    """(point, outward face normal) where a ray first meets the mesh placed at pose (trimesh)."""
    posed = mesh.copy().apply_transform(pose)
    hits, _, faces = posed.ray.intersects_location([start], [direction])
    first = np.argmin(np.linalg.norm(hits - start, axis=1))
    return hits[first], posed.face_normals[faces[first]]
