"""The sweep runner: cells and seeds, CSV output, resume, and bit-identical results on a
Dask LocalCluster with 1 and 2 workers."""

import functools
import json

import numpy as np
import pytest

from contactpose.harness import sweep
from contactpose.harness.sweep import Sweep, SweepError

CALLS = []


def draw_task(settings, rng, *, scale=1.0):
    """Cheap task: a few random numbers, two rows per cell (one with an extra column)."""
    CALLS.append((settings["a"], settings["seed"]))
    x = rng.normal(size=3) * scale * settings["a"]
    return [{"x0": x[0], "x1": x[1], "ok": bool(x[2] > 0), "time_fake": 1.0},
            {"x0": float(x.sum()), "label": f"a={settings['a']}", "time_fake": 2.0}]


def localize_task(settings, rng):
    """A real cell: simulate a grasp on a small mesh and localize it."""
    import contactpose as cp
    from contactpose.geometry import metrics
    from contactpose.sim import grasps as simulate

    def build():
        import trimesh

        ico = trimesh.creation.icosahedron()
        v = ico.vertices * (1.0 + 0.25 * np.random.default_rng(7).uniform(-1, 1, (len(ico.vertices), 1)))
        return cp.ObjectModel.from_mesh(trimesh.Trimesh(v * 0.05, ico.faces, process=False))

    model = sweep.cached("ico", build)
    g = simulate.grasp(model, rng, n=4, position_noise=settings["noise"], normal_noise_deg=1.0, noise="bounded")
    r = cp.localize(model, g.contacts, position_noise=settings["noise"], normal_noise_deg=1.0)
    best = r.best
    return {"status": r.status, "hypotheses": r.num_hypotheses,
            "rot_err_deg": float(metrics.rotation_error_deg(best.pose, g.pose)) if best else None,
            "t": best.pose[:3, 3].tolist().__repr__() if best else "", "time_total_s": r.timing["total"]}


def failing_task(settings, rng):
    if settings["a"] == 2 and settings["seed"] == 1:
        raise ValueError("boom")
    return draw_task(settings, rng)


def test_cells_order_keys_and_seeds():
    cells = sweep.make_cells({"a": [1, 2], "b": ["x", "y"]}, 2)
    assert [(c.settings["a"], c.settings["b"], c.seed) for c in cells[:3]] == [(1, "x", 0), (1, "x", 1), (1, "y", 0)]
    assert [c.index for c in cells] == list(range(8))
    # a cell's key and random stream do not depend on where it sits in the grid
    bigger = sweep.make_cells({"a": [0, 1, 2], "b": ["x", "y"]}, 3)
    by_key = {c.key: c for c in bigger}
    for c in cells:
        other = by_key[c.key]
        assert c.cell == other.cell
        a = np.random.default_rng(c.seed_sequence(5)).random(4)
        assert np.array_equal(a, np.random.default_rng(other.seed_sequence(5)).random(4))
    # seed_axes pairs cells: same grasp stream for every b, different across a and seeds
    s = {(c.settings["a"], c.settings["b"], c.seed): np.random.default_rng(c.seed_sequence(0, ("a",))).random()
         for c in cells}
    assert s[1, "x", 0] == s[1, "y", 0]
    assert len({s[1, "x", 0], s[2, "x", 0], s[1, "x", 1]}) == 3
    with pytest.raises(SweepError, match="reserved"):
        sweep.make_cells({"seed": [1]}, 1)
    with pytest.raises(SweepError, match="repeats"):
        sweep.make_cells([{"a": 1}, {"a": 1}], 1)


def test_format_value():
    assert sweep.format_value(0.1) == "0.1"
    assert float(sweep.format_value(np.float64(1 / 3))) == 1 / 3
    assert sweep.format_value(np.float32(0.5)) == "0.5"
    assert sweep.format_value(True) == "1" and sweep.format_value(np.bool_(False)) == "0"
    assert sweep.format_value(None) == "" and sweep.format_value(np.int64(3)) == "3"
    with pytest.raises(SweepError, match="must be str"):
        sweep.format_value([1, 2])


def test_serial_run_writes_sorted_csvs_and_resumes(tmp_path):
    grid = {"a": [1, 2, 3]}
    CALLS.clear()
    first = sweep.run(Sweep("toy", draw_task, grid, seeds=2, base_seed=3), tmp_path / "toy", workers=0)
    assert first.ran == 6 and first.skipped == 0 and len(CALLS) == 6
    header = first.results.read_text().splitlines()[0].split(",")
    assert header == ["cell", "a", "seed", "label", "ok", "x0", "x1"]          # no timing column
    assert "time_fake" in first.timings.read_text().splitlines()[0]
    config = json.loads(first.config.read_text())
    assert config["grid"] == {"a": [1, 2, 3]} and config["seeds"] == 2 and config["base_seed"] == 3

    # more seeds: only the new cells run, and the CSV equals a fresh run of the bigger sweep
    CALLS.clear()
    second = sweep.run(Sweep("toy", draw_task, grid, seeds=4, base_seed=3), tmp_path / "toy", workers=0)
    assert second.skipped == 6 and second.ran == 6 and sorted(CALLS) == [(a, s) for a in (1, 2, 3) for s in (2, 3)]
    fresh = sweep.run(Sweep("toy", draw_task, grid, seeds=4, base_seed=3), tmp_path / "fresh", workers=0)
    assert second.results.read_bytes() == fresh.results.read_bytes()
    rows = sweep.read_rows(fresh.results)
    assert [(r["a"], r["seed"]) for r in rows[:4]] == [("1", "0"), ("1", "0"), ("1", "1"), ("1", "1")]

    # a changed fixed config starts afresh
    CALLS.clear()
    task = functools.partial(draw_task, scale=2.0)
    third = sweep.run(Sweep("toy", task, grid, seeds=4, base_seed=3, config={"scale": 2.0}), tmp_path / "toy", workers=0)
    assert third.skipped == 0 and len(CALLS) == 12


def test_failed_cells_are_reported_and_retried(tmp_path):
    out = tmp_path / "f"
    with pytest.raises(SweepError, match="1 of 6 cells failed"):
        sweep.run(Sweep("f", failing_task, {"a": [1, 2, 3]}, seeds=2), out, workers=0)
    assert len(sweep.read_rows(out / "results.csv")) == 10
    CALLS.clear()
    report = sweep.run(Sweep("f", draw_task, {"a": [1, 2, 3]}, seeds=2), out, workers=0)
    assert report.ran == 1 and CALLS == [(2, 1)]
    fresh = sweep.run(Sweep("f", draw_task, {"a": [1, 2, 3]}, seeds=2), tmp_path / "g", workers=0)
    assert report.results.read_bytes() == fresh.results.read_bytes()


def test_local_cluster_one_and_two_workers_identical(tmp_path):
    """A tiny sweep that calls the library, on a LocalCluster with 1 and 2 workers."""
    make = lambda: Sweep("tiny", localize_task, {"noise": [0.0005, 0.001]}, seeds=3, base_seed=11)  # noqa: E731
    one = sweep.run(make(), tmp_path / "one", workers=1)
    two = sweep.run(make(), tmp_path / "two", workers=2)
    assert one.ran == two.ran == 6 and one.workers == 1 and two.workers == 2
    assert one.results.read_bytes() == two.results.read_bytes()
    rows = sweep.read_rows(one.results)
    assert len(rows) == 6 and all(r["status"] for r in rows) and "time_total_s" not in rows[0]
    assert "time_total_s" in sweep.read_rows(one.timings)[0]
    # in-process (no Dask) gives the same rows too
    serial = sweep.run(make(), tmp_path / "serial", workers=0)
    assert serial.results.read_bytes() == one.results.read_bytes()
    # resume on the cluster: nothing left to run, file unchanged
    again = sweep.run(make(), tmp_path / "two", workers=2)
    assert again.ran == 0 and again.skipped == 6
    assert again.results.read_bytes() == one.results.read_bytes()


def test_script_main_runs_plots_summarizes_and_redraws_from_csv(tmp_path, monkeypatch, capsys):
    """sweep.main is a whole experiment script: config by name, sweep, figures, summary."""
    configs = tmp_path / "experiments" / "configs"
    configs.mkdir(parents=True)
    (configs / "toy.json").write_text(json.dumps({"common": {"scale": 2.0}, "quick": {"seeds": 2}, "full": {"seeds": 5}}))
    monkeypatch.setattr(sweep, "ROOT", tmp_path)
    made, plotted = [], []

    def make_sweep(cfg):
        made.append(cfg)
        return Sweep("toy", functools.partial(draw_task, scale=cfg["scale"]), {"a": [1, 2]}, seeds=cfg["seeds"],
                     config=cfg)

    def summary(out):
        return f"{len(sweep.read_rows(out / sweep.RESULTS_CSV))} rows"

    argv = ["--quick", "--workers", "0", "--out", str(tmp_path / "res")]
    out = tmp_path / "res" / "toy"
    assert sweep.main("toy", "Toy sweep.\n\nMore.", make_sweep, plotted.append, summary, argv) == 0
    assert made == [{"scale": 2.0, "seeds": 2}] and plotted == [out]
    assert capsys.readouterr().out.splitlines() == ["8 rows", f"written: {out}"]   # 2 a x 2 seeds x 2 rows
    fresh = sweep.run(make_sweep(made[0]), tmp_path / "ref", workers=0)
    assert (out / sweep.RESULTS_CSV).read_bytes() == fresh.results.read_bytes()
    # --plot-only: no sweep is made or run; figures and summary come from the CSV
    made.clear()
    assert sweep.main("toy", "Toy sweep.", make_sweep, plotted.append, summary, argv + ["--plot-only"]) == 0
    assert made == [] and plotted == [out, out] and capsys.readouterr().out.startswith("8 rows\n")


def test_set_overrides_a_config_setting_and_refuses_unknown_keys_and_bad_json(tmp_path, monkeypatch, capsys):
    """--set KEY=JSON replaces one setting of the config file (the sweep and its config.json see
    it); a key the config lacks or a value that is not JSON exits 2 with one line naming it."""
    configs = tmp_path / "experiments" / "configs"
    configs.mkdir(parents=True)
    (configs / "toy.json").write_text(json.dumps({"common": {"scale": 2.0, "a": [1, 2]}, "quick": {"seeds": 2}}))
    monkeypatch.setattr(sweep, "ROOT", tmp_path)
    made = []

    def make_sweep(cfg):
        made.append(cfg)
        return Sweep("toy", functools.partial(draw_task, scale=cfg["scale"]), {"a": cfg["a"]}, seeds=cfg["seeds"],
                     config=cfg)

    argv = ["--quick", "--workers", "0", "--out", str(tmp_path / "res")]
    assert sweep.main("toy", "Toy.", make_sweep, lambda out: None, lambda out: "",
                      argv + ["--set", "seeds=3", "--set", "a=[5]"]) == 0
    assert made == [{"scale": 2.0, "a": [5], "seeds": 3}]
    assert len(sweep.read_rows(tmp_path / "res" / "toy" / sweep.RESULTS_CSV)) == 6   # 1 a x 3 seeds x 2 rows
    assert json.loads((tmp_path / "res" / "toy" / sweep.CONFIG_JSON).read_text())["config"]["seeds"] == 3
    capsys.readouterr()
    for bad, named in (("scal=1", "'scal=1'"), ("seeds=three", "'three'"), ("seeds", "'seeds'")):
        with pytest.raises(SystemExit) as stop:
            sweep.main("toy", "Toy.", make_sweep, lambda out: None, lambda out: "", argv + ["--set", bad])
        assert stop.value.code == 2
        message = capsys.readouterr().err.strip().splitlines()[-1]
        assert named in message and "Traceback" not in message


def test_write_rows_unions_columns_and_reads_back(tmp_path):
    path = tmp_path / "t.csv"
    sweep.write_rows(path, [{"a": 1, "b": 0.5}, {"c": "x", "a": 2}])
    assert path.read_text().splitlines()[0] == "a,b,c"
    assert sweep.read_rows(path) == [{"a": "1", "b": "0.5", "c": ""}, {"a": "2", "b": "", "c": "x"}]
