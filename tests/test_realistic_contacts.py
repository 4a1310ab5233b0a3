"""experiments/realistic_contacts.py: the exact "found" test and the incident facets on a small
built-in model; the quick run (YCB model builds, minutes) is marked slow."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from contactpose.geometry import metrics
from contactpose.geometry.kernels import point_triangle_distance
from contactpose.harness import sweep
from contactpose.model.object_model import ObjectModel, merged_mesh
from contactpose.model.symmetry import symmetry
from contactpose.sim import fingertip, objects
from contactpose.sim import grasps as simulate

EXPERIMENTS = Path(__file__).resolve().parent.parent / "experiments"
sys.path.insert(0, str(EXPERIMENTS))
import run_all  # noqa: E402

rc = run_all.load("realistic_contacts")
ts = run_all.load("truth_stages")


def small_setup(name="banana"):
    model = ObjectModel.from_mesh(objects.load(name))
    mesh = merged_mesh(model.vertices, model.faces)
    p = model.surface_points
    vertices = np.asarray(mesh.vertices)
    return rc.Setup(model, vertices, np.asarray(mesh.faces), None, None, (p.mean(axis=0), p.T @ p / len(p)),
                    np.arange(model.num_facets), metrics.hull_points(vertices), symmetry(model))


def test_score_gives_the_best_poses_mssd_over_every_vertex():
    """The MSSD column of the 53-facet banana (no symmetry): the largest displacement of any
    vertex between the best pose and the truth, by brute force; no pose, no MSSD."""
    s = small_setup()
    rng = np.random.default_rng(4)
    cfg = {"found_adds_frac": 0.05, "top1_adds_frac": 0.10}
    truth = simulate.random_pose(rng, max_translation=0.05)
    for _ in range(5):
        best = simulate.random_pose(rng, max_translation=0.05)
        moved = s.vertices @ (best[:3, :3] - truth[:3, :3]).T + (best[:3, 3] - truth[:3, 3])
        row = rc.score(s, np.stack([best, truth]), truth, cfg)
        assert row["mssd_mm"] == pytest.approx(1e3 * np.linalg.norm(moved, axis=1).max(), rel=1e-12)
    assert rc.score(s, np.zeros((0, 4, 4)), truth, cfg)["mssd_mm"] is None


def test_the_papers_workflow_decimates_in_the_objects_frame():
    """objects.decimate (the paper's 512 -> 53 facets, here to 100): about as many facets as
    asked, every kept vertex within 1 % of the diameter of the full surface (the same frame)."""
    full = objects.load("banana512")
    small = objects.decimate(full, 100)
    assert 90 <= len(small.faces) <= 100
    D = ObjectModel.from_mesh(full).diameter
    triangles = np.asarray(full.vertices)[np.asarray(full.faces)]
    gap = [point_triangle_distance(np.repeat(v[None], len(triangles), 0), triangles).min() for v in small.vertices]
    assert max(gap) < 0.01 * D


def test_embedding_distance_is_the_rms_displacement():
    s = small_setup()
    rng = np.random.default_rng(0)
    poses = np.stack([simulate.random_pose(rng, max_translation=0.05) for _ in range(20)])
    p = s.model.surface_points
    want = metrics.rms_displacement(poses, poses[0], p.mean(axis=0), p.T @ p / len(p))
    got = np.linalg.norm(rc.embed(s, poses) - rc.embed(s, poses[0]), axis=1)
    assert np.allclose(got, want, atol=1e-12)


def test_any_within_equals_adds_pose_by_pose():
    s = small_setup()
    rng = np.random.default_rng(1)
    truth = simulate.random_pose(rng, max_translation=0.05)
    D = s.model.diameter
    for k in range(30):
        # poses scattered around the truth, some within the limit, most not
        spread = rng.uniform(0.01, 0.5)
        poses = np.stack([truth @ simulate.pose_from(rng.normal(0, spread, 3), rng.normal(0, 0.2 * spread * D, 3))
                          for _ in range(200)])
        for frac in (0.02, 0.05, 0.1):
            limit = frac * D
            brute = any(metrics.adds(T, truth, s.model.surface_points, s.model.surface_tree) < limit for T in poses)
            found, _, exact = rc.any_within(s, poses, truth, limit, max_anchors=10_000)
            assert exact and found == brute, (k, frac)


def test_incident_facets_of_edges_and_vertices():
    s = small_setup("box")
    rng = np.random.default_rng(2)
    got = fingertip.approach(s.vertices, s.faces, rng, 400, 0.2 * s.model.diameter, cone_deg=60.0)
    kinds = set()
    for f, p, k in zip(got.facets, got.points, got.features):
        inc = rc.incident_facets(s, f, p, str(k))
        assert f in inc
        if k == fingertip.FACE:
            assert list(inc) == [f]
        else:  # two or more triangles, each holding the touched point
            d = point_triangle_distance(np.repeat(p[None], len(inc), axis=0), s.model.triangles[inc])
            assert len(inc) >= 2 and d.max() < 1e-9 * s.model.diameter, (k, d)
        kinds.add(str(k))
    assert {"edge", "vertex"} <= kinds


def test_placement_rank_is_the_first_pose_within_adds():
    """truth_stages.placement_rank: the first ranked pose within the ADD-S limit, by brute force."""
    s = small_setup()
    rng = np.random.default_rng(4)
    truth = simulate.random_pose(rng, max_translation=0.05)
    D = s.model.diameter
    for k in range(20):
        spread = rng.uniform(0.02, 0.6)
        poses = np.stack([truth @ simulate.pose_from(rng.normal(0, spread, 3), rng.normal(0, 0.2 * spread * D, 3))
                          for _ in range(60)])
        adds = np.array([metrics.adds(T, truth, s.model.surface_points, s.model.surface_tree) for T in poses])
        within = np.flatnonzero(adds < 0.05 * D)
        assert ts.placement_rank(s, poses, truth, 0.05 * D) == (int(within[0]) if len(within) else None), k


@pytest.mark.slow
def test_quick_run_writes_every_output(tmp_path):
    assert rc.main(["--quick", "--out", str(tmp_path)]) == 0
    out = tmp_path / "realistic_contacts"
    for f in ("grasps.csv", "timings.csv", "summary.csv", "summary.md", "models.csv", "config.json", "run.json",
              "realistic_contacts.png", "realistic_contacts.pdf"):
        assert (out / f).stat().st_size > 0, f
    rows = sweep.read_rows(out / "grasps.csv")
    assert {r["method"] for r in rows} == set(rc.METHODS)
    paper = [r for r in rows if r["method"] == "paper"]
    assert paper and all(int(r["paper_model_facets"]) <= 500 for r in paper)  # the YCB meshes decimated
    assert all(r["mssd_mm"] != "" for r in rows if r["ran"] == "1" and r["rot_err_deg"] != "")
    assert not any(k.startswith("time_") for k in rows[0])
    (out / "realistic_contacts.png").unlink()
    assert rc.main(["--quick", "--plot-only", "--out", str(tmp_path)]) == 0
    assert (out / "realistic_contacts.png").exists()
    # a run against itself: every figure of the side-by-side table is unchanged
    assert run_all.load("before_after").main([str(out), str(out)]) == 0
    table = [line for line in (out / "before_after.md").read_text().splitlines() if "→" in line]
    assert table and all(len(set(cell.split(" → "))) == 1 for line in table for cell in line.split(" | ")[2:-1]
                         if "→" in cell)


def test_the_methods_legend_says_not_run_and_how_many_ran():
    """A method that ran on no grasp is "not run" with its rows' reason, never a line at 0 %;
    one that ran on some says how many of the grasps it was given."""
    label = rc.method_label
    assert label("fast", [{"n": 100, "ran": 100}, {"n": 100, "ran": 100}]) == "fast (200 grasps)"
    assert label("paper", [{"n": 20, "ran": 8}, {"n": 20, "ran": 20}]) == "paper (40 grasps, 28 ran)"
    note = "not run: CHSEL not installed (pip install contactpose[peers])"
    assert label("chsel", [{"n": 20, "ran": 0}] * 4, note) == "chsel: not run (CHSEL not installed)"
    assert label("paper", [{"n": 20, "ran": 0}]) == "paper: not run"


def test_the_expected_time_counts_only_the_methods_that_run(tmp_path, monkeypatch):
    """expected_minutes: each chosen method's seconds a grasp times its grasps, summed by hand;
    CHSEL only when installed; spread over the workers (0: one, in process); no build counted
    for a model already cached (here: none cached, every object built)."""
    e = {"build_minutes": 2.0, "check_seconds": 0.5,
         "seconds": {"fast": 3.0, "paper": 2.0, "icp-multistart": 0.1, "scaling-series": 0.8,
                     "ss-published": 40.0, "ss-published-timed": 3.0, "chsel": 200.0}}
    cfg = {"objects": ["ycb:013_apple", "ycb:025_mug"], "radius_fracs": [0.0, 0.02], "seeds": 20,
           "paper_grasps": 5, "baseline_grasps": 20, "published_grasps": 5, "chsel_grasps": 20,
           "methods": ["chsel"], "estimate": e}
    monkeypatch.setattr(rc.chsel_peer, "available", lambda: "0.2.1")
    builds, grasps, missing = rc.expected_minutes(cfg, tmp_path, 0)
    assert (missing, builds) == (2, 4.0)
    assert grasps == pytest.approx(2 * 2 * 20 * 200.0 / 60)
    both = {**cfg, "methods": ["fast", "paper", "chsel"]}
    per_cell = 20 * (3.0 + 0.5) + 5 * 2.0 + 20 * 200.0
    assert rc.expected_minutes(both, tmp_path, 2)[1] == pytest.approx(4 * per_cell / 60 / 2)
    monkeypatch.setattr(rc.chsel_peer, "available", lambda: None)
    assert rc.expected_minutes(both, tmp_path, 2)[1] == pytest.approx(4 * (20 * 3.5 + 5 * 2.0) / 60 / 2)


def test_a_run_of_some_methods_is_checked_before_it_starts(tmp_path, capsys):
    """--set methods=[...]: unknown names, the timed series without the default method, and
    seeds beyond every chosen method's grasps exit 2 with one line; a valid subset passes."""
    cfg = {"methods": list(rc.METHODS), "seeds": 100, "paper_grasps": 20, "baseline_grasps": 100,
           "published_grasps": 20, "chsel_grasps": 20}
    assert rc.methods_problem(cfg) is None
    assert rc.methods_problem({**cfg, "methods": ["chsel"], "seeds": 20}) is None
    assert "lower seeds to 20" in rc.methods_problem({**cfg, "methods": ["chsel"]})
    assert "needs \"fast\"" in rc.methods_problem({**cfg, "methods": ["ss-published-timed"], "seeds": 20})
    assert "'icp'" in rc.methods_problem({**cfg, "methods": ["icp"]})
    assert rc.methods_problem({**cfg, "methods": ["chsel"], "seeds": [3, 19]}) is None
    assert "keep seeds below 20" in rc.methods_problem({**cfg, "methods": ["chsel"], "seeds": [3, 20]})
    for bad in (0, [], [2, 2], [-1], [1.5], "5"):
        assert "seeds" in rc.methods_problem({**cfg, "seeds": bad}), bad
    argv = ["--quick", "--out", str(tmp_path), "--set", 'methods=["chsel"]']
    assert rc.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lower seeds to 1" in err[0]
    assert not (tmp_path / "realistic_contacts" / "grasps.csv").exists()


def test_a_list_of_seeds_draws_the_same_grasps_as_a_count():
    """seeds=[3, 4] extends a run of seeds=3: its cells are the grasps 3 and 4 of seeds=5,
    drawn from the same seed sequences."""
    cfg = {"radius_fracs": [0.0, 0.02], "base_seed": 7}
    def draws(seeds):
        cells = rc.make_sweep({**cfg, "seeds": seeds}, "ycb:011_banana", "cache").cells()
        return {(c.settings["radius_frac"], c.seed): c.seed_sequence(cfg["base_seed"], ("object",)).spawn_key
                for c in cells}
    some, all_five = draws([3, 4]), draws(5)
    assert sorted({seed for _, seed in some}) == [3, 4]
    assert some == {k: v for k, v in all_five.items() if k[1] >= 3}
    assert rc.grasps_of({"seeds": [3, 4, 30], "paper_grasps": 20}, "paper") == 2


def test_runs_over_the_same_grasps_merge_and_others_are_refused(tmp_path):
    """merge_runs: a pass of other methods over the same draws joins; one that drew other grasps,
    ran one of this run's methods, or lacks an object is refused with one line."""
    cfg = {**sweep.load_config(rc.NAME, quick=True), "methods": ["fast"], "merge_runs": [str(tmp_path)]}

    def other_run(**changes):
        for name in cfg["objects"]:
            record = rc.make_sweep({**cfg, **changes}, name, tmp_path).config_record()
            d = rc.merge_dir(name, tmp_path)
            d.mkdir(parents=True, exist_ok=True)
            (d / sweep.CONFIG_JSON).write_text(json.dumps(record))

    assert "no run of" in rc.merge_problem(cfg, tmp_path)
    other_run(methods=["chsel"], seeds=1, chsel_grasps=1)
    assert rc.merge_problem(cfg, tmp_path) is None
    other_run(methods=["chsel", "fast"])
    assert "also ran fast" in rc.merge_problem(cfg, tmp_path)
    other_run(methods=["chsel"], normal_noise_deg=2.0)
    assert "(normal_noise_deg differ)" in rc.merge_problem(cfg, tmp_path)
    other_run(methods=["chsel"], base_seed=7)
    assert "drew other grasps" in rc.merge_problem(cfg, tmp_path)


def test_a_run_of_peers_alone_gets_its_summary_and_figure(tmp_path):
    """A pass of CHSEL alone (no rows of the default method, so no hypothesis counts) is
    summarized and drawn after each object: its rows are CHSEL's committed banana grasps, and
    each radius's strict share and AR_MSSD equal those worked out from the rows directly."""
    source = Path(__file__).resolve().parent.parent / "results" / "realistic_contacts" / "resume_chsel" / "011_banana"
    (tmp_path / "timings.csv").write_bytes((source / "timings.csv").read_bytes())
    rc.plot(tmp_path)
    assert (tmp_path / "realistic_contacts.png").stat().st_size > 0
    c = sweep.read_columns(tmp_path / "timings.csv")
    rows = [r for r in sweep.read_rows(tmp_path / "summary.csv") if r["split"] == "all"]
    assert {r["method"] for r in rows} == {"chsel"} and len(rows) == len(set(c["radius_frac"]))
    for r in rows:
        ran = (c["radius_frac"] == float(r["radius_frac"])) & (c["ran"] == 1)
        assert int(r["ran"]) == ran.sum()
        assert float(r["top1_strict"]) == pytest.approx(np.mean(c["top1_strict"][ran]))
        assert float(r["ar_mssd"]) == pytest.approx(np.mean([np.mean(c["mssd_mm"][ran] < f * c["diameter_mm"][0])
                                                             for f in np.arange(0.05, 0.51, 0.05)]))


def test_a_republication_keeps_the_record_of_the_run_that_made_the_rows(tmp_path):
    """publish with no grasp run in the call (a pass merged later): run.json keeps the earlier
    run's commit, machine and seconds and adds the call's own as "republished"; models.csv keeps
    the earlier build row though the cache's meta changed since (another pass rebuilt the
    model); a merged pass's run.json is carried. With the object run in the call, both are new."""
    out, other = tmp_path / "realistic_contacts", tmp_path / "other"
    (other / rc.NAME).mkdir(parents=True)
    (other / rc.NAME / "run.json").write_text(json.dumps({"seconds": 8.1}))
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"experiment": rc.NAME, "seconds": 4324.9, "workers": 2,
                                              "library": {"commit": "a" * 40}, "machine": {"cpu": "Xeon"}}))
    sweep.write_rows(out / "models.csv", [{"object": "ycb:011_banana", "build_s": 9.0, "commit": "a" * 12}])
    meta = {"object": "ycb:011_banana", "build_s": 3.0, "build_stage_s": {}, "warnings": [],
            "library": {"commit": "b" * 40}}
    cfg = {"merge_runs": [str(other)]}

    def publish(ran_here):
        rc.publish(out, cfg, [], [meta], 17.8, workers=0, ran_here=ran_here, earlier=rc.earlier_publication(out))
        return json.loads((out / "run.json").read_text()), sweep.read_rows(out / "models.csv")

    run, models = publish(set())
    assert (run["seconds"], run["workers"], run["library"], run["machine"]) == (4324.9, 2, {"commit": "a" * 40},
                                                                               {"cpu": "Xeon"})
    assert run["republished"]["library"] == rc.library_version()
    assert run["merged_runs"] == {str(other): {"seconds": 8.1}} and run["objects_done"] == ["ycb:011_banana"]
    assert [(m["build_s"], m["commit"]) for m in models] == [("9.0", "a" * 12)]
    run, models = publish({"ycb:011_banana"})
    assert (run["seconds"], run["workers"], "republished" in run) == (17.8, 0, False)
    assert run["library"] == rc.library_version() and run["machine"] == sweep.machine_description()
    assert [(m["build_s"], m["commit"]) for m in models] == [("3.0", "b" * 12)]


def test_the_methods_are_compared_on_the_grasps_every_method_was_given(tmp_path):
    """The banana's rows of both committed passes (ours on 100 grasps per radius, the peers on
    the first 20): the methods' table and panel count every method on those 20 per radius, and
    their shares equal those worked out from the rows of those grasps directly."""
    results = Path(__file__).resolve().parent.parent / "results" / "realistic_contacts"
    rows = [r for d in ("resume", "resume_chsel") for r in sweep.read_rows(results / d / "011_banana" / "timings.csv")]
    sweep.write_rows(tmp_path / "timings.csv", rows)
    rc.plot(tmp_path)
    c = sweep.read_columns(tmp_path / "timings.csv")
    summary = [r for r in sweep.read_rows(tmp_path / "summary.csv") if r["split"] == "same grasps"]
    given = set(c["method"])  # the committed passes predate the default method's variants
    assert given <= set(rc.METHODS)
    assert {r["method"] for r in summary} == given and len(summary) == 4 * len(given)
    for r in summary:
        sel = (c["method"] == r["method"]) & (c["radius_frac"] == float(r["radius_frac"])) & (c["seed"] < 20)
        ran = sel & (c["ran"] == 1)
        assert (int(r["grasps"]), int(r["ran"])) == (20, ran.sum())
        assert float(r["top1_strict"]) == pytest.approx(np.mean(c["top1_strict"][ran]))
    table = (tmp_path / "summary.md").read_text().split("## Methods on the same grasps")[1]
    fast = [line for line in table.splitlines() if line.startswith("| ") and " | fast | " in line]
    assert len(fast) == 4 and all(" / 20 | " in line for line in fast)
