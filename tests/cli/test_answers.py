"""The command line's answers: a diagnosed empty or poor answer exits 0 (3 with --strict) and
names its cause, following the suggestion fits; every printed number carries its unit, cost
beside chi2 with what each is; --help shows each default once; next-touch lists the likely
classes; a file that is not a mesh is called that; and the options --model-error, --refine,
--time-limit, track's --max-tracks and --no-reseed, and ``contactpose objects`` do what they say
(``contactpose demo`` is checked against the README in tests/test_readme.py)."""

import contextlib
import io
import json
import re
import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from contactpose import Contacts, ObjectModel, localize
from contactpose.cli import build_parser, main
from contactpose.cli import localize as cli_localize
from contactpose.cli.next_touch import LISTED_PROBABILITY
from contactpose.io import jsonfiles
from contactpose.options import fit_threshold
from contactpose.sim import grasps as simulate
from contactpose.sim import objects, ycb

NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)
NOISE_ARGS = ["--position-noise", "0.0005", "--normal-noise-deg", "1.0"]


def run(argv):
    """main(argv) with stdout and stderr captured -> (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def write_contacts(path, contacts, kind="finger_normal"):
    normals = contacts.finger_normals if kind == "finger_normal" else contacts.object_normals
    jsonfiles.write_json(path, {"contacts": [{"point": p.tolist(), kind: n.tolist()}
                                             for p, n in zip(contacts.points, normals)]})
    return str(path)


def grasp(name, seed, n=4):
    model = ObjectModel.from_mesh(objects.load(name))
    return model, simulate.grasp(model, np.random.default_rng(seed), n=n, **NOISE)


# ---------------------------------------------------------- the scenarios ---

def units(tmp):
    """The banana's mesh in millimetres, the contacts in metres (the default noise)."""
    mesh = objects.load("banana")
    trimesh.Trimesh(mesh.vertices * 1000.0, mesh.faces, process=False).export(tmp / "banana_mm.stl")
    _, g = grasp("banana", 0)
    return [tmp / "banana_mm.stl", "--contacts", write_contacts(tmp / "c.json", g.contacts)], None


def finger_off(tmp):
    """Finger 2 lifted 3 cm off the banana."""
    _, g = grasp("banana", 0)
    points = g.contacts.points.copy()
    points[2] -= 0.03 * g.contacts.finger_normals[2]
    path = write_contacts(tmp / "c.json", Contacts(points, finger_normals=g.contacts.finger_normals))
    return ["banana", "--contacts", path, *NOISE_ARGS], ["--max-outliers", "1"]


def subset_fits(tmp):
    """Five fingers on the rock, finger 3's normal read 30° off."""
    _, g = grasp("rock", 0, n=5)
    normals = g.contacts.finger_normals.copy()
    normals[3] = Rotation.from_rotvec([np.radians(30.0), 0.0, 0.0]).apply(normals[3])
    path = write_contacts(tmp / "c.json", Contacts(g.contacts.points, finger_normals=normals))
    return ["rock", "--contacts", path, *NOISE_ARGS], ["--max-outliers", "1"]


def inside_out(tmp):
    """A model file built from the rock's mesh with every face reversed (the build warns)."""
    rock = objects.load("rock")
    trimesh.Trimesh(rock.vertices, rock.faces[:, ::-1], process=False).export(tmp / "inverted.stl")
    code, _, err = run(["build-model", tmp / "inverted.stl", "-o", tmp / "inverted.npz"])
    assert code == 0 and "facet normals point inward" in err and "--fix-normals" in err
    _, g = grasp("rock", 1)
    return [tmp / "inverted.npz", "--contacts", write_contacts(tmp / "c.json", g.contacts), *NOISE_ARGS], None


def flipped(tmp):
    """The rock's outward normals given as finger normals."""
    _, g = grasp("rock", 2)
    path = write_contacts(tmp / "c.json", Contacts(g.contacts.points, finger_normals=g.contacts.object_normals))
    return ["rock", "--contacts", path, *NOISE_ARGS], None


def noise(tmp):
    """Noise of 0.5 mm and 1°, stated ten times smaller."""
    _, g = grasp("banana", 0)
    path = write_contacts(tmp / "c.json", g.contacts)
    return ["banana", "--contacts", path, "--position-noise", "0.00005", "--normal-noise-deg", "0.1"], "suggested"


SCENARIOS = {"units": units, "finger_off": (finger_off, "finger_off"), "subset_fits": (subset_fits, "finger_off"),
             "model_normals_inward": inside_out, "contact_normals_flipped": flipped, "noise_too_small": noise}


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_a_diagnosed_answer_exits_0_names_its_cause_and_3_with_strict(tmp_path, name):
    make, cause = SCENARIOS[name] if isinstance(SCENARIOS[name], tuple) else (SCENARIOS[name], name)
    argv, follow = make(tmp_path)
    out = tmp_path / "out.json"
    code, stdout, err = run(["localize", *argv, "-o", out])
    data = json.loads(out.read_text())
    assert code == 0 and "Traceback" not in err
    assert data["status"] in ("no_hypothesis", "poor_fit") and data["diagnosis"]["cause"] == cause
    assert re.search(rf"^cause: {cause}$", stdout, re.M) and data["diagnosis"]["message"] in stdout
    assert run(["localize", *argv, "--strict"])[0] == 3
    if follow == "suggested":  # the noise it names, on the command line as the hint says
        d = data["diagnosis"]
        follow = ["--position-noise", f"{d['position_noise']:.2g}", "--normal-noise-deg", f"{d['normal_noise_deg']:.2g}"]
        assert " ".join(follow) in stdout
    if follow:  # the suggestion fits: no longer empty or poor (with one finger fewer, maybe less sure than ok)
        code, stdout, _ = run(["localize", *argv, *follow, "--strict"])
        assert code == 0 and re.match(r"status: (ok|ambiguous|underdetermined)\b", stdout)


def test_an_answer_that_fits_exits_0_with_strict(tmp_path):
    _, g = grasp("banana", 0)
    code, stdout, _ = run(["localize", "banana", "--contacts", write_contacts(tmp_path / "c.json", g.contacts),
                           *NOISE_ARGS, "--strict"])
    assert code == 0 and stdout.startswith("status: ok\n") and "cause:" not in stdout


# ------------------------------------------------------- printed numbers ---

@pytest.mark.parametrize("extra,meaning", [([], "here chi2 itself"),
                                           (["--solver", "factor-graph"], "here -log Laplace evidence"),
                                           (["--method", "paper"], "here eq. (7)'s L")])
def test_cost_is_printed_beside_chi2_with_what_each_is(tmp_path, extra, meaning):
    _, g = grasp("banana", 0)
    out = tmp_path / "out.json"
    code, stdout, _ = run(["localize", "banana", "--contacts", write_contacts(tmp_path / "c.json", g.contacts),
                           *NOISE_ARGS, *extra, "-o", out])
    best = json.loads(out.read_text())["best"]
    assert code == 0
    chi2, cost = map(float, re.search(r"^  chi2: (\S+)  cost: (\S+)$", stdout, re.M).groups())
    assert chi2 == pytest.approx(best["chi2"], rel=1e-3) and cost == pytest.approx(best["cost"], rel=1e-3)
    assert (chi2 == cost) == (meaning == "here chi2 itself")
    assert f"fits within noise up to {fit_threshold(4):.3g}. cost: the ranking cost, {meaning}" in stdout
    assert re.search(r"^hypotheses: \d+  time: [\d.]+ ms$", stdout, re.M)
    assert "pose T_world_object (rotation | translation in mesh units):" in stdout


def test_help_shows_each_default_once():
    parser = build_parser()
    subs = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction").choices
    for name, sub in subs.items():
        formatter = sub.formatter_class(sub.prog)
        for action in sub._actions:
            shown = formatter._get_help_string(action) or ""
            assert shown.count("(default:") <= 1, (name, action.option_strings, shown)
    text = re.sub(r"\s+", " ", subs["localize"].format_help())
    assert text.count("(default: fitting)") == 1 and text.count("(default: 60.0)") == 1


def test_next_touch_lists_the_classes_above_the_floor(tmp_path):
    _, g = grasp("rock", 3, n=3)
    out = tmp_path / "touch.json"
    code, stdout, _ = run(["next-touch", "rock", "--contacts", write_contacts(tmp_path / "c.json", g.contacts),
                           "--position-noise", "0.001", "--normal-noise-deg", "2", "--candidates", "20", "-o", out])
    touch = json.loads(out.read_text())["touch"]
    p = np.array(touch["probabilities"])
    assert code == 0 and (p < LISTED_PROBABILITY).any() and (p >= LISTED_PROBABILITY).sum() > 1
    listed = [int(c) for c in re.findall(r"^  class (\d+) \(p ", stdout, re.M)]
    assert listed == np.flatnonzero(p >= LISTED_PROBABILITY).tolist()
    left = int((p < LISTED_PROBABILITY).sum())
    assert f"  {left} class{'es' if left > 1 else ''} below p {LISTED_PROBABILITY:g} not listed" in stdout
    groups = [o["group"] for o in touch["outcomes"]]
    for c in listed:  # "reads like" names exactly the other classes of its outcome group
        line = re.search(rf"^  class {c} \(p .*$", stdout, re.M).group(0)
        alike = [k for k in range(len(groups)) if k != c and groups[k] == groups[c]]
        named = re.search(r"reads like class(?:es)? ([\d, ]+)$", line)
        assert (named and [int(k) for k in named.group(1).split(", ")]) == (alike or None), line
    assert "(group" not in stdout and re.search(r"^next touch: point \[.+\] \(mesh units\)  direction", stdout, re.M)
    assert re.search(r"expected gain: [\d.]+ bits$", stdout, re.M)


def test_a_file_that_is_not_a_mesh_is_called_that(tmp_path):
    path = tmp_path / "notes.stl"
    path.write_text("these are my notes, not a mesh\n")
    code, _, err = run(["localize", path, "--contacts", tmp_path / "c.json"])
    assert code == 2 and err.count("\n") == 1 and f"{str(path)!r} as a mesh: it is not a mesh file" in err


# ------------------------------------------------------------- options ---

def test_model_error_widens_the_distance_tolerance(tmp_path):
    """--model-error L: the pair distance tolerance is 3·√2·σ + L (research/noise_model.md),
    and the answer is the library's with model_error=L; a negative L is bad input."""
    model, g = grasp("banana", 1)
    path = write_contacts(tmp_path / "c.json", g.contacts)
    out = tmp_path / "out.json"
    assert run(["localize", "banana", "--contacts", path, *NOISE_ARGS, "--model-error", "0.003", "-o", out])[0] == 0
    data = json.loads(out.read_text())
    assert data["tolerance"]["distance"] == pytest.approx(3 * np.sqrt(2) * 0.0005 + 0.003, rel=1e-12)
    want = localize(model, g.contacts, model_error=0.003, **NOISE)
    assert data["status"] == want.status and data["best"]["facets"] == want.best.facets.tolist()
    code, _, err = run(["localize", "banana", "--contacts", path, "--model-error", "-0.001"])
    assert code == 2 and "model_error must be >= 0, got -0.001" in err and err.count("\n") == 1


def test_twins_lists_every_symmetric_twin_of_a_placement(tmp_path):
    """--twins: on the box (its 4 rotations) every twin of a placement is written, as the
    library's localize(..., twins=True) lists them; by default one per placement, none of the
    written poses a twin of another (ADD-S on the surface points)."""
    from contactpose.geometry.metrics import adds_many
    model, g = grasp("box", 3)
    path = write_contacts(tmp_path / "c.json", g.contacts)
    written = {}
    for flag in ([], ["--twins"]):
        out = tmp_path / f"out{len(flag)}.json"
        assert run(["localize", "box", "--contacts", path, *NOISE_ARGS, *flag, "-o", out])[0] == 0
        written[bool(flag)] = np.array([h["pose"] for h in json.loads(out.read_text())["hypotheses"]])
    want = localize(model, g.contacts, twins=True, **NOISE)
    assert np.allclose(written[True], want.hypotheses.arrays.poses, atol=1e-9)
    one = written[False]
    assert len(one) < len(written[True])
    for k in range(len(one)):
        others = np.delete(one, k, axis=0)
        if len(others):
            assert adds_many(others, one[k], model.surface_points, model.surface_tree).min() > 0.01 * model.diameter


def test_refine_sets_how_many_hypotheses_the_factor_graph_refines(tmp_path, monkeypatch):
    """--refine K: the factor graph refines the best K, and with --keep all lists exactly them,
    their probabilities summing to 1; without it, the library's default; in vain without the graph."""
    _, g = grasp("rock", 3, n=3)
    args = ["localize", "rock", "--contacts", write_contacts(tmp_path / "c.json", g.contacts), "--position-noise",
            "0.001", "--normal-noise-deg", "2", "--solver", "factor-graph", "--keep", "all", "-o", tmp_path / "o.json"]
    for refine in (2, 4):
        assert run(args + ["--refine", refine])[0] == 0
        data = json.loads((tmp_path / "o.json").read_text())
        assert data["num_hypotheses"] == len(data["hypotheses"]) == refine
        assert sum(h["probability"] for h in data["hypotheses"]) == pytest.approx(1.0)
    code, _, err = run(args[:4] + ["--refine", "3"])
    assert code == 0 and "warning: --refine has no effect without --solver factor-graph" in err
    seen = {}

    def record(*a, **kw):
        seen.update(kw)
        raise KeyboardInterrupt  # the options are what is checked here

    monkeypatch.setattr(cli_localize, "localize", record)
    assert run(args)[0] == 130 and seen["refine"] == cli_localize.DEFAULT_REFINE == 20


def test_time_limit_bounds_the_search_and_0_lifts_it(tmp_path, monkeypatch):
    _, g = grasp("rock1k", 1)
    args = ["localize", "rock1k", "--contacts", write_contacts(tmp_path / "c.json", g.contacts),
            "--position-noise", "0.0005", "--normal-noise-deg", "10"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code, stdout, _ = run(args + ["--time-limit", "0.05", "-o", tmp_path / "o.json"])
    data = json.loads((tmp_path / "o.json").read_text())
    assert code == 0 and data["status"] == "time_limit" and "time limit" in data["hint"]
    seen = {}

    def record(*a, **kw):
        seen.update(kw)
        raise KeyboardInterrupt  # stop before the (long) unbounded search

    monkeypatch.setattr(cli_localize, "localize", record)
    assert run(args + ["--time-limit", "0"])[0] == 130 and seen["time_limit"] is None
    assert run(args)[0] == 130 and seen["time_limit"] == 60.0


def _sequence(tmp, seed=0, steps=8, slip_at=4):
    """A held banana: a first grasp, then 2 contacts per hand motion; at step ``slip_at`` + 1
    the object slips 25° and 1 cm more than the stated slip allows (no track explains it)."""
    model, g = grasp("banana", seed)
    rng = np.random.default_rng(seed + 100)
    contacts = lambda c: [{"point": p.tolist(), "finger_normal": n.tolist()}  # noqa: E731
                          for p, n in zip(c.points, c.finger_normals)]
    pose, out = g.pose, [{"contacts": contacts(g.contacts), "true_pose": g.pose.tolist()}]
    for k in range(steps):
        delta = simulate.pose_from(rotvec=0.1 * rng.normal(size=3), translation=0.02 * rng.normal(size=3))
        slip = simulate.pose_from(rotvec=[0, 0, np.radians(25.0)], translation=[0.01, 0, 0]) if k == slip_at else np.eye(4)
        pose = delta @ pose @ slip
        touch = simulate.grasp(model, rng, n=2, pose=pose, **NOISE)
        out.append({"contacts": contacts(touch.contacts), "true_pose": pose.tolist(),
                    "hand_motion": {"delta": delta.tolist(), "sigma_rot_deg": 1.0, "sigma_trans": 0.001}})
    (tmp / "seq.json").write_text(json.dumps({"steps": out}))
    return tmp / "seq.json"


def test_track_reseeds_unless_no_reseed(tmp_path):
    seq = _sequence(tmp_path)
    reseeds = {}
    for extra in ([], ["--no-reseed"]):
        code, stdout, _ = run(["track", "banana", "--sequence", seq, "--position-noise", "0.0005",
                               "-o", tmp_path / "t.json", *extra])
        steps = json.loads((tmp_path / "t.json").read_text())["steps"]
        assert code == 0 and all(s["reseeds"] == 0 for s in steps[:5])  # before the slip, every touch fits
        reseeds[bool(extra)] = steps[-1]["reseeds"]
        assert ("(reseeded: no track explained the touch)" in stdout) == (not extra)
    assert reseeds[False] >= 1 and reseeds[True] == 0


def test_track_keeps_at_most_max_tracks(tmp_path):
    """A first grasp of 3 contacts on rock1k leaves hundreds of poses: 20 tracks by default, 2 with --max-tracks 2."""
    model, g = grasp("rock1k", 0, n=3)
    rng = np.random.default_rng(7)
    delta = simulate.pose_from(rotvec=[0.0, 0.0, 0.1], translation=[0.01, 0.0, 0.0])
    touch = simulate.grasp(model, rng, n=2, pose=delta @ g.pose, **NOISE).contacts
    steps = [{"contacts": g.contacts.to_dict()["contacts"]},
             {"contacts": touch.to_dict()["contacts"],
              "hand_motion": {"delta": delta.tolist(), "sigma_rot_deg": 1.0, "sigma_trans": 0.001}}]
    (tmp_path / "seq.json").write_text(json.dumps({"steps": steps}))
    kept = {}
    for extra in ([], ["--max-tracks", "2"]):
        code, _, _ = run(["track", "rock1k", "--sequence", tmp_path / "seq.json", "--position-noise", "0.0005",
                          "--no-reseed", "-o", tmp_path / "t.json", *extra])
        data = json.loads((tmp_path / "t.json").read_text())
        assert code == 0
        kept[bool(extra)] = (data["steps"][0]["tracks"], max(s["tracks"] for s in data["steps"]), len(data["tracks"]))
    assert kept[False][0] == 20 and kept[True][0] == 2 and kept[True][1] <= 2 and kept[True][2] <= 2


def test_objects_lists_every_built_in_name():
    code, stdout, _ = run(["objects"])
    lines = stdout.splitlines()
    assert code == 0 and lines[0] == "procedural: " + ", ".join(objects.names(ycb_objects=False))
    assert re.match(rf"YCB \({len(ycb.names())} meshes, metres, 16,384 facets each", lines[1])
    assert [line.split()[0] for line in lines[2:]] == list(ycb.names())
    for name in [*objects.names(ycb_objects=False), *ycb.names()]:  # each name listed is one MESH may be
        assert objects.is_builtin(name), name
