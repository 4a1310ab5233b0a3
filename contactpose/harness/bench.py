"""`contactpose bench`: offline and online timings, the default method beside the paper's.

For each model: build time and peak memory (a fresh subprocess per build, so the
peak is the build's own), then the online stages (S_ij, tree, pose, ranking) over
random 4-finger grasps, for ``method="fast"`` and ``method="paper"`` on the same
grasps. The paper's method is skipped once one grasp exceeds ``--paper-cap`` seconds, and
on models built without a facet table. Recall is the share of grasps whose true tuple is
among the hypotheses (as patches on models searched by patches), with every facet assignment
listed (``distinct=False``, an untimed second call: the timed one lists distinct poses).
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from contactpose.contacts import Tolerance
from contactpose.errors import ContactPoseError
from contactpose.harness.sweep import machine_description
from contactpose.io.output import bench_header
from contactpose.localize import localize, warm_up
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

#: The models timed when none are named (``contactpose bench --help`` and the README show them).
DEFAULT_MODELS = ("banana", "rock1k", "espresso6767", "espresso83846", "ycb:011_banana")
#: What ``--out DIR`` holds: the report, the table, the figure of the stage times.
OUTPUT_FILES = ("bench.json", "bench.csv", "bench_stages.png")
STAGES = ("pairs", "tree", "pose", "rank", "total")
#: Sensor noise of the benchmark grasps: 0.5 mm and 1°, bounded within tolerance.
POSITION_NOISE = 0.0005
NORMAL_NOISE_DEG = 1.0
#: Warm-up grasps before timing (numba's cached kernels load on first call).
WARMUP = 3


#: Build repeats: the median of several for small models, one for large ones.
SMALL_MODEL_FACETS = 2000
#: Build options per model: the 83,846-facet espresso object is built for a hand of span
#: 0.25 m (research/scale.md), and its grasps are drawn within that span.
BUILD_OPTIONS = {"espresso83846": {"max_span": 0.25}}


def build_in_subprocess(name, mesh_path):
    """Build seconds (median over repeats) and peak RSS of a fresh process, in MiB, with the
    RSS before building (imports and mesh loaded) as the baseline. Warm-up builds first
    load the numba kernels; for large models the one timed build is the first."""
    code = (
        "import resource, time, json, warnings, numpy as np, trimesh\n"
        "warnings.simplefilter('ignore')\n"
        "from contactpose.sim import objects\nfrom contactpose.model.object_model import ObjectModel\n"
        f"mesh = trimesh.load({mesh_path!r}, force='mesh', process=False)\n"
        f"options = {BUILD_OPTIONS.get(name, {})!r}\n"
        "ObjectModel.from_mesh(objects.load('banana'))\n"
        "base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024\n"
        f"repeats = 7 if len(mesh.faces) < {SMALL_MODEL_FACETS} else 1\n"
        "ts = []\n"
        "for _ in range(repeats):\n"
        "    t = time.perf_counter(); m = ObjectModel.from_mesh(mesh, **options); ts.append(time.perf_counter() - t)\n"
        "print(json.dumps({'median': float(np.median(ts)), 'repeats': repeats, 'baseline_mib': base,\n"
        "                  'peak_mib': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,\n"
        "                  'seconds': m.build_seconds, 'pairs': m.num_pairs, 'facet_table': m.table is not None,\n"
        "                  'patches': None if m.patches is None else m.patches.count}))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def grasps_for(model, name, runs, rng):
    """The paper's protocol on the banana (§5), bounded-noise random grasps elsewhere; a
    model built for a hand span gets grasps whose contacts lie within it (with tolerance)."""
    if name == "banana":
        return [simulate.grasp(model, rng, n=4, pose=simulate.paper_pose(), where="centroid") for _ in range(runs)]
    grasps = []
    while len(grasps) < runs:
        g = simulate.grasp(model, rng, n=4, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG,
                           noise="bounded")
        if model.max_span is None or within_span(g.contacts, model.max_span):
            grasps.append(g)
    return grasps


def within_span(contacts, span):
    """Whether every contact pair, widened by the pair tolerance, is within the span."""
    slack = Tolerance.from_noise(POSITION_NOISE, NORMAL_NOISE_DEG).distance
    return contacts.spread + slack <= span


def true_found(model, result, grasp, method):
    """Whether the true tuple is among the hypotheses: as facets, or as patches where the
    model searches patches (which member of a flat patch a finger touches is not observable)."""
    facets = result.hypotheses.arrays.facets
    if method == "fast" and model.patch_table is not None:
        labels = model.patches.labels
        return bool(any(np.array_equal(labels[h], labels[grasp.facets]) for h in facets))
    return bool(any(np.array_equal(h, grasp.facets) for h in facets))


def time_method(model, grasps, method, cap):
    """Per-grasp stage timings and hypothesis counts; stops early past ``cap`` seconds."""
    rows = []
    for g in grasps[:WARMUP]:
        warm_up(model, g.contacts, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG, method=method)
    noise = dict(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG, method=method, diagnose=False)
    for g in grasps:
        r = localize(model, g.contacts, **noise)
        every = localize(model, g.contacts, **noise, distinct=False) if method == "fast" else r
        rows.append({**{s: r.timing[s] for s in STAGES}, "hypotheses": r.num_hypotheses,
                     "true_found": true_found(model, every, g, method)})
        if r.timing["total"] > cap:
            break
    return rows


def summarize(rows):
    """median / p95 / max per stage (ms) and hypothesis counts."""
    out = {}
    for s in STAGES:
        v = np.array([r[s] for r in rows]) * 1000
        out[s] = {"median_ms": float(np.median(v)), "p95_ms": float(np.percentile(v, 95)), "max_ms": float(v.max())}
    h = np.array([r["hypotheses"] for r in rows])
    out["hypotheses"] = {"median": float(np.median(h)), "p95": float(np.percentile(h, 95)), "max": int(h.max())}
    out["runs"] = len(rows)
    out["recall"] = float(np.mean([r["true_found"] for r in rows]))
    return out


def bench_model(name, runs, seed, cap, workdir):
    mesh = objects.load(name)
    path = os.path.join(workdir, f"{name}.ply")
    mesh.export(path)
    build = build_in_subprocess(name, path)
    model = ObjectModel.from_mesh(mesh, **BUILD_OPTIONS.get(name, {}))
    grasps = grasps_for(model, name, runs, np.random.default_rng(seed))
    fast = summarize(time_method(model, grasps, "fast", cap))
    out = {"model": name, "facets": model.num_facets, "ordered_pairs": model.num_pairs,
           "patches": None if model.patches is None else model.patches.count,
           "facet_table": model.table is not None, "build_options": BUILD_OPTIONS.get(name, {}),
           "build_median_ms": build["median"] * 1000, "build_repeats": build["repeats"],
           "build_stage_ms": {k: 1000.0 * v for k, v in build["seconds"].items()}, "build_peak_rss_mib": build["peak_mib"],
           "build_baseline_rss_mib": build["baseline_mib"], "fast": fast}
    if model.table is None:
        out.update(paper=None, paper_skipped="no facet table: the paper's method needs facet_pairs=True "
                   f"({model.num_facets} facets: ~{model.num_facets ** 2 * 20 / 2**30:.1f} GiB)")
        return out
    paper_rows = time_method(model, grasps, "paper", cap)
    paper = summarize(paper_rows)
    out.update(paper=paper, paper_complete=len(paper_rows) == len(grasps),
               ratio_paper_over_fast=paper["total"]["median_ms"] / fast["total"]["median_ms"])
    return out


#: The stage columns of the table, CSV and figure, with their headings.
TABLE_STAGES = (("pairs", "S_ij"), ("tree", "tree"), ("pose", "pose"), ("rank", "rank"))


def table_rows(results):
    """One row per model and method (the table, the CSV): build, median stage times, totals."""
    rows = []
    for r in results:
        for method in ("fast", "paper"):
            row = {"model": r["model"], "facets": r["facets"], "build_ms": r["build_median_ms"],
                   "peak_rss_mib": r["build_peak_rss_mib"], "method": method}
            s = r[method]
            if s is None:
                rows.append({**row, "note": f"skipped: {r['paper_skipped']}"})
                continue
            row.update({f"{k}_ms": s[k]["median_ms"] for k, _ in TABLE_STAGES})
            row.update(total_median_ms=s["total"]["median_ms"], total_p95_ms=s["total"]["p95_ms"],
                       total_max_ms=s["total"]["max_ms"], hypotheses_median=s["hypotheses"]["median"],
                       recall=s["recall"], runs=s["runs"])
            stopped = method == "paper" and not r["paper_complete"]
            rows.append({**row, "note": f"stopped after {s['runs']} runs: over the cap" if stopped else ""})
    return rows


CSV_COLUMNS = ("model", "facets", "build_ms", "peak_rss_mib", "method", *(f"{k}_ms" for k, _ in TABLE_STAGES),
               "total_median_ms", "total_p95_ms", "total_max_ms", "hypotheses_median", "recall", "runs", "note", "date",
               "machine")


def format_table(results):
    lines = [f"{'model':13s} {'m':>6s} {'build ms':>9s} {'peak MiB':>9s} | {'method':6s} {'S_ij':>7s} {'tree':>7s} "
             f"{'pose':>8s} {'rank':>7s} {'total med':>9s} {'p95':>8s} {'max':>8s} {'H med':>6s} {'recall':>6s}"]
    ratios = {r["model"]: r.get("ratio_paper_over_fast") for r in results}
    for row in table_rows(results):
        if "runs" not in row:
            lines.append(f"{row['model']:13s} {'':6s} {'':9s} {'':9s} | {row['method']:6s} {row['note']}")
            continue
        lines.append(
            f"{row['model']:13s} {row['facets']:6d} {row['build_ms']:9.2f} {row['peak_rss_mib']:9.0f} | "
            f"{row['method']:6s} {row['pairs_ms']:7.3f} {row['tree_ms']:7.3f} {row['pose_ms']:8.3f} "
            f"{row['rank_ms']:7.3f} {row['total_median_ms']:9.3f} {row['total_p95_ms']:8.2f} {row['total_max_ms']:8.2f} "
            f"{row['hypotheses_median']:6.0f} {row['recall']:6.2f}" + (f"  ({row['note']})" if row["note"] else ""))
        if row["method"] == "paper":
            lines.append(f"{'':13s} paper/fast median ratio: {ratios[row['model']]:.1f}x")
    return "\n".join(lines)


def write_csv(report, path):
    """The table as CSV, one row per model and method (times in ms), each with the machine
    and the date of the run."""
    where = {"date": report["date"], "machine": machine_text(report["machine"])}
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        writer.writerows({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()} | where
                         for row in table_rows(report["models"]))
    return path


def machine_text(machine):
    """The machine in a few words: "AMD EPYC, 2 cores, 23.5 GiB, Python 3.11.7"."""
    return (f"{machine.get('cpu')}, {machine.get('cores')} cores, {machine.get('memory_gib')} GiB, "
            f"Python {machine.get('python')}")


def utc_now():
    """The present time, UTC, ISO 8601 to the second."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def plot_stages(report, path):
    """PNG of the median time of each stage (log scale), fast beside paper, one panel per model;
    the machine and the date below."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter, NullFormatter

    results = report["models"]
    fig = Figure(figsize=(1.0 + 3.0 * len(results), 4.0), dpi=130)
    axes = fig.subplots(1, len(results), squeeze=False, sharey=True)[0]
    x = np.arange(len(TABLE_STAGES))
    for ax, r in zip(axes, results):
        for offset, method, color in ((-0.2, "fast", "#4c72b0"), (0.2, "paper", "#dd8452")):
            if r[method] is not None:
                ms = [r[method][stage]["median_ms"] for stage, _ in TABLE_STAGES]
                ax.bar(x + offset, ms, width=0.4, color=color, label=method)
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_xticks(x, [label for _, label in TABLE_STAGES], fontsize=8)
        ax.set_title(f"{r['model']} ({r['facets']} facets)" + ("" if r["paper"] else "\npaper: no facet table"),
                     fontsize=9)
        ax.tick_params(axis="y", labelsize=8)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("median time [ms]", fontsize=8)
    fig.suptitle(f"online stages, {results[0]['fast']['runs']} grasps per model", fontsize=10)
    fig.text(0.5, 0.01, f"{machine_text(report['machine'])}; {report['date']}", ha="center", fontsize=7)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path)
    return path


def check_bench_options(names, runs, paper_cap):
    """Raise ContactPoseError naming the first bad option."""
    unknown = [n for n in names if n not in objects.names()]
    if unknown:
        raise ContactPoseError(f"unknown model {unknown[0]!r}; choose from {objects.names()}")
    if not isinstance(runs, int) or runs < 1:
        raise ContactPoseError(f"--runs must be at least 1, got {runs!r}")
    if not paper_cap > 0:
        raise ContactPoseError(f"--paper-cap must be a positive number of seconds, got {paper_cap!r}")


def run_bench(names=DEFAULT_MODELS, *, runs=25, seed=0, paper_cap=20.0, out_dir=None, json_path=None):
    """Time every model, print the table; write files only where ``out_dir`` / ``json_path`` say.

    out_dir : folder for bench.json, bench.csv and bench_stages.png; json_path : the JSON report
    there instead (alone, without out_dir, it is the only file written). Returns 0.
    """
    check_bench_options(names, runs, paper_cap)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as workdir:
        results = [bench_model(n, runs, seed, paper_cap, workdir) for n in names]
    report = {**bench_header(), "machine": machine_description(), "date": utc_now(), "runs": runs, "seed": seed,
              "noise": {"position": POSITION_NOISE, "normal_deg": NORMAL_NOISE_DEG}, "models": results,
              "total_ms": 1000.0 * (time.perf_counter() - start)}
    print(f"machine: {report['machine']}, {report['date']}")
    print(format_table(results))
    for path in write_outputs(report, out_dir, json_path):
        print(f"written: {path}")
    return 0


def write_outputs(report, out_dir, json_path):
    """Write the report where asked; the paths written."""
    written = []
    if out_dir is not None:
        os.makedirs(out_dir, exist_ok=True)
        json_path = json_path or os.path.join(out_dir, OUTPUT_FILES[0])
    if json_path is not None:
        os.makedirs(os.path.dirname(json_path) or ".", exist_ok=True)
        with open(json_path, "w") as fh:
            json.dump(report, fh, indent=1)
        written.append(json_path)
    if out_dir is not None:
        written.append(write_csv(report, os.path.join(out_dir, OUTPUT_FILES[1])))
        written.append(plot_stages(report, os.path.join(out_dir, OUTPUT_FILES[2])))
    return written
