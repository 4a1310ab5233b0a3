"""Number of fingers n = 2…5 against ambiguity (the status of the result) and accuracy.

Each grasp puts n fingers at uniform random surface points of the object under a uniformly
random pose, with Gaussian noise (0.5 mm, 1°); ``localize`` (method "fast", no prior) is
told that noise. Per grasp: the status (ok / ambiguous / underdetermined / no_hypothesis),
the hypothesis count, recall (the true facet tuple is among the hypotheses, or some
hypothesis is within 5° and 5 % of the diameter of the truth: method fast searches coplanar
facets as patches, so the facet tuple alone undercounts on the box and carton), top-1 success
(rotation < 5°, translation < 5 % of the diameter) and ADD-S of the best pose (which forgives
the symmetric twins of the box and carton).

    .venv/bin/python experiments/fingers_sweep.py [--quick] [--workers N] [--scheduler tcp://HOST:PORT]
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import numpy as np

from contactpose.geometry import metrics
from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.options import STATUSES
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

NAME = "fingers_sweep"


def task(settings, rng, *, cfg):
    name, n = settings["object"], settings["fingers"]
    model = sweep.cached(("model", name), lambda: ObjectModel.from_mesh(objects.load(name)))
    g = simulate.grasp(model, rng, n=n, position_noise=cfg["position_noise"], normal_noise_deg=cfg["normal_noise_deg"])
    r = localize(model, g.contacts, position_noise=cfg["position_noise"], normal_noise_deg=cfg["normal_noise_deg"],
                 twins=True)  # the true facet tuple: every symmetric twin listed
    facets = r.hypotheses.arrays.facets
    best = r.best
    row = {"status": r.status, "hypotheses": r.num_hypotheses,
           "true_found": bool(len(facets) and np.any(np.all(facets == g.facets, axis=1))),
           "pose_found": bool(len(facets) and np.any(metrics.pose_success(r.hypotheses.arrays.poses, g.pose,
                                                                          model.diameter))),
           "success": False, "adds_success": False, "rot_err_deg": None, "trans_err_mm": None, "adds_frac": None,
           "time_total_ms": 1e3 * r.timing["total"]}
    if best is not None:
        a = metrics.adds(best.pose, g.pose, model.surface_points, model.surface_tree) / model.diameter
        row.update(success=bool(metrics.pose_success(best.pose, g.pose, model.diameter)),
                   adds_success=bool(a < metrics.SAME_CLASS_ADDS_FRAC), adds_frac=a,
                   rot_err_deg=float(metrics.rotation_error_deg(best.pose, g.pose)),
                   trans_err_mm=1e3 * float(metrics.translation_error(best.pose, g.pose)))
    return row


def make_sweep(cfg):
    grid = {"object": cfg["objects"], "fingers": cfg["fingers"]}
    return sweep.Sweep(NAME, functools.partial(task, cfg=cfg), grid, seeds=cfg["seeds"], base_seed=cfg["base_seed"],
                       config=cfg)


# --------------------------------------------------------------------------- figure

STATUS_COLORS = {"ok": "tab:green", "ambiguous": "tab:orange", "underdetermined": "tab:purple",
                 "no_hypothesis": "tab:red", "poor_fit": "tab:brown", "time_limit": "tab:gray"}


def plot(out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    c = sweep.read_columns(out / sweep.RESULTS_CSV)
    objs = list(dict.fromkeys(c["object"]))
    ns = np.unique(c["fingers"]).astype(int)
    with plt.rc_context(sweep.PAPER_RC):
        fig, axes = plt.subplots(1, 3, figsize=(sweep.PAGE_WIDTH, 2.5), gridspec_kw={"width_ratios": [1.6, 1, 1]})
        ax = axes[0]
        width = 0.8 / len(objs)
        for j, obj in enumerate(objs):
            bottom = np.zeros(len(ns))
            for status in STATUSES:
                frac = np.array([np.mean(c["status"][(c["object"] == obj) & (c["fingers"] == n)] == status) for n in ns])
                x = np.arange(len(ns)) + (j - (len(objs) - 1) / 2) * width
                ax.bar(x, frac, width * 0.92, bottom=bottom, color=STATUS_COLORS[status],
                       label=status if j == 0 else None, edgecolor="white", linewidth=0.3)
                bottom += frac
            for i, xi in enumerate(np.arange(len(ns)) + (j - (len(objs) - 1) / 2) * width):
                ax.text(xi, 1.01, obj[:3], ha="center", va="bottom", fontsize=4.5, rotation=90)
        ax.set_xticks(np.arange(len(ns)), [f"n = {n}" for n in ns])
        ax.set_ylabel("fraction of grasps")
        ax.set_ylim(0, 1.15)
        ax.set_title("status of the result, per object")
        fig.legend(*ax.get_legend_handles_labels(), loc="upper center", bbox_to_anchor=(0.5, 0.02), ncol=4,
                   frameon=False)
        markers = dict(zip(objs, "osD^v"))
        for obj in objs:
            sel = c["object"] == obj
            succ = [np.mean(c["adds_success"][sel & (c["fingers"] == n)]) for n in ns]
            hyp = [np.median(c["hypotheses"][sel & (c["fingers"] == n)]) for n in ns]
            axes[1].plot(ns, succ, "-" + markers[obj], ms=3, label=obj)
            axes[2].plot(ns, np.maximum(hyp, 0.8), "-" + markers[obj], ms=3, label=obj)
        axes[1].set_ylabel("top-1 success (ADD-S < 5 % diam.)")
        axes[1].set_ylim(-0.03, 1.03)
        axes[2].set_yscale("log")
        sweep.plain_log_axis(axes[2])
        axes[2].set_ylabel("median hypotheses")
        for ax in axes[1:]:
            ax.set_xlabel("fingers n")
            ax.set_xticks(ns)
        axes[2].legend(loc="upper right", frameon=False)
        return sweep.save_figure(fig, out, NAME)


def summary(out_dir):
    c = sweep.read_columns(Path(out_dir) / sweep.RESULTS_CSV)
    lines = []
    for obj in dict.fromkeys(c["object"]):
        for n in np.unique(c["fingers"]).astype(int):
            s = (c["object"] == obj) & (c["fingers"] == n)
            st = " ".join(f"{k} {np.mean(c['status'][s] == k):.2f}" for k in STATUSES)
            lines.append(f"{obj:8s} n={n}: {st} | recall {np.mean((c['pose_found'][s] == 1) | (c['true_found'][s] == 1)):.2f} "
                         f"success {np.mean(c['success'][s]):.2f} ADD-S success {np.mean(c['adds_success'][s]):.2f} "
                         f"median H {np.median(c['hypotheses'][s]):.0f}")
    return "\n".join(lines)


def main(argv=None):
    return sweep.main(NAME, __doc__, make_sweep, plot, summary, argv)


if __name__ == "__main__":
    sys.exit(main())
