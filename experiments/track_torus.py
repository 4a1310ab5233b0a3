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


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the torus's own mesh notes
        model = ObjectModel.from_mesh(trimesh.creation.torus(0.05, 0.015, major_sections=24, minor_sections=12))
    sequence, _ = simulate.touch_sequence(model, np.random.default_rng(0), 6, **NOISE)
    (OUT / "sequence.json").write_text(json.dumps(sequence))
    with tempfile.TemporaryDirectory() as folder:
        model.save(Path(folder) / "torus.npz")
        return cli(["track", str(Path(folder) / "torus.npz"), "--sequence", str(OUT / "sequence.json"),
                    "--position-noise", str(NOISE["position_noise"]), "-o", str(OUT / "track.json"),
                    "--plot", str(OUT / "track.png")])


if __name__ == "__main__":
    raise SystemExit(main())
