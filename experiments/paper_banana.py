"""The paper's §5 experiment on the banana: timings beside the paper's, and the success rate.

Protocol (Haidacher & Hirzinger 2003, §5): the 53-facet banana, rolled 5.7° about x and
shifted 10 mm in x, y and z; four fingers at the centroids of four random distinct facets
(no measurement noise; the search runs with the tolerances of 0.5 mm and 1° sensor noise);
25 runs. Both methods see the same 25 grasps: ``fast`` (default) and ``paper`` (the
published method: vertex-only Δmin, node-by-node tree, LM on eq. (7) from the identity).
Offline: model build time (pair characteristics + hash table), median of ``build_repeats``
builds per cell, with exact and with the paper's vertex-only bounds.

Writes results/paper_banana/: results.csv, timings.csv, config.json, run.json,
table.md (the timing table with both machines), paper_banana.png/.pdf.

    .venv/bin/python experiments/paper_banana.py [--quick] [--workers N] [--scheduler tcp://HOST:PORT]
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np

from contactpose.geometry import metrics
from contactpose.harness import sweep
from contactpose.localize import localize, warm_up
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

NAME = "paper_banana"

#: The paper's reported figures (§5), milliseconds, and its machine.
PAPER = {"features": 21.0, "table": 19.0, "offline": 40.0, "sij": 24.0, "tree_mean": 92.0, "tree_min": 16.0,
         "tree_max": 324.0, "total_mean": 116.0}
PAPER_MACHINE = "Sun Ultra II, one 750 MHz processor (as reported in the paper)"
GRID = [{"stage": "online", "method": "fast", "bounds": "exact"},
        {"stage": "online", "method": "paper", "bounds": "exact"},
        {"stage": "offline", "method": "", "bounds": "exact"},
        {"stage": "offline", "method": "", "bounds": "paper"}]


def protocol_pose(cfg):
    """The §5 pose: roll about x, the same shift in x, y and z."""
    return simulate.pose_from((np.radians(cfg["roll_deg"]), 0.0, 0.0), (cfg["shift_m"],) * 3)


def warmed_model(cfg):
    """The banana model, after a few untimed localizations (numba loads its kernels on first call;
    localize.warm_up also loads the in-facet bound's)."""
    model = ObjectModel.from_mesh(objects.load(cfg["object"]))
    rng = np.random.default_rng(0)
    for _ in range(cfg["warmup"]):
        g = simulate.grasp(model, rng, n=cfg["fingers"], pose=protocol_pose(cfg), where="centroid")
        for method in ("fast", "paper"):
            warm_up(model, g.contacts, position_noise=cfg["position_noise"],
                    normal_noise_deg=cfg["normal_noise_deg"], method=method)
    return model


def task(settings, rng, *, cfg):
    """One run: an online localization of one protocol grasp, or an offline build timing."""
    model = sweep.cached(("paper_banana", cfg["object"], cfg["warmup"]), lambda: warmed_model(cfg))
    if settings["stage"] == "offline":
        mesh = objects.load(cfg["object"])
        builds = [ObjectModel.from_mesh(mesh, bounds=settings["bounds"]).build_seconds
                  for _ in range(cfg["build_repeats"])]
        med = {k: float(np.median([b[k] for b in builds])) for k in ("features", "table", "total")}
        return {"facets": model.num_facets, "time_features_ms": 1e3 * med["features"],
                "time_table_ms": 1e3 * med["table"], "time_build_ms": 1e3 * med["total"]}
    g = simulate.grasp(model, rng, n=cfg["fingers"], pose=protocol_pose(cfg), where="centroid")
    r = localize(model, g.contacts, position_noise=cfg["position_noise"], normal_noise_deg=cfg["normal_noise_deg"],
                 method=settings["method"])
    facets = r.hypotheses.arrays.facets
    best = r.best
    return {
        "true_facets": " ".join(map(str, g.facets)), "status": r.status, "hypotheses": r.num_hypotheses,
        "true_found": bool(np.any(np.all(facets == g.facets, axis=1))) if len(facets) else False,
        "top1_facets": bool(best is not None and np.array_equal(best.facets, g.facets)),
        "success": bool(best is not None and metrics.pose_success(best.pose, g.pose, model.diameter)),
        "rot_err_deg": float(metrics.rotation_error_deg(best.pose, g.pose)) if best else None,
        "trans_err_mm": 1e3 * float(metrics.translation_error(best.pose, g.pose)) if best else None,
        **{f"time_{k}_ms": 1e3 * r.timing[k] for k in ("pairs", "tree", "pose", "rank", "total")},
    }


def make_sweep(cfg):
    return sweep.Sweep(NAME, functools.partial(task, cfg=cfg), GRID, seeds=cfg["runs"], base_seed=cfg["base_seed"],
                       seed_axes=(), config=cfg)


# --------------------------------------------------------------------------- table and figure

def summarize(out_dir):
    """Timing and success summary from timings.csv: {key: value}, milliseconds."""
    c = sweep.read_columns(Path(out_dir) / sweep.TIMINGS_CSV)
    s = {}
    for method in ("fast", "paper"):
        sel = (c["stage"] == "online") & (c["method"] == method)
        if not sel.any():
            continue
        tree = c["time_tree_ms"][sel] + c["time_pose_ms"][sel] + c["time_rank_ms"][sel]
        s[method] = {"runs": int(sel.sum()), "sij": float(np.mean(c["time_pairs_ms"][sel])),
                     "tree_mean": float(np.mean(tree)), "tree_min": float(np.min(tree)), "tree_max": float(np.max(tree)),
                     "total_mean": float(np.mean(c["time_total_ms"][sel])),
                     "total_median": float(np.median(c["time_total_ms"][sel])),
                     "hypotheses_mean": float(np.mean(c["hypotheses"][sel])),
                     "true_found": float(np.mean(c["true_found"][sel])), "success": float(np.mean(c["success"][sel])),
                     "totals": c["time_total_ms"][sel]}
    for bounds in ("paper", "exact"):
        sel = (c["stage"] == "offline") & (c["bounds"] == bounds)
        if sel.any():
            s[f"offline_{bounds}"] = {k: float(np.median(c[f"time_{k}_ms"][sel])) for k in ("features", "table", "build")}
    return s


def table_markdown(s, machine):
    """The timing table (markdown): the paper's numbers beside ours, both machines stated."""
    def f(x):
        return "–" if x is None else (f"{x:.3g}" if x < 100 else f"{x:.0f}")

    fast, paper = s.get("fast", {}), s.get("paper", {})
    off_p, off_e = s.get("offline_paper", {}), s.get("offline_exact", {})
    rows = [
        ("offline: pair characteristics (ms)", PAPER["features"], off_p.get("features"), off_e.get("features")),
        ("offline: hash table (ms)", PAPER["table"], off_p.get("table"), off_e.get("table")),
        ("online: S_ij (ms, mean)", PAPER["sij"], paper.get("sij"), fast.get("sij")),
        ("online: tree + tests (ms, mean)", PAPER["tree_mean"], paper.get("tree_mean"), fast.get("tree_mean")),
        ("online: tree + tests (ms, min)", PAPER["tree_min"], paper.get("tree_min"), fast.get("tree_min")),
        ("online: tree + tests (ms, max)", PAPER["tree_max"], paper.get("tree_max"), fast.get("tree_max")),
        ("online: total (ms, mean)", PAPER["total_mean"], paper.get("total_mean"), fast.get("total_mean")),
        ("hypotheses (mean)", None, paper.get("hypotheses_mean"), fast.get("hypotheses_mean")),
        ("true tuple among hypotheses", None, paper.get("true_found"), fast.get("true_found")),
        ("top-1 success (rot < 5°, trans < 5 % diam.)", None, paper.get("success"), fast.get("success")),
    ]
    ours = (f"{machine.get('cpu', '?')}, {machine.get('cores', '?')} cores, {machine.get('memory_gib', '?')} GiB, "
            f"Python {machine.get('python', '?')}, numpy {machine.get('numpy', '?')}; one Dask worker process, "
            "machine shared with other jobs")
    lines = [f"# Banana, §5 protocol: {fast.get('runs', paper.get('runs', 0))} runs", "",
             f"* Paper: {PAPER_MACHINE}.", f"* Ours: {ours}.",
             "* Ours, offline: `bounds=\"paper\"` is the paper's vertex-only Δmin; `exact` the exact triangle "
             "distance the default method needs. Online: `method=\"paper\"` and `method=\"fast\"` on the same grasps.",
             "* 'tree + tests' is our tree + pose fit + ranking, the paper's tree plus hypothesis tests.", "",
             "| quantity | paper (Sun Ultra II) | ours, method=paper | ours, method=fast |", "|---|---:|---:|---:|"]
    for name, ref, p, q in rows:
        if name.startswith("offline"):
            lines.append(f"| {name} | {f(ref)} | {f(p)} (bounds=paper) | {f(q)} (bounds=exact) |")
        else:
            lines.append(f"| {name} | {f(ref)} | {f(p)} | {f(q)} |")
    return "\n".join(lines) + "\n"


def plot(out_dir):
    """table.md and paper_banana.png/.pdf from the CSV (machine line from run.json)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    s = summarize(out)
    machine = sweep.read_run(out).get("machine", {})
    (out / "table.md").write_text(table_markdown(s, machine))
    with plt.rc_context(sweep.PAPER_RC):
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(sweep.PAGE_WIDTH, 2.6), gridspec_kw={"width_ratios": [1.6, 1]})
        labels = ["features", "table", "S_ij", "tree+tests\n(mean)", "total\n(mean)"]
        ref = [PAPER["features"], PAPER["table"], PAPER["sij"], PAPER["tree_mean"], PAPER["total_mean"]]
        series = [("paper, Sun Ultra II (reported)", ref, "0.55")]
        for method, bounds, color in (("paper", "paper", "tab:orange"), ("fast", "exact", "tab:blue")):
            m, o = s.get(method, {}), s.get(f"offline_{bounds}", {})
            series.append((f"ours, method={method}", [o.get("features", np.nan), o.get("table", np.nan), m.get("sij", np.nan),
                                                      m.get("tree_mean", np.nan), m.get("total_mean", np.nan)], color))
        x = np.arange(len(labels))
        w = 0.27
        for i, (name, vals, color) in enumerate(series):
            ax1.bar(x + (i - 1) * w, vals, w, label=name, color=color)
        ax1.set_yscale("log")
        ax1.set_xticks(x, labels)
        ax1.set_ylabel("time (ms)")
        ax1.axvline(1.5, color="k", lw=0.6)
        ax1.text(0.5, 0.98, "offline", transform=ax1.get_xaxis_transform(), ha="center", va="top")
        ax1.text(3.0, 0.98, "online", transform=ax1.get_xaxis_transform(), ha="center", va="top")
        ax1.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, frameon=False)
        ax1.set_title("Banana (m = 53), §5 protocol: stage times")
        for i, (method, color) in enumerate((("paper", "tab:orange"), ("fast", "tab:blue"))):
            if method in s:
                t = s[method]["totals"]
                jitter = np.linspace(-0.15, 0.15, len(t))
                ax2.plot(np.full(len(t), i) + jitter, t, "o", color=color, ms=3, alpha=0.8)
        ax2.plot([2], [PAPER["total_mean"]], "s", color="0.4", label="paper: mean")
        ax2.vlines(2, PAPER["sij"] + PAPER["tree_min"], PAPER["sij"] + PAPER["tree_max"], color="0.4",
                   label="paper: S_ij + tree min..max")
        ax2.set_yscale("log")
        ax2.set_xticks([0, 1, 2], ["ours\npaper", "ours\nfast", "paper\n(reported)"])
        ax2.set_xlim(-0.5, 2.5)
        ax2.set_ylabel("online time per grasp (ms)")
        ax2.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=1, frameon=False)
        sweep.plain_log_axis(ax1)
        sweep.plain_log_axis(ax2)
        succ = " · ".join(f"{m}: success {s[m]['success']:.0%}" for m in ("paper", "fast") if m in s)
        ax2.set_title(succ)
        cpu = machine.get("cpu", "this machine")
        fig.text(0.01, -0.02, f"ours: {cpu} ({machine.get('cores', '?')} cores, one worker); paper: {PAPER_MACHINE}",
                 fontsize=6, ha="left", va="top")
        return sweep.save_figure(fig, out, NAME)


def summary(out_dir):
    """The table of results (table.md, written by :func:`plot`)."""
    return (Path(out_dir) / "table.md").read_text()


def main(argv=None):
    return sweep.main(NAME, __doc__, make_sweep, plot, summary, argv)


if __name__ == "__main__":
    sys.exit(main())
