"""Outlier fingers: with ``max_outliers=1`` and one
planted bad finger among 5, how often is the top-1 pose right?

Grasps as in experiments/discrimination.py (``simulate.grasp``: contacts area-weighted on the
facets, uniform random rotation, translation within ±0.5 diameter, bounded noise σ_x =
0.5 mm, σ_n = 1°), but with 5 fingers; then one finger, chosen uniformly, is made bad (a
finger that touched something else): its point moves by ``displacement_frac`` (20 %) of the
object diameter in a uniformly random direction and its normal is replaced by a uniformly
random unit vector. One sweep cell is one grasp; its generator (``contactpose.sweep``,
seeded per cell) makes every random draw, in this order: grasp, bad finger, direction,
normal.

Per grasp, ``localize`` (method fast, told the noise) runs five times, closed form unless said:

* ``mo``     the 5 contacts with the bad one, ``max_outliers=1``: the acceptance;
* ``plain``  the same contacts without ``max_outliers`` (every finger must be assigned);
* ``oracle`` only the 4 good contacts: what the grasp can tell at best once the bad finger
  is known, so a failure here is the ambiguity of the 4 contacts, not the outlier handling;
* ``clean``  the 5 contacts before the bad finger was planted, ``max_outliers=1``: the
  cost of allowing an outlier when there is none (does the top-1 drop a good finger?);
* ``fg``     as ``mo`` with ``solver="factor-graph"`` (the best 20 hypotheses refined with
  point-to-facet factors), to show what a refined pose changes.

A top-1 miss under ``mo`` gets the first cause that applies (``causes``): no hypothesis;
the wrong finger left out (or none); the true tuple not found; the true tuple ranked first
but its closed-form pose off; another tuple first that places the surface the same way (a
symmetric twin: strict misses, ADD-S is right); another placement first.

Columns: top-1 success strict (``metrics.pose_success``: rotation < 5°, translation < 5 %
of the diameter) and by ADD-S (< 5 % of the diameter, which forgives symmetric twins);
``named``: the top-1 hypothesis leaves exactly the planted finger out; ``true_found``: the
true tuple (the 4 good fingers' true facets, the planted finger -1; compared by patch label
on models with patches, whose coplanar facets are interchangeable) is among the hypotheses,
and ``true_rank`` its rank; ``true_class``: some pose class fitting within noise is the true
placement; hypothesis counts, status and (``time_*``, timings.csv only) milliseconds.

Writes results/discrimination/outliers_grasps.csv (one row per grasp), outliers_timings.csv
(the same with times), outliers_summary.csv (per mesh and all), outliers_config.json,
outliers_run.json and outliers.png/pdf (drawn from the CSVs alone). The sweep itself runs
in results/discrimination/_scratch/outliers/ (not committed), so a rerun resumes there (the
runner checks only the config: pass ``--fresh`` after changing the library or this script)::

    .venv/bin/python experiments/outlier_fingers.py               # 5 meshes x 300 grasps
    .venv/bin/python experiments/outlier_fingers.py --quick       # 2 meshes x 3 grasps, smoke run
    .venv/bin/python experiments/outlier_fingers.py --plot-only   # redraw from the CSVs
"""

from __future__ import annotations

import functools
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from contactpose.contacts import Contacts
from contactpose.geometry import metrics
from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

NAME = "outlier_fingers"
#: Results go beside the other parts of the discrimination experiment, prefixed.
RESULTS = "discrimination"
PREFIX = "outliers_"
#: Failure causes of a top-1 miss under max_outliers, in the order they are tested.
CAUSES = ("no_hypothesis", "wrong_finger", "true_lost", "true_pose_off", "twin", "other_placement")
CAUSE_TEXT = {"no_hypothesis": "no hypothesis", "wrong_finger": "wrong finger left out",
              "true_lost": "true tuple not found", "true_pose_off": "true tuple first, its pose off",
              "twin": "symmetric twin first (ADD-S right)", "other_placement": "another placement first"}


# --------------------------------------------------------------------------- the grasp

def plant_outlier(model, contacts, rng, displacement_frac):
    """Make one random finger bad: its point moved by displacement_frac · diameter in a
    uniformly random direction, its normal a uniformly random unit vector.
    -> (Contacts, index of the bad finger)"""
    j = int(rng.integers(contacts.n))
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    points = contacts.points.copy()
    points[j] += displacement_frac * model.diameter * direction
    normals = contacts.object_normals.copy()
    normals[j] = normal
    return Contacts(points, object_normals=normals), j


def patch_labels(model):
    """Facet -> patch label on models with patches (coplanar facets are interchangeable),
    else the identity."""
    return model.patches.labels if model.patch_table is not None else np.arange(model.num_facets)


def keyed(labels, facets):
    """Facet tuples as label tuples; unassigned fingers (-1) stay -1."""
    facets = np.asarray(facets)
    return np.where(facets < 0, -1, labels[np.maximum(facets, 0)])


def top1(model, result, pose):
    """Top-1 columns of a result: strict success, ADD-S success, errors."""
    best = result.best
    if best is None:
        return {"strict": False, "adds": False, "adds_frac": None, "rot_err_deg": None, "trans_err_frac": None}
    a = metrics.adds(best.pose, pose, model.surface_points, model.surface_tree) / model.diameter
    return {"strict": bool(metrics.pose_success(best.pose, pose, model.diameter)),
            "adds": bool(a < metrics.SAME_CLASS_ADDS_FRAC), "adds_frac": a,
            "rot_err_deg": float(metrics.rotation_error_deg(best.pose, pose)),
            "trans_err_frac": float(metrics.translation_error(best.pose, pose)) / model.diameter}


def true_class(model, result, pose):
    """Whether some pose class of the result is the true placement."""
    limit = metrics.SAME_CLASS_ADDS_FRAC * model.diameter
    return any(metrics.adds(c.pose, pose, model.surface_points, model.surface_tree) < limit for c in result.classes)


def timed(model, contacts, **options):
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "contacts span ... diameter": the bad finger may lie off the object
        result = localize(model, contacts, twins=True, **options)  # the true tuple: every symmetric twin listed
    return result, 1e3 * (time.perf_counter() - start)


def task(settings, rng, *, cfg):
    name = settings["object"]
    model = sweep.cached(("model", name), lambda: ObjectModel.from_mesh(objects.load(name)))
    noise = dict(position_noise=cfg["position_noise"], normal_noise_deg=cfg["normal_noise_deg"])
    g = simulate.grasp(model, rng, n=cfg["fingers"], noise=cfg["noise"], **noise)
    bad, j = plant_outlier(model, g.contacts, rng, cfg["displacement_frac"])
    good = np.setdiff1d(np.arange(cfg["fingers"]), [j])
    labels = patch_labels(model)
    truth_facets = np.where(np.arange(cfg["fingers"]) == j, -1, g.facets)
    row = {"facets": model.num_facets, "planted": j}

    # max_outliers=1: the acceptance
    r, ms = timed(model, bad, max_outliers=cfg["max_outliers"], **noise)
    facets = r.hypotheses.arrays.facets
    match = np.flatnonzero((keyed(labels, facets) == keyed(labels, truth_facets)).all(axis=1)) if len(facets) else []
    out = r.best.outliers if r.best is not None else np.empty(0, dtype=int)
    t = top1(model, r, g.pose)
    row.update({
        "mo_status": r.status, "mo_hyp": r.num_hypotheses, "mo_classes": len(r.classes),
        "mo_strict": t["strict"], "mo_adds": t["adds"], "mo_adds_frac": t["adds_frac"],
        "mo_rot_err_deg": t["rot_err_deg"], "mo_trans_err_frac": t["trans_err_frac"],
        "mo_top_outliers": " ".join(str(int(k)) for k in out),
        "mo_top_underdetermined": bool(r.best is not None and r.best.underdetermined),
        "named": bool(len(out) == 1 and out[0] == j),
        "true_found": bool(len(match)),
        "true_found_facets": bool(len(facets) and (facets == truth_facets).all(axis=1).any()),
        "true_rank": int(match[0]) if len(match) else None,
        "pose_found": bool(len(facets) and metrics.pose_success(r.hypotheses.arrays.poses, g.pose,
                                                                 model.diameter).any()),
        "true_class": true_class(model, r, g.pose),
        "mo_best_chi2": float(r.best.chi2) if r.best is not None else None,
        "true_chi2": float(r.hypotheses.arrays.chi2[match[0]]) if len(match) else None,
        "time_mo_ms": ms,
    })
    # without max_outliers
    r, ms = timed(model, bad, **noise)
    t = top1(model, r, g.pose)
    row.update({"plain_status": r.status, "plain_hyp": r.num_hypotheses, "plain_strict": t["strict"],
                "plain_adds": t["adds"], "time_plain_ms": ms})
    # the 4 good contacts alone
    r, ms = timed(model, bad.permuted(good), **noise)
    t = top1(model, r, g.pose)
    facets = r.hypotheses.arrays.facets
    row.update({"oracle_status": r.status, "oracle_hyp": r.num_hypotheses, "oracle_strict": t["strict"],
                "oracle_adds": t["adds"], "oracle_classes": len(r.classes),
                "oracle_true_found": bool(len(facets) and (keyed(labels, facets) == labels[g.facets[good]])
                                          .all(axis=1).any()),
                "time_oracle_ms": ms})
    # the clean grasp (no bad finger), max_outliers=1
    r, ms = timed(model, g.contacts, max_outliers=cfg["max_outliers"], **noise)
    t = top1(model, r, g.pose)
    row.update({"clean_status": r.status, "clean_strict": t["strict"], "clean_adds": t["adds"],
                "clean_dropped": bool(r.best is not None and len(r.best.outliers) > 0), "time_clean_ms": ms})
    # max_outliers=1 with the factor graph's refinement
    r, ms = timed(model, bad, max_outliers=cfg["max_outliers"], solver="factor-graph", **noise)
    t = top1(model, r, g.pose)
    out = r.best.outliers if r.best is not None else np.empty(0, dtype=int)
    row.update({"fg_status": r.status, "fg_strict": t["strict"], "fg_adds": t["adds"],
                "fg_named": bool(len(out) == 1 and out[0] == j), "time_fg_ms": ms})
    return row


def make_sweep(cfg):
    return sweep.Sweep(NAME, functools.partial(task, cfg=cfg), {"object": cfg["objects"]}, seeds=cfg["seeds"],
                       base_seed=cfg["base_seed"], config=cfg)


# --------------------------------------------------------------------------- tables

def causes(c, crit):
    """(H,) str: why each grasp's top-1 under max_outliers failed by criterion crit
    ("strict" | "adds"), or "" where it succeeded. Tested in CAUSES order."""
    out = np.full(len(c["mo_" + crit]), "", dtype=object)
    fail = c["mo_" + crit] == 0
    named, found, first = c["named"] == 1, c["true_found"] == 1, c["true_rank"] == 0
    for cause, sel in (("no_hypothesis", c["mo_hyp"] == 0), ("wrong_finger", ~named), ("true_lost", ~found),
                       ("true_pose_off", first), ("twin", c["mo_adds"] == 1), ("other_placement", np.ones_like(fail))):
        pick = fail & (out == "") & sel
        out[pick] = cause
    return out


def summarize(c, t):
    """outliers_summary.csv rows: one per mesh and one over all. c, t : columns of the
    grasps and timings CSVs."""
    rows = []
    meshes = list(dict.fromkeys(c["object"]))
    why = {crit: causes(c, crit) for crit in ("strict", "adds")}
    for mesh in meshes + ["all"]:
        s = np.ones(len(c["object"]), bool) if mesh == "all" else c["object"] == mesh
        st = np.ones(len(t["object"]), bool) if mesh == "all" else t["object"] == mesh
        share = lambda k: float(np.mean(c[k][s] == 1))
        row = {"mesh": mesh, "facets": int(c["facets"][s][0]) if mesh != "all" else "", "grasps": int(s.sum()),
               "mo_strict": share("mo_strict"), "mo_adds": share("mo_adds"),
               "plain_strict": share("plain_strict"), "plain_adds": share("plain_adds"),
               "oracle_strict": share("oracle_strict"), "oracle_adds": share("oracle_adds"),
               "named": share("named"), "true_found": share("true_found"), "pose_found": share("pose_found"),
               "true_class": share("true_class"), "oracle_true_found": share("oracle_true_found"),
               "clean_strict": share("clean_strict"), "clean_adds": share("clean_adds"),
               "clean_dropped": share("clean_dropped"), "fg_strict": share("fg_strict"), "fg_adds": share("fg_adds"),
               "fg_named": share("fg_named"), "same_as_oracle_strict": float(np.mean(c["mo_strict"][s] == c["oracle_strict"][s])),
               "same_as_oracle_adds": float(np.mean(c["mo_adds"][s] == c["oracle_adds"][s])),
               "true_first": float(np.mean(c["true_rank"][s] == 0)),
               "mo_no_hypothesis": float(np.mean(c["mo_status"][s] == "no_hypothesis")),
               "mo_ambiguous": float(np.mean(c["mo_status"][s] == "ambiguous")),
               "mo_underdetermined": float(np.mean(c["mo_status"][s] == "underdetermined")),
               "plain_no_hypothesis": float(np.mean(c["plain_status"][s] == "no_hypothesis")),
               "mo_hyp_median": float(np.median(c["mo_hyp"][s])), "mo_hyp_p95": float(np.percentile(c["mo_hyp"][s], 95)),
               "plain_hyp_median": float(np.median(c["plain_hyp"][s])),
               "oracle_hyp_median": float(np.median(c["oracle_hyp"][s])),
               "mo_ms_median": float(np.median(t["time_mo_ms"][st])), "mo_ms_p95": float(np.percentile(t["time_mo_ms"][st], 95)),
               "plain_ms_median": float(np.median(t["time_plain_ms"][st])),
               "fg_ms_median": float(np.median(t["time_fg_ms"][st]))}
        for crit in ("strict", "adds"):
            for cause in CAUSES:
                row[f"fail_{crit}_{cause}"] = int(np.sum(why[crit][s] == cause))
            row[f"fail_{crit}_true_pose_off_underdetermined"] = int(np.sum((why[crit][s] == "true_pose_off")
                                                                          & (c["mo_top_underdetermined"][s] == 1)))
        rows.append(row)
    return rows


def files(out_dir):
    out = Path(out_dir)
    return {k: out / f"{PREFIX}{k}" for k in ("grasps.csv", "timings.csv", "summary.csv", "config.json", "run.json")}


def publish(stage, out_dir):
    """Copy the sweep's files from its staging directory under the prefixed names, and write
    the summary."""
    f = files(out_dir)
    for src, dst in (("results.csv", "grasps.csv"), ("timings.csv", "timings.csv"), ("config.json", "config.json"),
                     ("run.json", "run.json")):
        shutil.copyfile(Path(stage) / src, f[dst])
    write_summary(out_dir)


def write_summary(out_dir):
    f = files(out_dir)
    rows = summarize(sweep.read_columns(f["grasps.csv"]), sweep.read_columns(f["timings.csv"]))
    sweep.write_rows(f["summary.csv"], rows)
    return rows


# --------------------------------------------------------------------------- figure

def plot(out_dir):
    """outliers.png/pdf from outliers_grasps.csv (via outliers_summary.csv)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in write_summary(out_dir) if r["mesh"] != "all"]
    x = np.arange(len(rows))
    bars = [("mo_strict", "oracle_strict", "max_outliers=1, strict", "tab:blue"),
            ("mo_adds", "oracle_adds", "max_outliers=1, ADD-S", "lightsteelblue"),
            ("fg_strict", None, "+ factor graph, strict", "tab:green"),
            ("fg_adds", None, "+ factor graph, ADD-S", "palegreen"),
            ("plain_adds", None, "without max_outliers, ADD-S", "tab:red")]
    with plt.rc_context(sweep.PAPER_RC):
        fig = plt.figure(figsize=(sweep.PAGE_WIDTH, 5.0))
        grid = fig.add_gridspec(2, 2, height_ratios=[1.1, 1])
        axes = [fig.add_subplot(grid[0, :]), fig.add_subplot(grid[1, 0]), fig.add_subplot(grid[1, 1])]
        ax = axes[0]
        width = 0.8 / len(bars)
        for b, (key, oracle, label, color) in enumerate(bars):
            pos = x + (b - (len(bars) - 1) / 2) * width
            ax.bar(pos, [r[key] for r in rows], width, color=color, label=label)
            if oracle:
                ax.plot(pos, [r[oracle] for r in rows], "k_", ms=5, mew=1.2,
                        label="4 good fingers alone" if b == 0 else None)
        ax.axhline(0.9, color="k", ls="--", lw=0.8, label="acceptance 90 %")
        ax.set_ylabel("top-1 success (share of grasps)")
        ax.set_ylim(0, 1.3)
        ax.set_yticks(np.linspace(0, 1, 6))
        ax.set_title("top-1 with one bad finger among 5 (0.5 mm, 1°, bounded noise)")
        ax.legend(loc="upper center", ncol=4, frameon=False)
        ax = axes[1]
        diag = [("named", "planted finger named", "tab:purple"), ("true_found", "true tuple found", "tab:olive"),
                ("true_first", "true tuple ranked first", "tab:cyan"), ("clean_dropped", "no bad finger: one dropped",
                                                                          "tab:gray")]
        width = 0.8 / len(diag)
        for b, (key, label, color) in enumerate(diag):
            ax.bar(x + (b - (len(diag) - 1) / 2) * width, [r[key] for r in rows], width, color=color, label=label)
        ax.set_ylabel("share of grasps")
        ax.set_ylim(0, 1.4)
        ax.set_yticks(np.linspace(0, 1, 6))
        ax.set_title("max_outliers=1: the search")
        ax.legend(loc="upper center", ncol=2, fontsize=6, frameon=False)
        ax = axes[2]
        bottom = np.zeros(len(rows))
        colors = dict(zip(CAUSES, ("tab:gray", "tab:red", "tab:orange", "gold", "tab:cyan", "tab:brown")))
        for cause in CAUSES:
            v = np.array([r[f"fail_strict_{cause}"] / r["grasps"] for r in rows])
            ax.bar(x, v, 0.6, bottom=bottom, color=colors[cause], label=CAUSE_TEXT[cause])
            bottom += v
        ax.set_ylabel("strict top-1 misses (share of grasps)")
        ax.set_ylim(0, 1.0)
        ax.set_title("why the strict top-1 missed (first cause that applies)")
        ax.legend(loc="upper left", fontsize=6, frameon=False)
        axes[0].set_xticks(x, [f"{r['mesh']}\n{r['facets']} facets, {r['grasps']} grasps" for r in rows])
        for ax in axes[1:]:
            ax.set_xticks(x, [r["mesh"] for r in rows])
        return sweep.save_figure(fig, out_dir, "outliers")


def summary(out_dir):
    rows = sweep.read_rows(files(out_dir)["summary.csv"])
    cols = [("mo_strict", "mo strict"), ("mo_adds", "mo ADD-S"), ("plain_strict", "plain st"),
            ("plain_adds", "plain AS"), ("oracle_strict", "4 good st"), ("oracle_adds", "4 good AS"),
            ("fg_strict", "fg st"), ("fg_adds", "fg AS"), ("named", "named"), ("true_found", "true"),
            ("clean_dropped", "clean drop")]
    lines = [f"{'mesh':8s} {'grasps':>6s} " + " ".join(f"{h:>9s}" for _, h in cols) + f" {'ms':>6s}"]
    for r in rows:
        lines.append(f"{r['mesh']:8s} {r['grasps']:>6s} " + " ".join(f"{100 * float(r[k]):9.1f}" for k, _ in cols)
                     + f" {float(r['mo_ms_median']):6.1f}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- driver

def main(argv=None):
    args, config, _ = sweep.start(NAME, __doc__, argv)
    out = sweep.results_dir(args, RESULTS)
    stage = out / "_scratch" / "outliers"
    if not args.plot_only:
        sweep.run_logged(make_sweep(config), stage, args, config)
        publish(stage, out)
    return sweep.finish(out, plot, summary)


if __name__ == "__main__":
    sys.exit(main())
