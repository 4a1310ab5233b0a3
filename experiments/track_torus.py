"""``contactpose track`` on a symmetric object: a torus of 24 sections (48 rotations map it onto
itself), a first grasp of 4 contacts, then 6 touches of 1 or 2 contacts after hand motions of
about 6° and 2 cm (noise 0.5 mm and 1°). The errors are printed, written and plotted modulo
the symmetry beside the raw ones, which jump between the twins of the one placement. Writes
results/track_torus/sequence.json, track.json and track.png::

    .venv/bin/python experiments/track_torus.py
"""

from __future__ import annotations

import json
import tempfile
import warnings
from pathlib import Path

import numpy as np
import trimesh

from contactpose import ObjectModel
from contactpose.cli import main as cli
from contactpose.sim import grasps as simulate

OUT = Path(__file__).resolve().parent.parent / "results" / "track_torus"
NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)


def _contacts(c):
    return [{"point": p.tolist(), "finger_normal": n.tolist()} for p, n in zip(c.points, c.finger_normals)]


def sequence(model, rng, steps=6):
    """A first grasp of 4 contacts, then ``steps`` touches of 1 or 2 after hand motions."""
    g = simulate.grasp(model, rng, n=4, **NOISE)
    pose, out = g.pose, [{"contacts": _contacts(g.contacts), "true_pose": g.pose.tolist()}]
    for k in range(steps):
        delta = simulate.pose_from(rotvec=0.1 * rng.normal(size=3), translation=0.02 * rng.normal(size=3))
        pose = delta @ pose
        touch = simulate.grasp(model, rng, n=1 + k % 2, pose=pose, **NOISE)
        out.append({"contacts": _contacts(touch.contacts), "true_pose": pose.tolist(),
                    "hand_motion": {"delta": delta.tolist(), "sigma_rot_deg": 1.0, "sigma_trans": 0.001}})
    return {"steps": out}


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the torus's own mesh notes
        model = ObjectModel.from_mesh(trimesh.creation.torus(0.05, 0.015, major_sections=24, minor_sections=12))
    (OUT / "sequence.json").write_text(json.dumps(sequence(model, np.random.default_rng(0))))
    with tempfile.TemporaryDirectory() as folder:
        model.save(Path(folder) / "torus.npz")
        return cli(["track", str(Path(folder) / "torus.npz"), "--sequence", str(OUT / "sequence.json"),
                    "--position-noise", str(NOISE["position_noise"]), "-o", str(OUT / "track.json"),
                    "--plot", str(OUT / "track.png")])


if __name__ == "__main__":
    raise SystemExit(main())
