"""Bin counts of the hash table K3 (p_Δmax, p_Δmin, p_α) against the candidate count, the
query time and the build time: the trade-off the paper notes (§3.1) but never measured.

One bin count is varied at a time, the other two stay at the default (32, 32, 64). For each
setting the model is built ``build_repeats`` times (median build time: the table, and the
whole build), then the same ``grasps`` random 4-finger grasps (0.5 mm, 1°, noise bounded
within the tolerance) are queried. Per grasp, summed over the 6 finger pairs:

* ``candidates``: stored pairs in the bins eq. (5) visits (what the bins hand to the exact test);
* ``admissible``: pairs passing the exact interval test (independent of the bins, a check);
* ``time_query_ms``: one ``PairTable.query_all`` call (S_ij for all finger pairs, direction
  test included), the minimum over ``query_repeats`` calls.

    .venv/bin/python experiments/bin_sweep.py [--quick] [--workers N] [--scheduler tcp://HOST:PORT]
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path

import numpy as np

from contactpose.contacts import Tolerance
from contactpose.harness import sweep
from contactpose.model.object_model import ObjectModel
from contactpose.model.table import bin_index, query_limits
from contactpose.search.pairs import pair_conditions
from contactpose.sim import grasps as simulate
from contactpose.sim import objects

NAME = "bin_sweep"
AXES = ("p_dmax", "p_dmin", "p_alpha")


def candidate_count(table, conditions, tolerance):
    """Stored pairs in the bins that eq. (5) visits, summed over the finger pairs.

    The bins are those of ``PairTable.query``: Δmax bins from t1(Δ̃ - σ_Δ) up, Δmin bins up to
    t2(Δ̃ + σ_Δ), α bins from t3(α̃ - σ_α - w) to t3(α̃ + σ_α).
    """
    p1, p2, p3 = table.bins
    counts = np.diff(table.offsets).reshape(p1, p2, p3)
    # prefix sums over α, so a run of α bins costs one subtraction
    cum = np.concatenate([np.zeros((p1, p2, 1), np.int64), np.cumsum(counts, axis=2)], axis=2)
    total = 0
    for d, a in zip(conditions.distance, conditions.angle):
        lo_d, hi_d, lo_a, hi_a = query_limits(d, a, tolerance.distance, tolerance.angle)
        a0 = int(bin_index(lo_d, table.mins[0], table.widths[0], p1))
        b1 = int(bin_index(hi_d, table.mins[1], table.widths[1], p2))
        c0 = int(bin_index(lo_a - table.alpha_width, table.mins[2], table.widths[2], p3))
        c1 = int(bin_index(hi_a, table.mins[2], table.widths[2], p3))
        total += int((cum[a0:, :b1 + 1, c1 + 1] - cum[a0:, :b1 + 1, c0]).sum())
    return total


def task(settings, rng, *, cfg):
    bins = tuple(settings[a] for a in AXES)
    mesh = sweep.cached(("mesh", settings["object"]), lambda: objects.load(settings["object"]))
    sweep.cached(("warm", settings["object"]), lambda: ObjectModel.from_mesh(mesh))  # numba kernels loaded
    builds = []
    for _ in range(cfg["build_repeats"]):
        model = ObjectModel.from_mesh(mesh, bins=bins)
        builds.append(model.build_seconds)
    tolerance = Tolerance.from_noise(cfg["position_noise"], cfg["normal_noise_deg"])
    nonempty = int(np.count_nonzero(np.diff(model.table.offsets)))
    rows = []
    for g_index in range(cfg["grasps"]):
        g = simulate.grasp(model, rng, n=4, position_noise=cfg["position_noise"],
                           normal_noise_deg=cfg["normal_noise_deg"], noise="bounded")
        cond = pair_conditions(g.contacts)
        times = []
        for _ in range(cfg["query_repeats"]):
            t = time.perf_counter()
            first, _, _ = model.table.query_all(cond, tolerance, "exact", True)
            times.append(time.perf_counter() - t)
        admissible = sum(len(model.table.query(d, a, tolerance.distance, tolerance.angle))
                         for d, a in zip(cond.distance, cond.angle))
        rows.append({"grasp": g_index, "facets": model.num_facets, "stored_pairs": len(model.features.k),
                     "bins_total": int(np.prod(bins)), "bins_nonempty": nonempty,
                     "candidates": candidate_count(model.table, cond, tolerance), "admissible": admissible,
                     "ordered_after_direction": len(first), "time_query_ms": 1e3 * min(times),
                     "time_table_ms": 1e3 * float(np.median([b["table"] for b in builds])),
                     "time_build_ms": 1e3 * float(np.median([b["total"] for b in builds]))})
    return rows


def grid(cfg):
    """One axis varied at a time, the others at the default."""
    default = dict(zip(AXES, cfg["default_bins"]))
    return [{"object": obj, "axis": axis, **{**default, axis: value}}
            for obj in cfg["objects"] for axis in AXES for value in cfg[axis]]


def make_sweep(cfg):
    return sweep.Sweep(NAME, functools.partial(task, cfg=cfg), grid(cfg), seeds=1, base_seed=cfg["base_seed"],
                       seed_axes=("object",), config=cfg)


# --------------------------------------------------------------------------- figure

def plot(out_dir):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    c = sweep.read_columns(out / sweep.TIMINGS_CSV)
    objs = list(dict.fromkeys(c["object"]))
    styles = dict(zip(objs, ("-o", "--s", ":^")))
    colors = dict(zip(AXES, ("tab:blue", "tab:orange", "tab:green")))
    names = {"p_dmax": "p_Δmax", "p_dmin": "p_Δmin", "p_alpha": "p_α"}
    with plt.rc_context(sweep.PAPER_RC):
        fig, axes = plt.subplots(1, 3, figsize=(sweep.PAGE_WIDTH, 2.4))
        panels = (("candidates", "candidates per grasp (pairs in visited bins)"),
                  ("time_query_ms", "S_ij query time per grasp (ms)"), ("time_table_ms", "table build time (ms)"))
        for ax, (col, label) in zip(axes, panels):
            for obj in objs:
                for axis in AXES:
                    sel = (c["object"] == obj) & (c["axis"] == axis)
                    values = np.unique(c[axis][sel])
                    y = [np.median(c[col][sel & (c[axis] == v)]) for v in values]
                    ax.plot(values, y, styles[obj], color=colors[axis], ms=3, mfc="none" if obj != objs[0] else colors[axis])
                if col == "candidates":
                    sel = c["object"] == obj
                    ax.axhline(np.median(c["admissible"][sel]), color="0.4", lw=0.7, ls=styles[obj][:-1] or "-")
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ticks = np.unique(np.concatenate([c[a] for a in AXES]))
            ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
            ax.minorticks_off()
            sweep.plain_log_axis(ax, "y")
            ax.set_xlabel("bins along the varied axis")
            ax.set_ylabel(label)
        axes[0].text(0.02, 0.02, "grey: admissible pairs (exact test)", transform=axes[0].transAxes, fontsize=6)
        default = sweep.load_config(NAME, False)["default_bins"]
        handles = [plt.Line2D([], [], color=colors[a], label=f"vary {names[a]}") for a in AXES]
        handles += [plt.Line2D([], [], color="k", ls=styles[o][:-1], marker=styles[o][-1], ms=3,
                               mfc="k" if o == objs[0] else "none",
                               label=f"{o} (m = {int(c['facets'][c['object'] == o][0])})") for o in objs]
        fig.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, 0.02), ncol=len(handles), frameon=False)
        fig.suptitle(f"Bins of K3: one axis varied, others at the default {tuple(default)}", y=1.0)
        return sweep.save_figure(fig, out, NAME)


def summary(out_dir):
    c = sweep.read_columns(Path(out_dir) / sweep.TIMINGS_CSV)
    lines = []
    for obj in dict.fromkeys(c["object"]):
        for axis in AXES:
            sel = (c["object"] == obj) & (c["axis"] == axis)
            for v in np.unique(c[axis][sel]):
                s = sel & (c[axis] == v)
                lines.append(f"{obj:10s} {axis:8s}={int(v):4d}: candidates {np.median(c['candidates'][s]):9.0f} "
                             f"admissible {np.median(c['admissible'][s]):7.0f} query {np.median(c['time_query_ms'][s]):7.3f} ms "
                             f"table build {np.median(c['time_table_ms'][s]):7.1f} ms")
    return "\n".join(lines)


def main(argv=None):
    return sweep.main(NAME, __doc__, make_sweep, plot, summary, argv)


if __name__ == "__main__":
    sys.exit(main())
