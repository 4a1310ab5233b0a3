"""``contactpose track``: a simulated sequence in, the trajectory out (schema-valid JSON, a
plot), and bad sequence files named in one line with exit code 2."""

import json
import re
import warnings

import jsonschema
import numpy as np
import pytest
import trimesh

from contactpose.cli import main
from contactpose.geometry.metrics import rotation_error_deg
from contactpose.io import output
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)


def _sequence(model, rng, steps):
    """A first grasp, then touches of 1 or 2 contacts after hand motions of about 6° and 2 cm."""
    return simulate.touch_sequence(model, rng, steps, **NOISE)


def test_track_writes_the_trajectory(tmp_path, capsys):
    model = ObjectModel.from_mesh(objects.load("banana"))
    seq, last = _sequence(model, np.random.default_rng(3), 6)
    (tmp_path / "seq.json").write_text(json.dumps(seq))
    code = main(["track", "banana", "--sequence", str(tmp_path / "seq.json"), "-o", str(tmp_path / "out.json"),
                 "--plot", str(tmp_path / "err.png"), "--position-noise", "0.0005"])
    assert code == 0
    assert capsys.readouterr().out.count("step ") == 7
    data = json.loads((tmp_path / "out.json").read_text())
    errors = list(jsonschema.Draft202012Validator(output.load_schema("track")).iter_errors(data))
    assert not errors, errors[0].message
    assert len(data["steps"]) == 7
    assert rotation_error_deg(np.array(data["steps"][-1]["pose"]), last) < 3.0
    assert data["steps"][-1]["rot_err_deg"] < 3.0
    assert (tmp_path / "err.png").stat().st_size > 1000


def test_track_writes_association_covariances(tmp_path, capsys):
    """--association-samples: each final track carries its association covariance, the
    covariance plus a positive semidefinite term, in schema-valid JSON; a negative count
    exits 2 with one line, and without -o the flag warns that it does nothing."""
    model = ObjectModel.from_mesh(objects.load("banana"))
    seq, _ = _sequence(model, np.random.default_rng(4), 4)
    (tmp_path / "seq.json").write_text(json.dumps(seq))
    args = ["track", "banana", "--sequence", str(tmp_path / "seq.json"), "-o", str(tmp_path / "out.json")]
    assert main(args + ["--association-samples", "3", "--seed", "1"]) == 0
    data = json.loads((tmp_path / "out.json").read_text())
    errors = list(jsonschema.Draft202012Validator(output.load_schema("track")).iter_errors(data))
    assert not errors, errors[0].message
    for t in data["tracks"]:
        spread, cov = np.array(t["association_covariance"]), np.array(t["covariance"])
        assert np.linalg.eigvalsh(spread - cov).min() >= -1e-9 * np.abs(spread).max()
    capsys.readouterr()
    assert main(args[:4] + ["--association-samples", "3"]) == 0
    assert "warning: --association-samples has no effect without -o" in capsys.readouterr().err
    assert main(args + ["--association-samples", "-1"]) == 2
    err = capsys.readouterr().err
    assert "--association-samples must be an integer >= 0, got -1" in err and err.count("\n") == 1, err


def test_bad_sequence_exits_2_with_one_line(tmp_path, capsys):
    cases = [({"steps": []}, "with at least one step"),
             ({"steps": [{"contacts": [{"point": [0, 0, 0], "finger_normal": [0, 0, 1]}]}]},
              "step 0: need at least 2 contacts, got 1"),
             ({"steps": [{"contacts": [{"point": [0, 0, 0], "finger_normal": [0, 0, 1]},
                                       {"point": [0.05, 0, 0], "finger_normal": [0, 0, 1]}]},
                         {"contacts": [{"point": [0, 0, 0], "finger_normal": [0, 0, 1]}],
                          "hand_motion": {"delta": [[1, 0, 0, 0]]}}]},
              "step 1 hand_motion delta must be a 4x4 matrix")]
    for seq, want in cases:
        (tmp_path / "seq.json").write_text(json.dumps(seq))
        assert main(["track", "banana", "--sequence", str(tmp_path / "seq.json")]) == 2
        err = capsys.readouterr().err
        assert want in err and err.count("\n") == 1, err


def test_track_on_a_symmetric_torus_reports_errors_modulo_symmetry(tmp_path, capsys):
    """A torus of 24 sections (a model file: lengths in mesh units): every step's error modulo
    its symmetry stays below 2° while the raw error is a twin's (up to 180°), one track is
    kept, and the JSON carries both errors, the symmetry in words and validates."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model = ObjectModel.from_mesh(trimesh.creation.torus(0.05, 0.015, major_sections=24, minor_sections=12))
    model.save(tmp_path / "torus.npz")
    seq, _ = _sequence(model, np.random.default_rng(0), 6)
    (tmp_path / "seq.json").write_text(json.dumps(seq))
    code = main(["track", str(tmp_path / "torus.npz"), "--sequence", str(tmp_path / "seq.json"), "--position-noise",
                 "0.0005", "-o", str(tmp_path / "out.json"), "--plot", str(tmp_path / "err.png")])
    assert code == 0
    lines = capsys.readouterr().out.splitlines()
    pattern = r"step \d+: 1 track\(s\), .*  error ([\d.]+)° \(raw ([\d.]+)°\), ([\d.e-]+) mesh units \(raw ([\d.e-]+) mesh units\)"
    found = [re.fullmatch(pattern, line) for line in lines]
    assert len(lines) == 7 and all(found), lines
    assert max(float(m.group(1)) for m in found) < 2.0
    data = json.loads((tmp_path / "out.json").read_text())
    errors = list(jsonschema.Draft202012Validator(output.load_schema("track")).iter_errors(data))
    assert not errors, errors[0].message
    assert "24-fold about axis (0.00, 0.00, 1.00)" in data["symmetry"]
    truth = [np.array(step["true_pose"]) for step in seq["steps"]]
    for step, true_pose in zip(data["steps"], truth):
        assert step["tracks"] == 1 and step["rot_err_sym_deg"] < 2.0
        assert step["rot_err_sym_deg"] <= step["rot_err_deg"] + 1e-9
        assert np.isclose(step["rot_err_deg"], rotation_error_deg(np.array(step["pose"]), true_pose))
    assert (tmp_path / "err.png").stat().st_size > 1000


def test_track_prints_millimetres_for_a_built_in_object(tmp_path, capsys):
    """A built-in object is in metres: its errors print in mm (raw alone: the banana has no
    symmetry), and the JSON's symmetry is empty with equal raw and modulo-symmetry errors."""
    model = ObjectModel.from_mesh(objects.load("banana"))
    seq, _ = _sequence(model, np.random.default_rng(5), 2)
    (tmp_path / "seq.json").write_text(json.dumps(seq))
    assert main(["track", "banana", "--sequence", str(tmp_path / "seq.json"), "-o", str(tmp_path / "out.json")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert all(line.endswith(" mm") and "raw" not in line for line in lines), lines
    data = json.loads((tmp_path / "out.json").read_text())
    assert data["symmetry"] == ""
    for step in data["steps"]:
        assert step["rot_err_sym_deg"] == pytest.approx(step["rot_err_deg"], abs=1e-9)
        assert step["trans_err_sym"] == pytest.approx(step["trans_err"], abs=1e-12)
