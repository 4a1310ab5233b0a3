"""The quick versions of the experiments (what `make results-quick` runs), into a tmp dir:
CSV, figures and config are written, and the CSV is identical bit for bit across runs and
across 1 and 2 Dask workers."""

import sys
from pathlib import Path

import numpy as np
import pytest

from contactpose.harness import sweep

EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments"
sys.path.insert(0, str(EXPERIMENTS))
import run_all  # noqa: E402

OUTPUTS = ("results.csv", "timings.csv", "config.json", "run.json")


def run(name, out, *extra):
    assert run_all.load(name).main(["--quick", "--fresh", "--out", str(out), *extra]) == 0
    return out / name


def check_outputs(directory, stems):
    for f in OUTPUTS:
        assert (directory / f).stat().st_size > 0, f
    for stem in stems:
        for ext in ("png", "pdf"):
            assert (directory / f"{stem}.{ext}").stat().st_size > 1000, f"{stem}.{ext}"


def test_noise_sweep_quick_identical_on_one_and_two_workers(tmp_path):
    one = run("noise_sweep", tmp_path / "one", "--workers", "1")
    two = run("noise_sweep", tmp_path / "two", "--workers", "2")
    check_outputs(one, ["noise_sweep", "noise_sweep_solvers"])
    assert (one / "results.csv").read_bytes() == (two / "results.csv").read_bytes()
    assert sweep.read_run(one)["workers"] == 1 and sweep.read_run(two)["workers"] == 2
    rows = sweep.read_rows(one / "results.csv")
    assert {r["variant"] for r in rows} >= {"fast/closed-form", "paper/lm"}
    assert not any(k.startswith("time_") for k in rows[0])


def test_fingers_and_bins_quick_identical_across_runs_and_redrawn(tmp_path):
    first = run("fingers_sweep", tmp_path / "a", "--workers", "0")
    second = run("fingers_sweep", tmp_path / "b", "--workers", "0")
    check_outputs(first, ["fingers_sweep"])
    assert (first / "results.csv").read_bytes() == (second / "results.csv").read_bytes()
    bins = run("bin_sweep", tmp_path / "a", "--workers", "0")
    check_outputs(bins, ["bin_sweep"])
    c = sweep.read_columns(bins / "results.csv")
    assert np.all(c["candidates"] >= c["admissible"]) and len(set(c["admissible"])) <= int(c["grasp"].max()) + 1
    # figures come from the CSV alone
    (bins / "bin_sweep.png").unlink()
    assert run_all.load("bin_sweep").main(["--quick", "--plot-only", "--out", str(tmp_path / "a")]) == 0
    assert (bins / "bin_sweep.png").exists()


def test_candidate_count_matches_brute_force():
    """bin_sweep.candidate_count counts exactly the stored pairs whose bins eq. (5) visits."""
    from contactpose.contacts import Tolerance
    from contactpose.model.object_model import ObjectModel
    from contactpose.model.table import bin_index, query_limits
    from contactpose.search.pairs import pair_conditions
    from contactpose.sim import grasps as simulate
    from contactpose.sim import objects

    bin_sweep = run_all.load("bin_sweep")
    model = ObjectModel.from_mesh(objects.load("box"), bins=(8, 8, 16))
    t, f = model.table, model.features
    tolerance = Tolerance.from_noise(0.0005, 1.0)
    g = simulate.grasp(model, np.random.default_rng(3), n=4, position_noise=0.0005, normal_noise_deg=1.0)
    cond = pair_conditions(g.contacts)
    key = [bin_index(v, t.mins[i], t.widths[i], t.bins[i]) for i, v in enumerate((f.dmax, f.dmin("exact"), f.alpha))]
    want = 0
    for d, a in zip(cond.distance, cond.angle):
        lo_d, hi_d, lo_a, hi_a = query_limits(d, a, tolerance.distance, tolerance.angle)
        a0 = bin_index(lo_d, t.mins[0], t.widths[0], t.bins[0])
        b1 = bin_index(hi_d, t.mins[1], t.widths[1], t.bins[1])
        c0 = bin_index(lo_a - t.alpha_width, t.mins[2], t.widths[2], t.bins[2])
        c1 = bin_index(hi_a, t.mins[2], t.widths[2], t.bins[2])
        want += int(np.sum((key[0] >= a0) & (key[1] <= b1) & (key[2] >= c0) & (key[2] <= c1)))
    assert bin_sweep.candidate_count(t, cond, tolerance) == want


def test_scaling_meshes_are_closed_rocks_of_20_f2_facets():
    scaling = run_all.load("scaling")
    for f in (2, 3, 5):
        mesh = scaling.rock_mesh(f)
        assert len(mesh.faces) == 20 * f * f
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
        assert np.isclose(np.ptp(mesh.vertices, axis=0).max(), 0.12)
    assert np.array_equal(scaling.rock_mesh(3).vertices, scaling.rock_mesh(3).vertices)


@pytest.mark.parametrize("name", ["banana", "carton"])
def test_baseline_contact_cost_is_chi2_at_the_true_pose(name):
    """The baselines' likelihood finds each contact's own facet: χ² of 12 dof at the truth."""
    from contactpose import peers as baselines
    from contactpose.model.object_model import ObjectModel
    from contactpose.sim import grasps as simulate
    from contactpose.sim import objects

    model = ObjectModel.from_mesh(objects.load(name))
    surface = baselines.sample_surface(model)
    costs = []
    for seed in range(60):
        g = simulate.grasp(model, np.random.default_rng(seed), n=4, position_noise=0.0005, normal_noise_deg=1.0)
        costs.append(baselines.contact_cost(model, surface, g.contacts, g.pose[None], 0.0005, 1.0)[0])
    assert 8 < np.median(costs) < 14 and max(costs) < 45   # χ²(12): median 11.3, 99.9 % 32.9


def test_scaling_series_and_icp_improve_on_a_close_prior():
    from contactpose import peers as baselines
    from contactpose.geometry import metrics
    from contactpose.model.object_model import ObjectModel
    from contactpose.sim import grasps as simulate
    from contactpose.sim import objects
    from contactpose.types import PosePrior

    model = ObjectModel.from_mesh(objects.load("banana"))
    surface = baselines.sample_surface(model)
    target = baselines.icp_target(surface, 5000)
    rng = np.random.default_rng(1)
    g = simulate.grasp(model, rng, n=4, position_noise=0.0005, normal_noise_deg=1.0)
    start = g.pose.copy()
    start[:3, 3] += 0.004
    noise = dict(position_noise=0.0005, normal_noise_deg=1.0)
    icp = baselines.icp(model, surface, target, g.contacts, start, **noise)
    ss = baselines.scaling_series(model, surface, g.contacts, rng, prior=PosePrior(start, 3.0, 0.004), initial=500,
                                  per_ball=16, max_particles=500, **noise)
    for r in (icp, ss):
        assert metrics.translation_error(r.pose, g.pose) < 0.004
        assert r.cost < baselines.contact_cost(model, surface, g.contacts, start[None], **noise)[0]


def test_outlier_fingers_quick_writes_prefixed_files_and_names_the_bad_finger(tmp_path):
    """experiments/outlier_fingers.py --quick: prefixed files beside the discrimination
    results (none of that part's names), CSV identical across runs, the planted finger found."""
    outliers = run_all.load("outlier_fingers")
    for out in ("a", "b"):
        assert outliers.main(["--quick", "--fresh", "--workers", "0", "--out", str(tmp_path / out)]) == 0
    a, b = tmp_path / "a" / "discrimination", tmp_path / "b" / "discrimination"
    assert (a / "outliers_grasps.csv").read_bytes() == (b / "outliers_grasps.csv").read_bytes()
    assert sorted(p.name for p in a.iterdir() if p.is_file()) == sorted(
        ["outliers_grasps.csv", "outliers_timings.csv", "outliers_summary.csv", "outliers_config.json",
         "outliers_run.json", "outliers.png", "outliers.pdf"])
    c = sweep.read_columns(a / "outliers_grasps.csv")
    assert np.all(c["true_found"] == 1) and np.mean(c["named"]) >= 0.5


def test_sequential_counts_the_reseeding_touches():
    """The summary's reseed line: touches whose reseed count grew, per sequence, and their time."""
    reseeded = run_all.load("sequential").reseeded
    counts = {0: [0, 1, 1, 2], 1: [0, 0, 0, 0], 2: [1, 1, 1, 1]}
    rows = [dict(method=m, sequence=q, touch=k + 1, ms=100.0 * (1 + n) if m == "track" else 1.0,
                 reseeds=n if m == "track" else "")
            for q, ns in counts.items() for k, n in enumerate(ns) for m in ("track", "batch")]
    assert reseeded(rows) == ["", "track: 3 reseeds in 2 of 3 sequences (12 touches), 200 ms per reseeding touch "
                                  "(median)."]
    assert reseeded([dict(r, reseeds="") for r in rows]) == []


def test_sequential_smoke(tmp_path):
    """experiments/sequential.py on the rock: one short tracking sequence (a row per touch and
    method, finite errors for the track, the summary table; a second run of one method keeps
    the others' rows), two active-localization sequences per strategy, two coverage
    sequences, and one speed sequence."""
    main = run_all.load("sequential").main
    assert main(["rock", "--sequences", "1", "--steps", "3", "--out", str(tmp_path)]) == 0
    rows = sweep.read_rows(tmp_path / "steps.csv")
    assert len(rows) == 12 and {r["method"] for r in rows} == {"track", "batch", "relocalize", "pf"}
    track = [r for r in rows if r["method"] == "track"]
    assert all(np.isfinite(float(r["rot_deg"])) for r in track)
    # the rock has no symmetry: the errors modulo symmetry are the raw ones
    assert all(float(r["rot_sym_deg"]) == float(r["rot_deg"]) and float(r["trans_sym_mm"]) == float(r["trans_mm"])
               for r in track)
    assert "| track |" in (tmp_path / "summary.md").read_text()
    assert all(int(r["reseeds"]) >= 0 for r in track) and all(r["reseeds"] == "" for r in rows if r["method"] != "track")
    assert main(["rock", "--sequences", "1", "--steps", "3", "--methods", "pf", "--out", str(tmp_path)]) == 0
    again = sweep.read_rows(tmp_path / "steps.csv")
    timeless = lambda table: sorted(str({k: v for k, v in r.items() if k != "ms"}) for r in table)
    assert timeless(again) == timeless(rows)  # the same sequences: the pf rows come back
    assert main(["rock", "--part", "active", "--sequences", "2", "--out", str(tmp_path)]) == 0
    active = sweep.read_rows(tmp_path / "active.csv")
    assert len(active) == 4 and all(2 <= float(r["touches_single"]) <= 16 for r in active)
    assert "| rock | suggested | 2 |" in (tmp_path / "active.md").read_text()
    assert main(["rock", "--part", "coverage", "--sequences", "2", "--steps", "2", "--out", str(tmp_path)]) == 0
    cover = sweep.read_rows(tmp_path / "coverage.csv")
    assert [r["facets"] for r in cover] == ["given", "associated"] * 2
    assert all(0.0 <= float(r["level"]) <= 1.0 and float(r["sd_axis0_deg"]) > 0 for r in cover)
    assert "| rock | associated | 2 |" in (tmp_path / "coverage.md").read_text()
    assert main(["rock", "--part", "speed", "--sequences", "1", "--steps", "2", "--out", str(tmp_path)]) == 0
    speed = sweep.read_rows(tmp_path / "speed.csv")
    assert len(speed) == 2 and all(float(r["ms"]) > 0 for r in speed)


def test_memory_particle_filter_beats_dead_reckoning_on_a_held_object():
    """A held rock, 15 touches of 2 noisy contacts after known hand motions with a slip of 1°
    and 1 % of the diameter per touch: the particle filter (memory of 4 contacts) stays far
    closer to the truth than the hand motions alone, whose error is the slip's random walk."""
    from contactpose import peers as baselines
    from contactpose.geometry import metrics
    from contactpose.model.object_model import ObjectModel
    from contactpose.sim import grasps as simulate
    from contactpose.sim import objects
    from tests.tracking.test_track import _motion

    model = ObjectModel.from_mesh(objects.load("rock"))
    d = model.diameter
    surface = baselines.sample_surface(model, neighbour_radius=None)
    noise = dict(position_noise=0.0025 * d, normal_noise_deg=1.0)
    filtered, reckoned = [], []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        g = simulate.grasp(model, rng, n=4, **noise)
        pf = baselines.MemoryParticleFilter(model, surface, g.pose[None], g.contacts, rng, particles=500, **noise)
        X, dead = g.pose, g.pose
        for _ in range(15):
            delta = _motion(rng, 10.0, 0.05 * d)
            X, dead = delta @ X @ _motion(rng, 1.0, 0.01 * d), delta @ dead
            touch = simulate.grasp(model, rng, n=2, pose=X, **noise).contacts
            filtered.append(metrics.rotation_error_deg(pf.add(touch, (delta, 1.0, 0.01 * d)), X))
            reckoned.append(metrics.rotation_error_deg(dead, X))
    assert np.median(filtered) < 0.5 * np.median(reckoned)
    assert np.median(filtered) < 3.0


def test_ceiling_smoke(tmp_path):
    """experiments/ceiling.py on the rock, two grasps per radius: a row each, the ceiling 0 where
    a wrong placement fits better and one over the tying placements otherwise, posteriors in
    [0, 1], a finite bound, and the summary's row; a run on the carton then keeps the rock's rows."""
    assert run_all.load("ceiling").main(["rock", "--grasps", "2", "--out", str(tmp_path)]) == 0
    rows = sweep.read_rows(tmp_path / "grasps.csv")
    assert len(rows) == 4 and {float(r["radius_frac"]) for r in rows} == {0.02, 0.05}
    for r in rows:
        beaten = float(r["wrong_chi2"]) < float(r["true_chi2"]) - 1e-6
        assert float(r["ceiling"]) == (0.0 if beaten else 1.0 / (1 + int(r["ties"])))
        assert 0.0 <= float(r["p_true"]) <= 1.0
        assert np.isfinite(float(r["bound_rot_deg"])) and float(r["true_chi2"]) >= 0.0
    assert "| rock | 2 % | 2 (all) |" in (tmp_path / "summary.md").read_text()
    assert run_all.load("ceiling").main(["carton", "--grasps", "1", "--out", str(tmp_path)]) == 0
    again = sweep.read_rows(tmp_path / "grasps.csv")  # the rock's rows kept, the carton's added
    assert [r for r in again if r["object"] == "rock"] == rows and sum(r["object"] == "carton" for r in again) == 2
    assert "| rock | 2 % | 2 (all) |" in (tmp_path / "summary.md").read_text()
