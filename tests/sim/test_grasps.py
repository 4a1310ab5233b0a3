"""Simulated touch sequences (sim.grasps.touch_sequence): a document that ``track`` reads, whose
true poses follow the stated hand motions and whose noise-free contacts lie on the posed surface
with the surface's outward normals reversed (finger normals point into the object)."""

import numpy as np
import trimesh

from contactpose.io.jsonfiles import parse_sequence
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects


def test_a_touch_sequence_follows_its_hand_motions_on_the_surface():
    mesh = objects.load("rock")
    model = ObjectModel.from_mesh(mesh)
    doc, last = simulate.touch_sequence(model, np.random.default_rng(2), 5)
    steps = doc["steps"]
    assert len(parse_sequence(doc)) == 6 and [len(s["contacts"]) for s in steps] == [4, 1, 2, 1, 2, 1]
    assert "hand_motion" not in steps[0] and np.array_equal(np.array(steps[-1]["true_pose"]), last)
    for before, step in zip(steps, steps[1:]):
        delta = np.array(step["hand_motion"]["delta"])
        assert np.allclose(delta @ np.array(before["true_pose"]), np.array(step["true_pose"]), atol=1e-12)
    for step in steps:
        T = np.array(step["true_pose"])
        points = np.array([c["point"] for c in step["contacts"]])
        normals = np.array([c["finger_normal"] for c in step["contacts"]])
        local = (points - T[:3, 3]) @ T[:3, :3]
        closest, distance, face = trimesh.proximity.closest_point(mesh, local)
        assert distance.max() < 1e-9 * model.diameter
        assert np.allclose(normals @ T[:3, :3], -mesh.face_normals[face], atol=1e-9)
