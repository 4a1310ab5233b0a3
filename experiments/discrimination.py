"""Discrimination beyond the paper: hypothesis counts, recall, top-1 and
pose classes stage by stage, and ambiguity resolved by suggested vs random extra touches.

Meshes: the built-in banana, box, carton, cylinder, sphere, rock, rock1k, and a concave
U-channel made here (8 mm slot), where the free-space check has something to reject.
Grasps: 4 contacts, area-weighted on the facets, uniform random rotation, translation
within ±0.5 diameter, bounded noise (σ_x = 0.5 mm, σ_n = 1°, every pair inside its
tolerance); a grasp whose true contact a finger of the given radius could not make (its
normal ray re-enters the object: the channel's slot walls) is redrawn. Stages, each
adding to the one before:

1. ``paper``      the paper's constraints: S_ij from distance and angle with vertex-only
                  Δmin, joined by the tree (facet level);
2. ``direction``  + direction constraints (exact Δmin, h_kl / h_lk), facet level, no
                  handedness test;
3. ``patches``    + patches and the handedness test: the full default search, ``localize``;
4. ``in_facet``   + the in-facet check: keep the hypotheses that some pose near their
                  closed form may fit within noise, triangles included
                  (``contactpose.scoring.infacet.within_noise``, a lower bound on the best χ²);
5. ``free_space`` + the free-space check (``localize(..., finger_radius=r)``: the ray of one
                  finger radius, on determined hypotheses).

Stages 1–3 rank by the plane χ² (normal and point-to-plane residuals of the closed-form
pose), which is all their constraints can tell; ``fit`` counts the hypotheses among the
best 256 that pass the fit test under it. At facet level (stages 1–2) tuples on the same
planes are posed once (one per distinct plane tuple, as the patch search of stage 3 does).
Stages 4–5 rank by the full χ². Columns per stage: hypotheses left, recall (the true facet
tuple is among them; stages 3–5 compare patch labels on
models with patches, whose coplanar facets are interchangeable), top-1 (the best pose is
the true placement: ADD-S < 5 % of the diameter; ``top1_strict``: rotation < 5° and
translation < 5 % of the diameter), and distinct pose classes among the fitting hypotheses
(``scoring.classes.classify_poses``: ADD-S grouping of the best 256).

Touch study: every grasp left with >= 2 pose classes by ``localize`` gets up to two extra
touches, suggested (``touch.suggest_touch``) or random (a random candidate probe), made on
the true pose with the same noise and added to the contacts. A probe that touches nothing
adds no contact; the classes that predicted a contact for it are then counted as ruled out.

``*_ms`` columns time a stage with its ranking and class grouping (``patches_ms``:
localize's total).

Writes results/discrimination/: grasps.csv (one row per grasp), summary.csv (mesh x stage),
touch.csv (one row per ambiguous grasp and strategy), touch_summary.csv, config.json,
counts.png/pdf and touch.png/pdf (drawn from the CSVs alone)::

    .venv/bin/python experiments/discrimination.py             # 300 grasps per mesh (2,100)
    .venv/bin/python experiments/discrimination.py --quick     # 15 grasps per mesh, smoke run
    .venv/bin/python experiments/discrimination.py --plot-only # redraw the figures
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import time
import zlib
from typing import NamedTuple

import numpy as np

from contactpose.contacts import Tolerance
from contactpose.costs.facet import normal_residuals, offset_residuals, whitened_cost
from contactpose.costs.frame import object_frame as to_object_frame
from contactpose.geometry.metrics import SAME_CLASS_ADDS_FRAC, adds, pose_success
from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.options import fit_threshold
from contactpose.peers import random_touch
from contactpose.scoring.classes import MAX_CLASS_HYPOTHESES, classify_poses
from contactpose.scoring.freespace import free_space_violations
from contactpose.scoring.infacet import within_noise
from contactpose.search.pairs import admissible_pairs, pair_conditions
from contactpose.search.tree import join_tuples
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.sim.touch import simulate_touch, with_contact
from contactpose.solvers.closed_form import fit_poses
from contactpose.tracking import next_touch as touchmod

log = logging.getLogger("discrimination")

MESHES = ("banana", "box", "carton", "cylinder", "sphere", "rock", "rock1k", "channel")
KIND = {"banana": "curved", "box": "box-like", "carton": "box-like", "cylinder": "symmetric",
        "sphere": "symmetric", "rock": "irregular", "rock1k": "irregular", "channel": "concave"}
STAGES = ("paper", "direction", "patches", "in_facet", "free_space")
POSITION_NOISE = 0.0005
NORMAL_NOISE_DEG = 1.0
FINGERS = 4
#: Hypotheses posed at once when ranking a large facet-level set.
CHUNK = 100_000


# ------------------------------------------------------------------ stages

def channel_mesh():
    """A U-channel (concave): 60 x 40 x 50 mm with an 8 mm slot 30 mm deep, 36 facets."""
    import trimesh

    w, h, floor, slot, length = 0.06, 0.04, 0.01, 0.008, 0.05
    a, b = (w - slot) / 2, (w + slot) / 2
    v2 = np.array([(0, 0), (w, 0), (w, floor), (b, floor), (a, floor), (0, floor), (0, h), (a, h), (b, h), (w, h)])
    f2 = np.array([(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5), (5, 4, 7), (5, 7, 6), (3, 2, 9), (3, 9, 8)])
    mesh = trimesh.creation.extrude_triangulation(v2, f2, length)
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def load_mesh(name):
    return channel_mesh() if name == "channel" else objects.load(name)


def feasible_grasp(model, rng, finger_radius):
    """A simulated grasp whose true contacts a finger of ``finger_radius`` can make (the
    normal ray of that length stays outside the object), and the number of redraws."""
    for redraws in range(1000):
        grasp = simulate.grasp(model, rng, n=FINGERS, position_noise=POSITION_NOISE,
                               normal_noise_deg=NORMAL_NOISE_DEG, noise="bounded")
        if not free_space_violations(model, grasp.facets[None], grasp.pose[None], grasp.contacts, finger_radius)[0]:
            return grasp, redraws
    raise RuntimeError("no feasible grasp in 1000 draws")


def facet_tuples(model, contacts, tolerance, stage):
    """Facet tuples of stage 1 (paper) or 2 (direction)."""
    paper = stage == "paper"
    S = admissible_pairs(model, pair_conditions(contacts), tolerance, bounds="paper" if paper else "exact",
                         direction=not paper)
    return join_tuples(S, contacts.n)


def plane_ids(model):
    """(m,) int: facets on the same plane (normal and offset equal to 1e-9) share an id."""
    key = np.round(np.column_stack([model.planes.normals, model.planes.offsets / model.diameter]), 9)
    return np.unique(key, axis=0, return_inverse=True)[1].ravel()



class View(NamedTuple):
    """The best hypotheses of a stage, best first: chi2 (H,), poses (H, 4, 4)."""

    chi2: np.ndarray
    poses: np.ndarray


def ranked_planes(model, contacts, facets, tolerance):
    """Closed-form poses and plane χ² (no lateral term) of facet tuples (H, n).

    Tuples whose facets lie on the same planes have the same plane χ² and, unless
    underdetermined, the same pose: each distinct plane tuple is posed once (its first
    facet tuple), in chunks. Returns a view of the best MAX_CLASS_HYPOTHESES distinct
    plane tuples, best first (chi2, poses), as classify_poses wants it.
    """
    if len(facets) == 0:
        return View(np.zeros(0), np.zeros((0, 4, 4)))
    _, first = np.unique(plane_ids(model)[facets], axis=0, return_index=True)
    reps = facets[first]

    def fit(f):
        return fit_poses(model.planes.normals[f], model.planes.offsets[f], contacts.points,
                         contacts.finger_normals, angle_tol=tolerance.normal_noise, centroids=model.centroids[f])

    chi2 = np.empty(len(reps))
    for lo in range(0, len(reps), CHUNK):
        f = reps[lo:lo + CHUNK]
        pf = fit(f)
        r_n = normal_residuals(pf.R, model.planes.normals[f], contacts.finger_normals)
        r_o = offset_residuals(to_object_frame(pf.R, pf.t, contacts.points), model.planes.normals[f],
                               model.planes.offsets[f])
        chi2[lo:lo + CHUNK] = whitened_cost(r_n, r_o, np.zeros_like(r_o), tolerance.normal_noise,
                                            tolerance.position_noise)
    order = np.argsort(chi2, kind="stable")[:MAX_CLASS_HYPOTHESES]
    return View(chi2[order], fit(reps[order]).poses())


def ranked_view(chi2, poses_of):
    """The best MAX_CLASS_HYPOTHESES hypotheses, best first, as classify_poses wants them."""
    order = np.argsort(chi2, kind="stable")[:MAX_CLASS_HYPOTHESES]
    poses = poses_of(order) if len(order) else np.zeros((0, 4, 4))
    return View(chi2[order], poses)


def has_row(tuples, row):
    return bool(len(tuples)) and bool((np.asarray(tuples) == np.asarray(row)).all(axis=1).any())


def stage_stats(model, grasp, prefix, tuples, truth_key, key_of, view):
    """Row entries of one stage: hypotheses, recall, fit, top-1, classes."""
    n = grasp.contacts.n
    out = {f"{prefix}_hyp": len(tuples), f"{prefix}_recall": has_row(key_of(tuples), truth_key),
           f"{prefix}_fit": int(np.sum(view.chi2 <= fit_threshold(n)))}
    if len(view.chi2):
        best = view.poses[0]
        out[f"{prefix}_top1"] = adds(best, grasp.pose, model.surface_points, model.surface_tree) \
            < SAME_CLASS_ADDS_FRAC * model.diameter
        out[f"{prefix}_top1_strict"] = bool(pose_success(best, grasp.pose, model.diameter))
        out[f"{prefix}_classes"] = len(classify_poses(model, view.poses, view.chi2, n))
    else:
        out.update({f"{prefix}_top1": False, f"{prefix}_top1_strict": False, f"{prefix}_classes": 0})
    return out


def run_grasp(model, name, i, grasp, tolerance, args):
    """One row of grasps.csv, and the localize result (for the touch study)."""
    noise = dict(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)
    row = {"mesh": name, "kind": KIND.get(name, ""), "facets": model.num_facets, "grasp": i}
    patched = model.patch_table is not None
    labels = model.patches.labels if patched else np.arange(model.num_facets)
    same = lambda t: t  # facet-level stages compare facets
    # stages 1-2: facet-level searches
    for stage in ("paper", "direction"):
        start = time.perf_counter()
        tuples = facet_tuples(model, grasp.contacts, tolerance, stage)
        view = ranked_planes(model, grasp.contacts, tuples, tolerance)
        row.update(stage_stats(model, grasp, stage, tuples, grasp.facets, same, view))
        row[f"{stage}_ms"] = 1000 * (time.perf_counter() - start)
    # stage 3: the default search
    result = localize(model, grasp.contacts, twins=True, **noise)  # the true tuple: every symmetric twin listed
    a = result.hypotheses.arrays
    truth = labels[grasp.facets]
    key = lambda t: labels[t] if len(t) else t
    r_n, r_o = a.residuals[..., :3], a.residuals[..., 3]
    chi2 = whitened_cost(r_n, r_o, np.zeros_like(r_o), tolerance.normal_noise, tolerance.position_noise)
    view = ranked_view(chi2, lambda idx: a.poses[idx])
    row.update(stage_stats(model, grasp, "patches", a.facets, truth, key, view))
    row["patches_ms"] = 1000 * result.timing["total"]
    row["status"] = result.status
    # stage 4: the in-facet check as a filter (contactpose.scoring.infacet: a lower bound on the best χ²
    # with the lateral term over the poses near the closed form)
    fits = np.flatnonzero(within_noise(model, grasp.contacts, a, result.tolerance, fit_threshold(grasp.contacts.n)))
    row.update(stage_stats(model, grasp, "in_facet", a.facets[fits], truth, key, a.take(fits)))
    # a true tuple that the search found but the fit test dropped: was its pose a family?
    found = np.flatnonzero((key(a.facets) == truth).all(axis=1)) if len(a.facets) else []
    row["in_facet_dropped_underdetermined"] = bool(
        row["patches_recall"] and not row["in_facet_recall"] and a.fit.underdetermined[found].all())
    row["in_facet_classes"] = len(result.classes)
    # stage 5: + free space
    start = time.perf_counter()
    kept = localize(model, grasp.contacts, finger_radius=args.finger_radius, twins=True, **noise).hypotheses.arrays
    free = fits[np.isin(_keys(a.facets[fits]), _keys(kept.facets))]
    row.update(stage_stats(model, grasp, "free_space", a.facets[free], truth, key, a.take(free)))
    row["free_space_ms"] = 1000 * (time.perf_counter() - start)
    return row, result


def _keys(facets):
    """(H, n) facet tuples -> (H,) one comparable key per tuple."""
    return np.ascontiguousarray(facets).view(np.dtype((np.void, facets.dtype.itemsize * facets.shape[1]))).ravel()


# ------------------------------------------------------------------ touches

def true_classes(model, result, pose):
    """Whether each pose class of ``result`` is the true placement."""
    return [adds(c.pose, pose, model.surface_points, model.surface_tree) < SAME_CLASS_ADDS_FRAC * model.diameter
            for c in result.classes]


def touch_episode(model, name, i, grasp, result, strategy, rng, touches):
    """Up to ``touches`` extra touches by one strategy; a row of touch.csv."""
    noise = dict(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)
    make = touchmod.suggest_touch if strategy == "suggested" else random_touch
    row = {"mesh": name, "grasp": i, "strategy": strategy, "classes_0": len(result.classes),
           "truth_in_0": any(true_classes(model, result, grasp.pose))}
    contacts, current, count = grasp.contacts, result, len(result.classes)
    for k in range(1, touches + 1):
        if count > 1:
            start = time.perf_counter()
            probe = make(model, current, rng=rng, contacts=contacts)
            row[f"plan_ms_{k}"] = 1000 * (time.perf_counter() - start)
            row[f"gain_{k}"] = probe.expected_gain
            measured = simulate_touch(model, grasp.pose, probe, rng, **noise)
            row[f"miss_{k}"] = measured is None
            if measured is None:
                # no contact: the classes that predicted one are ruled out; nothing to re-localize
                count = int(np.sum(probe.contact_share < 1.0)) if count == len(current.classes) else count
            else:
                contacts = with_contact(contacts, *measured)
                current = localize(model, contacts, twins=True, **noise)
                count = len(current.classes)
        row[f"classes_{k}"] = count
        row[f"resolved_{k}"] = count == 1
        truth = true_classes(model, current, grasp.pose)
        row[f"resolved_true_{k}"] = count == 1 and len(truth) == 1 and truth[0]
    return row


# ------------------------------------------------------------------ summaries

def summarize(rows):
    """summary.csv: one row per (mesh, stage), plus 'all' over meshes."""
    out = []
    meshes = list(dict.fromkeys(r["mesh"] for r in rows))
    for mesh in meshes + ["all"]:
        sel = [r for r in rows if mesh == "all" or r["mesh"] == mesh]
        col = lambda k: np.array([r[k] for r in sel], dtype=float)
        paper_median = np.median(col("paper_hyp"))
        for stage in STAGES:
            h = col(f"{stage}_hyp")
            out.append({
                "mesh": mesh, "kind": KIND.get(mesh, "all"), "facets": sel[0]["facets"] if mesh != "all" else "",
                "stage": stage, "grasps": len(sel),
                "hyp_median": np.median(h), "hyp_p95": np.percentile(h, 95), "hyp_max": h.max(),
                "drop_vs_paper_median": paper_median / max(np.median(h), 1e-9),
                "recall": col(f"{stage}_recall").mean(), "misses": int(len(sel) - col(f"{stage}_recall").sum()),
                "fit_median": np.median(col(f"{stage}_fit")),
                "top1": col(f"{stage}_top1").mean(), "top1_strict": col(f"{stage}_top1_strict").mean(),
                "classes_mean": col(f"{stage}_classes").mean(),
                "ambiguous_share": np.mean(col(f"{stage}_classes") > 1),
                "ms_median": np.median(col(f"{stage}_ms")) if f"{stage}_ms" in sel[0] else "",
            })
    return out


def summarize_touch(rows, touches):
    out = []
    meshes = list(dict.fromkeys(r["mesh"] for r in rows))
    for mesh in meshes + ["all"]:
        for strategy in ("suggested", "random"):
            sel = [r for r in rows if (mesh == "all" or r["mesh"] == mesh) and r["strategy"] == strategy]
            if not sel:
                continue
            item = {"mesh": mesh, "strategy": strategy, "ambiguous_grasps": len(sel),
                    "classes_0_mean": np.mean([r["classes_0"] for r in sel])}
            for k in range(1, touches + 1):
                item[f"resolved_{k}"] = np.mean([r[f"resolved_{k}"] for r in sel])
                item[f"resolved_true_{k}"] = np.mean([r[f"resolved_true_{k}"] for r in sel])
                item[f"classes_{k}_mean"] = np.mean([r[f"classes_{k}"] for r in sel])
                tried = [r for r in sel if f"miss_{k}" in r and r[f"miss_{k}"] != ""]
                item[f"miss_{k}"] = np.mean([r[f"miss_{k}"] for r in tried]) if tried else ""
            plan = [r["plan_ms_1"] for r in sel if r.get("plan_ms_1", "") != ""]
            item["plan_ms_median"] = np.median(plan) if plan else ""
            out.append(item)
    return out


# ------------------------------------------------------------------ figures

def plot(out):
    """counts.png/pdf and touch.png/pdf from summary.csv and touch_summary.csv."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = [r for r in sweep.read_rows(os.path.join(out, "summary.csv")) if r["mesh"] != "all"]
    meshes = list(dict.fromkeys(r["mesh"] for r in summary))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    width = 0.8 / len(STAGES)
    x = np.arange(len(meshes))
    for s, stage in enumerate(STAGES):
        rows = [next(r for r in summary if r["mesh"] == m and r["stage"] == stage) for m in meshes]
        med = np.array([float(r["hyp_median"]) for r in rows])
        p95 = np.array([float(r["hyp_p95"]) for r in rows])
        pos = x + (s - (len(STAGES) - 1) / 2) * width
        axes[0].bar(pos, np.maximum(med, 0.8), width, label=stage.replace("_", "-"))
        axes[0].errorbar(pos, np.maximum(med, 0.8), yerr=[np.zeros_like(med), np.maximum(p95 - med, 0)],
                         fmt="none", ecolor="k", elinewidth=0.6, capsize=1.5)
        cls = np.array([float(r["classes_mean"]) for r in rows])
        axes[1].bar(pos, cls, width, label=stage.replace("_", "-"))
    axes[0].set_yscale("log")
    axes[0].set_ylabel("hypotheses per grasp (median, bar to p95)")
    axes[1].set_ylabel("pose classes fitting within noise (mean)")
    for ax in axes:
        ax.set_xticks(x)
        ax.set_xticklabels([f"{m}\n{next(r['facets'] for r in summary if r['mesh'] == m)} f" for m in meshes])
    axes[0].legend(fontsize=8, ncol=2)
    axes[0].set_title("Hypotheses left, stage by stage (4 contacts, 0.5 mm, 1°)")
    axes[1].set_title("Distinct pose classes")
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(os.path.join(out, f"counts.{ext}"), dpi=150)
    plt.close(fig)

    path = os.path.join(out, "touch_summary.csv")
    if not os.path.exists(path):
        return
    touch = sweep.read_rows(path)
    meshes = [m for m in dict.fromkeys(r["mesh"] for r in touch)]
    touches = sum(1 for k in touch[0] if k.startswith("resolved_") and not k.startswith("resolved_true"))
    fig, ax = plt.subplots(figsize=(max(6, 1.3 * len(meshes) + 2), 4))
    x = np.arange(len(meshes))
    bars = [(s, k) for k in range(1, touches + 1) for s in ("suggested", "random")]
    width = 0.8 / len(bars)
    colors = {"suggested": ("tab:blue", "lightsteelblue"), "random": ("tab:orange", "navajowhite")}
    for b, (strategy, k) in enumerate(bars):
        vals = []
        for m in meshes:
            r = next((r for r in touch if r["mesh"] == m and r["strategy"] == strategy), None)
            vals.append(float(r[f"resolved_{k}"]) if r else np.nan)
        ax.bar(x + (b - (len(bars) - 1) / 2) * width, vals, width, color=colors[strategy][k - 1],
               label=f"{strategy}, after {k} touch{'es' if k > 1 else ''}")
    n = {m: next(r["ambiguous_grasps"] for r in touch if r["mesh"] == m) for m in meshes}
    ax.set_xticks(x)
    ax.set_xticklabels([f"{m}\n(n={n[m]})" for m in meshes])
    ax.set_ylabel("ambiguous grasps resolved to one class")
    ax.set_ylim(0, 1.2)
    ax.set_yticks(np.linspace(0, 1, 6))
    ax.legend(fontsize=8, ncol=4, loc="upper center")
    ax.set_title("Extra touches after a 4-contact grasp left >= 2 pose classes")
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(os.path.join(out, f"touch.{ext}"), dpi=150)
    plt.close(fig)


# ------------------------------------------------------------------ driver

def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--grasps", type=int, default=300, help="grasps per mesh")
    p.add_argument("--meshes", nargs="+", default=list(MESHES))
    p.add_argument("--touches", type=int, default=2, help="extra touches per ambiguous grasp")
    p.add_argument("--finger-radius", type=float, default=0.01, help="free-space check ray length (m)")
    p.add_argument("--seed", type=int, default=2009)
    p.add_argument("--out", default="results/discrimination")
    p.add_argument("--quick", action="store_true", help="15 grasps per mesh")
    p.add_argument("--plot-only", action="store_true", help="only redraw the figures from the CSVs")
    args = p.parse_args(argv)
    if args.quick:
        args.grasps = 15
    return args


def print_summary(summary, touch_summary):
    print(f"{'mesh':9s} {'stage':10s} {'median':>9s} {'p95':>10s} {'max':>10s} {'drop':>7s} {'recall':>7s} "
          f"{'top1':>5s} {'classes':>7s} {'amb':>5s}")
    for r in summary:
        print(f"{r['mesh']:9s} {r['stage']:10s} {r['hyp_median']:9.0f} {r['hyp_p95']:10.0f} {r['hyp_max']:10.0f} "
              f"{r['drop_vs_paper_median']:7.1f} {r['recall']:7.4f} {r['top1']:5.2f} {r['classes_mean']:7.2f} "
              f"{r['ambiguous_share']:5.2f}")
    for r in touch_summary:
        print(f"touch {r['mesh']:9s} {r['strategy']:9s} n={r['ambiguous_grasps']:4d} "
              + " ".join(f"resolved_{k}={r[f'resolved_{k}']:.3f}" for k in (1, 2) if f"resolved_{k}" in r))


def main(argv=None):
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    os.makedirs(args.out, exist_ok=True)
    if args.plot_only:
        plot(args.out)
        return 0
    tolerance = Tolerance.from_noise(POSITION_NOISE, NORMAL_NOISE_DEG)
    rows, touch_rows = [], []
    started = time.perf_counter()
    for name in args.meshes:
        model = ObjectModel.from_mesh(load_mesh(name))
        m = zlib.crc32(name.encode())  # the same grasps whichever meshes run
        rng = np.random.default_rng([args.seed, m])
        mesh_start = time.perf_counter()
        for i in range(args.grasps):
            grasp, redraws = feasible_grasp(model, rng, args.finger_radius)
            row, result = run_grasp(model, name, i, grasp, tolerance, args)
            row["redraws"] = redraws
            rows.append(row)
            if len(result.classes) > 1 and args.touches > 0:
                for s, strategy in enumerate(("suggested", "random")):
                    touch_rng = np.random.default_rng([args.seed, m, i, s])
                    touch_rows.append(touch_episode(model, name, i, grasp, result, strategy, touch_rng,
                                                    args.touches))
            if (i + 1) % 50 == 0:
                log.info("%s: %d/%d grasps, %.0f s", name, i + 1, args.grasps, time.perf_counter() - mesh_start)
        log.info("%s done in %.0f s", name, time.perf_counter() - mesh_start)
    summary = summarize(rows)
    touch_summary = summarize_touch(touch_rows, args.touches) if touch_rows else []
    sweep.write_rows(os.path.join(args.out, "grasps.csv"), rows)
    sweep.write_rows(os.path.join(args.out, "summary.csv"), summary)
    if touch_rows:
        sweep.write_rows(os.path.join(args.out, "touch.csv"), touch_rows)
        sweep.write_rows(os.path.join(args.out, "touch_summary.csv"), touch_summary)
    config = {**vars(args), "position_noise": POSITION_NOISE, "normal_noise_deg": NORMAL_NOISE_DEG,
              "fingers": FINGERS, "noise": "bounded", "where": "area",
              "pose": "uniform random rotation, translation within ±0.5 diameter",
              "stages": list(STAGES), "max_class_hypotheses": MAX_CLASS_HYPOTHESES,
              "touch": {"n_candidates": 200, "prior": "likelihood", "separation": 1.0,
                        "family_weight": touchmod.FAMILY_WEIGHT, "miss_penalty": touchmod.MISS_PENALTY},
              "seconds": time.perf_counter() - started, "python": platform.python_version()}
    with open(os.path.join(args.out, "config.json"), "w") as fh:
        json.dump(config, fh, indent=1)
    plot(args.out)
    print_summary(summary, touch_summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
