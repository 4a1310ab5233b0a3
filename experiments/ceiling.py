"""The best strict top-1 a ranking by fit can reach on the benchmark's grasps, beside ours.

On a nearly symmetric object a wrong placement can fit four contacts as well as the true one,
or better; a ranking by the surface χ² then names the truth only where it fits best, and a tie
is a fair choice (contactpose.harness.ceiling, research/ceiling.md). The grasps are those of
experiments/coarse_edges.py (the same seeds, so row k is its grasp k): 4 rounded fingertips of
radius r, cone 30°, Gaussian noise 0.25 % of the diameter and 1°, localize told the noise and
the radius. Per grasp: whether our best pose is strictly right (rotation < 5° and translation
< 5 % of the diameter, modulo the symmetry group), the true placement's least surface χ² and
the best wrong one's, the true placement's posterior, the ceiling (1 if the true placement fits
best, 1/m if it ties with m − 1 others, else 0), and the Cramér–Rao RMS rotation error of the
grasp (the strict target of issue "a search whose work follows the shape" counts grasps where it
is below 2°). Writes results/ceiling/grasps.csv and summary.md, keeping the rows of objects not
in this run. With ``--free-space`` localize is also given the free space the fingertips swept
(the points the benchmark gives CHSEL), so that a wrong placement whose object meets it is no
competitor: ours and the ceiling with free space (default out: results/ceiling_free)::

    .venv/bin/python experiments/ceiling.py                        # 4 objects x 2 radii x 50 grasps
    .venv/bin/python experiments/ceiling.py banana512 --grasps 5
    .venv/bin/python experiments/ceiling.py ycb:025_mug --grasps 20 --free-space
"""

from __future__ import annotations

import csv
import sys
import time
import warnings

import numpy as np
from coarse_edges import OBJECTS, RADII, arguments, cells, write
from regions_check import CONFIG, grasp_with_free_space
from scipy.spatial import cKDTree

from contactpose.cli.common import model_or_mesh
from contactpose.contacts import FreeSpace
from contactpose.harness.ceiling import placement_fits
from contactpose.model.object_model import merged_mesh
from contactpose.uncertainty.bounds import rotation_bound_deg

#: The strict target counts grasps whose Cramér–Rao RMS rotation error is below this (degrees).
BOUND_DEG = 2.0
FIELDS = ("object", "facets", "radius_frac", "grasp", "face_only", "bound_rot_deg", "best_right", "best_rot_deg",
          "best_trans_frac", "true_chi2", "wrong_chi2", "ties", "p_true", "ceiling", "wrong_fits_better", "drifted",
          "seconds")


def run_object(name, grasps, radii, free_space=False):
    """One row per grasp of one object (dicts with FIELDS); free_space: localize is given the
    space the fingertips swept."""
    model = model_or_mesh(name)
    merged = merged_mesh(model.vertices, model.faces)
    vertices, faces = np.asarray(merged.vertices), np.asarray(merged.faces)
    tree, D = cKDTree(vertices), model.diameter
    sx, sn = CONFIG["position_noise_frac"] * D, CONFIG["normal_noise_deg"]
    rows = []
    for k, frac in enumerate(radii):
        rng = np.random.default_rng(CONFIG["base_seed"] + k)
        for g in range(grasps):
            contacts, pose, face_only, free = grasp_with_free_space(model, vertices, faces, rng, frac * D)
            start = time.perf_counter()
            fits = placement_fits(model, contacts, pose, position_noise=sx, normal_noise_deg=sn,
                                  finger_radius=frac * D, free_space=FreeSpace(points=free) if free_space else None)
            R, t = pose[:3, :3], pose[:3, 3]
            bound = rotation_bound_deg(vertices, tree, D, (contacts.points - t) @ R, -contacts.finger_normals @ R,
                                       sx, np.radians(sn))
            rows.append(dict(object=name, facets=model.num_facets, radius_frac=frac, grasp=g, face_only=face_only,
                             bound_rot_deg=bound, best_right=fits.best_right, best_rot_deg=fits.best_errors[0],
                             best_trans_frac=fits.best_errors[1] / D, true_chi2=fits.true_chi2,
                             wrong_chi2=float(fits.wrong_chi2.min()) if len(fits.wrong_chi2) else np.inf,
                             ties=fits.ties, p_true=float(fits.posterior[0]), ceiling=fits.ceiling,
                             wrong_fits_better=fits.wrong_fits_better, drifted=fits.drifted,
                             seconds=time.perf_counter() - start))
    return rows


def earlier_rows(path):
    """The rows of an earlier run's grasps.csv, typed as run_object makes them ([] if none)."""
    if not path.exists():
        return []
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    flags = ("face_only", "best_right", "wrong_fits_better", "drifted")
    counts = ("facets", "grasp", "ties")
    return [{k: v if k == "object" else v == "True" if k in flags else int(v) if k in counts else float(v)
             for k, v in r.items()} for r in rows]


def summary(rows):
    """Markdown lines: per object and radius, all grasps and those with a bound below BOUND_DEG."""
    lines = ["| object | r | grasps | ours: best strictly right | ceiling (the truth fits best; ties shared) | "
             "true placement's posterior, mean | a wrong placement fits as well | truth's fit drifted | "
             "ours: rotation error, median | Cramér–Rao RMS rotation, median |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, frac, cell in cells(rows):
        for split, sel in (("all", cell), (f"bound < {BOUND_DEG:g}°", [r for r in cell
                                                                       if r["bound_rot_deg"] < BOUND_DEG])):
            if sel:
                lines.append(f"| {name} | {100 * frac:g} % | {len(sel)} ({split}) | "
                             f"{np.mean([r['best_right'] for r in sel]):.0%} | {np.mean([r['ceiling'] for r in sel]):.0%} | "
                             f"{np.mean([r['p_true'] for r in sel]):.0%} | "
                             f"{np.mean([r['wrong_fits_better'] for r in sel]):.0%} | "
                             f"{sum(r['drifted'] for r in sel)} | {np.median([r['best_rot_deg'] for r in sel]):.2f}° | "
                             f"{np.median([r['bound_rot_deg'] for r in sel]):.2f}° |")
    return lines


def main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    free = "--free-space" in argv
    argv = [a for a in argv if a != "--free-space"]
    args = arguments(argv, __doc__, 50, "ceiling_free" if free else "ceiling")
    warnings.simplefilter("ignore")
    args.out.mkdir(parents=True, exist_ok=True)
    start, rows, names = time.perf_counter(), [], args.objects or OBJECTS
    kept = [r for r in earlier_rows(args.out / "grasps.csv") if r["object"] not in names]
    for name in names:  # written after each object, so that a long run keeps what it has
        rows += run_object(name, args.grasps, RADII, free)
        print(f"{name}: {len(rows)} grasps so far, {time.perf_counter() - start:.0f} s", flush=True)
        write(args.out, FIELDS, kept + rows, f"# The best strict top-1 a ranking by fit can reach, beside ours\n\n"
              f"{len(kept) + len(rows)} grasps ({len(kept)} of other objects kept from an earlier run)",
              f"ceiling.py --grasps {args.grasps} {' '.join(args.objects)}{' --free-space' * free}".strip(),
              time.perf_counter() - start,
              summary(kept + rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
