"""LM versus factor-graph fusion (issue 4): pose error and top-1 success on the same inputs.

Every grasp is localized once (``localize``, method "fast": all admissible facet tuples,
closed-form poses, ranked by χ²). The solvers then see the same hypothesis set:

* ``closed-form``: the top-ranked closed-form hypothesis;
* ``paper-lm``: the paper's LM on eq. (7) (``solvers.lm.fit_lm``) on the best
  ``LM_CANDIDATES`` closed-form hypotheses, started from the vision prior's pose (the
  paper's use of vision, §4) and ranked by eq. (7);
* ``fg``: ``refine_hypotheses`` without a prior (Huber, k = 20), top by probability;
* ``fg-prior``: the same with the vision prior as a PriorFactorPose3.

The prior is the true pose perturbed by ξ ~ N(0, diag(σ_r², σ_t²)) (right perturbation)
and carries exactly that covariance. Top-1 success: the top hypothesis puts the surface
where the truth does (ADD-S < SAME_CLASS_ADDS_FRAC · diameter, so symmetric twins count);
``strict``: rotation < 5° and translation < 5 % of the diameter.

Parts: ``sweep`` (contact noise and prior noise, four objects), ``acceptance`` (prior on
the near-symmetric box and cylinder, ≥ 300 grasps each), ``outlier`` (n = 5, one point
moved by 20 % of the diameter; hypotheses by leave-one-out, see :func:`outlier_hypotheses`),
``speed`` (refinement time per hypothesis, Jacobian check). Writes CSV + config under
results/lm_vs_factor_graph/ and draws the figures from the CSVs alone::

    .venv/bin/python experiments/lm_vs_factor_graph.py            # full run
    .venv/bin/python experiments/lm_vs_factor_graph.py --quick    # smoke run, ~1 min
    .venv/bin/python experiments/lm_vs_factor_graph.py --plot-only
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import os
import time
import warnings

import gtsam
import numpy as np

from contactpose import objects, simulate
from contactpose.contacts import Contacts, Tolerance
from contactpose.geometry import point_triangle_distance
from contactpose.localize import PosePrior, localize
from contactpose.metrics import SAME_CLASS_ADDS_FRAC, adds, pose_success, rotation_error_deg, translation_error
from contactpose.model import ObjectModel
from contactpose.residuals import paper_cost, paper_offset_residuals, normal_residuals
from contactpose.solvers import factor_graph as fg
from contactpose.solvers.lm import fit_lm_all

log = logging.getLogger("lm_vs_factor_graph")

AMBIGUOUS_OBJECTS = ("box", "cylinder")
DISTINCT_OBJECTS = ("banana", "rock")
#: (σ_x as a fraction of the diameter, σ_n in degrees), sensor noise levels of the sweep.
CONTACT_NOISE = ((0.001, 0.5), (0.0025, 1.0), (0.005, 2.0), (0.0075, 3.0))
DEFAULT_CONTACT = (0.0025, 1.0)
#: (σ_r in degrees, σ_t as a fraction of the diameter) of the vision prior.
PRIOR_NOISE = ((2.0, 0.01), (5.0, 0.025), (10.0, 0.05), (20.0, 0.10), (40.0, 0.20))
DEFAULT_PRIOR = (10.0, 0.05)
#: The paper's LM runs on this many of the best closed-form hypotheses (it would run on all).
LM_CANDIDATES = 20
OUTLIER_FRAC = 0.20
#: Leave-one-out: keep this many hypotheses of each 4-contact subset.
OUTLIER_PER_SUBSET = 20
METHODS = ("closed-form", "paper-lm", "fg", "fg-prior")
OUTLIER_METHODS = ("closed-form", "paper-lm", "fg-none", "fg-huber", "fg-cauchy")
FULL = dict(sweep_grasps=60, acceptance_grasps=300, outlier_grasps=300, speed_refinements=200, jacobian_trials=200)
QUICK = dict(sweep_grasps=4, acceptance_grasps=15, outlier_grasps=10, speed_refinements=60, jacobian_trials=20)


# ----------------------------------------------------------------- helpers ---

def noisy_prior(T_true, sigma_rot_deg, sigma_trans, rng):
    """PosePrior at T_true · Exp(ξ), ξ ~ N(0, diag(σ_r² I, σ_t² I)), with that covariance."""
    xi = np.concatenate([rng.normal(0.0, np.radians(sigma_rot_deg), 3), rng.normal(0.0, sigma_trans, 3)])
    pose = gtsam.Pose3(T_true).retract(xi).matrix()
    return PosePrior(pose, sigma_rot_deg=sigma_rot_deg, sigma_trans=sigma_trans)


def score(model, T_est, T_true):
    """Top-1 metrics of one estimate (None: no estimate)."""
    if T_est is None:
        return dict(success=0, strict=0, adds_frac=np.nan, rot_err_deg=np.nan, trans_err_frac=np.nan)
    d = adds(T_est, T_true, model.surface_points, model.surface_tree) / model.diameter
    return dict(success=int(d < SAME_CLASS_ADDS_FRAC), strict=int(pose_success(T_est, T_true, model.diameter)),
                adds_frac=float(d),
                rot_err_deg=float(rotation_error_deg(T_est, T_true)),
                trans_err_frac=float(translation_error(T_est, T_true) / model.diameter))


def paper_lm_top(model, contacts, arrays, start):
    """The paper's LM on eq. (7) for the best LM_CANDIDATES rows; the pose of least ℒ."""
    top = arrays.take(slice(0, LM_CANDIDATES))
    if len(top.cost) == 0:
        return None
    normals = model.planes.normals[top.facets]
    T, cost, _ = fit_lm_all(normals, model.planes.offsets[top.facets], contacts.points,
                            contacts.finger_normals, start)
    return T[int(np.argmin(cost))]


def localize_arrays(model, contacts, sx, sn):
    r = localize(model, contacts, position_noise=sx, normal_noise_deg=sn)
    return r.hypotheses.arrays, r.timing["total"]


def reachable(model, refinement, T_true):
    """Whether some refined hypothesis is in the truth's pose class (search and k, not ranking)."""
    limit = SAME_CLASS_ADDS_FRAC * model.diameter
    return int(any(adds(T, T_true, model.surface_points, model.surface_tree) < limit for T in refinement.poses))


# ------------------------------------------------------------------- sweep ---

def run_grasp(model, name, g, sx_frac, sn_deg, priors, rng, part):
    """All methods on one grasp, for each (σ_r, σ_t frac) prior level. -> list of CSV rows

    Besides the truth, each method's top-1 is compared with the same method applied to the
    true facet tuple alone (``right_hypothesis``): that separates choosing the right
    hypothesis from how well its pose is determined (a free direction is known only as
    well as the prior knows it).
    """
    sx = sx_frac * model.diameter
    tol = Tolerance.from_noise(sx, sn_deg)
    arrays, t_loc = localize_arrays(model, g.contacts, sx, sn_deg)
    true_arrays = fg.closed_form_arrays(model, g.contacts, g.facets[None], tol)
    base = dict(part=part, object=name, sigma_x_frac=sx_frac, sigma_n_deg=sn_deg, n_hyp=len(arrays.cost),
                determined=int(not true_arrays.fit.underdetermined[0]))
    rows = []
    found = len(arrays.cost) > 0
    clock = time.perf_counter()
    ref = fg.refine_hypotheses(model, g.contacts, arrays, tol) if found else None
    t_fg = time.perf_counter() - clock
    fg_amb = int(fg.ambiguous(model, ref).ambiguous) if found else 0
    oracle_fg = fg.refine_hypotheses(model, g.contacts, true_arrays, tol).poses[0]
    for sr, st in priors:
        prior = noisy_prior(g.pose, sr, st * model.diameter, rng)
        level = dict(base, prior_rot_deg=sr, prior_trans_frac=st)

        def row(method, T, oracle, seconds, ambiguous=0, reach=-1, p_top=np.nan):
            return dict(level, method=method, seconds=seconds, ambiguous=ambiguous, reachable=reach, p_top=p_top,
                        right_hypothesis=same_class(model, T, oracle), **score(model, T, g.pose))
        rows.append(row("closed-form", arrays.poses[0] if found else None, true_arrays.poses[0], t_loc))
        clock = time.perf_counter()
        T_lm = paper_lm_top(model, g.contacts, arrays, prior.pose)
        rows.append(row("paper-lm", T_lm, paper_lm_top(model, g.contacts, true_arrays, prior.pose),
                        t_loc + time.perf_counter() - clock))
        rows.append(row("fg", ref.poses[0] if found else None, oracle_fg, t_loc + t_fg, fg_amb,
                        p_top=ref.probability[0] if found else np.nan))
        clock = time.perf_counter()
        refp = fg.refine_hypotheses(model, g.contacts, arrays, tol, prior=prior) if found else None
        t_p = time.perf_counter() - clock
        oracle = fg.refine_hypotheses(model, g.contacts, true_arrays, tol, prior=prior).poses[0]
        rows.append(row("fg-prior", refp.poses[0] if found else None, oracle, t_loc + t_p,
                        int(fg.ambiguous(model, refp).ambiguous) if found else 0,
                        reachable(model, refp, g.pose) if found else 0, refp.probability[0] if found else np.nan))
    return rows


def same_class(model, T, T_ref):
    """1 when T puts the surface where T_ref does (ADD-S < SAME_CLASS_ADDS_FRAC · diameter)."""
    if T is None:
        return 0
    return int(adds(T, T_ref, model.surface_points, model.surface_tree) < SAME_CLASS_ADDS_FRAC * model.diameter)


def sweep(models, n_grasps, rng):
    """Contact-noise levels at the default prior, and prior levels at the default contact noise."""
    rows = []
    for name, model in models.items():
        for sx_frac, sn_deg in CONTACT_NOISE:
            priors = PRIOR_NOISE if (sx_frac, sn_deg) == DEFAULT_CONTACT else (DEFAULT_PRIOR,)
            for _ in range(n_grasps):
                g = simulate.grasp(model, rng, n=4, position_noise=sx_frac * model.diameter,
                                   normal_noise_deg=sn_deg)
                rows += run_grasp(model, name, g, sx_frac, sn_deg, priors, rng, "sweep")
            log.info("sweep %s σ=(%.4g, %g°): %d rows", name, sx_frac, sn_deg, len(rows))
    return rows


def acceptance(models, n_grasps, rng):
    """Prior 10° / 5 % on the near-symmetric objects, default contact noise."""
    rows = []
    for name in AMBIGUOUS_OBJECTS:
        model = models[name]
        for _ in range(n_grasps):
            g = simulate.grasp(model, rng, n=4, position_noise=DEFAULT_CONTACT[0] * model.diameter,
                               normal_noise_deg=DEFAULT_CONTACT[1])
            rows += run_grasp(model, name, g, *DEFAULT_CONTACT, (DEFAULT_PRIOR,), rng, "acceptance")
        log.info("acceptance %s: %d grasps", name, n_grasps)
    return rows


# ----------------------------------------------------------------- outlier ---

def outlier_hypotheses(model, contacts, tol):
    """5-contact facet tuples for contacts of which one may be far off (no outlier handling
    in ``localize``): for each contact j, ``localize`` the other four (normal tolerance),
    keep their best OUTLIER_PER_SUBSET tuples and give contact j the facet that best fits it
    under that tuple's pose (whitened point-to-triangle distance plus normal residual).
    Adds ``localize`` on all contacts. -> HypothesisArrays (closed-form, ranked by χ²)
    """
    n = contacts.n
    valid = np.flatnonzero(model.planes.valid)
    tuples = []
    for j in range(n):
        keep = np.delete(np.arange(n), j)
        sub = Contacts(contacts.points[keep], finger_normals=contacts.finger_normals[keep])
        arrays = localize(model, sub, position_noise=tol.position_noise,
                          normal_noise_deg=np.degrees(tol.normal_noise)).hypotheses.arrays
        arrays = arrays.take(slice(0, OUTLIER_PER_SUBSET))
        for facets, T in zip(arrays.facets, arrays.poses):
            p = T[:3, :3].T @ (contacts.points[j] - T[:3, 3])
            dist = point_triangle_distance(np.broadcast_to(p, (len(valid), 3)), model.triangles[valid])
            r_n = model.planes.normals[valid] @ T[:3, :3].T + contacts.finger_normals[j]
            cost = dist**2 / tol.position_noise**2 + np.sum(r_n**2, axis=1) / tol.normal_noise**2
            full = np.empty(n, dtype=np.int64)
            full[keep], full[j] = facets, valid[np.argmin(cost)]
            tuples.append(full)
    whole = localize(model, contacts, position_noise=tol.position_noise,
                     normal_noise_deg=np.degrees(tol.normal_noise)).hypotheses.arrays
    tuples += list(whole.facets[:OUTLIER_PER_SUBSET])
    if not tuples:
        return fg.closed_form_arrays(model, contacts, np.zeros((0, n), np.int64), tol)
    return fg.closed_form_arrays(model, contacts, np.unique(np.array(tuples), axis=0), tol)


def displaced_grasp(model, rng, n=5):
    """A grasp whose contact 0..n-1 (random) has its point moved by OUTLIER_FRAC · diameter."""
    sx_frac, sn_deg = DEFAULT_CONTACT
    g = simulate.grasp(model, rng, n=n, position_noise=sx_frac * model.diameter, normal_noise_deg=sn_deg)
    points = g.contacts.points.copy()
    direction = rng.normal(size=3)
    j = int(rng.integers(n))
    points[j] += OUTLIER_FRAC * model.diameter * direction / np.linalg.norm(direction)
    return simulate.Grasp(Contacts(points, finger_normals=g.contacts.finger_normals), g.pose, g.facets,
                          g.points_object), j


def outlier(models, n_grasps, rng):
    rows = []
    sx_frac, sn_deg = DEFAULT_CONTACT
    for name in DISTINCT_OBJECTS:
        model = models[name]
        tol = Tolerance.from_noise(sx_frac * model.diameter, sn_deg)
        for _ in range(n_grasps):
            g, j = displaced_grasp(model, rng)
            clock = time.perf_counter()
            with warnings.catch_warnings():  # "contacts span more than the diameter": the outlier
                warnings.simplefilter("ignore", UserWarning)
                arrays = outlier_hypotheses(model, g.contacts, tol)
            t_h = time.perf_counter() - clock
            base = dict(part="outlier", object=name, sigma_x_frac=sx_frac, sigma_n_deg=sn_deg,
                        n_hyp=len(arrays.cost), determined=1, prior_rot_deg=np.nan, prior_trans_frac=np.nan,
                        ambiguous=0, reachable=-1, right_hypothesis=-1, p_top=np.nan)
            if len(arrays.cost) == 0:
                rows += [dict(base, method=m, seconds=t_h, **score(model, None, g.pose)) for m in OUTLIER_METHODS]
                continue
            rows.append(dict(base, method="closed-form", seconds=t_h, **score(model, arrays.poses[0], g.pose)))
            clock = time.perf_counter()
            normals = model.planes.normals[arrays.facets]
            offsets = model.planes.offsets[arrays.facets]
            T_lm = np.array([fit_lm_all(nk[None], dk[None], g.contacts.points, g.contacts.finger_normals, T0)[0][0]
                             for nk, dk, T0 in zip(normals, offsets, arrays.poses)])
            r_n = normal_residuals(T_lm[:, :3, :3], normals, g.contacts.finger_normals)
            cost = paper_cost(r_n, paper_offset_residuals(T_lm[:, :3, 3], g.contacts.points,
                                                          g.contacts.finger_normals, offsets))
            rows.append(dict(base, method="paper-lm", seconds=t_h + time.perf_counter() - clock,
                             **score(model, T_lm[int(np.argmin(cost))], g.pose)))
            for robust in ("none", "huber", "cauchy"):
                clock = time.perf_counter()
                ref = fg.refine_hypotheses(model, g.contacts, arrays, tol, robust=robust, k=0)
                amb = int(fg.ambiguous(model, ref).ambiguous)
                rows.append(dict(base, method=f"fg-{robust}", seconds=t_h + time.perf_counter() - clock,
                                 ambiguous=amb, reachable=reachable(model, ref, g.pose), p_top=ref.probability[0],
                                 **score(model, ref.poses[0], g.pose)))
        log.info("outlier %s: %d grasps", name, n_grasps)
    return rows


# ------------------------------------------------------------------- speed ---

def speed(models, n_refinements, n_trials, rng, repeats=3):
    """Refinement time per hypothesis (refine_hypotheses defaults: k = 20, Huber, n = 4) and
    the largest relative Jacobian error against numerical derivatives.

    Each grasp's refinement runs ``repeats`` times; per hypothesis the least wall and
    thread-CPU time is kept (the machine is shared, and the least time is the one least
    disturbed), then the median over hypotheses is reported, with the first run's wall time.
    """
    from gtsam.utils.numerical_derivative import numericalDerivative11

    out = {}
    for name in DISTINCT_OBJECTS:
        model = models[name]
        sx_frac, sn_deg = DEFAULT_CONTACT
        tol = Tolerance.from_noise(sx_frac * model.diameter, sn_deg)
        first, wall, cpu, iters, per_call, top = [], [], [], [], [], []
        while len(wall) < n_refinements:
            g = simulate.grasp(model, rng, n=4, position_noise=tol.position_noise, normal_noise_deg=sn_deg)
            arrays, _ = localize_arrays(model, g.contacts, tol.position_noise, sn_deg)
            if len(arrays.cost) == 0:
                continue
            runs, calls = [], []
            for _ in range(repeats):
                clock = time.perf_counter()
                runs.append(fg.refine_hypotheses(model, g.contacts, arrays, tol))
                calls.append((time.perf_counter() - clock) / min(fg.DEFAULT_K, len(arrays.cost)))
            first += runs[0].seconds.tolist()
            wall += np.min([r.seconds for r in runs], axis=0).tolist()
            cpu_min = np.min([r.cpu_seconds for r in runs], axis=0)
            cpu += cpu_min.tolist()
            top.append(cpu_min[0])
            iters += runs[0].iterations.tolist()
            per_call.append(min(calls))
        out[name] = dict(refinements=len(wall), median_ms_wall_first_run=1e3 * float(np.median(first)),
                         median_ms_wall=1e3 * float(np.median(wall)), median_ms_cpu=1e3 * float(np.median(cpu)),
                         p90_ms_cpu=1e3 * float(np.percentile(cpu, 90)),
                         median_ms_cpu_most_probable=1e3 * float(np.median(top)),
                         median_ms_wall_whole_call_per_hypothesis=1e3 * float(np.median(per_call)),
                         median_iterations=float(np.median(iters)), mean_iterations=float(np.mean(iters)))
        log.info("speed %s: %s", name, out[name])
    worst = 0.0
    model = models["rock"]
    tol = Tolerance.from_noise(DEFAULT_CONTACT[0] * model.diameter, DEFAULT_CONTACT[1])
    for trial in range(n_trials):
        robust = fg.ROBUST_KERNELS[trial % 3]
        g = simulate.grasp(model, rng, n=5, where="centroid")
        tri = model.triangles[g.facets]
        p = g.points_object + 1.5 * (tri[:, 0] - g.points_object) * (np.arange(5) >= 2)[:, None]  # 3 outside
        p += rng.normal(0, 0.002, (5, 1)) * model.planes.normals[g.facets]
        R, t = g.pose[:3, :3], g.pose[:3, 3]
        contacts = Contacts(p @ R.T + t, object_normals=simulate.perturb_normals(
            model.planes.normals[g.facets] @ R.T, np.radians(2.0), rng))
        pose = gtsam.Pose3(g.pose).retract(np.concatenate([rng.normal(0, 0.002, 3), rng.normal(0, 2e-4, 3)]))
        data = fg.pack_contacts(model, contacts, g.facets)
        pk = fg.kernel_params(tol, robust)
        _, J = fg.contact_residuals(pose.matrix(), data, pk)
        J_num = numericalDerivative11(
            lambda P: fg.contact_residuals(P.matrix(), data, pk, jacobian=False)[0], pose, 1e-6)
        worst = max(worst, float(np.abs(J - J_num).max() / np.abs(J).max()))
    out["jacobian_max_rel_error"] = worst
    out["jacobian_trials"] = n_trials
    return out


# ----------------------------------------------------------------- figures ---

def _read(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def summarise(rows):
    """Success rates and median errors per (part, object, noise, prior, method)."""
    keys = ("part", "object", "sigma_x_frac", "sigma_n_deg", "prior_rot_deg", "prior_trans_frac", "method")
    groups = {}
    for r in rows:
        groups.setdefault(tuple(str(r[k]) for k in keys), []).append(r)
    out = []
    for key, grp in groups.items():
        f = {c: np.array([float(r[c]) for r in grp]) for c in
             ("success", "strict", "adds_frac", "rot_err_deg", "trans_err_frac", "seconds", "reachable",
              "ambiguous", "right_hypothesis", "determined", "n_hyp")}
        det = f["determined"] == 1
        found = f["n_hyp"] > 0
        out.append(dict(zip(keys, key), grasps=len(grp), success=f["success"].mean(), strict=f["strict"].mean(),
                        right_hypothesis=_valid_mean(f["right_hypothesis"]), determined_grasps=int(det.sum()),
                        success_determined=f["success"][det].mean() if det.any() else np.nan,
                        found_grasps=int(found.sum()),
                        success_found=f["success"][found].mean() if found.any() else np.nan,
                        success_found_determined=f["success"][found & det].mean() if (found & det).any() else np.nan,
                        right_hypothesis_found=_valid_mean(f["right_hypothesis"][found]),
                        median_adds_frac=np.nanmedian(f["adds_frac"]),
                        median_rot_err_deg=np.nanmedian(f["rot_err_deg"]),
                        median_trans_err_frac=np.nanmedian(f["trans_err_frac"]),
                        reachable=_valid_mean(f["reachable"]),
                        flagged_ambiguous=f["ambiguous"].mean(),
                        median_seconds=np.median(f["seconds"])))
    return out


def _valid_mean(x):
    """Mean of the entries >= 0 (-1 marks "not measured"), NaN when none."""
    x = x[x >= 0]
    return float(x.mean()) if len(x) else np.nan


def plot(out_dir):
    """Figures from grasps.csv alone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = summarise(_read(os.path.join(out_dir, "grasps.csv")))
    names = AMBIGUOUS_OBJECTS + DISTINCT_OBJECTS
    fig, axes = plt.subplots(3, len(names), figsize=(4 * len(names), 10), squeeze=False)
    style = {"closed-form": "o-", "paper-lm": "s--", "fg": "^-", "fg-prior": "D-"}
    levels = ", ".join(f"{sn:g}" for _, sn in CONTACT_NOISE)
    for col, name in enumerate(names):
        for method in METHODS:
            sel = [s for s in summary if s["part"] == "sweep" and s["object"] == name and s["method"] == method]
            noise = sorted((s for s in sel if float(s["prior_rot_deg"]) == DEFAULT_PRIOR[0]),
                           key=lambda s: float(s["sigma_x_frac"]))
            prior = sorted((s for s in sel if float(s["sigma_x_frac"]) == DEFAULT_CONTACT[0]),
                           key=lambda s: float(s["prior_rot_deg"]))
            x = [100 * float(s["sigma_x_frac"]) for s in noise]
            axes[0, col].plot(x, [100 * s["success"] for s in noise], style[method], label=method)
            axes[1, col].plot([float(s["prior_rot_deg"]) for s in prior], [100 * s["success"] for s in prior],
                              style[method], label=method)
            axes[2, col].plot(x, [100 * s["median_adds_frac"] for s in noise], style[method], label=method)
        axes[0, col].set_title(f"{name}{' (near-symmetric)' if name in AMBIGUOUS_OBJECTS else ''}")
        axes[0, col].set_xlabel(f"contact noise σx (% diameter; σn = {levels}°)")
        axes[1, col].set_xlabel("prior σ_rot (°; σ_trans = σ_rot/2 % diameter)")
        axes[2, col].set_xlabel("contact noise σx (% diameter)")
        axes[1, col].set_xscale("log")
        axes[1, col].set_xticks([p for p, _ in PRIOR_NOISE], [f"{p:g}" for p, _ in PRIOR_NOISE])
        axes[1, col].minorticks_off()
        axes[2, col].set_yscale("log")
        axes[2, col].axhline(100 * SAME_CLASS_ADDS_FRAC, color="k", lw=0.8, ls=":")
        for row in range(2):
            axes[row, col].set_ylim(-3, 103)
    axes[0, 0].set_ylabel("top-1 success % (prior 10°/5%)")
    axes[1, 0].set_ylabel("top-1 success % (σx 0.25%, σn 1°)")
    axes[2, 0].set_ylabel("median ADD-S of top-1 (% diameter)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("LM vs factor graph, n = 4: top-1 success = ADD-S < 5% diameter (symmetric twins count)")
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(os.path.join(out_dir, f"lm_vs_factor_graph.{ext}"), dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    acc = [s for s in summary if s["part"] == "acceptance"]
    bars = (("success", "all grasps", None), ("success_found", "search found hypotheses", "//"),
            ("success_found_determined", "... and contacts determine the pose", "xx"))
    for i, name in enumerate(AMBIGUOUS_OBJECTS):
        for j, (col, label, hatch) in enumerate(bars):
            vals = [next((100 * float(s[col]) for s in acc if s["object"] == name and s["method"] == m), np.nan)
                    for m in METHODS]
            axes[0].bar(np.arange(len(METHODS)) + 0.14 * (3 * i + j) - 0.35, vals, width=0.14, hatch=hatch,
                        color=f"C{i}", edgecolor="k", lw=0.4, label=f"{name}: {label}")
    axes[0].set_xticks(np.arange(len(METHODS)), METHODS)
    axes[0].axhline(99, color="k", lw=0.8, ls=":")
    axes[0].set_ylim(0, 105)
    axes[0].set_title("prior 10° / 5% on near-symmetric objects, n = 4")
    axes[0].set_ylabel("top-1 success % (ADD-S < 5% diameter)")
    axes[0].legend(fontsize=7, loc="lower left")
    out = [s for s in summary if s["part"] == "outlier"]
    for i, name in enumerate(DISTINCT_OBJECTS):
        vals = [next((100 * s["success"] for s in out if s["object"] == name and s["method"] == m), np.nan)
                for m in OUTLIER_METHODS]
        axes[1].bar(np.arange(len(OUTLIER_METHODS)) + 0.4 * i - 0.2, vals, width=0.4, label=name)
    axes[1].set_xticks(np.arange(len(OUTLIER_METHODS)), OUTLIER_METHODS)
    axes[1].axhline(90, color="k", lw=0.8, ls=":")
    axes[1].set_ylim(0, 105)
    axes[1].set_title(f"n = 5, one point moved {OUTLIER_FRAC:.0%} of the diameter")
    axes[1].legend()
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(os.path.join(out_dir, f"acceptance.{ext}"), dpi=120)
    plt.close(fig)


def _write_csv(path, rows):
    fields = list(rows[0])
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)


# -------------------------------------------------------------------- main ---

def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="few grasps: a smoke run")
    parser.add_argument("--out", default="results/lm_vs_factor_graph")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--parts", nargs="*", default=["sweep", "acceptance", "outlier", "speed"])
    parser.add_argument("--plot-only", action="store_true", help="redraw the figures from the CSVs")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    os.makedirs(args.out, exist_ok=True)
    if args.plot_only:
        plot(args.out)
        return 0
    sizes = QUICK if args.quick else FULL
    config = dict(seed=args.seed, quick=args.quick, parts=args.parts, contact_noise=CONTACT_NOISE,
                  default_contact=DEFAULT_CONTACT, prior_noise=PRIOR_NOISE, default_prior=DEFAULT_PRIOR,
                  lm_candidates=LM_CANDIDATES, outlier_frac=OUTLIER_FRAC, outlier_per_subset=OUTLIER_PER_SUBSET,
                  fg_k=fg.DEFAULT_K, huber_k=fg.HUBER_K, cauchy_k=fg.CAUCHY_K,
                  ambiguous_probability=fg.AMBIGUOUS_PROBABILITY, success_adds_frac=SAME_CLASS_ADDS_FRAC,
                  **sizes)
    with open(os.path.join(args.out, "config.json"), "w") as fh:
        json.dump(config, fh, indent=1)
    rng = np.random.default_rng(args.seed)
    models = {name: ObjectModel.from_mesh(objects.load(name)) for name in AMBIGUOUS_OBJECTS + DISTINCT_OBJECTS}
    for model in models.values():  # compile / load the numba kernels outside the timings
        g = simulate.grasp(model, np.random.default_rng(0), n=4)
        fg.refine_hypotheses(model, g.contacts, localize_arrays(model, g.contacts, 0.001, 1.0)[0],
                             Tolerance.from_noise(0.001, 1.0))
    rows = []
    if "sweep" in args.parts:
        rows += sweep(models, sizes["sweep_grasps"], rng)
    if "acceptance" in args.parts:
        rows += acceptance(models, sizes["acceptance_grasps"], rng)
    if "outlier" in args.parts:
        rows += outlier(models, sizes["outlier_grasps"], rng)
    if rows:
        _write_csv(os.path.join(args.out, "grasps.csv"), rows)
        _write_csv(os.path.join(args.out, "summary.csv"), summarise(_read(os.path.join(args.out, "grasps.csv"))))
    if "speed" in args.parts:
        result = speed(models, sizes["speed_refinements"], sizes["jacobian_trials"], rng)
        with open(os.path.join(args.out, "speed.json"), "w") as fh:
            json.dump(result, fh, indent=1)
    if os.path.exists(os.path.join(args.out, "grasps.csv")):
        plot(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
