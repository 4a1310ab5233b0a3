"""Touch until sure (contactpose.tracking.sure) on the carton: 4 contacts on its walls leave
its height free and a quarter turn about its axis open; simulated fingertip probes on the
true pose settle it."""

import numpy as np
import pytest

from contactpose import ContactPoseError, TouchSession, simulate
from contactpose.geometry.sampling import perturb_normals
from contactpose.model.symmetry import symmetry
from contactpose.sim.fingertip import sweep_spheres
from contactpose.tracking import SureRun, Touch, random_probe, touch_until_sure


def noise(model):
    return dict(position_noise=0.0025 * model.diameter, normal_noise_deg=1.0)


def toucher(model, pose, rng, radius=0.0):
    """touch(origin, direction) -> (point, finger normal) in the world frame, or None: one ball
    swept on the object at its true pose, with the sensor noise."""
    R, t = pose[:3, :3], pose[:3, 3]
    sigma = noise(model)

    def touch(origin, direction):
        f = sweep_spheres(model.vertices, model.faces, ((origin - t) @ R)[None], (direction @ R)[None], radius)
        if not f.hit[0]:
            return None
        point = f.points[0] @ R.T + t + rng.normal(0.0, sigma["position_noise"], 3)
        normal = perturb_normals(-(f.normals[0] @ R.T)[None], np.radians(sigma["normal_noise_deg"]), rng)[0]
        return point, normal
    return touch


def wall_grasp(model, seed):
    """4 contacts on the carton's walls (not near the bottom or the roof), at a random pose."""
    rng = np.random.default_rng(seed)
    n, c = model.planes.normals, model.triangles.mean(axis=1)
    body = np.flatnonzero((np.abs(n[:, 2]) < 0.1) & (c[:, 2] > 0.03) & (c[:, 2] < 0.14))
    g = simulate.grasp(model, rng, n=4, facets=rng.choice(body, 4, replace=False), **noise(model))
    return g, rng


def strictly_right(model, T_est, T_true):
    rot, trans = symmetry(model).errors(T_est, T_true)
    return rot < 5.0 and trans < 0.05 * model.diameter


def test_suggested_touches_stop_at_ok_and_right(carton_model):
    g, rng = wall_grasp(carton_model, 0)
    run = touch_until_sure(carton_model, g.contacts, toucher(carton_model, g.pose, rng), rng=rng, max_touches=6,
                           **noise(carton_model))
    assert isinstance(run, SureRun) and run.statuses[0] != "ok"  # the grasp alone is not enough
    assert run.result.status == "ok" and run.stopped == "ok" and run.statuses[-1] == "ok"
    assert "ok" not in run.statuses[:-1] and len(run.statuses) == run.touches + 1 <= 7
    assert run.touches_to_ok() == run.touches >= 1
    assert run.result.confidence >= 0.99
    assert strictly_right(carton_model, run.result.best.pose, g.pose)
    assert all(isinstance(s.probe, Touch) for s in run.steps)
    assert run.session.contacts.n == 4 + run.touches - run.misses


def test_never_more_than_max_touches_and_random_policy(carton_model):
    g, rng = wall_grasp(carton_model, 1)
    touch = toucher(carton_model, g.pose, rng)
    none = touch_until_sure(carton_model, g.contacts, touch, rng=rng, max_touches=0, **noise(carton_model))
    assert none.touches == 0 and none.statuses == [none.result.status] and none.stopped == "max_touches"
    for policy in ("random", "suggested"):
        run = touch_until_sure(carton_model, g.contacts, touch, rng=np.random.default_rng(5), max_touches=1,
                               policy=policy, **noise(carton_model))
        assert run.touches <= 1 and len(run.statuses) == run.touches + 1
        assert run.stopped == ("ok" if run.result.status == "ok" else "max_touches")
    # the random baseline gets there too, given touches enough
    run = touch_until_sure(carton_model, g.contacts, touch, rng=rng, max_touches=12, policy="random",
                           **noise(carton_model))
    assert run.touches <= 12
    if run.sure:
        assert strictly_right(carton_model, run.result.best.pose, g.pose)
    # a session goes on from its contacts
    session = TouchSession(carton_model, **noise(carton_model))
    session.add(g.contacts)
    again = touch_until_sure(session, None, touch, rng=rng, max_touches=6)
    assert again.session is session and again.statuses[0] == session.history[0].status


def test_random_probe_aims_at_the_best_pose(carton_model):
    g, rng = wall_grasp(carton_model, 0)
    session = TouchSession(carton_model, **noise(carton_model))
    r = session.add(g.contacts)
    probe = random_probe(carton_model, r, rng, contacts=session.contacts)
    assert isinstance(probe, Touch) and probe.start.shape == probe.direction.shape == (3,)
    assert np.linalg.norm(probe.direction) == pytest.approx(1.0)


@pytest.mark.parametrize("change, words", [
    (dict(rng=0), "rng must be a numpy.random.Generator"),
    (dict(max_touches=-1), "max_touches must be"),
    (dict(policy="greedy"), "policy must be one of"),
    (dict(touch=3), "touch must be a callable"),
    (dict(model="carton"), "session_or_model must be"),
    (dict(contacts=np.zeros((4, 3))), "contacts must be"),
    (dict(touch=lambda o, d: (o,)), "touch must return"),
    (dict(touch=lambda o, d: (o, d[:2])), "touch must return a finite point"),
])
def test_bad_arguments(carton_model, change, words):
    g, _ = wall_grasp(carton_model, 0)
    args = dict(model=carton_model, contacts=g.contacts, touch=lambda o, d: None, rng=np.random.default_rng(0),
                max_touches=2)
    args.update(change)
    with pytest.raises(ContactPoseError) as info:
        touch_until_sure(args.pop("model"), args.pop("contacts"), args.pop("touch"), **args, **noise(carton_model))
    message = str(info.value)
    assert words in message and "\n" not in message
    with pytest.raises(ContactPoseError, match="own options"):
        touch_until_sure(TouchSession(carton_model), g.contacts, lambda o, d: None, rng=np.random.default_rng(0),
                         position_noise=0.001)
