"""A quick check of the default method on the realistic-contacts protocol: YCB objects built
with the defaults (surface regions on fine meshes), N grasps per fingertip radius, no baselines.

The protocol and its numbers are those of experiments/configs/realistic_contacts.json
("common"): a uniformly random pose, 4 fingertips (fingertip.approach, cone 30°) of radius
0-5 % of the diameter, Gaussian sensor noise 0.25 % / 1°, localize told the noise. The
generator is seeded per object and radius (base_seed), so the grasps are not the
benchmark's cells. Prints one line per object and radius and writes them to
results/regions_check/summary.md::

    .venv/bin/python experiments/regions_check.py ycb:011_banana ycb:013_apple --grasps 25
"""

from __future__ import annotations

import argparse
import collections
import json
import resource
import time
import warnings
from pathlib import Path

import numpy as np

from contactpose import Contacts, ObjectModel, localize
from contactpose.geometry import metrics
from contactpose.geometry.sampling import perturb_normals
from contactpose.model.object_model import merged_mesh
from contactpose.sim import fingertip, objects
from contactpose.sim import grasps as simulate

ROOT = Path(__file__).resolve().parent.parent
CONFIG = json.loads((ROOT / "experiments" / "configs" / "realistic_contacts.json").read_text())["common"]


def grasp(model, vertices, faces, rng, radius):
    """Contacts and the true pose of one grasp. -> (Contacts, pose, face_only)"""
    return grasp_with_free_space(model, vertices, faces, rng, radius)[:3]


def grasp_with_free_space(model, vertices, faces, rng, radius):
    """:func:`grasp`, and the free space the fingertips of the hitting draw swept before they
    touched (world frame, free_spacing_frac of the diameter apart, without noise; it draws
    nothing). -> (Contacts, pose, face_only, points (F, 3))"""
    D = model.diameter
    pose = simulate.random_pose(rng, max_translation=CONFIG["translation_frac"] * D)
    got = fingertip.approach(vertices, faces, rng, CONFIG["fingers"], radius, cone_deg=CONFIG["cone_deg"],
                             mode=CONFIG["mode"])
    while not got.hit.all():
        got = fingertip.approach(vertices, faces, rng, CONFIG["fingers"], radius, cone_deg=CONFIG["cone_deg"],
                                 mode=CONFIG["mode"])
    R, t = pose[:3, :3], pose[:3, 3]
    sx = CONFIG["position_noise_frac"] * D
    world = got.points @ R.T + t + rng.normal(0.0, sx, got.points.shape)
    finger = perturb_normals(-(got.normals @ R.T), np.radians(CONFIG["normal_noise_deg"]), rng)
    free = fingertip.swept_free_points(got, CONFIG["free_spacing_frac"] * D) @ R.T + t
    return Contacts(world, finger_normals=finger), pose, all(str(k) == fingertip.FACE for k in got.features), free


def check(model, vertices, faces, frac, grasps, seed):
    """One line of figures for one radius."""
    rng = np.random.default_rng(seed)
    D, sx = model.diameter, CONFIG["position_noise_frac"] * model.diameter
    rows, statuses = [], collections.Counter()
    for _ in range(grasps):
        contacts, pose, face_only = grasp(model, vertices, faces, rng, frac * D)
        r = localize(model, contacts, position_noise=sx, normal_noise_deg=CONFIG["normal_noise_deg"])
        statuses[r.status] += 1
        poses = r.hypotheses.arrays.poses
        a = metrics.adds_many(poses[:200], pose, model.surface_points, model.surface_tree) if len(poses) else [np.inf]
        best = poses[0] if len(poses) else None
        rows.append((np.min(a) < CONFIG["found_adds_frac"] * D, a[0] < CONFIG["top1_adds_frac"] * D, face_only,
                     r.timing["total"], len(poses), r.num_assignments,
                     np.nan if best is None else metrics.rotation_error_deg(best, pose),
                     np.nan if best is None else 1e3 * metrics.translation_error(best, pose)))
    x = np.array(rows, dtype=float)
    fo = x[:, 2] > 0

    def share(sel):
        return f"{x[sel, 1].mean():.0%} of {sel.sum()}" if sel.any() else "-"
    return (f"r = {100 * frac:.0f} %: found {x[:, 0].mean():.0%}, top-1 {x[:, 1].mean():.0%} (face-only {share(fo)}, "
            f"edge/vertex {share(~fo)}), no hypothesis {np.mean(x[:, 4] == 0):.0%}; best pose median "
            f"{np.nanmedian(x[:, 6]):.2f}° / {np.nanmedian(x[:, 7]):.1f} mm; online median {1e3 * np.median(x[:, 3]):.0f} ms,"
            f" p95 {1e3 * np.percentile(x[:, 3], 95):.0f} ms; hypotheses median {np.median(x[:, 4]):.0f} "
            f"(assignments {np.median(x[:, 5]):.0f}); {dict(statuses)}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("objects", nargs="+")
    parser.add_argument("--grasps", type=int, default=25)
    parser.add_argument("--region-deg", type=float, default=None,
                        help="grow regions at this angle instead of the default (patch_tol_deg='auto')")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    out = ROOT / "results" / "regions_check" / ("" if args.region_deg is None else f"regions_{args.region_deg:g}deg")
    out.mkdir(parents=True, exist_ok=True)
    lines = []
    for name in args.objects:
        start = time.perf_counter()
        tol = "auto" if args.region_deg is None else args.region_deg
        model = ObjectModel.from_mesh(objects.load(name), patch_tol_deg=tol)
        build = time.perf_counter() - start
        merged = merged_mesh(model.vertices, model.faces)
        vertices, faces = np.asarray(merged.vertices), np.asarray(merged.faces)
        lines.append(f"{name}: build {build:.1f} s, {model.patches.count} regions at {model.patches.tol_deg:g}°, "
                     f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")
        print(lines[-1], flush=True)
        for k, frac in enumerate(CONFIG["radius_fracs"]):
            lines.append("  " + check(model, vertices, faces, frac, args.grasps, CONFIG["base_seed"] + k))
            print(lines[-1], flush=True)
        (out / "summary.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
