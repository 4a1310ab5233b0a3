"""``contactpose bench``: files only where --out / --json say, and one list of default models."""

import csv
import datetime
import json
import re
from pathlib import Path

import matplotlib.image
import pytest

from contactpose.cli import main
from contactpose.harness import bench

ROOT = Path(__file__).resolve().parents[1]
ARGV = ["bench", "--models", "banana", "--runs", "2"]


@pytest.fixture(scope="module")
def bench_out(tmp_path_factory):
    """A real two-grasp bench of the banana, written with --out."""
    out = tmp_path_factory.mktemp("bench") / "out"
    assert main([*ARGV, "--out", str(out)]) == 0
    return out


@pytest.fixture
def fake_bench(bench_out, monkeypatch):
    """bench_model returns the banana result of ``bench_out`` at once."""
    model = json.loads((bench_out / "bench.json").read_text())["models"][0]
    monkeypatch.setattr(bench, "bench_model", lambda *args: model)


def test_out_writes_json_csv_and_stage_figure(bench_out):
    assert sorted(p.name for p in bench_out.iterdir()) == sorted(bench.OUTPUT_FILES)
    report = json.loads((bench_out / "bench.json").read_text())
    assert report["runs"] == 2 and [m["model"] for m in report["models"]] == ["banana"]
    rows = list(csv.DictReader((bench_out / "bench.csv").open()))
    assert [(r["model"], r["method"]) for r in rows] == [("banana", "fast"), ("banana", "paper")]
    for r, method in zip(rows, ("fast", "paper")):
        stats = report["models"][0][method]
        assert float(r["total_median_ms"]) == pytest.approx(stats["total"]["median_ms"], abs=1e-4)  # CSV: 4 decimals
        assert all(float(r[f"{stage}_ms"]) >= 0 for stage, _ in bench.TABLE_STAGES)
        assert r["date"] == report["date"] and str(report["machine"]["cores"]) in r["machine"]
    when = datetime.datetime.strptime(report["date"], "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=datetime.timezone.utc)
    assert abs((datetime.datetime.now(datetime.timezone.utc) - when).total_seconds()) < 3600  # this run's date
    image = matplotlib.image.imread(bench_out / "bench_stages.png")
    assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 200


def test_no_out_or_json_writes_nothing(tmp_path, monkeypatch, capsys, fake_bench):
    monkeypatch.chdir(tmp_path)
    assert main(ARGV) == 0
    assert list(tmp_path.iterdir()) == []
    out = capsys.readouterr().out
    assert re.search(r"^banana +53 .*\| fast ", out, re.M) and "written" not in out


def test_json_alone_writes_only_that_file(tmp_path, monkeypatch, fake_bench):
    monkeypatch.chdir(tmp_path)
    assert main([*ARGV, "--json", "sub/report.json"]) == 0
    assert [p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")] == ["sub", "sub/report.json"]
    assert json.loads((tmp_path / "sub" / "report.json").read_text())["models"][0]["model"] == "banana"


@pytest.mark.parametrize("argv,mention", [(["--runs", "0"], "--runs must be at least 1, got 0"),
                                          (["--models", "pear"], "unknown model 'pear'"),
                                          (["--paper-cap", "-1"], "--paper-cap must be a positive number")])
def test_bad_options_exit_2_before_any_work(tmp_path, monkeypatch, capsys, argv, mention):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(bench, "bench_model", lambda *args: pytest.fail("benched despite a bad option"))
    assert main(["bench", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("contactpose: error: ") and mention in err and list(tmp_path.iterdir()) == []


def test_default_models_are_the_ones_documented():
    """The command line reference's synopsis names bench.DEFAULT_MODELS."""
    text = (ROOT / "docs" / "reference" / "cli.md").read_text()
    synopsis = re.search(r"contactpose bench \[--models ([\w: ]+)\]", text)
    assert synopsis and tuple(synopsis.group(1).split()) == bench.DEFAULT_MODELS


def test_help_shows_the_default_models():
    text = re.sub(r"\s+", " ", bench_help())
    assert f"(default: {' '.join(bench.DEFAULT_MODELS)})" in text


def bench_help():
    """``contactpose bench --help`` as text."""
    from contactpose.cli import build_parser

    parser = build_parser()
    action = next(a for a in parser._actions if a.dest == "command")
    return action.choices["bench"].format_help()


def test_make_bench_writes_results_bench():
    target = re.search(r"^bench:.*\n((?:\t.*\n)+)", (ROOT / "Makefile").read_text(), re.M)
    assert target and "contactpose bench --out results/bench" in target.group(1)


WARM_UP_SCRIPT = """
import numpy as np
from contactpose.localize import localize, warm_up
from contactpose.model.object_model import ObjectModel
from contactpose.solvers import polish
from contactpose.sim import grasps as simulate, objects
model = ObjectModel.from_mesh(objects.load("banana"))
g = simulate.grasp(model, np.random.default_rng(0), n=4, pose=simulate.paper_pose(), where="centroid")
localize(model, g.contacts, position_noise=0.0005)
before = len(polish._bound_kernel.signatures)
warm_up(model, g.contacts, position_noise=0.0005)
print(before, len(polish._bound_kernel.signatures))
"""


def test_warm_up_loads_the_in_facet_bound_that_a_clean_grasp_skips():
    """In a fresh process, localize on a clean grasp (every hypothesis fits by its planes) leaves
    the in-facet bound's kernel unloaded, so the first timed grasp that needs it paid for the
    load (25–40 ms on the paper's banana); warm_up loads it."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", WARM_UP_SCRIPT], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.split() == ["0", "1"]
