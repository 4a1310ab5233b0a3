"""Cramér–Rao bounds of the pose on the realistic-contacts protocol: how accurate any unbiased
estimator can be from 4 fingertip contacts at the benchmark's noise (uncertainty.bounds).

Per grasp (fingertip.approach as in experiments/configs/realistic_contacts.json, "common"):
the Fisher information of the pose with each contact's facet known, and with its location on
the surface unknown (a quadric fitted to the mesh vertices within --neighbourhood of the
diameter; the slides marginalised out). One error is drawn from each bound per grasp; the
table gives the median and p90 of those draws. Objects with a continuous symmetry have no
rotation bound about their axis and are marked. Writes results/pose_bounds/summary.md and
bounds.csv::

    .venv/bin/python experiments/pose_bounds.py ycb:011_banana ycb:035_power_drill --grasps 300
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from contactpose.harness import sweep
from contactpose.model.object_model import merged_mesh, mesh_diameter
from contactpose.sim import fingertip, objects, ycb
from contactpose.uncertainty.bounds import local_quadric, pose_information

ROOT = Path(__file__).resolve().parent.parent
CONFIG = json.loads((ROOT / "experiments" / "configs" / "realistic_contacts.json").read_text())["common"]


def draws(info, rng):
    """One pose error (rotation in degrees, translation) drawn from N(0, info⁻¹)."""
    xi = rng.multivariate_normal(np.zeros(6), np.linalg.inv(info))
    return np.degrees(np.linalg.norm(xi[:3])), np.linalg.norm(xi[3:])


def bounds(name, grasps, frac, neighbourhood, rng):
    """(facet-known, location-unknown) error draws, (grasps, 2) each, for one object and radius."""
    mesh = objects.load(name)
    merged = merged_mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces))
    vertices, faces = np.asarray(merged.vertices), np.asarray(merged.faces)
    tree, D = cKDTree(vertices), mesh_diameter(vertices)
    sx, sn = CONFIG["position_noise_frac"] * D, np.radians(CONFIG["normal_noise_deg"])
    known, unknown = [], []
    while len(known) < grasps:
        got = fingertip.approach(vertices, faces, rng, CONFIG["fingers"], frac * D, cone_deg=CONFIG["cone_deg"],
                                 mode=CONFIG["mode"])
        if not got.hit.all():
            continue
        fits = [local_quadric(vertices, tree, x, nu, neighbourhood * D) for x, nu in zip(got.points, got.normals)]
        known.append(draws(pose_information(got.points, got.normals, sx, sn), rng))
        unknown.append(draws(pose_information(got.points, got.normals, sx, sn, hessians=np.stack([H for _, H in fits]),
                                              tangents=np.stack([T for T, _ in fits])), rng))
    return np.array(known), np.array(unknown), D


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("objects", nargs="+")
    parser.add_argument("--grasps", type=int, default=300)
    parser.add_argument("--radius", type=float, default=0.0, help="fingertip radius, fraction of the diameter")
    parser.add_argument("--neighbourhood", type=float, default=0.03,
                        help="quadric fit radius, fraction of the diameter (default: 0.03)")
    parser.add_argument("--seed", type=int, default=99)
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    out = ROOT / "results" / "pose_bounds"
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    rows = []
    for name in args.objects:
        known, unknown, D = bounds(name, args.grasps, args.radius, args.neighbourhood, rng)
        row = {"object": name, "symmetry": ycb.symmetry(name) or "", "radius_frac": args.radius,
               "neighbourhood_frac": args.neighbourhood, "grasps": args.grasps}
        for label, x in (("facet_known", known), ("location_unknown", unknown)):
            row[f"{label}_rot_deg_median"], row[f"{label}_rot_deg_p90"] = np.median(x[:, 0]), np.percentile(x[:, 0], 90)
            row[f"{label}_trans_pct_median"] = 100 * np.median(x[:, 1]) / D
        rows.append(row)
        print(row, flush=True)
    sweep.write_rows(out / "bounds.csv", rows)
    lines = ["# Cramér–Rao bounds of the pose (4 fingertip contacts, σ_x = "
             f"{100 * CONFIG['position_noise_frac']:g} % of the diameter, σ_n = {CONFIG['normal_noise_deg']:g}°)", "",
             f"Fingertip radius {100 * args.radius:g} % of the diameter, {args.grasps} grasps per object, quadric "
             f"neighbourhood {100 * args.neighbourhood:g} % of the diameter; median / p90 of one error drawn per grasp.",
             "Continuous symmetry: the rotation about the axis is not observable, the figure is not a bound.", "",
             "| object | sym. | facet known: rotation (°) | location unknown: rotation (°) | translation (% diam.), "
             "known / unknown |", "|---|---|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['object']} | {r['symmetry']} | {r['facet_known_rot_deg_median']:.2f} / "
                     f"{r['facet_known_rot_deg_p90']:.2f} | {r['location_unknown_rot_deg_median']:.2f} / "
                     f"{r['location_unknown_rot_deg_p90']:.2f} | {r['facet_known_trans_pct_median']:.2f} / "
                     f"{r['location_unknown_trans_pct_median']:.2f} |")
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
