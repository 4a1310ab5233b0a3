"""Offline and online time against the facet count m (log-log), with the paper's two data points.

Meshes: star-shaped rocks of increasing resolution, built here deterministically
(:func:`rock_mesh`): a geodesic sphere of frequency f (m = 20 f² facets) with a smooth
random radial field (the same field for every f, so only the resolution changes), scaled
to ``size``. Per mesh: the model is built ``build_repeats`` times with exact bounds (the
default method) and with the paper's vertex-only bounds (median times); then ``grasps``
random 4-finger grasps (``grasps_large`` above ``large_facets``; bounded noise) are
localized with method "fast", and with method "paper" while m ≤ paper_max_facets and its
closed-form search stays within ``paper_cap`` hypotheses (its LM costs 10–50 ms per
hypothesis). Two noise levels: "fine" (0.1 mm, 0.25°) on every mesh, and "default"
(0.5 mm, 1°) up to ``default_max_facets``: beyond it the facets are smaller than the
tolerance and the hypothesis count explodes (5.5 million on one m = 3,920 grasp, 400 s).

The paper's points: banana, m = 53: 40 ms offline, 116 ms online (Sun Ultra II); espresso
machine, m = 6,767: searched only with per-finger restrictions (no time reported).

    .venv/bin/python experiments/scaling.py [--quick] [--workers N] [--scheduler tcp://HOST:PORT]
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import numpy as np
import trimesh

from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.localize import warm_up as warm_localize
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

NAME = "scaling"
PAPER_BANANA = {"m": 53, "offline_ms": 40.0, "online_ms": 116.0}
PAPER_ESPRESSO_M = 6767
#: Seed of the radial field: one rock shape at every resolution.
SHAPE_SEED = 4


def geodesic_sphere(freq):
    """Unit geodesic sphere: every icosahedron face split into freq² triangles, vertices merged
    and pushed to the sphere. -> (vertices (V, 3), faces (20 freq², 3)), outward winding."""
    ico = trimesh.creation.icosahedron()
    i, j = np.array([(i, j) for i in range(freq + 1) for j in range(freq + 1 - i)]).T
    index = {(a, b): n for n, (a, b) in enumerate(zip(i, j))}
    local = [(index[p, q], index[p + 1, q], index[p, q + 1]) for p in range(freq) for q in range(freq - p)]
    local += [(index[p + 1, q], index[p + 1, q + 1], index[p, q + 1]) for p in range(freq) for q in range(freq - p - 1)]
    local = np.array(local)
    verts, faces = [], []
    for face in ico.faces:
        a, b, c = ico.vertices[face]
        verts.append(a + (i[:, None] / freq) * (b - a) + (j[:, None] / freq) * (c - a))
        faces.append(local + len(i) * len(faces))
    verts, faces = np.concatenate(verts), np.concatenate(faces)
    # merge the vertices shared by neighbouring patches (exact grid points, rounded keys)
    keys = np.round(verts / np.linalg.norm(verts, axis=1, keepdims=True), 9)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)                      # keep vertices in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    unit = verts[first[order]]
    return unit / np.linalg.norm(unit, axis=1, keepdims=True), rank[inverse.ravel()][faces]


def rock_mesh(freq, size=0.12, seed=SHAPE_SEED, waves=12, max_freq=4.0, amplitude=0.25):
    """A star-shaped rock with 20 freq² facets: radius 1 + amplitude·field(direction) on the
    geodesic sphere, largest bounding-box extent ``size`` (m), centred on its bounding box."""
    dirs, faces = geodesic_sphere(freq)
    radius = 1.0 + amplitude * objects.radial_noise(dirs, np.random.default_rng(seed), waves, max_freq)
    verts = dirs * radius[:, None]
    verts *= size / np.ptp(verts, axis=0).max()
    verts -= (verts.max(0) + verts.min(0)) / 2
    return trimesh.Trimesh(verts, faces, process=False)


def warm_up(cfg):
    """Load numba's kernels before timing: build a small rock and localize on it with both methods."""
    model = ObjectModel.from_mesh(rock_mesh(2, cfg["size"]))
    sx, sn = cfg["noise"]["default"]
    g = simulate.grasp(model, np.random.default_rng(0), n=4, position_noise=sx, normal_noise_deg=sn, noise="bounded")
    for method in ("fast", "paper"):
        warm_localize(model, g.contacts, position_noise=sx, normal_noise_deg=sn, method=method)
    return model


def offline(mesh, cfg):
    rows = []
    repeats = cfg["build_repeats"] if len(mesh.faces) <= cfg["large_facets"] else cfg["build_repeats_large"]
    for bounds in ("exact", "paper"):
        builds = []
        for _ in range(repeats):
            model = ObjectModel.from_mesh(mesh, bounds=bounds)
            builds.append(model.build_seconds)
        rows.append({"bounds": bounds, "method": "", "grasp": -1, "facets": model.num_facets,
                     "ordered_pairs": model.num_pairs, **{f"time_{k}_ms": 1e3 * float(np.median([b[k] for b in builds]))
                                                           for k in ("features", "table", "total")}})
    return rows


def online(mesh, rng, noise, cfg):
    model = ObjectModel.from_mesh(mesh)
    sx, sn = cfg["noise"][noise]
    grasps = cfg["grasps"] if model.num_facets <= cfg["large_facets"] else cfg["grasps_large"]
    rows = []
    for gi in range(grasps):
        g = simulate.grasp(model, rng, n=4, position_noise=sx, normal_noise_deg=sn, noise="bounded")
        count = None
        for method, solver in (("fast", "closed-form"), ("paper", "closed-form"), ("paper", "lm")):
            row = {"bounds": "exact", "method": f"{method}/{solver}", "grasp": gi, "facets": model.num_facets,
                   "ordered_pairs": model.num_pairs}
            if method == "paper" and (model.num_facets > cfg["paper_max_facets"]
                                      or (solver == "lm" and count > cfg["paper_cap"])):
                rows.append({**row, "ran": False})
                continue
            r = localize(model, g.contacts, position_noise=sx, normal_noise_deg=sn, method=method, solver=solver)
            if method == "paper":
                count = r.num_hypotheses
            found = r.hypotheses.arrays.facets
            rows.append({**row, "ran": True, "hypotheses": r.num_hypotheses,
                         "true_found": bool(len(found) and np.any(np.all(found == g.facets, axis=1))),
                         **{f"time_{k}_ms": 1e3 * r.timing[k] for k in ("pairs", "tree", "pose", "rank", "total")}})
    return rows


def task(settings, rng, *, cfg):
    sweep.cached("warm", lambda: warm_up(cfg))
    mesh = rock_mesh(settings["frequency"], cfg["size"])
    if settings["part"] == "offline":
        return offline(mesh, cfg)
    return online(mesh, rng, settings["noise"], cfg)


def grid(cfg):
    """Offline builds per mesh; online runs per mesh and noise level (default noise up to
    default_max_facets, where the hypothesis count stays tractable)."""
    cells = []
    for f in cfg["frequencies"]:
        cells.append({"frequency": f, "part": "offline", "noise": ""})
        for noise in cfg["noise"]:
            if noise == "default" and 20 * f * f > cfg["default_max_facets"]:
                continue
            cells.append({"frequency": f, "part": "online", "noise": noise})
    return cells


def make_sweep(cfg):
    return sweep.Sweep(NAME, functools.partial(task, cfg=cfg), grid(cfg), seeds=1, base_seed=cfg["base_seed"],
                       seed_axes=("frequency", "noise"), config=cfg)


# --------------------------------------------------------------------------- figure

def slope(m, t):
    """Least-squares slope of log t against log m."""
    ok = np.isfinite(t) & (t > 0)
    return float(np.polyfit(np.log(m[ok]), np.log(t[ok]), 1)[0]) if ok.sum() >= 2 else np.nan


def online_curve(c, method, noise, col="time_total_ms", stat=np.median):
    """(m, statistic, p10, p90) of an online column over the grasps that ran."""
    sel = (c["part"] == "online") & (c["method"] == method) & (c["noise"] == noise) & (c["ran"] == 1)
    m = np.unique(c["facets"][sel])
    vals = [c[col][sel & (c["facets"] == v)] for v in m]
    return (m, np.array([stat(v) for v in vals]), np.array([np.percentile(v, 10) for v in vals]),
            np.array([np.percentile(v, 90) for v in vals]))


def plot(out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    c = sweep.read_columns(out / sweep.TIMINGS_CSV)
    cfg = json.loads((out / sweep.CONFIG_JSON).read_text())["config"]
    ms = np.unique(c["facets"])
    noise_label = {k: f"{v[0] * 1e3:g} mm, {v[1]:g}°" + (" (dashed)" if k == "default" else "")
                   for k, v in cfg["noise"].items()}
    styles = {"fine": "-", "default": "--"}
    with plt.rc_context(sweep.PAPER_RC):
        fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(sweep.PAGE_WIDTH, 3.3))
        for bounds, color, label in (("exact", "tab:blue", "exact Δmin (default)"), ("paper", "tab:orange", "vertex-only Δmin (paper)")):
            sel = (c["part"] == "offline") & (c["bounds"] == bounds)
            m, t = c["facets"][sel], c["time_total_ms"][sel]
            ax1.plot(m, t, "-o", color=color, ms=3, label=f"{label}, slope {slope(m, t):.2f}")
        ax1.plot([PAPER_BANANA["m"]], [PAPER_BANANA["offline_ms"]], "*", color="k", ms=8, label="paper: banana (Sun Ultra II)")
        ax1.set_ylabel("offline build time (ms)")
        ax1.set_title("offline: pair features + table")
        for noise in cfg["noise"]:
            for method, color, label in (("fast/closed-form", "tab:blue", "fast"), ("paper/lm", "tab:orange", "paper (LM)")):
                m, med, lo, hi = online_curve(c, method, noise)
                if not len(m):
                    continue
                ax2.plot(m, med, styles[noise] + "o", color=color, ms=3,
                         label=f"{label}, {noise_label[noise]}, slope {slope(m, med):.2f}")
                ax2.fill_between(m, lo, hi, color=color, alpha=0.12, lw=0)
                mh, hmed, _, _ = online_curve(c, method.replace("/lm", "/closed-form"), noise, "hypotheses")
                if method.startswith("fast") or noise == "default":
                    ax3.plot(mh, np.maximum(hmed, 0.8), styles[noise] + "o", color=color, ms=3,
                             label=f"{label.split(' ')[0]} search, {noise_label[noise]}")
        ax2.plot([PAPER_BANANA["m"]], [PAPER_BANANA["online_ms"]], "*", color="k", ms=8, label="paper: banana (Sun Ultra II)")
        ax2.set_ylabel("online time per grasp (ms)")
        ax2.set_title("online: median, 10–90 % band")
        ax3.set_ylabel("median hypotheses per grasp")
        ax3.set_title("hypotheses")
        for ax in (ax1, ax2, ax3):
            ax.axvline(PAPER_ESPRESSO_M, color="0.4", ls=":", lw=0.8)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("facets m")
            ax.set_xlim(min(40, ms.min() * 0.8), max(PAPER_ESPRESSO_M * 1.5, ms.max() * 1.3))
            sweep.plain_log_axis(ax, "x", subs=(1.0,))
            sweep.plain_log_axis(ax, "y")
            ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False, fontsize=5.5)
        ax1.text(PAPER_ESPRESSO_M, 0.97, "paper: espresso, m = 6,767,\nonly with per-finger\nrestrictions ",
                 transform=ax1.get_xaxis_transform(), fontsize=5.5, ha="right", va="top", color="0.3")
        return sweep.save_figure(fig, out, NAME)


def summary(out_dir):
    c = sweep.read_columns(Path(out_dir) / sweep.TIMINGS_CSV)
    lines = []
    for m in np.unique(c["facets"]):
        s = c["facets"] == m
        off = {b: c["time_total_ms"][s & (c["part"] == "offline") & (c["bounds"] == b)] for b in ("exact", "paper")}
        line = f"m={int(m):6d}: build exact {off['exact'][0]:9.1f} ms, paper bounds {off['paper'][0]:9.1f} ms |"
        for noise in dict.fromkeys(c["noise"][c["part"] == "online"]):
            for v in ("fast/closed-form", "paper/lm"):
                sel = s & (c["method"] == v) & (c["noise"] == noise) & (c["ran"] == 1)
                if sel.any():
                    line += (f" {noise} {v.split('/')[0]} {np.median(c['time_total_ms'][sel]):.1f} ms"
                             f" (H {np.median(c['hypotheses'][sel]):.0f}, n={sel.sum()});")
        lines.append(line)
    return "\n".join(lines)


def main(argv=None):
    return sweep.main(NAME, __doc__, make_sweep, plot, summary, argv)


if __name__ == "__main__":
    sys.exit(main())
