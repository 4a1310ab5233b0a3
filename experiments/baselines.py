"""Ours against baselines a user might pick instead, on the same grasps: accuracy against time,
with and without a vision prior.

Per grasp (4 fingers at uniform random surface points, uniformly random pose, Gaussian noise
0.5 mm / 1°) and per prior level (σ_rot, σ_trans; the prior is the true pose perturbed by
that noise, drawn once per grasp and level and shared by every method):

* ``ours-fast``: ``localize`` (method fast), best hypothesis; without and with the prior;
* ``ours-paper``: ``localize(method="paper")`` (LM from the prior), when its closed-form
  search finds at most ``paper_cap`` hypotheses;
* ``prior``: the prior pose itself (what vision alone gives);
* ``icp``: Open3D point-to-plane ICP of finger pads from the prior
  (:func:`contactpose.peers.icp`), pad radius and correspondence distance chosen by the
  tuning sweep on other grasps (``tuning/``);
* ``icp-multistart``: the same ICP from K random starts, no prior, lowest contact χ² wins;
* ``scaling-series``: the Scaling-Series particle filter (:func:`contactpose.peers.scaling_series`)
  with the prior and globally, at three particle budgets (S, M, L);
* ``ss-published``: the Scaling Series as published (:func:`contactpose.peers.scaling_series_published`),
  no prior, its whole schedule, with M particles per neighbourhood for each M of ``published_series``.

Success: rotation error < 5° and translation error < 5 % of the diameter.

Writes results/baselines/ (results.csv, timings.csv, summary.md, baselines.png/.pdf) and
results/baselines/tuning/ (the ICP tuning sweep).

    .venv/bin/python experiments/baselines.py [--quick] [--workers N] [--scheduler tcp://HOST:PORT]
"""

from __future__ import annotations

import functools
import logging
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose import peers as bl
from contactpose.geometry import metrics
from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.localize import warm_up as warm_localize
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.types import PosePrior

NAME = "baselines"
log = logging.getLogger(NAME)


def prior_label(level):
    return "none" if level is None else f"{level[0]:g}deg/{level[1] * 1e3:g}mm"


def setup(name, cfg):
    """Model, surface samples and Open3D target of an object, once per worker process."""
    def build():
        model = ObjectModel.from_mesh(objects.load(name))
        surface = bl.sample_surface(model)
        target = bl.icp_target(surface, cfg["icp_target_points"])
        warm_up(model, surface, target, cfg)
        return model, surface, target
    return sweep.cached(("baselines", name, cfg["icp_target_points"]), build)


def warm_up(model, surface, target, cfg):
    """One untimed call of everything timed (numba and Open3D load lazily on first use)."""
    rng = np.random.default_rng(0)
    noise = dict(position_noise=cfg["position_noise"], normal_noise_deg=cfg["normal_noise_deg"])
    g = simulate.grasp(model, rng, n=cfg["fingers"], **noise)
    prior = PosePrior(g.pose, 10.0, 0.01)
    for method, solver in (("fast", "closed-form"), ("paper", "closed-form"), ("paper", "lm")):
        warm_localize(model, g.contacts, prior=prior, method=method, solver=solver, **noise)
    bl.icp(model, surface, target, g.contacts, g.pose, **noise)
    bl.scaling_series(model, surface, g.contacts, rng, prior=prior, initial=50, per_ball=4, max_particles=50, **noise)


def draw_prior(pose, rng, level):
    """The true pose perturbed: rotation vector ~ N(0, σ_rot²) (world frame), translation + N(0, σ_t²)."""
    sr, st = level
    T = pose.copy()
    T[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, np.radians(sr), 3)).as_matrix() @ pose[:3, :3]
    T[:3, 3] = pose[:3, 3] + rng.normal(0.0, st, 3)
    return PosePrior(T, sr, st)


def grasp_and_priors(model, rng, cfg):
    g = simulate.grasp(model, rng, n=cfg["fingers"], position_noise=cfg["position_noise"],
                       normal_noise_deg=cfg["normal_noise_deg"])
    return g, {prior_label(tuple(level)): draw_prior(g.pose, rng, tuple(level)) for level in cfg["priors"]}


def score(model, grasp, pose):
    """Accuracy columns of an estimated pose (None: no estimate)."""
    if pose is None:
        return {"success": False, "adds_success": False, "rot_err_deg": None, "trans_err_mm": None}
    a = metrics.adds(pose, grasp.pose, model.surface_points, model.surface_tree) / model.diameter
    return {"success": bool(metrics.pose_success(pose, grasp.pose, model.diameter)),
            "adds_success": bool(a < metrics.SAME_CLASS_ADDS_FRAC),
            "rot_err_deg": float(metrics.rotation_error_deg(pose, grasp.pose)),
            "trans_err_mm": 1e3 * float(metrics.translation_error(pose, grasp.pose))}


# --------------------------------------------------------------------------- tuning

def tuning_task(settings, rng, *, cfg):
    model, surface, target = setup(settings["object"], cfg)
    g, priors = grasp_and_priors(model, rng, cfg)
    noise = dict(position_noise=cfg["position_noise"], normal_noise_deg=cfg["normal_noise_deg"])
    rows = []
    for label, prior in priors.items():
        for radius in cfg["icp_patch_radius"]:
            for corr in cfg["icp_max_correspondence"]:
                t = time.perf_counter()
                r = bl.icp(model, surface, target, g.contacts, prior.pose, patch_radius=radius, max_correspondence=corr,
                           iterations=cfg["icp_iterations"], **noise)
                rows.append({"prior": label, "patch_radius": radius, "max_correspondence": corr, "cost": r.cost,
                             **score(model, g, r.pose), "time_icp_ms": 1e3 * (time.perf_counter() - t)})
    return rows


def pick_icp(tuning_csv):
    """(patch_radius, max_correspondence) with the best success over the tuning grasps
    (all objects and prior levels); ties go to the lower median rotation error."""
    c = sweep.read_columns(tuning_csv)
    best = None
    for radius in np.unique(c["patch_radius"]):
        for corr in np.unique(c["max_correspondence"]):
            sel = (c["patch_radius"] == radius) & (c["max_correspondence"] == corr)
            key = (-np.mean(c["success"][sel]), float(np.median(c["rot_err_deg"][sel])))
            if best is None or key < best[0]:
                best = (key, float(radius), float(corr))
    return best[1], best[2]


# --------------------------------------------------------------------------- evaluation

def eval_task(settings, rng, *, cfg):
    model, surface, target = setup(settings["object"], cfg)
    g, priors = grasp_and_priors(model, rng, cfg)
    noise = dict(position_noise=cfg["position_noise"], normal_noise_deg=cfg["normal_noise_deg"])
    rows = []

    def add(method, prior, budget, pose, seconds, cost=None, ran=True):
        rows.append({"method": method, "prior": prior, "budget": budget, "ran": ran, "cost": cost,
                     **score(model, g, pose if ran else None), "time_method_ms": 1e3 * seconds if ran else None})

    def ours(method, prior):
        t = time.perf_counter()
        r = localize(model, g.contacts, prior=prior, method=method, **noise)
        return r, time.perf_counter() - t

    r, dt = ours("fast", None)
    add("ours-fast", "none", "", r.best.pose if r.best else None, dt)
    for label, prior in priors.items():
        add("prior", label, "", prior.pose, 0.0)
        r, dt = ours("fast", prior)
        add("ours-fast", label, "", r.best.pose if r.best else None, dt)
        count = localize(model, g.contacts, method="paper", solver="closed-form", **noise).num_hypotheses
        if count <= cfg["paper_cap"]:
            r, dt = ours("paper", prior)
            add("ours-paper", label, "", r.best.pose if r.best else None, dt)
        else:
            add("ours-paper", label, "", None, 0.0, ran=False)
        t = time.perf_counter()
        b = bl.icp(model, surface, target, g.contacts, prior.pose, patch_radius=cfg["icp_patch_radius_tuned"],
                   max_correspondence=cfg["icp_max_correspondence_tuned"], iterations=cfg["icp_iterations"], **noise)
        add("icp", label, "", b.pose, time.perf_counter() - t, b.cost)
        for ss in cfg["scaling_series"]:
            t = time.perf_counter()
            b = bl.scaling_series(model, surface, g.contacts, rng, prior=prior, initial=ss["initial"],
                                  per_ball=ss["per_ball"], max_particles=ss["max_particles"], **noise)
            add("scaling-series", label, ss["label"], b.pose, time.perf_counter() - t, b.cost)
    for starts in cfg["multistart"]:
        t = time.perf_counter()
        b = bl.icp_multistart(model, surface, target, g.contacts, rng, starts=starts,
                              patch_radius=cfg["icp_patch_radius_tuned"],
                              max_correspondence=cfg["icp_max_correspondence_tuned"],
                              iterations=cfg["icp_iterations"], **noise)
        add("icp-multistart", "none", f"K={starts}", b.pose, time.perf_counter() - t, b.cost)
    for ss in cfg["scaling_series"]:
        t = time.perf_counter()
        b = bl.scaling_series(model, surface, g.contacts, rng, prior=None, initial=ss["initial"],
                              per_ball=ss["per_ball"], max_particles=ss["max_particles"], **noise)
        add("scaling-series", "none", ss["label"], b.pose, time.perf_counter() - t, b.cost)
    for m in cfg["published_series"]:
        t = time.perf_counter()
        b = bl.scaling_series_published(model, surface, g.contacts, rng, per_neighbourhood=m, **noise)
        add("ss-published", "none", f"M={m}", b.pose, time.perf_counter() - t, b.cost)
        rows[-1].update(particles=b.evaluations, stopped=b.stopped)
    return rows


def tuning_sweep(cfg):
    return sweep.Sweep("baselines_tuning", functools.partial(tuning_task, cfg=cfg), {"object": cfg["objects"]},
                       seeds=cfg["tuning_seeds"], base_seed=cfg["tuning_seed"], config=cfg)


def eval_sweep(cfg):
    return sweep.Sweep(NAME, functools.partial(eval_task, cfg=cfg), {"object": cfg["objects"]}, seeds=cfg["seeds"],
                       base_seed=cfg["base_seed"], config=cfg)


# --------------------------------------------------------------------------- figure and summary

MARKERS = {"ours-fast": ("o", "tab:blue"), "ours-paper": ("s", "tab:cyan"), "prior": ("x", "0.4"),
           "icp": ("^", "tab:red"), "icp-multistart": ("v", "tab:red"), "scaling-series": ("D", "tab:green"),
           "ss-published": ("P", "olive")}


def stats(c):
    """{(object, prior, method, budget): (success, median time ms, n run, n, ADD-S success)} over grasps."""
    out = {}
    keys = zip(c["object"], c["prior"], c["method"], c["budget"])
    for key in dict.fromkeys(keys):
        obj, prior, method, budget = key
        sel = (c["object"] == obj) & (c["prior"] == prior) & (c["method"] == method) & (c["budget"] == budget)
        ran = sel & (c["ran"] == 1)
        out[key] = (float(np.mean(c["success"][ran])) if ran.any() else np.nan,
                    float(np.median(c["time_method_ms"][ran])) if ran.any() else np.nan, int(ran.sum()), int(sel.sum()),
                    float(np.mean(c["adds_success"][ran])) if ran.any() else np.nan)
    return out


def _budget_label(budget):
    return "" if budget in ("", None) or (isinstance(budget, float) and np.isnan(budget)) else str(budget)


def plot(out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    c = sweep.read_columns(out / sweep.TIMINGS_CSV)
    c["budget"] = np.array([_budget_label(b) for b in c["budget"]], dtype=object)
    priors = list(dict.fromkeys(c["prior"]))
    priors = ["none"] + [p for p in priors if p != "none"]
    s = stats({**c, "object": np.full(len(c["method"]), "all", dtype=object)})
    with plt.rc_context(sweep.PAPER_RC):
        fig, axes = plt.subplots(1, len(priors), figsize=(sweep.PAGE_WIDTH, 2.5), sharey=True, sharex=True)
        for ax, prior in zip(np.atleast_1d(axes), priors):
            for method, (marker, color) in MARKERS.items():
                pts = sorted([(v[1], v[0], k[3]) for k, v in s.items() if k[1] == prior and k[2] == method and v[2]],
                             key=lambda p: p[0])
                if not pts:
                    continue
                if method == "prior":
                    ax.axhline(pts[0][1], color=color, lw=0.8, ls=":", label="prior alone")
                    continue
                x, y, b = zip(*pts)
                ax.plot(x, y, "-" + marker, color=color, ms=4, label=method, mfc="none" if method == "icp-multistart" else color)
                for xi, yi, bi in zip(x, y, b):
                    if bi:
                        ax.annotate(bi, (xi, yi), textcoords="offset points", xytext=(3, -7), fontsize=5.5)
            ax.set_xscale("log")
            ax.set_xlabel("median time per grasp (ms)")
            ax.set_title("no prior" if prior == "none" else f"prior σ = {prior.replace('deg', '°, ').replace('/', '')}")
            ax.set_ylim(-0.03, 1.03)
        np.atleast_1d(axes)[0].set_ylabel("success (rot < 5°, trans < 5 % diam.)")
        for ax in np.atleast_1d(axes):
            sweep.plain_log_axis(ax, "x", subs=(1.0,))
        handles, labels = [], []
        for ax in np.atleast_1d(axes):
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if lab not in labels:
                    handles.append(h)
                    labels.append(lab)
        fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.02), ncol=len(labels), frameon=False)
        objs = ", ".join(dict.fromkeys(c["object"]))
        fig.suptitle(f"Same grasps for every method ({objs}; 4 fingers, 0.5 mm, 1°)", y=1.0)
        paths = sweep.save_figure(fig, out, NAME)
    (out / "summary.md").write_text(summary_markdown(c))
    return paths


def summary_markdown(c):
    s = stats(c)
    lines = ["# Baselines: success and median time per grasp", "",
             "Success: rotation error < 5° and translation error < 5 % of the diameter. Time: median wall time "
             "of one localization (ms). `run` counts grasps where the method ran (the paper's LM only runs "
             "with at most `paper_cap` hypotheses).", "",
             "ADD-S success: the surface lands within 5 % of the diameter of where it is (forgives near-symmetric "
             "placements, e.g. the banana turned about its long axis).", "",
             "| object | prior | method | budget | success | ADD-S success | median ms | run/grasps |",
             "|---|---|---|---|---:|---:|---:|---:|"]
    for (obj, prior, method, budget), (succ, ms, n_run, n, adds) in s.items():
        lines.append(f"| {obj} | {prior} | {method} | {budget} | {succ:.2f} | {adds:.2f} | {ms:.3g} | {n_run}/{n} |")
    return "\n".join(lines) + "\n"


def summary(out_dir):
    """The table of results (summary.md, written by :func:`plot`)."""
    return (Path(out_dir) / "summary.md").read_text()


def main(argv=None):
    """Tune ICP on its own sweep (results/baselines/tuning/), then run every method."""
    args, cfg, out = sweep.start(NAME, __doc__, argv)
    if not args.plot_only:
        sweep.run_logged(tuning_sweep(cfg), out / "tuning", args, cfg)
    radius, corr = pick_icp(out / "tuning" / sweep.RESULTS_CSV)
    log.info("ICP tuned: patch radius %.3g m, max correspondence %.3g m", radius, corr)
    if not args.plot_only:
        cfg = {**cfg, "icp_patch_radius_tuned": radius, "icp_max_correspondence_tuned": corr}
        sweep.run_logged(eval_sweep(cfg), out, args, cfg)
    return sweep.finish(out, plot, summary)


if __name__ == "__main__":
    sys.exit(main())
