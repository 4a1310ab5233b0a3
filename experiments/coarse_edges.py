"""The default method on coarse meshes with sharp edges: the built-in coarse objects, rounded
fingertips that may touch an edge or a vertex, the realistic-contacts noise.

The figures any search over the surface must beat where the facet table is used (issue "a search
whose work follows the shape"; research/surface_search.md). The grasps are those of
experiments/regions_check.py (its ``grasp``: a uniformly random pose, 4 fingertips of radius r,
cone 30°, Gaussian noise 0.25 % of the diameter and 1°, localize told the noise), seeded per
object and radius; localize is told the fingertips' radius (``finger_radius``). Per grasp:
whether every contact is on a face, the status, the hypotheses
listed, whether the best and whether any listed hypothesis is right (rotation < 5° and
translation < 5 % of the diameter, modulo the object's symmetry group), the best pose's errors
and the online time. Writes results/coarse_edges/grasps.csv and summary.md, split into
face-only grasps and grasps with an edge or vertex contact::

    .venv/bin/python experiments/coarse_edges.py                 # 4 objects x 2 radii x 50 grasps
    .venv/bin/python experiments/coarse_edges.py rock --grasps 5
"""

from __future__ import annotations

import argparse
import csv
import platform
import time
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from regions_check import CONFIG, grasp

from contactpose import ObjectModel, localize
from contactpose.geometry.metrics import SUCCESS_ROT_DEG, SUCCESS_TRANS_FRAC
from contactpose.localize import warm_up
from contactpose.model.object_model import merged_mesh
from contactpose.model.symmetry import symmetry
from contactpose.sim import objects

ROOT = Path(__file__).resolve().parent.parent
OBJECTS = ("rock", "rock1k", "carton", "banana512")
RADII = (0.02, 0.05)
FIELDS = ("object", "facets", "radius_frac", "grasp", "face_only", "status", "hypotheses", "best_right", "any_right",
          "rot_err_deg", "trans_err_frac", "seconds")


def run_object(name, grasps, radii):
    """One row per grasp of one object (dicts with FIELDS)."""
    model = ObjectModel.from_mesh(objects.load(name))
    merged = merged_mesh(model.vertices, model.faces)
    vertices, faces = np.asarray(merged.vertices), np.asarray(merged.faces)
    group, D = symmetry(model), model.diameter
    rows = []
    noise = dict(position_noise=CONFIG["position_noise_frac"] * D, normal_noise_deg=CONFIG["normal_noise_deg"],
                 diagnose=False)
    warm_up(model, grasp(model, vertices, faces, np.random.default_rng(0), radii[0] * D)[0], **noise)
    for k, frac in enumerate(radii):
        rng = np.random.default_rng(CONFIG["base_seed"] + k)
        for g in range(grasps):
            contacts, pose, face_only = grasp(model, vertices, faces, rng, frac * D)
            result = localize(model, contacts, finger_radius=frac * D, **noise)
            poses = result.hypotheses.arrays.poses
            rot, trans = group.errors(poses, pose) if len(poses) else (np.array([np.inf]), np.array([np.inf]))
            right = (rot < SUCCESS_ROT_DEG) & (trans < SUCCESS_TRANS_FRAC * D)
            rows.append(dict(object=name, facets=model.num_facets, radius_frac=frac, grasp=g, face_only=face_only,
                             status=result.status, hypotheses=len(poses), best_right=bool(right[0]),
                             any_right=bool(right.any()), rot_err_deg=float(rot[0]), trans_err_frac=float(trans[0] / D),
                             seconds=result.timing["total"]))
    return rows


def summary(rows):
    """Markdown lines: per object and radius, all grasps and the face-only / edge-vertex split."""
    lines = ["| object | facets | r | split | grasps | no hypothesis | any listed right | best right | "
             "best rotation error, median | online median / p95 |", "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
    for name, frac, cell in cells(rows):
        for split, sel in (("all", cell), ("face only", [r for r in cell if r["face_only"]]),
                           ("edge or vertex", [r for r in cell if not r["face_only"]])):
            if not sel:
                continue
            t = np.array([r["seconds"] for r in sel]) * 1e3
            rot = np.array([r["rot_err_deg"] for r in sel])
            lines.append(
                f"| {name} | {sel[0]['facets']} | {100 * frac:g} % | {split} | {len(sel)} | "
                f"{outcomes(sel)} | {np.median(rot[np.isfinite(rot)]) if np.isfinite(rot).any() else np.nan:.2f}° | "
                f"{np.median(t):.0f} / {np.percentile(t, 95):.0f} ms |")
    return lines


def cells(rows):
    """The rows of each object and radius: [(object, radius_frac, rows)], the objects in the
    order they first appear, the radii ascending."""
    names = list(dict.fromkeys(r["object"] for r in rows))
    keys = sorted({(r["object"], r["radius_frac"]) for r in rows}, key=lambda k: (names.index(k[0]), k[1]))
    return [(name, frac, [r for r in rows if r["object"] == name and r["radius_frac"] == frac]) for name, frac in keys]


def outcomes(sel):
    """'no hypothesis | any listed right | best right' shares of the rows ``sel``, for a table row."""
    return (f"{np.mean([r['hypotheses'] == 0 for r in sel]):.0%} | {np.mean([r['any_right'] for r in sel]):.0%} | "
            f"{np.mean([r['best_right'] for r in sel]):.0%}")


def arguments(argv, doc, grasps, name):
    """The command line of a coarse-objects experiment: objects, --grasps, --out (results/<name>)."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("objects", nargs="*", default=list(OBJECTS))
    parser.add_argument("--grasps", type=int, default=grasps)
    parser.add_argument("--out", type=Path, default=ROOT / "results" / name)
    return parser.parse_args(argv)


def main(argv=None):
    args = arguments(argv, __doc__, 50, "coarse_edges")
    warnings.simplefilter("ignore")
    args.out.mkdir(parents=True, exist_ok=True)
    start, rows = time.perf_counter(), []
    for name in args.objects:
        rows += run_object(name, args.grasps, RADII)
        print(f"{name}: {len(rows)} grasps so far, {time.perf_counter() - start:.0f} s", flush=True)
    write(args.out, FIELDS, rows, f"# The default method on coarse meshes with sharp edges\n\n{len(rows)} grasps",
          f"coarse_edges.py --grasps {args.grasps}", time.perf_counter() - start, summary(rows))
    return 0


def write(out, fields, rows, title, command, seconds, lines):
    """grasps.csv (``fields`` of ``rows``) and summary.md (``title``, the date, machine, seconds and
    ``experiments/<command>``, what right means, then the table ``lines``) in ``out``; prints the table."""
    with open(out / "grasps.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    head = (f"{title}, {datetime.now(timezone.utc):%Y-%m-%d}, {platform.machine()}, {seconds:.0f} s "
            f"(`experiments/{command}`). Right: rotation < {SUCCESS_ROT_DEG:g}° and translation < "
            f"{100 * SUCCESS_TRANS_FRAC:g} % of the diameter, modulo the object's symmetry group.\n")
    (out / "summary.md").write_text(head + "\n" + "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    raise SystemExit(main())
