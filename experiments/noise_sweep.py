"""Sensor noise against recall, top-1 success, pose error and hypothesis count, both methods,
and the pose solvers (Levenberg–Marquardt against the closed form; the factor graph when
``localize`` offers ``solver="factor-graph"``).

Grid: position noise σ_x × normal noise σ_n (per-axis standard deviations, Gaussian, not
truncated), 4 fingers on the banana at uniform random surface points, uniformly random
pose. Each grasp comes with a vision prior (the true pose perturbed by σ_rot, σ_trans) that
every variant receives; localize is told the true σ_x, σ_n. Variants, on the same grasp:

* ``fast/closed-form`` (the default) and ``paper/closed-form``: all hypotheses of each
  method's search, closed-form poses;
* ``fast/lm`` and ``paper/lm`` (the paper's method as published): LM from the prior, run
  only when the closed-form run of the same method found at most ``lm_cap`` hypotheses
  (LM costs about 10 ms per hypothesis); otherwise the row says ``ran = 0``.

Recall (of the search, so read from the closed-form variants): the true facet tuple is
among the hypotheses (``true_found``) or some hypothesis has rotation error < 5° and
translation error < 5 % of the diameter (``pose_found``; method fast returns one facet per
patch of coplanar facets, so the facet tuple alone would undercount). Top-1 success: the
best hypothesis meets those bounds.

    .venv/bin/python experiments/noise_sweep.py [--quick] [--workers N] [--scheduler tcp://HOST:PORT]
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.geometry import metrics
from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.options import SOLVERS
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.types import PosePrior

NAME = "noise_sweep"


def variants():
    """(method, solver) pairs; the factor graph only if this contactpose offers it."""
    out = [("fast", "closed-form"), ("paper", "closed-form"), ("fast", "lm"), ("paper", "lm")]
    if "factor-graph" in SOLVERS:
        out.append(("fast", "factor-graph"))
    return out


def perturbed_prior(pose, rng, sigma_rot_deg, sigma_trans):
    """A PosePrior around pose: rotation vector ~ N(0, σ_rot²) applied in the world frame,
    translation + N(0, σ_trans²)."""
    T = pose.copy()
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, np.radians(sigma_rot_deg), 3)).as_matrix() @ pose[:3, :3]
    T[:3, 3] = pose[:3, 3] + rng.normal(0.0, sigma_trans, 3)
    return PosePrior(T, sigma_rot_deg, sigma_trans)


def outcome(model, grasp, result):
    """Recall, top-1 and pose-error columns of one localization."""
    facets = result.hypotheses.arrays.facets
    best = result.best
    row = {"status": result.status, "hypotheses": result.num_hypotheses,
           "true_found": bool(len(facets) and np.any(np.all(facets == grasp.facets, axis=1))),
           "pose_found": bool(len(facets) and np.any(metrics.pose_success(result.hypotheses.arrays.poses, grasp.pose,
                                                                          model.diameter))),
           "top1_facets": bool(best is not None and np.array_equal(best.facets, grasp.facets)),
           "success": False, "rot_err_deg": None, "trans_err_mm": None, "adds_frac": None}
    if best is not None:
        row.update(success=bool(metrics.pose_success(best.pose, grasp.pose, model.diameter)),
                   rot_err_deg=float(metrics.rotation_error_deg(best.pose, grasp.pose)),
                   trans_err_mm=1e3 * float(metrics.translation_error(best.pose, grasp.pose)),
                   adds_frac=metrics.adds(best.pose, grasp.pose, model.surface_points, model.surface_tree) / model.diameter)
    return row


def task(settings, rng, *, cfg):
    model = sweep.cached(("model", cfg["object"]), lambda: ObjectModel.from_mesh(objects.load(cfg["object"])))
    sx, sn = settings["position_noise_mm"] * 1e-3, settings["normal_noise_deg"]
    grasp = simulate.grasp(model, rng, n=cfg["fingers"], position_noise=sx, normal_noise_deg=sn)
    prior = perturbed_prior(grasp.pose, rng, cfg["prior_sigma_rot_deg"], cfg["prior_sigma_trans"])
    rows, counts = [], {}
    for method, solver in variants():
        row = {"variant": f"{method}/{solver}", "method": method, "solver": solver}
        if solver != "closed-form" and counts.get(method, 0) > cfg["lm_cap"]:
            rows.append({**row, "ran": False, "hypotheses": counts[method]})
            continue
        r = localize(model, grasp.contacts, position_noise=sx, normal_noise_deg=sn, prior=prior,
                     method=method, solver=solver, diagnose=False, twins=True)  # the true tuple: every twin listed
        if solver == "closed-form":
            counts[method] = r.num_hypotheses
        rows.append({**row, "ran": True, **outcome(model, grasp, r),
                     **{f"time_{k}_ms": 1e3 * r.timing[k] for k in ("pairs", "tree", "pose", "rank", "total")}})
    return rows


def make_sweep(cfg):
    grid = {"position_noise_mm": cfg["position_noise_mm"], "normal_noise_deg": cfg["normal_noise_deg"]}
    return sweep.Sweep(NAME, functools.partial(task, cfg=cfg), grid, seeds=cfg["seeds"], base_seed=cfg["base_seed"],
                       config={**cfg, "variants": [f"{m}/{s}" for m, s in variants()]})


# --------------------------------------------------------------------------- figures

def cell_stats(c, variant, px, nd):
    sel = (c["variant"] == variant) & (c["position_noise_mm"] == px) & (c["normal_noise_deg"] == nd)
    ran = sel & (c["ran"] == 1)
    rot = c["rot_err_deg"][ran]
    found = (c["pose_found"] == 1) | (c["true_found"] == 1)
    return {"recall": np.mean(found[ran]) if ran.any() else np.nan,
            "success": np.mean(c["success"][ran]) if ran.any() else np.nan,
            "rot": np.nanmedian(rot) if np.isfinite(rot).any() else np.nan,
            "hyp": np.median(c["hypotheses"][sel]) if sel.any() else np.nan,
            "coverage": ran.sum() / max(sel.sum(), 1), "n": int(sel.sum())}


def plot(out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    c = sweep.read_columns(out / sweep.RESULTS_CSV)
    pxs, nds = np.unique(c["position_noise_mm"]), np.unique(c["normal_noise_deg"])
    colors = plt.cm.viridis(np.linspace(0, 0.85, len(nds)))
    paths = []
    with plt.rc_context(sweep.PAPER_RC):
        fig, axes = plt.subplots(1, 4, figsize=(sweep.PAGE_WIDTH, 2.2))
        panels = [("recall", "recall (a hypothesis within 5°, 5 %)", False), ("success", "top-1 success", False),
                  ("rot", "median rotation error (°)", True), ("hyp", "median hypotheses", True)]
        for ax, (key, label, log_y) in zip(axes, panels):
            for nd, color in zip(nds, colors):
                for method, style in (("fast", "-o"), ("paper", "--s")):
                    # the search (recall, count) is the solver's input; success and error use the
                    # method's own solver: closed form for fast, LM (the paper's) for paper
                    solver = "closed-form" if method == "fast" or key in ("recall", "hyp") else "lm"
                    y = [cell_stats(c, f"{method}/{solver}", px, nd)[key] for px in pxs]
                    ax.plot(pxs, y, style, color=color, ms=3, mfc="none" if method == "paper" else color)
            ax.set_xscale("log")
            ax.set_xticks(pxs, [f"{p:g}" for p in pxs])
            ax.minorticks_off()
            ax.set_xlabel("position noise σ_x (mm)")
            ax.set_ylabel(label)
            if log_y:
                ax.set_yscale("log")
                sweep.plain_log_axis(ax)
            else:
                ax.set_ylim(-0.03, 1.03)
        axes[2].axhline(metrics.SUCCESS_ROT_DEG, color="0.5", lw=0.6, ls=":")
        handles = [plt.Line2D([], [], color=col, label=f"σ_n = {nd:g}°") for nd, col in zip(nds, colors)]
        handles += [plt.Line2D([], [], color="k", ls="-", marker="o", ms=3, label="fast (closed form)"),
                    plt.Line2D([], [], color="k", ls="--", marker="s", mfc="none", ms=3,
                               label="paper (success, error: LM where ≤ cap hypotheses)")]
        fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=len(handles), frameon=False)
        paths += sweep.save_figure(fig, out, NAME)

        # solvers, paired: on the grasps where every variant ran (the LM and factor-graph
        # variants are capped), pooled over position noise, against normal noise
        vs = list(dict.fromkeys(c["variant"]))
        ran_all = {cell for cell in dict.fromkeys(c["cell"])
                   if np.all(c["ran"][c["cell"] == cell] == 1)}
        paired = np.array([cell in ran_all for cell in c["cell"]])
        fig, axes = plt.subplots(1, 3, figsize=(sweep.PAGE_WIDTH, 2.3))
        for v, marker in zip(vs, "osD^v<>"):
            sel = c["variant"] == v
            succ = [np.mean(c["success"][sel & paired & (c["normal_noise_deg"] == nd)]) for nd in nds]
            rot = [np.nanmedian(c["rot_err_deg"][sel & paired & (c["normal_noise_deg"] == nd)]) for nd in nds]
            cover = [np.mean(c["ran"][sel & (c["normal_noise_deg"] == nd)]) for nd in nds]
            style = "-" if v.startswith("fast") else "--"
            axes[0].plot(nds, succ, style + marker, ms=3, label=v)
            axes[1].plot(nds, rot, style + marker, ms=3, label=v)
            axes[2].plot(nds, cover, style + marker, ms=3, label=v)
        n_pairs = [int(np.sum(paired & (c["variant"] == vs[0]) & (c["normal_noise_deg"] == nd))) for nd in nds]
        axes[0].set_ylabel("top-1 success")
        axes[0].set_title("paired grasps: " + ", ".join(f"{n}" for n in n_pairs) + " per σ_n", fontsize=6.5)
        axes[1].set_ylabel("median rotation error (°)")
        axes[1].set_yscale("log")
        axes[1].axhline(metrics.SUCCESS_ROT_DEG, color="0.5", lw=0.6, ls=":")
        axes[2].set_ylabel("fraction of grasps run (cap)")
        for ax in axes:
            ax.set_xscale("log")
            ax.set_xticks(nds, [f"{n:g}" for n in nds])
            ax.minorticks_off()
            ax.set_xlabel("normal noise σ_n (°), all σ_x pooled")
        sweep.plain_log_axis(axes[1])
        axes[0].set_ylim(-0.03, 1.03)
        axes[2].set_ylim(-0.03, 1.03)
        fig.legend(*axes[0].get_legend_handles_labels(), loc="upper center", bbox_to_anchor=(0.5, 0.02),
                   ncol=len(vs), frameon=False)
        paths += sweep.save_figure(fig, out, f"{NAME}_solvers")
    return paths


def headline(out_dir):
    """One line per variant at each noise level: recall and success."""
    c = sweep.read_columns(Path(out_dir) / sweep.RESULTS_CSV)
    lines = []
    for v in dict.fromkeys(c["variant"]):
        for px in np.unique(c["position_noise_mm"]):
            for nd in np.unique(c["normal_noise_deg"]):
                s = cell_stats(c, v, px, nd)
                lines.append(f"{v:20s} σx={px:<5g}mm σn={nd:<4g}° recall {s['recall']:.2f} success {s['success']:.2f} "
                             f"median rot {s['rot']:.2f}° median H {s['hyp']:.0f} run on {s['coverage']:.0%}")
    return "\n".join(lines)


def main(argv=None):
    return sweep.main(NAME, __doc__, make_sweep, plot, headline, argv)


if __name__ == "__main__":
    sys.exit(main())
