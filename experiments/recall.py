"""Recall of the true facet tuple and top-1 pose success, fast vs paper.

For each mesh (banana, carton, rock, rock1k) the script simulates ``--grasps`` random grasps
(uniform random rotation, translation within ±0.5 diameter; 4 contacts sampled
area-weighted on the facets; bounded noise, σ_x = 0.5 mm and σ_n = 1°, each contact's
error within half the pair tolerance so every pair lies inside it) and records per grasp:

* ``fast``: ``localize(method="fast")`` — hypothesis count, whether the true facet tuple
  is among the hypotheses, whether the true *patch* tuple is (models with coplanar patches),
  status, and top-1 success of the best hypothesis;
* ``facet_search``: the facet-level search of the default method from its public stages
  (S_ij with the direction test, the tree with the handedness test, no patches) —
  hypothesis count and recall;
* ``paper``: the paper's hypothesis set (vertex-only Δmin, no direction test,
  ``admissible_pairs(..., bounds="paper", direction=False)`` joined by ``join_tuples``,
  the same set as the paper's node-by-node tree) — hypothesis count and recall, for every
  grasp. Its per-hypothesis LM is slow, so top-1 success of ``localize(method="paper")``
  (LM on eq. 7 from the identity, as with no prior) is measured only on the first
  ``--paper-grasps`` grasps per mesh and only where the paper has at most
  ``--lm-max-hypotheses`` hypotheses; ``paper_cf`` is the same method with the exact
  closed-form minimum of eq. 7 (``solver="closed-form"``), on the same subset up to
  ``--cf-max-hypotheses``. Skipped grasps are counted in the summary.

Top-1 success (``contactpose.geometry.metrics.pose_success``): rotation error < 5° and translation
error < 5 % of the diameter. ``*_top1_adds`` counts symmetric twins as success (ADD-S below
5 % of the diameter), which matters on the carton.

Writes results/recall/recall.csv (one row per grasp), summary.csv and config.json::

    .venv/bin/python experiments/recall.py             # 500 grasps per mesh (~15 min on 2 cores)
    .venv/bin/python experiments/recall.py --quick     # 20 grasps per mesh, smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from contactpose.contacts import Tolerance
from contactpose.geometry.metrics import SAME_CLASS_ADDS_FRAC, adds, pose_success, rotation_error_deg, translation_error
from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.search.pairs import admissible_pairs, pair_conditions
from contactpose.search.tree import TripleTest, join_tuples
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

MESHES = ("banana", "carton", "rock", "rock1k")
POSITION_NOISE = 0.0005
NORMAL_NOISE_DEG = 1.0
FINGERS = 4


def has_row(tuples, row):
    """Whether (H, n) int tuples contain the row (n,)."""
    return bool(len(tuples)) and bool((tuples == np.asarray(row)).all(axis=1).any())


def top1(model, result, grasp):
    """(strict success, ADD-S success, rotation error °, translation error) of the best hypothesis."""
    best = result.best
    if best is None:
        return False, False, np.nan, np.nan
    strict = bool(pose_success(best.pose, grasp.pose, model.diameter))
    same = adds(best.pose, grasp.pose, model.surface_points, model.surface_tree) < SAME_CLASS_ADDS_FRAC * model.diameter
    return strict, bool(same), float(rotation_error_deg(best.pose, grasp.pose)), float(translation_error(best.pose, grasp.pose))


def facet_search(model, contacts, tolerance):
    """Facet tuples of the default method's facet-level search (no patches)."""
    S = admissible_pairs(model, pair_conditions(contacts), tolerance, "exact", direction=True)
    triple = TripleTest(model.planes.normals, contacts.object_normals, tolerance.per_contact_bounds()[1])
    return join_tuples(S, contacts.n, triple)


def paper_hypotheses(model, contacts, tolerance):
    """The paper's hypothesis set: vertex-only Δmin, distance and angle only."""
    S = admissible_pairs(model, pair_conditions(contacts), tolerance, bounds="paper", direction=False)
    return join_tuples(S, contacts.n)


def run_grasp(model, name, i, grasp, tolerance, args):
    """One row of recall.csv."""
    noise = dict(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)
    row = {"mesh": name, "grasp": i, "true_facets": " ".join(map(str, grasp.facets))}
    fast = localize(model, grasp.contacts, twins=True, **noise)  # the true tuple: every symmetric twin listed
    facets = fast.hypotheses.arrays.facets
    row.update(fast_hypotheses=fast.num_hypotheses, fast_recall=has_row(facets, grasp.facets),
               fast_status=fast.status, fast_ms=1000 * fast.timing["total"],
               fast_best_underdetermined=bool(fast.best is not None and fast.best.underdetermined))
    labels = model.patches.labels if model.patch_table is not None else None
    row["fast_patch_recall"] = (has_row(labels[facets], labels[grasp.facets]) if labels is not None
                                else row["fast_recall"])
    (row["fast_top1"], row["fast_top1_adds"], row["fast_rot_err_deg"],
     row["fast_trans_err"]) = top1(model, fast, grasp)
    search = facet_search(model, grasp.contacts, tolerance)
    row.update(facet_search_hypotheses=len(search), facet_search_recall=has_row(search, grasp.facets))
    paper = paper_hypotheses(model, grasp.contacts, tolerance)
    row.update(paper_hypotheses=len(paper), paper_recall=has_row(paper, grasp.facets))
    for key, solver, cap in (("paper_lm", "lm", args.lm_max_hypotheses),
                             ("paper_cf", "closed-form", args.cf_max_hypotheses)):
        row[f"{key}_run"] = i < args.paper_grasps and len(paper) <= cap
        row[f"{key}_top1"] = row[f"{key}_top1_adds"] = ""
        if row[f"{key}_run"]:
            start = time.perf_counter()
            result = localize(model, grasp.contacts, method="paper", solver=solver, **noise)
            row[f"{key}_top1"], row[f"{key}_top1_adds"], _, _ = top1(model, result, grasp)
            row[f"{key}_ms"] = 1000 * (time.perf_counter() - start)
    return row


def summarize(name, rows):
    """One row of summary.csv from the grasp rows of one mesh."""
    col = lambda key: np.array([r[key] for r in rows])
    fast_h, paper_h, search_h = col("fast_hypotheses"), col("paper_hypotheses"), col("facet_search_hypotheses")
    determined = ~col("fast_best_underdetermined").astype(bool)
    out = {
        "mesh": name, "grasps": len(rows),
        "fast_recall": col("fast_recall").mean(), "fast_patch_recall": col("fast_patch_recall").mean(),
        "facet_search_recall": col("facet_search_recall").mean(), "paper_recall": col("paper_recall").mean(),
        "fast_hyp_median": np.median(fast_h), "fast_hyp_p95": np.percentile(fast_h, 95),
        "facet_search_hyp_median": np.median(search_h), "paper_hyp_median": np.median(paper_h),
        "paper_hyp_p95": np.percentile(paper_h, 95),
        "fast_top1": col("fast_top1").mean(), "fast_top1_adds": col("fast_top1_adds").mean(),
        "fast_top1_determined": col("fast_top1")[determined].mean() if determined.any() else np.nan,
        "fast_determined": int(determined.sum()),
        "fast_ms_median": np.median(col("fast_ms")), "fast_ms_p95": np.percentile(col("fast_ms"), 95),
    }
    for status in ("ok", "no_hypothesis", "underdetermined", "ambiguous"):
        out[f"fast_status_{status}"] = int(np.sum(col("fast_status") == status))
    for key in ("paper_lm", "paper_cf"):
        ran = [r for r in rows if r[f"{key}_run"]]
        out[f"{key}_grasps"] = len(ran)
        out[f"{key}_top1"] = np.mean([r[f"{key}_top1"] for r in ran]) if ran else np.nan
        out[f"{key}_top1_adds"] = np.mean([r[f"{key}_top1_adds"] for r in ran]) if ran else np.nan
        out[f"{key}_ms_median"] = np.median([r[f"{key}_ms"] for r in ran]) if ran else np.nan
    return out


def print_summary(summary):
    cols = [("mesh", "{}"), ("grasps", "{}"), ("fast_recall", "{:.1%}"), ("fast_patch_recall", "{:.1%}"),
            ("facet_search_recall", "{:.1%}"), ("paper_recall", "{:.1%}"), ("fast_hyp_median", "{:.0f}"),
            ("paper_hyp_median", "{:.0f}"), ("fast_top1", "{:.1%}"), ("fast_top1_adds", "{:.1%}"),
            ("paper_lm_grasps", "{}"), ("paper_lm_top1", "{:.1%}"), ("paper_cf_grasps", "{}"),
            ("paper_cf_top1", "{:.1%}"), ("fast_ms_median", "{:.2f}")]
    print("  ".join(k for k, _ in cols))
    for s in summary:
        print("  ".join(fmt.format(s[k]) for k, fmt in cols))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grasps", type=int, default=500, help="grasps per mesh")
    p.add_argument("--paper-grasps", type=int, default=100,
                   help="the first this many grasps per mesh also run the paper's full method for top-1")
    p.add_argument("--lm-max-hypotheses", type=int, default=2000,
                   help="skip the paper's LM (≈ 8 ms per hypothesis) on grasps with more hypotheses")
    p.add_argument("--cf-max-hypotheses", type=int, default=200_000,
                   help="skip the paper method with closed-form poses on grasps with more hypotheses")
    p.add_argument("--meshes", nargs="+", default=list(MESHES))
    p.add_argument("--seed", type=int, default=2003)
    p.add_argument("--out", default="results/recall")
    p.add_argument("--quick", action="store_true", help="20 grasps per mesh, paper top-1 on 10")
    args = p.parse_args(argv)
    if args.quick:
        args.grasps, args.paper_grasps = 20, 10
    return args


def main(argv=None):
    args = parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    config = {k: v for k, v in vars(args).items()}
    config.update(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG, fingers=FINGERS,
                  noise="bounded", where="area", pose="uniform random rotation, translation within ±0.5 diameter",
                  success="rotation < 5 deg and translation < 5 % of diameter (metrics.pose_success)")
    with open(os.path.join(args.out, "config.json"), "w") as fh:
        json.dump(config, fh, indent=1)
    tolerance = Tolerance.from_noise(POSITION_NOISE, NORMAL_NOISE_DEG)
    rows, summary = [], []
    for index, name in enumerate(args.meshes):
        model = ObjectModel.from_mesh(objects.load(name))
        rng = np.random.default_rng([args.seed, index])
        start = time.perf_counter()
        mesh_rows = []
        for i in range(args.grasps):
            grasp = simulate.grasp(model, rng, n=FINGERS, where="area", noise="bounded",
                                   position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)
            mesh_rows.append(run_grasp(model, name, i, grasp, tolerance, args))
        rows += mesh_rows
        summary.append(summarize(name, mesh_rows))
        print(f"{name}: {args.grasps} grasps in {time.perf_counter() - start:.1f} s", flush=True)
        sweep.write_rows(os.path.join(args.out, "recall.csv"), rows)
        sweep.write_rows(os.path.join(args.out, "summary.csv"), summary)
    print_summary(summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
