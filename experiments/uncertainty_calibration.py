"""Calibration of the pose uncertainty: Laplace covariance versus emcee samples.

For each simulated grasp, the hypothesis with the true facets is refined in the factor graph
(``refine_hypotheses``, same kernel) and its pose posterior sampled (``uncertainty.sample_pose``,
default settings). The true pose's tangent coordinates at the optimum, ξ = Log(T*⁻¹ T_true),
give the smallest credible level whose region holds the truth:

* ``level_laplace``: χ²₆ CDF of ξᵀ Σ⁻¹ ξ, Σ the factor graph's marginal covariance;
* ``level_mahalanobis``: χ²₆ CDF of the Mahalanobis distance from the sample mean under
  the sample covariance;
* ``level_hpd``: the fraction of samples whose log-posterior exceeds the truth's (the
  highest-posterior-density region through the truth).

A region of nominal level α covers the truth when the level ≤ α; a calibrated method covers
it in a fraction α of the grasps. ``coverage.csv`` also splits each type by whether every
contact lies inside its facet triangle at T* (``n_outside`` = 0): where one does not, the
lateral residual is active and the Laplace covariance takes its one-sided curvature. Grasp types (object ``rock``, σ_x = 0.25 % of the
diameter, σ_n = 1°, Gaussian noise, contacts uniform on area-weighted random facets):

* ``4-contact``: n = 4 with well-spread normals, λ_min(Σ n_k n_kᵀ) ≥ 0.1 (Huber, the default);
* ``4-contact-none``: the same grasps' kind without a robust kernel (the Gaussian likelihood);
* ``3-contact``: n = 3, every grasp whose factor graph gives a covariance;
* ``near-degenerate``: n = 4 with λ_min in [0.002, 0.02]: the normals nearly leave a
  translation free (above the closed form's "undetermined" threshold, n·sin²σ_n = 0.0012).

Writes ``grasps.csv`` (one row per grasp and type), ``coverage.csv`` (the table),
``reliability.png``/``.pdf`` (drawn from ``grasps.csv`` alone) and ``config.json`` under
results/uncertainty_calibration/::

    .venv/bin/python experiments/uncertainty_calibration.py            # full run, ~10 min
    .venv/bin/python experiments/uncertainty_calibration.py --quick    # smoke run, ~1 min
    .venv/bin/python experiments/uncertainty_calibration.py --plot-only

A fine mesh of a smooth surface, the YCB banana (16,384 facets; 4-contact type only)::

    .venv/bin/python experiments/uncertainty_calibration.py --object ycb:011_banana --types 4-contact \
        --out results/uncertainty_calibration/ycb_banana
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import os
import time
import warnings

import numpy as np
from scipy.stats import chi2

from contactpose.contacts import Tolerance
from contactpose.costs import facet
from contactpose.costs import robust as kernels
from contactpose.model.object_model import ObjectModel
from contactpose.scoring import refine
from contactpose.scoring.rank import closed_form_arrays
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.uncertainty import sampling as unc

log = logging.getLogger("uncertainty_calibration")

OBJECT = "rock"
POSITION_NOISE_FRAC = 0.0025
NORMAL_NOISE_DEG = 1.0
#: name -> contacts, λ_min(Σ n nᵀ) range of the true facets' normals, robust kernel
TYPES = {
    "4-contact": dict(n=4, lam=(0.1, np.inf), robust="huber"),
    "4-contact-none": dict(n=4, lam=(0.1, np.inf), robust="none"),
    "3-contact": dict(n=3, lam=(0.0, np.inf), robust="huber"),
    "near-degenerate": dict(n=4, lam=(0.002, 0.02), robust="huber"),
}
LEVELS = (0.5, 0.68, 0.95)
METHODS = ("laplace", "mahalanobis", "hpd")
FULL = dict(grasps=200, samples=unc.DEFAULT_SAMPLES)
QUICK = dict(grasps=12, samples=1000)


def draw_grasp(model, spec, tol, rng, max_tries=10_000):
    """A grasp whose true facets' normals have λ_min(Σ n nᵀ) in spec["lam"]."""
    lo, hi = spec["lam"]
    for _ in range(max_tries):
        facets = simulate.choose_facets(model, spec["n"], rng)
        normals = model.planes.normals[facets]
        lam = float(np.linalg.eigvalsh(normals.T @ normals)[0])
        if lo <= lam <= hi:
            g = simulate.grasp(model, rng, n=spec["n"], facets=facets, position_noise=tol.position_noise,
                               normal_noise_deg=np.degrees(tol.normal_noise))
            return g, lam
    raise RuntimeError(f"no facets with λ_min in [{lo}, {hi}] in {max_tries} draws")


def run_grasp(model, g, tol, robust, n_samples, rng):
    """Levels of the truth under the three regions, and the sampler's figures. -> dict or None"""
    arrays = closed_form_arrays(model, g.contacts, g.facets[None], tol)
    ref = refine.refine_hypotheses(model, g.contacts, arrays, tol, robust=robust, k=1)
    if not ref.determined[0]:
        return None
    T, cov = ref.poses[0], ref.covariance[0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", unc.SamplingWarning)
        s = unc.sample_pose(model, g.contacts, ref.facets[0], T, cov, tol, robust=robust, n_samples=n_samples,
                            rng=rng, progress=False, surface=model.has_regions)
    post = unc.PosePosterior(model, g.contacts, ref.facets[0], T, tol, robust=robust, surface=model.has_regions)
    xi = post.tangent(g.pose)
    # contacts outside their triangle at T* (r_l > 0): there the Laplace Hessian holds the
    # lateral term's curvature, though the posterior is flat on the triangle's side
    e, _ = facet.factor_rows(T, post.data, facet.kernel_params(tol, "none"), jacobian=False)
    n_outside = int(np.sum(facet.lateral_norms(e, g.contacts.n) > 0))
    d2 = float(xi[0] @ np.linalg.solve(cov, xi[0]))
    # how the sample spread differs from Laplace: per-axis sd ratio, and the volume ratio
    sd_ratio = np.sqrt(np.diag(s.covariance) / np.diag(cov))
    return dict(
        level_laplace=chi2.cdf(d2, 6), level_mahalanobis=float(chi2.cdf(s.mahalanobis2(xi)[0], 6)),
        level_hpd=float(s.hpd_credibility(post(xi))[0]), d2_laplace=d2,
        same_facets=int(np.array_equal(ref.facets[0], g.facets)), chi2=float(ref.chi2[0]), n_outside=n_outside,
        sd_ratio_min=float(sd_ratio.min()), sd_ratio_max=float(sd_ratio.max()),
        volume_ratio=float(np.sqrt(np.linalg.det(s.covariance) / np.linalg.det(cov))),
        rot_sd_deg=float(np.degrees(np.sqrt(np.trace(cov[:3, :3]) / 3))),
        trans_sd_frac=float(np.sqrt(np.trace(cov[3:, 3:]) / 3) / model.diameter),
        seconds=s.seconds, steps=s.steps, tau=float(s.tau.max()), acceptance=s.acceptance,
        converged=int(s.converged), warned=int(any(issubclass(w.category, unc.SamplingWarning) for w in caught)),
    )


def run_type(model, name, spec, n_grasps, n_samples, tol, rng):
    rows, skipped = [], 0
    clock = time.perf_counter()
    while len(rows) < n_grasps:
        g, lam = draw_grasp(model, spec, tol, rng)
        row = run_grasp(model, g, tol, spec["robust"], n_samples, rng)
        if row is None:
            skipped += 1
            continue
        rows.append(dict(type=name, grasp=len(rows), n=spec["n"], robust=spec["robust"], lam_min=lam, **row))
        if len(rows) % 25 == 0:
            log.info("%s: %d/%d grasps, %.0f s", name, len(rows), n_grasps, time.perf_counter() - clock)
    log.info("%s: %d grasps (%d without a covariance skipped) in %.0f s", name, len(rows), skipped,
             time.perf_counter() - clock)
    return rows, skipped


SUBSETS = {"all": lambda r: True, "all inside": lambda r: int(r["n_outside"]) == 0,
           "some outside": lambda r: int(r["n_outside"]) > 0}


def coverage_table(rows):
    """Coverage of the truth by each method's regions at LEVELS, per type and subset (all
    grasps; those with every contact inside its triangle at T*; the others). -> list of dicts"""
    out = []
    for name in dict.fromkeys(r["type"] for r in rows):
        for subset, keep in SUBSETS.items():
            sub = [r for r in rows if r["type"] == name and keep(r)]
            if not sub:
                continue
            seconds = np.array([float(r["seconds"]) for r in sub])
            for method in METHODS:
                levels = np.array([float(r[f"level_{method}"]) for r in sub])
                for a in LEVELS:
                    out.append(dict(type=name, subset=subset, method=method, nominal=a,
                                    coverage=float(np.mean(levels <= a)), grasps=len(sub),
                                    binomial_se=float(np.sqrt(a * (1 - a) / len(sub))),
                                    seconds_median=float(np.median(seconds)),
                                    seconds_p95=float(np.percentile(seconds, 95)), seconds_max=float(seconds.max())))
    return out


def plot(out_dir):
    """Reliability diagram from grasps.csv alone: coverage against nominal level per type."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = _read(os.path.join(out_dir, "grasps.csv"))
    types = list(dict.fromkeys(r["type"] for r in rows))
    alpha = np.linspace(0.0, 1.0, 101)
    fig, axes = plt.subplots(1, len(types), figsize=(3.6 * len(types), 3.8), sharey=True, squeeze=False)
    style = {"laplace": ("Laplace (χ²₆)", "C0", "-"), "mahalanobis": ("emcee, sample cov.", "C1", "--"),
             "hpd": ("emcee, HPD", "C3", "-")}
    for ax, name in zip(axes[0], types):
        sub = [r for r in rows if r["type"] == name]
        band = 1.96 * np.sqrt(alpha * (1 - alpha) / len(sub))
        ax.fill_between(alpha, alpha - band, alpha + band, color="0.85", label="±1.96 binomial s.e.")
        ax.plot(alpha, alpha, color="0.4", lw=0.8)
        for method in METHODS:
            levels = np.array([float(r[f"level_{method}"]) for r in sub])
            label, color, ls = style[method]
            ax.plot(alpha, [np.mean(levels <= a) for a in alpha], color=color, ls=ls, label=label)
        for a in LEVELS:
            ax.axvline(a, color="0.7", lw=0.5, ls=":")
        ax.set_title(f"{name} ({len(sub)} grasps)", fontsize=10)
        ax.set_xlabel("nominal level")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect("equal")
    axes[0, 0].set_ylabel("coverage of the true pose")
    axes[0, 0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(os.path.join(out_dir, f"reliability.{ext}"), dpi=150)
    plt.close(fig)


def _write_csv(path, rows):
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def _read(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="few grasps: a smoke run")
    parser.add_argument("--out", default="results/uncertainty_calibration")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--object", default=OBJECT, help=f"object name (default {OBJECT})")
    parser.add_argument("--types", nargs="*", default=list(TYPES), choices=list(TYPES))
    parser.add_argument("--grasps", type=int, help="grasps per type (default 200, --quick 12)")
    parser.add_argument("--plot-only", action="store_true", help="redraw the figure from grasps.csv")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    os.makedirs(args.out, exist_ok=True)
    if args.plot_only:
        plot(args.out)
        return 0
    sizes = dict(QUICK if args.quick else FULL)
    if args.grasps:
        sizes["grasps"] = args.grasps
    model = ObjectModel.from_mesh(objects.load(args.object))
    tol = Tolerance.from_noise(POSITION_NOISE_FRAC * model.diameter, NORMAL_NOISE_DEG)
    config = dict(
        seed=args.seed, quick=args.quick, object=args.object, position_noise_frac=POSITION_NOISE_FRAC,
        normal_noise_deg=NORMAL_NOISE_DEG, noise="gaussian", where="area",
        types={k: dict(v, lam=list(v["lam"])) for k, v in TYPES.items() if k in args.types},
        levels=LEVELS, hypothesis="true facets, refined by scoring.refine.refine_hypotheses(k=1)",
        sampler=dict(walkers=unc.DEFAULT_WALKERS, init_scale=unc.INIT_SCALE, tau_chain=unc.TAU_CHAIN,
                     burn_tau=unc.BURN_TAU, thin_tau=unc.THIN_TAU, pilot_steps=unc.PILOT_STEPS,
                     first_steps=unc.FIRST_STEPS, max_steps=unc.MAX_STEPS,
                     independence_fraction=unc.INDEPENDENCE_FRACTION, independence_scale=unc.INDEPENDENCE_SCALE),
        huber_k=kernels.HUBER_K, cpus=os.cpu_count(), load_average_at_start=list(os.getloadavg()), **sizes)
    with open(os.path.join(args.out, "config.json"), "w") as fh:
        json.dump(config, fh, indent=1)
    # load the numba kernels outside the timings
    g, _ = draw_grasp(model, TYPES["4-contact"], tol, np.random.default_rng(12345))
    run_grasp(model, g, tol, "huber", 200, np.random.default_rng(0))
    seeds = np.random.SeedSequence(args.seed).spawn(len(TYPES))
    rows, skipped = [], {}
    for (name, spec), seed in zip(TYPES.items(), seeds):
        if name not in args.types:
            continue
        new, skipped[name] = run_type(model, name, spec, sizes["grasps"], sizes["samples"], tol,
                                      np.random.default_rng(seed))
        rows += new
        _write_csv(os.path.join(args.out, "grasps.csv"), rows)
    table = coverage_table(rows)
    _write_csv(os.path.join(args.out, "coverage.csv"), table)
    config["skipped_without_covariance"] = skipped
    with open(os.path.join(args.out, "config.json"), "w") as fh:
        json.dump(config, fh, indent=1)
    plot(args.out)
    for r in table:
        log.info("%-16s %-13s %-12s %.2f -> %.3f (± %.3f, %d grasps)", r["type"], r["subset"], r["method"],
                 r["nominal"], r["coverage"], r["binomial_se"], r["grasps"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
