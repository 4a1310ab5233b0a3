"""``contactpose track``: a simulated sequence in, the trajectory out (schema-valid JSON, a
plot), and bad sequence files named in one line with exit code 2."""

import json

import jsonschema
import numpy as np

from contactpose.cli import main
from contactpose.geometry.metrics import rotation_error_deg
from contactpose.io import output
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)


def _contacts(c):
    return [{"point": p.tolist(), "finger_normal": n.tolist()} for p, n in zip(c.points, c.finger_normals)]


def _sequence(model, rng, steps):
    """A first grasp, then touches of 1 or 2 contacts after hand motions of about 6° and 2 cm."""
    g = simulate.grasp(model, rng, n=4, **NOISE)
    pose, out = g.pose, [{"contacts": _contacts(g.contacts), "true_pose": g.pose.tolist()}]
    for k in range(steps):
        delta = simulate.pose_from(rotvec=0.1 * rng.normal(size=3), translation=0.02 * rng.normal(size=3))
        pose = delta @ pose
        touch = simulate.grasp(model, rng, n=1 + k % 2, pose=pose, **NOISE)
        out.append({"contacts": _contacts(touch.contacts), "true_pose": pose.tolist(),
                    "hand_motion": {"delta": delta.tolist(), "sigma_rot_deg": 1.0, "sigma_trans": 0.001}})
    return {"steps": out}, pose


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
