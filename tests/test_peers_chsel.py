"""The outside peer CHSEL (contactpose.peers.chsel): without its optional extra it refuses in one
line naming the install; the benchmark then writes a "not run" row with the reason, never a
score. With the extra installed, it runs on a small closed mesh and returns poses that place
the surface (marked slow: minutes on two cores)."""

import numpy as np
import pytest
import trimesh

from contactpose.errors import ContactPoseError
from contactpose.peers import chsel as chsel_peer


def test_without_the_extra_it_refuses_and_names_the_install(monkeypatch):
    monkeypatch.setattr(chsel_peer, "available", lambda: None)
    with pytest.raises(ContactPoseError, match=r"pip install contactpose\[peers\]") as err:
        chsel_peer.ChselPeer(np.eye(3), np.array([[0, 1, 2]]))
    assert "\n" not in str(err.value)


def test_the_benchmark_row_says_not_run_without_the_extra(monkeypatch):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "experiments"))
    import run_all

    rc = run_all.load("realistic_contacts")
    monkeypatch.setattr(chsel_peer, "available", lambda: None)
    row = rc.outside_peer("ycb:011_banana", "/nonexistent", {}, None, None, None, None, None)
    assert row == {"ran": False, "note": "not run: CHSEL not installed (pip install contactpose[peers])"}


@pytest.mark.slow
@pytest.mark.skipif(chsel_peer.available() is None, reason="the optional extra peers is not installed")
def test_with_the_extra_it_returns_sorted_poses_of_the_object():
    box = trimesh.creation.box(extents=(0.12, 0.08, 0.05))
    peer = chsel_peer.ChselPeer(box.vertices, box.faces)
    rng = np.random.default_rng(0)
    surface = box.sample(40, seed=1)
    best, poses, rmse = peer.localize(surface, np.array([[0.2, 0.0, 0.0], [0.0, 0.2, 0.0]]), rng, scale=0.05)
    assert poses.shape == (chsel_peer.BATCH, 4, 4) and np.all(np.diff(rmse) >= 0)
    assert np.allclose(poses[:, :3, :3] @ poses[:, :3, :3].transpose(0, 2, 1), np.eye(3), atol=1e-4)
    assert np.array_equal(best.pose, poses[0])
    # T_world_object: the world points brought into the object frame lie on the box
    inside = surface @ np.linalg.inv(best.pose)[:3, :3].T + np.linalg.inv(best.pose)[:3, 3]
    assert np.abs(trimesh.proximity.signed_distance(box, inside)).mean() < 0.005
