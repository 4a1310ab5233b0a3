"""The JSON the CLI writes matches its schema (contactpose/data/*.schema.json), with units.

Each localize case runs the CLI in-process on the built-in banana and keeps the Result the
CLI computed, so the JSON can be checked against it: counts, ``best``, times in ms against
``Result.timing`` in seconds, sample summaries in the units the schema names.
"""

import contextlib
import io
import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from conftest import NORMAL_NOISE_DEG, POSITION_NOISE

from contactpose.cli import localize as cli_localize
from contactpose.cli import main
from contactpose.contacts import Contacts
from contactpose.io import jsonfiles, output
from contactpose.localize import localize
from contactpose.options import STATUSES
from contactpose.schema import RESIDUAL_COLUMNS, SCHEMA_VERSION, TANGENT_ORDER, result_units
from contactpose.sim import grasps as simulate

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
CONTACTS = str(EXAMPLES / "banana_contacts.json")
PRIOR = str(EXAMPLES / "banana_prior.json")
NOISE_ARGS = ["--position-noise", str(POSITION_NOISE), "--normal-noise-deg", str(NORMAL_NOISE_DEG)]
#: localize cases: name -> (contacts file key, extra arguments).
CASES = {
    "plain": ("example", []),
    "top1": ("example", ["--top", "1"]),
    "factor_graph": ("example", ["--solver", "factor-graph", "--prior", PRIOR]),
    "samples": ("example", ["--samples", "200", "--seed", "0"]),
    "outliers": ("five", [*NOISE_ARGS, "--max-outliers", "1"]),
    "outliers_top1": ("five", [*NOISE_ARGS, "--max-outliers", "1", "--top", "1"]),
    "finger_off": ("five", [*NOISE_ARGS]),
    "no_hypothesis": ("millimetres", []),
    "underdetermined": ("two", []),
    "paper": ("example", ["--method", "paper"]),
}


def strict_json(text):
    """json.loads that refuses NaN and Infinity (not JSON)."""
    def refuse(name):
        raise ValueError(f"{name} is not JSON")
    return json.loads(text, parse_constant=refuse)


def validate(data, kind):
    errors = sorted(jsonschema.Draft202012Validator(output.load_schema(kind)).iter_errors(data), key=str)
    assert not errors, "\n".join(f"{list(e.absolute_path)}: {e.message}" for e in errors[:10])


def write_contacts(path, contacts):
    jsonfiles.write_json(path, {"contacts": [{"point": p.tolist(), "finger_normal": n.tolist()}
                                             for p, n in zip(contacts.points, contacts.finger_normals)]})
    return str(path)


@pytest.fixture(scope="module")
def contact_files(tmp_path_factory, banana_model):
    """The example contacts, and four variants: 5 fingers with one off its facet, the example
    in millimetres (no hypothesis), and only two contacts (underdetermined)."""
    tmp = tmp_path_factory.mktemp("schema")
    example = jsonfiles.read_contacts(CONTACTS)
    g = simulate.grasp(banana_model, np.random.default_rng(1), n=5, noise="bounded",
                       position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)
    points = g.contacts.points.copy()
    points[2] += 0.02 * g.contacts.finger_normals[2]  # finger 2 lifted 2 cm off its facet
    return {
        "example": CONTACTS,
        "five": write_contacts(tmp / "five.json", Contacts(points, finger_normals=g.contacts.finger_normals)),
        "millimetres": write_contacts(tmp / "mm.json", Contacts(example.points * 5.0,
                                                                finger_normals=example.finger_normals)),
        "two": write_contacts(tmp / "two.json", example.permuted(np.arange(2))),
    }


def run_cli(argv):
    """main(argv) with stdout and stderr captured -> (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def run_case(contact_files, tmp_path_factory):
    """name -> (name, JSON text, the Result the CLI computed, stdout) of one localize case, run once."""
    done = {}

    def run(name):
        if name not in done:
            key, extra = CASES[name]
            path = tmp_path_factory.mktemp(name) / "out.json"
            seen = []

            def keep(*args, **kwargs):
                seen.append(localize(*args, **kwargs))
                return seen[-1]

            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(cli_localize, "localize", keep)
                code, stdout, _ = run_cli(["localize", "banana", "--contacts", contact_files[key], *extra,
                                           "-o", str(path)])
            assert code == 0
            done[name] = name, path.read_text(), seen[0], stdout
        return done[name]

    return run


@pytest.fixture(params=list(CASES))
def case(request, run_case):
    """Every localize case in turn."""
    return run_case(request.param)


# ----------------------------------------------------------------- schemas ---

@pytest.mark.parametrize("kind", output.SCHEMA_KINDS)
def test_schema_is_valid_draft_2020_12(kind):
    schema = output.load_schema(kind)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["properties"]["schema_version"]["const"] == SCHEMA_VERSION
    assert {"schema_version", "units"} <= set(schema["required"])


def test_schema_statuses_cover_the_library():
    enum = output.load_schema("result")["properties"]["status"]["enum"]
    assert set(STATUSES) <= set(enum)
    assert {"ok", "poor_fit", "no_hypothesis", "underdetermined", "ambiguous", "time_limit"} == set(enum)


def test_touch_schema_shares_the_result_definitions():
    result, touch = output.load_schema("result"), output.load_schema("touch")
    assert touch["$defs"]["status"] == result["properties"]["status"]
    for name in ("pose_class", "pose", "number_or_null"):
        assert touch["$defs"][name] == result["$defs"][name], name


def test_unknown_schema_kind_is_named():
    with pytest.raises(ValueError, match="one of .*got 'results'"):
        output.load_schema("results")


# ---------------------------------------------------------------- localize ---

def test_localize_json_matches_schema(case):
    _, text, _, _ = case
    validate(strict_json(text), "result")


def test_counts_best_and_units(case):
    name, text, result, _ = case
    data = strict_json(text)
    assert data["schema_version"] == SCHEMA_VERSION and data["units"] == result_units()
    assert data["units"]["time"] == "ms" and data["units"]["tangent_order"] == list(TANGENT_ORDER)
    assert data["status"] == result.status and data["num_hypotheses"] == result.num_hypotheses
    assert data["num_returned"] == len(data["hypotheses"]) == len(result.hypotheses) <= data["num_hypotheses"]
    assert data["best"] == (data["hypotheses"][0] if data["hypotheses"] else None)
    assert data["residual_columns"] == list(RESIDUAL_COLUMNS)
    for h in data["hypotheses"]:
        assert all(len(row) == len(RESIDUAL_COLUMNS) for row in h["residuals"])
        assert len(h["residuals"]) == len(h["facets"])
    if name.endswith("top1"):
        assert data["num_returned"] == 1


def test_timing_is_in_milliseconds(case):
    _, text, result, stdout = case
    timing = strict_json(text)["timing_ms"]
    assert set(timing) == set(result.timing)
    for stage, seconds in result.timing.items():
        assert timing[stage] == pytest.approx(1000.0 * seconds, rel=1e-12)
    assert f"time: {timing['total']:.2f} ms" in stdout  # the console's milliseconds


def test_top_lists_fewer_than_found(run_case):
    _, text, _, _ = run_case("outliers_top1")
    data = strict_json(text)
    assert data["num_returned"] == 1 < data["num_hypotheses"]


def test_outlier_fingers_have_null_residuals(run_case):
    _, text, _, _ = run_case("outliers")
    data = strict_json(text)
    assert data["best"]["outliers"] == [2] and data["best"]["facets"][2] == -1
    for h in data["hypotheses"]:
        for finger, row in enumerate(h["residuals"]):
            assert (row == [None] * 5) == (finger in h["outliers"])


def test_optional_parts_are_null_unless_computed(case):
    name, text, result, _ = case
    data = strict_json(text)
    for h in data["hypotheses"]:
        assert (h["covariance"] is not None) == (name == "factor_graph")
        assert (h["probability"] is not None) == (name == "factor_graph")
    for rank, h in enumerate(data["hypotheses"]):
        assert (h["samples"] is not None) == (name == "samples" and rank == 0)
    assert "extra" not in data and not result.extra


def test_no_hypothesis_gives_null_best(run_case):
    _, text, _, _ = run_case("no_hypothesis")
    data = strict_json(text)
    assert data["status"] == "no_hypothesis" and "units" in data["hint"]
    assert data["best"] is None and data["hypotheses"] == [] and data["classes"] == []
    assert data["num_hypotheses"] == data["num_returned"] == 0


def test_free_directions_are_lists(case):
    name, text, result, _ = case
    data = strict_json(text)
    for h, hyp in zip(data["hypotheses"], result.hypotheses):
        assert np.allclose(np.reshape(h["free_translation"], (-1, 3)), hyp.free_translation)
        assert h["free_rotation"] == ([] if hyp.free_rotation is None else [hyp.free_rotation.tolist()])
        assert h["underdetermined"] == bool(h["free_translation"] or h["free_rotation"])
    if name == "underdetermined":
        assert data["status"] == "underdetermined" and data["best"]["free_translation"]


def test_method_and_solver(case):
    name, text, _, _ = case
    data = strict_json(text)
    expected = {"paper": ("paper", "lm"), "factor_graph": ("fast", "factor-graph")}.get(name, ("fast", "closed-form"))
    assert (data["method"], data["solver"]) == expected


def test_sample_summary_units(run_case):
    _, text, result, _ = run_case("samples")
    summary, s = strict_json(text)["best"]["samples"], result.best.samples
    assert summary["n_samples"] == 200 == len(s.xi)
    assert np.allclose(summary["mean"], s.xi.mean(axis=0))  # radians, as the covariance
    assert np.allclose(summary["covariance"], np.cov(s.xi, rowvar=False))
    q = np.quantile(s.xi, [0.025, 0.975], axis=0).T
    q[:3] = np.degrees(q[:3])  # rotation rows in degrees
    assert np.allclose(summary["intervals"]["0.95"], q)
    assert summary["time_ms"] == pytest.approx(1000.0 * s.seconds)


def test_tolerance_units(case):
    _, text, result, _ = case
    tol = strict_json(text)["tolerance"]
    assert tol["distance"] == result.tolerance.distance
    assert tol["angle_deg"] == pytest.approx(np.degrees(result.tolerance.angle))
    assert tol["normal_noise_deg"] == pytest.approx(np.degrees(result.tolerance.normal_noise))


def test_diagnosis_is_written_for_an_empty_or_poor_answer(case):
    """null for an answer that fits; for an empty or poor one the Result's Diagnosis, its
    message in the hint."""
    name, text, result, stdout = case
    written = strict_json(text)["diagnosis"]
    if result.status not in ("no_hypothesis", "poor_fit") or result.method != "fast":
        assert written is None and result.diagnosis is None
        return
    assert written == result.diagnosis.to_dict() and written["message"] in result.hint
    assert f"cause: {written['cause']}" in stdout
    if name == "finger_off":  # finger 2 of five lifted 2 cm off its facet
        assert (written["cause"], written["finger"], written["max_outliers"]) == ("finger_off", 2, 1)


def _mutations(data):
    """(what is wrong, a copy of the valid localize JSON ``data`` with that defect)."""
    def changed(edit):
        copy = json.loads(json.dumps(data))
        edit(copy)
        return copy
    hypothesis = lambda d: d["hypotheses"][0]  # noqa: E731
    return [
        ("an unknown key", changed(lambda d: d.update(comment="hand-edited"))),
        ("a required key missing", changed(lambda d: d.pop("tolerance"))),
        ("another schema version", changed(lambda d: d.update(schema_version="1.1"))),
        ("an unknown status", changed(lambda d: d.update(status="great"))),
        ("a time in seconds as text", changed(lambda d: d["timing_ms"].update(total="0.4 s"))),
        ("a negative time", changed(lambda d: d["timing_ms"].update(total=-1.0))),
        ("a facet index below -1", changed(lambda d: hypothesis(d)["facets"].__setitem__(0, -2))),
        ("a pose of 3 rows", changed(lambda d: hypothesis(d).update(pose=hypothesis(d)["pose"][:3]))),
        ("a residual row of 4 columns", changed(lambda d: hypothesis(d)["residuals"][0].pop())),
        ("an unknown cause", changed(lambda d: d.update(diagnosis={
            "cause": "gremlins", "message": "", "finger": None, "max_outliers": None, "scale": None,
            "position_noise": None, "normal_noise_deg": None, "tested": []}))),
        ("a diagnosis without its fields", changed(lambda d: d.update(diagnosis={"cause": "units"}))),
    ]


def test_the_result_schema_rejects_bad_documents(run_case):
    """Each defect of a valid localize JSON makes it invalid, and the validator says where."""
    valid = strict_json(run_case("plain")[1])
    validate(valid, "result")
    validator = jsonschema.Draft202012Validator(output.load_schema("result"))
    for what, bad in _mutations(valid):
        assert not validator.is_valid(bad), what


@pytest.mark.parametrize("kind", output.SCHEMA_KINDS)
def test_every_schema_rejects_unknown_keys_and_missing_ones(kind):
    schema = output.load_schema(kind)
    validator = jsonschema.Draft202012Validator(schema)
    assert schema["additionalProperties"] is False
    errors = list(validator.iter_errors({"schema_version": SCHEMA_VERSION, "surprise": 1}))
    assert any(e.validator == "additionalProperties" for e in errors), kind
    assert any(e.validator == "required" for e in errors), kind


# ---------------------------------------------------------------- other outputs ---

#: Contacts on the box (0.10 x 0.06 x 0.04) near its (+x, +y) edge: the box as it is and turned
#: 90 degrees about that edge both fit (two pose classes).
BOX_AMBIGUOUS = {"contacts": [
    {"point": [0.05, 0.007, 0.005], "object_normal": [1.0, 0.0, 0.0]},
    {"point": [0.02, 0.03, -0.005], "object_normal": [0.0, 1.0, 0.0]},
    {"point": [0.01, -0.01, 0.02], "object_normal": [0.0, 0.0, 1.0]},
    {"point": [0.015, 0.005, -0.02], "object_normal": [0.0, 0.0, -1.0]}]}


@pytest.mark.parametrize("model", ["banana", "box"])
def test_next_touch_json_matches_schema(tmp_path, model):
    contacts = CONTACTS
    if model == "box":
        contacts = str(tmp_path / "box.json")
        jsonfiles.write_json(contacts, BOX_AMBIGUOUS)
    out = tmp_path / "touch.json"
    code, stdout, _ = run_cli(["next-touch", model, "--contacts", contacts, *NOISE_ARGS, "--candidates", "50",
                               "-o", str(out)])
    assert code == 0
    data = strict_json(out.read_text())
    validate(data, "touch")
    assert data["units"] == output.TOUCH_UNITS and data["status"] in stdout
    assert len(data["touch"]["outcomes"]) == len(data["touch"]["probabilities"]) == max(1, len(data["classes"]))
    if model == "box":
        assert data["status"] == "ambiguous" and len(data["classes"]) > 1


def test_scan_report_json_matches_schema(tmp_path):
    pytest.importorskip("open3d")
    import trimesh

    from contactpose.sim.range_scanner import scan

    points, normals = scan(trimesh.creation.icosphere(subdivisions=3, radius=0.05), np.random.default_rng(0),
                           resolution=48)
    np.save(tmp_path / "cloud.npy", np.hstack([points, normals]))
    out = tmp_path / "report.json"
    code, _, _ = run_cli(["scan", str(tmp_path / "cloud.npy"), "-o", str(tmp_path / "mesh.ply"), "--faces", "300",
                          "--report-json", str(out)])
    assert code == 0
    data = strict_json(out.read_text())
    validate(data, "scan_report")
    assert data["units"] == output.SCAN_UNITS
    assert data["total_ms"] == pytest.approx(sum(data["timings_ms"].values()))
    assert 1.0 < data["total_ms"] < 600_000.0  # milliseconds, not seconds


def test_bench_json_matches_schema(tmp_path):
    out = tmp_path / "bench.json"
    code, _, _ = run_cli(["bench", "--models", "banana", "--runs", "2", "--json", str(out), "--out", str(tmp_path)])
    assert code == 0
    data = strict_json(out.read_text())
    validate(data, "bench")
    assert data["units"]["time"] == "ms" and data["total_ms"] > 1.0


# ------------------------------------------------------------------- repr ---

def test_result_and_hypothesis_repr_are_one_line(case):
    name, _, result, _ = case
    text = repr(result)
    assert "\n" not in text and len(text) < 200 and "[[" not in text
    assert text.startswith(f"Result(status={result.status!r}, ") and f"method={result.method!r}" in text
    assert text.endswith(f"{1000 * result.timing['total']:.2f} ms)")
    if result.best is None:
        assert "0 hypotheses" in text
        return
    assert f"best facets {result.best.facets.tolist()}" in text
    h = repr(result.best)
    assert "\n" not in h and "[[" not in h and len(h) < 200
    assert h.startswith(f"Hypothesis(facets {result.best.facets.tolist()}, chi2 ")
    if name == "samples":
        assert "200 samples" in h
    if name == "underdetermined":
        assert "underdetermined (free: 1 translation" in h


def test_result_repr_counts(banana_model):
    r = localize(banana_model, jsonfiles.read_contacts(CONTACTS))
    one = repr(r)
    assert "1 hypothesis (" in one and "1 pose class," in one and "solver=" not in one
    r.num_hypotheses = 3
    assert "1 of 3 hypotheses" in repr(r)


def test_prior_to_dict_round_trips():
    prior = jsonfiles.read_prior(PRIOR)
    back = jsonfiles.parse_prior(json.loads(json.dumps(prior.to_dict())))
    assert np.array_equal(back.pose, prior.pose) and back.sigma_rot_deg == prior.sigma_rot_deg
