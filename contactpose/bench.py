"""`contactpose bench`: offline and online timings, the default method beside the paper's.

For each model: build time and peak memory (a fresh subprocess per build, so the
peak is the build's own), then the online stages (S_ij, tree, pose, ranking) over
random 4-finger grasps, for ``method="fast"`` and ``method="paper"`` on the same
grasps. The paper's method is skipped once one grasp exceeds ``--paper-cap`` seconds, and
on models built without a facet table. Recall is the share of grasps whose true tuple is
among the hypotheses (as patches on models searched by patches).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from contactpose.contacts import Tolerance
from contactpose.errors import ContactPoseError
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.sweep import machine_description

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
        localize(model, g.contacts, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG, method=method)
    for g in grasps:
        r = localize(model, g.contacts, position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG, method=method)
        rows.append({**{s: r.timing[s] for s in STAGES}, "hypotheses": r.num_hypotheses,
                     "true_found": true_found(model, r, g, method)})
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
           "build_stage_seconds": build["seconds"], "build_peak_rss_mib": build["peak_mib"],
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


def format_table(results):
    lines = [f"{'model':13s} {'m':>6s} {'build ms':>9s} {'peak MiB':>9s} | {'method':6s} {'S_ij':>7s} {'tree':>7s} "
             f"{'pose':>8s} {'rank':>7s} {'total med':>9s} {'p95':>8s} {'max':>8s} {'H med':>6s} {'recall':>6s}"]
    for r in results:
        for method in ("fast", "paper"):
            s = r[method]
            if s is None:
                lines.append(f"{r['model']:13s} {'':6s} {'':9s} {'':9s} | {method:6s} skipped: {r['paper_skipped']}")
                continue
            lines.append(
                f"{r['model']:13s} {r['facets']:6d} {r['build_median_ms']:9.2f} {r['build_peak_rss_mib']:9.0f} | {method:6s} "
                + " ".join(f"{s[k]['median_ms']:7.3f}" for k in ("pairs", "tree"))
                + f" {s['pose']['median_ms']:8.3f} {s['rank']['median_ms']:7.3f} {s['total']['median_ms']:9.3f} "
                f"{s['total']['p95_ms']:8.2f} {s['total']['max_ms']:8.2f} {s['hypotheses']['median']:6.0f} {s['recall']:6.2f}"
                + ("" if method == "fast" or r["paper_complete"] else f"  (stopped after {s['runs']} runs: over the cap)"))
        if r["paper"] is not None:
            lines.append(f"{'':13s} paper/fast median ratio: {r['ratio_paper_over_fast']:.1f}x")
    return "\n".join(lines)


def run_bench(args):
    names = args.models or ["banana", "rock1k", "espresso6767", "espresso83846"]
    unknown = [n for n in names if n not in objects.names()]
    if unknown:
        raise ContactPoseError(f"unknown model {unknown[0]!r}; choose from {objects.names()}")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as workdir:
        results = [bench_model(n, args.runs, args.seed, args.paper_cap, workdir) for n in names]
    report = {"machine": machine_description(), "runs": args.runs, "seed": args.seed,
              "noise": {"position": POSITION_NOISE, "normal_deg": NORMAL_NOISE_DEG}, "models": results,
              "seconds": time.perf_counter() - start}
    print(f"machine: {report['machine']}")
    print(format_table(results))
    os.makedirs(args.out, exist_ok=True)
    path = args.json or os.path.join(args.out, "bench.json")
    with open(path, "w") as fh:
        json.dump(report, fh, indent=1)
    print(f"written: {path}")
    return 0
