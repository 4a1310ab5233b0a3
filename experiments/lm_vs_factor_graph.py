"""LM versus factor-graph fusion: pose error and top-1 success on the same inputs.

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
objects whose contacts alone are ambiguous: box, cylinder, the two-fold symmetric twin_rock
and the three-fold symmetric tri_rock, ≥ 300 grasps each, through
``localize(..., solver="factor-graph")``), ``outlier`` (n = 5, one point moved by 20 % of
the diameter, through ``localize(..., max_outliers=1)``), ``speed`` (refinement time per
hypothesis, Jacobian check). Writes CSV + config under results/lm_vs_factor_graph/ (rows
of the parts run replace that part's rows in grasps.csv) and draws the figures from the CSVs alone::

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

from contactpose.contacts import Contacts, Tolerance
from contactpose.costs import association, facet
from contactpose.costs import robust as kernels
from contactpose.costs.facet import normal_residuals
from contactpose.costs.paper import paper_cost, paper_offset_residuals
from contactpose.geometry.metrics import SAME_CLASS_ADDS_FRAC, adds, pose_success, rotation_error_deg, translation_error
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.options import AMBIGUOUS_PROBABILITY, DEFAULT_REFINE, OUTLIER_PENALTY, ROBUST
from contactpose.scoring import refine
from contactpose.scoring.classes import pose_classes
from contactpose.scoring.rank import closed_form_arrays, refined_arrays
from contactpose.scoring.status import ambiguous
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.solvers.lm import fit_lm_all
from contactpose.types import PosePrior

log = logging.getLogger("lm_vs_factor_graph")

AMBIGUOUS_OBJECTS = ("box", "cylinder")
#: Acceptance 1: contacts alone leave a discrete choice (symmetric twins, equally fitting poses).
#: tri_rock comes last, so the other objects draw the same grasps as before it was added.
ACCEPTANCE_OBJECTS = ("box", "cylinder", "twin_rock", "tri_rock")
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
METHODS = ("closed-form", "paper-lm", "fg", "fg-prior")
OUTLIER_METHODS = ("closed-form", "paper-lm", "fg-none", "fg-huber", "fg-cauchy", "fg-huber-all")
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


def refined_ambiguous(model, contacts, refinement, arrays, tolerance):
    """The library's ambiguity rule on a factor-graph refinement: its hypotheses' pose
    classes, weighted by their probabilities (scoring.status.ambiguous)."""
    refined = refined_arrays(model, contacts, refinement, arrays.fit.take(refinement.index), tolerance)
    return ambiguous(pose_classes(model, refined, fits=np.ones(len(refined.cost), bool)))


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
    true_arrays = closed_form_arrays(model, g.contacts, g.facets[None], tol)
    base = dict(part=part, object=name, sigma_x_frac=sx_frac, sigma_n_deg=sn_deg, n_hyp=len(arrays.cost),
                determined=int(not true_arrays.fit.underdetermined[0]))
    rows = []
    found = len(arrays.cost) > 0
    clock = time.perf_counter()
    ref = refine.refine_hypotheses(model, g.contacts, arrays, tol) if found else None
    t_fg = time.perf_counter() - clock
    fg_amb = int(refined_ambiguous(model, g.contacts, ref, arrays, tol)) if found else 0
    oracle_fg = refine.refine_hypotheses(model, g.contacts, true_arrays, tol).poses[0]
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
        refp = refine.refine_hypotheses(model, g.contacts, arrays, tol, prior=prior) if found else None
        t_p = time.perf_counter() - clock
        oracle = refine.refine_hypotheses(model, g.contacts, true_arrays, tol, prior=prior).poses[0]
        rows.append(row("fg-prior", refp.poses[0] if found else None, oracle, t_loc + t_p,
                        int(refined_ambiguous(model, g.contacts, refp, arrays, tol)) if found else 0,
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
    for name in AMBIGUOUS_OBJECTS + DISTINCT_OBJECTS:
        model = models[name]
        for sx_frac, sn_deg in CONTACT_NOISE:
            priors = PRIOR_NOISE if (sx_frac, sn_deg) == DEFAULT_CONTACT else (DEFAULT_PRIOR,)
            for _ in range(n_grasps):
                g = simulate.grasp(model, rng, n=4, position_noise=sx_frac * model.diameter,
                                   normal_noise_deg=sn_deg)
                rows += run_grasp(model, name, g, sx_frac, sn_deg, priors, rng, "sweep")
            log.info("sweep %s σ=(%.4g, %g°): %d rows", name, sx_frac, sn_deg, len(rows))
    return rows


def acceptance(models, n_grasps, rng):
    """Prior 10° / 5 % on objects whose contacts alone are ambiguous, default contact noise,
    through ``localize(..., solver="factor-graph")`` with and without the prior."""
    rows = []
    for name in ACCEPTANCE_OBJECTS:
        model = models[name]
        for _ in range(n_grasps):
            g = simulate.grasp(model, rng, n=4, position_noise=DEFAULT_CONTACT[0] * model.diameter,
                               normal_noise_deg=DEFAULT_CONTACT[1])
            rows += acceptance_grasp(model, name, g, rng)
        log.info("acceptance %s: %d grasps", name, n_grasps)
    return rows


def acceptance_grasp(model, name, g, rng):
    """fg-prior and fg (library path) on one grasp. -> two CSV rows

    ``right_hypothesis``: the top-1 is within the strict thresholds (5°, 5 %) of the same
    refinement run on the true facet tuple alone (the oracle), i.e. the factor graph chose
    the right hypothesis, twin included; ``free_err_sigma``: for grasps whose true tuple
    leaves translation free, the top-1's error along the free directions over the prior's σ_t;
    ``rescued``: 0, or 1 when ``localize`` searched again at wider tolerances, 2 when it also
    added the prior-pose assignment (its warning).
    """
    sx, (sr, st) = DEFAULT_CONTACT[0] * model.diameter, DEFAULT_PRIOR
    prior = noisy_prior(g.pose, sr, st * model.diameter, rng)
    tol = Tolerance.from_noise(sx, DEFAULT_CONTACT[1])
    true_arrays = closed_form_arrays(model, g.contacts, g.facets[None], tol)
    fit = true_arrays.fit
    base = dict(part="acceptance", object=name, sigma_x_frac=DEFAULT_CONTACT[0], sigma_n_deg=DEFAULT_CONTACT[1],
                prior_rot_deg=sr, prior_trans_frac=st, determined=int(not fit.underdetermined[0]),
                free_translation=int(fit.free_translation_mask[0].sum()), free_rotation=int(fit.free_rotation_mask[0]),
                reachable=-1)
    rows = []
    for method, p in (("fg-prior", prior), ("fg", None)):
        oracle = refine.refine_hypotheses(model, g.contacts, true_arrays, tol, prior=p).poses[0]
        clock = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            r = localize(model, g.contacts, position_noise=sx, normal_noise_deg=DEFAULT_CONTACT[1], prior=p,
                         solver="factor-graph")
        seconds = time.perf_counter() - clock
        rescued = [str(w.message) for w in caught if "searched again" in str(w.message)]
        T = r.best.pose if r.best is not None else None
        free = fit.free_translation[0][fit.free_translation_mask[0]]
        err = np.nan if T is None or not len(free) else float(np.linalg.norm(free @ (T[:3, 3] - g.pose[:3, 3])))
        rows.append(dict(base, method=method, seconds=seconds, n_hyp=r.num_hypotheses, status=r.status,
                         rescued=2 if any("best-fitting facet" in m for m in rescued) else int(bool(rescued)),
                         ambiguous=int(r.status == "ambiguous"),
                         p_top=r.best.probability if r.best is not None else np.nan,
                         right_hypothesis=int(T is not None and bool(pose_success(T, oracle, model.diameter))),
                         free_err_sigma=err / (st * model.diameter), **score(model, T, g.pose)))
    return rows


# ----------------------------------------------------------------- outlier ---

def completed(model, contacts, arrays, tol):
    """Facet tuples of ``arrays`` with each unassigned finger given its best-fitting facet
    under the hypothesis's closed-form pose, for methods that assign every finger. -> (H, n)"""
    facets = arrays.facets.copy()
    for h in np.flatnonzero((facets < 0).any(axis=1)):
        facets[h] = np.where(facets[h] < 0, association.nearest_fit_facets(model, contacts, arrays.poses[h], tol), facets[h])
    return facets


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
    for name in DISTINCT_OBJECTS:
        model = models[name]
        for _ in range(n_grasps):
            g, j = displaced_grasp(model, rng)
            with warnings.catch_warnings():  # "contacts span more than the diameter": the outlier
                warnings.simplefilter("ignore", UserWarning)
                rows += outlier_grasp(model, name, g, j)
        log.info("outlier %s: %d grasps", name, n_grasps)
    return rows


def outlier_grasp(model, name, g, j):
    """Every outlier method on one displaced grasp. -> CSV rows

    ``localize(..., max_outliers=1)`` gives the shared hypothesis set (each finger may be
    left unassigned, at OUTLIER_PENALTY): ``closed-form`` is its top row; ``paper-lm`` runs
    eq. (7) LM from each row's closed form on the completed tuple (:func:`completed`) and
    keeps the least ℒ; ``fg-<kernel>`` is ``localize(..., max_outliers=1,
    solver="factor-graph", robust=<kernel>)``; ``fg-huber-all`` the default factor graph
    without ``max_outliers`` (every finger assigned).
    """
    sx, sn = DEFAULT_CONTACT[0] * model.diameter, DEFAULT_CONTACT[1]
    tol = Tolerance.from_noise(sx, sn)
    opts = dict(position_noise=sx, normal_noise_deg=sn)
    clock = time.perf_counter()
    arrays = localize(model, g.contacts, max_outliers=1, **opts).hypotheses.arrays
    t_h = time.perf_counter() - clock
    base = dict(part="outlier", object=name, sigma_x_frac=DEFAULT_CONTACT[0], sigma_n_deg=sn, n_hyp=len(arrays.cost),
                determined=1, prior_rot_deg=np.nan, prior_trans_frac=np.nan, ambiguous=0, right_hypothesis=-1,
                p_top=np.nan, displaced=j)
    found = len(arrays.cost) > 0
    rows = [dict(base, method="closed-form", seconds=t_h, reachable=-1,
                 **score(model, arrays.poses[0] if found else None, g.pose))]
    clock = time.perf_counter()
    T_lm = None
    if found:
        facets = completed(model, g.contacts, arrays, tol)
        normals, offsets = model.planes.normals[facets], model.planes.offsets[facets]
        T_all = np.array([fit_lm_all(nk[None], dk[None], g.contacts.points, g.contacts.finger_normals, T0)[0][0]
                          for nk, dk, T0 in zip(normals, offsets, arrays.poses)])
        r_n = normal_residuals(T_all[:, :3, :3], normals, g.contacts.finger_normals)
        cost = paper_cost(r_n, paper_offset_residuals(T_all[:, :3, 3], g.contacts.points,
                                                      g.contacts.finger_normals, offsets))
        T_lm = T_all[int(np.argmin(cost))]
    rows.append(dict(base, method="paper-lm", seconds=t_h + time.perf_counter() - clock, reachable=-1,
                     **score(model, T_lm, g.pose)))
    for method, robust, outliers in (("fg-none", "none", 1), ("fg-huber", "huber", 1), ("fg-cauchy", "cauchy", 1),
                                     ("fg-huber-all", "huber", 0)):
        clock = time.perf_counter()
        r = localize(model, g.contacts, max_outliers=outliers, solver="factor-graph", robust=robust, **opts)
        seconds = time.perf_counter() - clock
        best = r.best
        rows.append(dict(base, method=method, seconds=seconds, n_hyp=r.num_hypotheses,
                         ambiguous=int(r.status == "ambiguous"), p_top=best.probability if best else np.nan,
                         reachable=int(best is not None and list(best.outliers) == [j]),
                         **score(model, best.pose if best else None, g.pose)))
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
                runs.append(refine.refine_hypotheses(model, g.contacts, arrays, tol))
                calls.append((time.perf_counter() - clock) / min(DEFAULT_REFINE, len(arrays.cost)))
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
        robust = ROBUST[trial % 3]
        g = simulate.grasp(model, rng, n=5, where="centroid")
        tri = model.triangles[g.facets]
        p = g.points_object + 1.5 * (tri[:, 0] - g.points_object) * (np.arange(5) >= 2)[:, None]  # 3 outside
        p += rng.normal(0, 0.002, (5, 1)) * model.planes.normals[g.facets]
        R, t = g.pose[:3, :3], g.pose[:3, 3]
        contacts = Contacts(p @ R.T + t, object_normals=simulate.perturb_normals(
            model.planes.normals[g.facets] @ R.T, np.radians(2.0), rng))
        pose = gtsam.Pose3(g.pose).retract(np.concatenate([rng.normal(0, 0.002, 3), rng.normal(0, 2e-4, 3)]))
        data = facet.pack_contacts(model, contacts, g.facets)
        pk = facet.kernel_params(tol, robust)
        _, J = facet.factor_rows(pose.matrix(), data, pk)
        J_num = numericalDerivative11(
            lambda P: facet.factor_rows(P.matrix(), data, pk, jacobian=False)[0], pose, 1e-6)
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
        f = {c: np.array([float(r.get(c) or "nan") for r in grp]) for c in
             ("success", "strict", "adds_frac", "rot_err_deg", "trans_err_frac", "seconds", "reachable",
              "ambiguous", "right_hypothesis", "determined", "n_hyp", "rescued", "free_err_sigma")}
        det = f["determined"] == 1
        rescued = f["rescued"] > 0  # NaN (parts without rescue) compares False
        found = (f["n_hyp"] > 0) & ~rescued
        free = np.isfinite(f["free_err_sigma"])
        out.append(dict(zip(keys, key), grasps=len(grp), success=f["success"].mean(), strict=f["strict"].mean(),
                        strict_determined=_mean(f["strict"][det]), strict_found=_mean(f["strict"][found]),
                        strict_found_determined=_mean(f["strict"][found & det]),
                        undetermined_grasps=int((~det).sum()), success_undetermined=_mean(f["success"][~det]),
                        strict_undetermined=_mean(f["strict"][~det]),
                        free_within_prior_sigma=_mean(f["free_err_sigma"][free] < 1.0),
                        rescued_grasps=int(rescued.sum()), success_rescued=_mean(f["success"][rescued]),
                        strict_rescued=_mean(f["strict"][rescued]),
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


def _mean(x):
    """Mean, NaN when empty."""
    return float(np.mean(x)) if len(x) else np.nan


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

    fig, axes = plt.subplots(1, 2, figsize=(13, 6))
    acc = [s for s in summary if s["part"] == "acceptance"]
    bars = (("success", "ADD-S, all grasps", ".."), ("strict", "strict, all grasps", None),
            ("strict_determined", "strict, contacts determine the pose", "//"),
            ("right_hypothesis", "right hypothesis (= oracle)", "xx"))
    methods = ("fg-prior", "fg")
    width = 0.8 / (len(ACCEPTANCE_OBJECTS) * len(bars))
    for i, name in enumerate(ACCEPTANCE_OBJECTS):
        for j, (col, label, hatch) in enumerate(bars):
            vals = [next((100 * float(s[col]) for s in acc if s["object"] == name and s["method"] == m), np.nan)
                    for m in methods]
            axes[0].bar(np.arange(len(methods)) + width * (len(bars) * i + j) - 0.4, vals, width=width, hatch=hatch,
                        color=f"C{i}", edgecolor="k", lw=0.4, label=f"{name}: {label}")
    axes[0].set_xticks(np.arange(len(methods)), ["with prior 10° / 5 %", "without prior"])
    axes[0].axhline(99, color="k", lw=0.8, ls=":")
    axes[0].set_ylim(0, 105)
    axes[0].set_title("objects whose contacts alone are ambiguous, n = 4")
    axes[0].set_ylabel("top-1 success % (strict: < 5°, < 5 % diameter; or ADD-S)")
    axes[0].legend(fontsize=6, loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=3)
    out = [s for s in summary if s["part"] == "outlier"]
    for i, name in enumerate(DISTINCT_OBJECTS):
        vals = [next((100 * s["success"] for s in out if s["object"] == name and s["method"] == m), np.nan)
                for m in OUTLIER_METHODS]
        axes[1].bar(np.arange(len(OUTLIER_METHODS)) + 0.4 * i - 0.2, vals, width=0.4, label=name)
    axes[1].set_xticks(np.arange(len(OUTLIER_METHODS)), OUTLIER_METHODS, fontsize=7)
    axes[1].set_ylabel("top-1 success % (ADD-S < 5 % diameter)")
    axes[1].axhline(90, color="k", lw=0.8, ls=":")
    axes[1].set_ylim(0, 105)
    axes[1].set_title(f"n = 5, one point moved {OUTLIER_FRAC:.0%} of the diameter")
    axes[1].legend()
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(os.path.join(out_dir, f"acceptance.{ext}"), dpi=120)
    plt.close(fig)


def _write_config(path, config, parts):
    """config.json maps each part to the settings of the run that last wrote its rows."""
    old = {}
    if os.path.exists(path):
        with open(path) as fh:
            old = json.load(fh)
        if "seed" in old:  # one run's config (older layout): it made all its parts
            old = {part: old for part in old.get("parts", [])}
    old.update({part: config for part in parts})
    with open(path, "w") as fh:
        json.dump(old, fh, indent=1)


def _write_csv(path, rows):
    """rows : dicts, whose keys may differ by part (missing cells are written empty)."""
    fields = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields, restval="")
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
                  lm_candidates=LM_CANDIDATES, outlier_frac=OUTLIER_FRAC, outlier_penalty=OUTLIER_PENALTY,
                  rescue_widen=refine.RESCUE_WIDEN, acceptance_objects=ACCEPTANCE_OBJECTS,
                  fg_k=DEFAULT_REFINE, huber_k=kernels.HUBER_K, cauchy_k=kernels.CAUCHY_K,
                  ambiguous_probability=AMBIGUOUS_PROBABILITY, success_adds_frac=SAME_CLASS_ADDS_FRAC,
                  **sizes)
    _write_config(os.path.join(args.out, "config.json"), config, args.parts)
    rng = np.random.default_rng(args.seed)
    names = dict.fromkeys(AMBIGUOUS_OBJECTS + DISTINCT_OBJECTS + ACCEPTANCE_OBJECTS)
    models = {name: ObjectModel.from_mesh(objects.load(name)) for name in names}
    for model in models.values():  # compile / load the numba kernels outside the timings
        g = simulate.grasp(model, np.random.default_rng(0), n=4)
        refine.refine_hypotheses(model, g.contacts, localize_arrays(model, g.contacts, 0.001, 1.0)[0],
                             Tolerance.from_noise(0.001, 1.0))
    rows = []
    if "sweep" in args.parts:
        rows += sweep(models, sizes["sweep_grasps"], rng)
    if "acceptance" in args.parts:
        rows += acceptance(models, sizes["acceptance_grasps"], rng)
    if "outlier" in args.parts:
        rows += outlier(models, sizes["outlier_grasps"], rng)
    if rows:
        path = os.path.join(args.out, "grasps.csv")
        kept = [r for r in _read(path) if r["part"] not in args.parts] if os.path.exists(path) else []
        _write_csv(path, kept + rows)
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
