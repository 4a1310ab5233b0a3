"""The command line: build-model and localize, and bad input.

Bad input must exit with code 2 and print exactly one line on stderr, without a
traceback. Outputs are checked against the library called directly.
"""

import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import NORMAL_NOISE_DEG, POSITION_NOISE

from contactpose.cli import main
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

EXAMPLE_CONTACTS = Path(__file__).resolve().parents[2] / "examples" / "banana_contacts.json"
NOISE_ARGS = ["--position-noise", str(POSITION_NOISE), "--normal-noise-deg", str(NORMAL_NOISE_DEG)]


@pytest.fixture(scope="module")
def banana_npz(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "banana.npz"
    ObjectModel.from_mesh(objects.load("banana")).save(path)
    return path


def write_json(path, data):
    path.write_text(json.dumps(data))
    return str(path)


def grasp_file(tmp_path, model, seed, kind="finger_normal", n=4):
    rng = np.random.default_rng(seed)
    g = simulate.grasp(model, rng, n=n, noise="bounded", position_noise=POSITION_NOISE,
                       normal_noise_deg=NORMAL_NOISE_DEG)
    normals = g.contacts.finger_normals if kind == "finger_normal" else g.contacts.object_normals
    data = {"contacts": [{"point": p.tolist(), kind: v.tolist()} for p, v in zip(g.contacts.points, normals)]}
    return write_json(tmp_path / f"contacts_{seed}.json", data), g


def test_build_model_prints_counts_time_size_and_writes_file(tmp_path, capsys):
    out = tmp_path / "b.npz"
    assert main(["build-model", "banana", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert re.search(r"^facets: 53 \(0 degenerate, excluded\)$", text, re.M)
    assert re.search(r"^ordered pairs: 2809$", text, re.M)
    ms = re.search(r"^build time: ([\d.]+) ms", text, re.M)
    assert ms and float(ms.group(1)) > 0
    size = re.search(r"^file: (.+) \(([\d.]+) KiB\)$", text, re.M)
    assert size and size.group(1) == str(out)
    assert float(size.group(2)) == pytest.approx(out.stat().st_size / 1024, abs=0.051)
    model = ObjectModel.load(out, mesh=objects.load("banana"))
    assert model.num_facets == 53 and model.num_pairs == 2809


def test_build_model_from_mesh_file_with_options(tmp_path, capsys, monkeypatch):
    stl = tmp_path / "rockmesh.stl"
    objects.load("rock").export(stl)
    monkeypatch.chdir(tmp_path)
    assert main(["build-model", str(stl), "--bins", "4", "7", "3", "--bounds", "paper"]) == 0
    text = capsys.readouterr().out
    model = ObjectModel.load(tmp_path / "rockmesh.npz", mesh=stl, bins=(4, 7, 3), bounds="paper")
    assert f"facets: {model.num_facets} " in text
    assert f"ordered pairs: {model.num_pairs}" in text


def test_build_model_reports_degenerate_facets(tmp_path, capsys):
    mesh = objects.load("banana")
    faces = np.vstack([mesh.faces[:5], [[0, 0, 1]], mesh.faces[5:]])
    mesh.faces = faces
    ply = tmp_path / "degenerate.ply"
    mesh.export(ply)
    assert main(["build-model", str(ply), "-o", str(tmp_path / "d.npz")]) == 0
    captured = capsys.readouterr()
    assert "facets: 54 (1 degenerate, excluded)" in captured.out
    assert "ordered pairs: 2809" in captured.out
    assert re.search(r"contactpose: warning: 1 degenerate facets .*: 5$", captured.err, re.M)


@pytest.mark.parametrize("kind", ["finger_normal", "object_normal"])
def test_localize_prints_status_and_writes_json(tmp_path, capsys, banana_npz, kind):
    model = ObjectModel.load(banana_npz)
    contacts_path, g = grasp_file(tmp_path, model, seed=3, kind=kind)
    out = tmp_path / "result.json"
    assert main(["localize", str(banana_npz), "--contacts", contacts_path, *NOISE_ARGS, "-o", str(out)]) == 0
    text = capsys.readouterr().out
    api = localize(model, g.contacts, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)
    assert text.splitlines()[0].startswith(f"status: {api.status}")
    assert f"hypotheses: {api.num_hypotheses} " in text
    assert f"best facets: {api.best.facets.tolist()}" in text
    data = json.loads(out.read_text())
    assert data["status"] == api.status and data["num_hypotheses"] == api.num_hypotheses
    assert [h["facets"] for h in data["hypotheses"]] == [h.facets.tolist() for h in api.hypotheses]
    assert np.allclose(data["hypotheses"][0]["pose"], api.best.pose, atol=1e-12)
    assert g.facets.tolist() in [h["facets"] for h in data["hypotheses"]]


def test_localize_keep_all_writes_every_distinct_pose(tmp_path, capsys, rock_model):
    """--keep all writes what localize(keep="all") lists, the default what keep="fitting" does."""
    contacts_path, g = grasp_file(tmp_path, rock_model, seed=5)
    npz = tmp_path / "rock.npz"
    rock_model.save(npz)
    for keep in ("all", "fitting"):
        out = tmp_path / f"{keep}.json"
        extra = ["--keep", keep] if keep == "all" else []
        assert main(["localize", str(npz), "--contacts", contacts_path, *NOISE_ARGS, *extra, "-o", str(out)]) == 0
        api = localize(rock_model, g.contacts, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG,
                       keep=keep)
        data = json.loads(out.read_text())
        assert [h["facets"] for h in data["hypotheses"]] == [h.facets.tolist() for h in api.hypotheses]
        assert data["num_returned"] == len(api.hypotheses) and data["num_hypotheses"] == api.num_hypotheses
    capsys.readouterr()


def test_localize_with_prior_paper_method_and_top(tmp_path, capsys):
    model = ObjectModel.from_mesh(objects.load("banana"))
    contacts_path, g = grasp_file(tmp_path, model, seed=4)
    prior = write_json(tmp_path / "prior.json",
                       {"pose": g.pose.tolist(), "sigma_rot_deg": 5.0, "sigma_trans": 0.01})
    out = tmp_path / "r.json"
    # a built-in object name instead of a model file
    rc = main(["localize", "banana", "--contacts", contacts_path, "--prior", prior, "--method", "paper",
               "--top", "2", *NOISE_ARGS, "-o", str(out)])
    assert rc == 0
    data = json.loads(out.read_text())
    assert data["method"] == "paper" and data["solver"] == "lm"
    assert len(data["hypotheses"]) == min(2, data["num_hypotheses"])
    assert "status:" in capsys.readouterr().out


def bad_inputs(tmp, npz):
    """(argv, what the error line must mention) for inputs a user can get wrong."""
    good = {"contacts": [{"point": [0, 0, 0], "finger_normal": [0, 0, 1]},
                         {"point": [0.05, 0, 0], "finger_normal": [0, 1, 0]},
                         {"point": [0, 0.03, 0], "finger_normal": [1, 0, 0]}]}
    both = {"contacts": [dict(good["contacts"][0], object_normal=[0, 0, -1])] + good["contacts"][1:]}
    (tmp / "invalid.json").write_text('{"contacts": [ {"point": [0, 0, 0], ')
    write_json(tmp / "good.json", good)
    write_json(tmp / "both.json", both)
    write_json(tmp / "one.json", {"contacts": good["contacts"][:1]})
    write_json(tmp / "badprior.json", {"pose": np.eye(4).tolist(), "sigma_rot_deg": -1, "sigma_trans": 0.01})
    write_json(tmp / "shearprior.json", {"pose": [[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                                         "sigma_rot_deg": 1, "sigma_trans": 0.01})
    (tmp / "notamodel.npz").write_bytes(b"PK\x03\x04 this is not a zip")
    loc = ["localize", str(npz), "--contacts"]
    return [
        (loc + [str(tmp / "missing.json")], "does not exist"),
        (loc + [str(tmp / "invalid.json")], "not valid JSON"),
        (loc + [str(tmp / "both.json")], "exactly one"),
        (loc + [str(tmp / "one.json")], "at least 2"),
        (loc + [str(tmp / "good.json"), "--prior", str(tmp / "badprior.json")], "sigma_rot_deg"),
        (loc + [str(tmp / "good.json"), "--prior", str(tmp / "shearprior.json")], "rigid"),
        (loc + [str(tmp / "good.json"), "--top", "0"], "top"),
        (loc + [str(tmp / "good.json"), "--position-noise", "-1"], "position_noise"),
        (["localize", str(tmp / "missing.npz"), "--contacts", str(tmp / "good.json")], "does not exist"),
        (["localize", str(tmp / "notamodel.npz"), "--contacts", str(tmp / "good.json")], "model file"),
        (["build-model", str(tmp / "missing.stl")], "does not exist"),
        (["build-model", "banana", "--bins", "0", "4", "4", "-o", str(tmp / "x.npz")], "bins"),
        (["next-touch", str(npz), "--contacts", str(tmp / "missing.json")], "does not exist"),
        (["next-touch", str(npz), "--contacts", str(tmp / "good.json"), "--candidates", "0"], "--candidates"),
    ]


def test_bad_input_exits_2_with_one_line(tmp_path, capsys, banana_npz):
    for argv, mention in bad_inputs(tmp_path, banana_npz):
        rc = main(argv)
        captured = capsys.readouterr()
        lines = captured.err.splitlines()
        assert rc == 2, argv
        assert len(lines) == 1, (argv, captured.err)
        assert lines[0].startswith("contactpose: error: ") and mention in lines[0], lines[0]
        assert "Traceback" not in captured.err + captured.out


def test_debug_flag_shows_the_exception(tmp_path, banana_npz):
    from contactpose.errors import ContactsError

    with pytest.raises(ContactsError):
        main(["--debug", "localize", str(banana_npz), "--contacts", str(tmp_path / "missing.json")])


def test_next_touch_suggests_a_probe_that_touches_the_best_pose(tmp_path, capsys, banana_npz):
    out = tmp_path / "touch.json"
    argv = ["next-touch", str(banana_npz), "--contacts", str(EXAMPLE_CONTACTS), *NOISE_ARGS, "--candidates", "50",
            "-o", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    data = json.loads(out.read_text())
    touch, pose = data["touch"], np.array(data["classes"][0]["pose"])
    assert data["status"] == "ok" and re.search(r"^next touch: point \[.+\] \(mesh units\)  direction \[.+\] "
                                                r"\(unit vector, into the object\)$", text, re.M)
    # independent check: trimesh's ray cast against the banana placed at the best pose
    posed = objects.load("banana").apply_transform(pose)
    hits, _, faces = posed.ray.intersects_location([touch["start"]], [touch["direction"]])
    first = np.argmin(np.linalg.norm(hits - touch["start"], axis=1))
    np.testing.assert_allclose(hits[first], touch["point"], atol=1e-6)
    assert np.dot(posed.face_normals[faces[first]], touch["direction"]) < 0  # approaches from outside
    np.testing.assert_allclose(touch["outcomes"][0]["normal"], posed.face_normals[faces[first]], atol=1e-6)
