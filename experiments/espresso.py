"""The paper's espresso-machine experiment, recreated on a simulated scan.

The paper scanned a real coffee maker into 83,846 facets, cut off regions of little
interest and reduced the mesh to 6,767 facets, then localized grasps on it. Here:

1. generate the procedural machine (``contactpose.sim.espresso.espresso_machine``, about
   80,000 facets): the *true* object;
2. scan it with the simulated range scanner (``contactpose.sim.range_scanner.scan``);
3. reconstruct, crop everything below z = 0.035 m (the plinth and the drip tray's sides:
   the machine stands there) and reduce to about 6,767 facets (``contactpose.scan.reconstruct``);
4. build the contact model of the reduced mesh (``ObjectModel.from_mesh`` defaults);
5. simulate grasps on the true object and localize them on the scanned model.

Grasps. ``simulate.grasp`` needs a model of the true object, and an 80k-facet pair table
is out of reach, so contacts are made directly: area-uniform samples of the true
surface (``trimesh.sample``), kept where the surface is exterior (not inside another
part of the machine) and within ``--max-gap`` (2 mm) of the scanned model, so every
contact lies on a surface the cropped model has. Four distinct samples, a uniform
random rotation and a translation within ±0.5 diameter, then the sensor noise of
``simulate.grasp`` (Gaussian, σ_x = 0.5 mm per axis, σ_n = 1° per tangent axis).

Localization. ``localize(model, contacts, position_noise=σ_x, normal_noise_deg=σ_n,
model_error=e)``. The model differs from the object, so the pair tolerance gets the extra
length ``e``; by default ``e`` is the scan report's 95th-percentile cloud-to-mesh
distance (``--model-error p95``). There is no separate tolerance for the model's
normal error: a contact whose nearest model facet is tilted by more than the angle
bound must be matched to a neighbouring facet that fits, or the grasp fails. The CSV
records each grasp's worst gap to the model and worst nearest-facet normal error, and
summary.json breaks the success rate down by them and by status. Top-1 success is
``metrics.pose_success`` (rotation < 5°, translation < 5 % of the model's diameter).

Scanner noise. ``--range-noise`` defaults to 0.1 % of the range (0.2–0.5 mm σ here, a
laser scanner's class). At the issue's 0.5 % (1.2–2.3 mm σ) the reduced model's facet
normals are off by 7° at the median, far outside any workable normal tolerance, and
loosening the tolerance makes the 6,767-facet search explode (research/scan.md).

Writes results/espresso/: espresso6767.ply (the reduced model's mesh), espresso_true.ply
(the generated object, 1.5 MB, regenerated on every run), grasps.csv (one row per grasp),
summary.json, config.json, espresso.png (drawn from grasps.csv alone)::

    .venv/bin/python experiments/espresso.py             # 100 grasps, about 13 min on 2 busy cores
    .venv/bin/python experiments/espresso.py --quick     # 20k -> 1,000 facets, 6 grasps, < 60 s
    .venv/bin/python experiments/espresso.py --plot-only # redraw espresso.png from grasps.csv
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import numpy as np
import open3d as o3d
import trimesh

from contactpose.contacts import Contacts, Tolerance
from contactpose.geometry.metrics import (
    SUCCESS_ROT_DEG,
    SUCCESS_TRANS_FRAC,
    pose_success,
    rotation_error_deg,
    translation_error,
)
from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.options import STATUSES
from contactpose.scan.reconstruct import ScanOptions, scan_to_mesh, surface_agreement, write_mesh
from contactpose.sim import grasps as simulate
from contactpose.sim.espresso import SIZE, espresso_machine, espresso_parts
from contactpose.sim.range_scanner import scan

#: Everything below this height is cut off: the plinth and the drip tray's sides.
CROP = (-1.0, -1.0, 0.035, 1.0, 1.0, 1.0)
#: Probe distance along the normal for the exterior test, metres.
EXTERIOR_PROBE = 0.0005
STAGES = ("pairs", "tree", "pose", "rank")
#: Bins (degrees) of a grasp's worst nearest-facet normal error, for the success breakdown.
NORMAL_ERR_EDGES = (0, 5, 10, 20, 45, 180)


def exterior_mask(points, normals):
    """(n,) bool: samples of the machine's surface that are not inside another part.

    points, normals : (n, 3) float on ``espresso_machine()``. The parts overlap without
    a union, so their surfaces also run inside the machine; a sample is exterior when a
    probe just outside it along its normal lies in no part.
    """
    parts = list(espresso_parts().values())
    scale = SIZE / trimesh.util.concatenate(parts).extents.max()  # as espresso_machine scales
    probe = o3d.core.Tensor(np.ascontiguousarray(points + EXTERIOR_PROBE * normals, dtype=np.float32))
    inside = np.zeros(len(points), dtype=bool)
    for part in parts:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor((part.vertices * scale).astype(np.float32)),
                            o3d.core.Tensor(part.faces.astype(np.uint32)))
        inside |= scene.compute_occupancy(probe).numpy() > 0.5
    return ~inside


def contact_pool(truth, mesh, args, seed):
    """Area-uniform samples of the true surface that the model covers.

    Returns points (k, 3), outward normals (k, 3), true facets (k,), and the model's gap (k,)
    and normal error in degrees (k,) at each.
    """
    points, faces = trimesh.sample.sample_surface(truth, args.surface_samples, seed=seed)
    normals = truth.face_normals[faces]
    gap, angle, _ = surface_agreement(points, normals, mesh)
    keep = exterior_mask(points, normals) & (gap <= args.max_gap)
    return points[keep], normals[keep], faces[keep], gap[keep], angle[keep]


def simulate_grasp(pool, rng, args, diameter):
    """One grasp on the true object: (simulate.Grasp, indices into the pool)."""
    points, normals, faces = pool[:3]
    idx = rng.choice(len(points), args.fingers, replace=False)
    pose = simulate.random_pose(rng, max_translation=0.5 * diameter)
    R, t = pose[:3, :3], pose[:3, 3]
    # simulate.grasp's Gaussian noise: σ_x per axis on points, σ_n per tangent axis on normals
    measured = points[idx] @ R.T + t + rng.normal(0.0, args.position_noise, (args.fingers, 3))
    turned = simulate.perturb_normals(normals[idx] @ R.T, math.radians(args.normal_noise_deg), rng)
    contacts = Contacts(measured, object_normals=turned)
    return simulate.Grasp(contacts, pose, faces[idx], points[idx]), idx


def localize_grasp(model, grasp, model_error, args):
    """One row of grasps.csv without the model-error columns."""
    result = localize(model, grasp.contacts, position_noise=args.position_noise,
                      normal_noise_deg=args.normal_noise_deg, model_error=model_error)
    row = {"status": result.status, "hypotheses": result.num_hypotheses,
           "seconds": result.timing["total"], **{f"{k}_seconds": result.timing[k] for k in STAGES}}
    best = result.best
    if best is None:
        return row | {"success": False, "rot_err_deg": math.nan, "trans_err_mm": math.nan,
                      "underdetermined": False, "best_facets": ""}
    return row | {
        "success": bool(pose_success(best.pose, grasp.pose, model.diameter)),
        "rot_err_deg": float(rotation_error_deg(best.pose, grasp.pose)),
        "trans_err_mm": 1000.0 * float(translation_error(best.pose, grasp.pose)),
        "underdetermined": bool(best.underdetermined),
        "best_facets": " ".join(map(str, best.facets)),
    }


def load_or_build(mesh, cache):
    """The model of ``mesh`` (from ``cache`` when it holds this mesh's model), and the
    seconds it took to build (None when loaded)."""
    if cache and os.path.exists(cache):
        try:
            return ObjectModel.load(cache, mesh=mesh), None
        except Exception as exc:  # stale or unreadable cache: rebuild
            print(f"model cache {cache} not used: {exc}")
    start = time.perf_counter()
    model = ObjectModel.from_mesh(mesh)
    seconds = time.perf_counter() - start
    if cache:
        model.save(cache)
    return model, seconds


def spread(values):
    """median, p90 and max of the finite values (NaN when there are none)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if not len(v):
        return {"median": math.nan, "p90": math.nan, "max": math.nan, "n": 0}
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(v.max()), "n": int(len(v))}


def array_bytes(obj, seen=None):
    """Bytes of all numpy arrays reachable through an object's attributes (model size in memory)."""
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, dict):
        return sum(array_bytes(v, seen) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(array_bytes(v, seen) for v in obj)
    return sum(array_bytes(v, seen) for v in vars(obj).values()) if hasattr(obj, "__dict__") else 0


def summarize(rows, extra):
    """summary.json's content from the grasp rows and the run's other figures."""
    col = lambda key: np.array([r[key] for r in rows])
    success, statuses, normal_err = col("success").astype(bool), col("status"), col("model_normal_err_max_deg")
    rate = lambda mask: {"grasps": int(mask.sum()), "success_rate": float(success[mask].mean()) if mask.any() else None}
    return {
        **extra,
        "grasps": len(rows),
        "success_rate": float(success.mean()),
        "status": {s: int((statuses == s).sum()) for s in STATUSES},
        "success_by_status": {s: rate(statuses == s) for s in STATUSES},
        "success_by_model_normal_err_deg": {f"{lo}-{hi}": rate((normal_err >= lo) & (normal_err < hi))
                                            for lo, hi in zip(NORMAL_ERR_EDGES[:-1], NORMAL_ERR_EDGES[1:])},
        "rot_err_deg": spread(col("rot_err_deg")),
        "trans_err_mm": spread(col("trans_err_mm")),
        "rot_err_deg_success": spread(col("rot_err_deg")[col("success").astype(bool)]),
        "trans_err_mm_success": spread(col("trans_err_mm")[col("success").astype(bool)]),
        "localize_seconds": spread(col("seconds")),
        "hypotheses": spread(col("hypotheses")),
        "contact_model_gap_mm": spread(col("model_gap_max_mm")),
        "contact_model_normal_err_deg": spread(col("model_normal_err_max_deg")),
    }


def plot(csv_path, png_path):
    """Pose-error and timing histograms, from grasps.csv alone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    rows = sweep.read_rows(csv_path)
    num = lambda key: np.array([float(r[key]) if r[key] not in ("", "nan") else np.nan for r in rows])
    ok = np.array([r["success"] == "True" for r in rows])
    rot, trans, secs = num("rot_err_deg"), num("trans_err_mm"), num("seconds")
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), dpi=120)
    panels = ((rot, "rotation error [deg]", (0.05, 180.0), float(rows[0]["rot_threshold_deg"])),
              (trans, "translation error [mm]", (0.1, 2000.0), float(rows[0]["trans_threshold_mm"])),
              (secs, "localize time [s]", (0.01, max(1000.0, np.nanmax(secs) * 1.5)), None))
    for ax, (values, label, (lo, hi), threshold) in zip(axes, panels):
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        bins = np.geomspace(lo, hi, 30)
        clipped = np.clip(values, lo, hi)
        ax.hist([clipped[ok & np.isfinite(values)], clipped[~ok & np.isfinite(values)]], bins=bins,
                stacked=True, color=["#2e8b57", "#c0392b"], label=["top-1 success", "failure"])
        if threshold is not None:
            ax.axvline(threshold, color="0.3", linestyle="--", linewidth=1, label="success threshold")
        ax.set_xscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("grasps")
    axes[0].legend(fontsize=8)
    none = int(np.sum(~np.isfinite(rot)))
    fig.suptitle(f"espresso: {len(rows)} grasps localized on the scanned model, top-1 success {ok.mean():.0%}"
                 + (f" ({none} without hypothesis)" if none else ""), fontsize=10)
    fig.tight_layout()
    fig.savefig(png_path)
    plt.close(fig)
    return png_path


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--true-faces", type=int, default=80_000, help="facets of the generated object")
    p.add_argument("--faces", type=int, default=6_767, help="target facets of the reduced model")
    p.add_argument("--views", type=int, default=12, help="scanner viewpoints")
    p.add_argument("--resolution", type=int, default=160, help="rays per image side per view")
    p.add_argument("--range-noise", type=float, default=0.001, help="range noise, fraction of the range")
    p.add_argument("--grasps", type=int, default=100)
    p.add_argument("--fingers", type=int, default=4)
    p.add_argument("--position-noise", type=float, default=0.0005, help="σ_x per axis, metres")
    p.add_argument("--normal-noise-deg", type=float, default=1.0, help="σ_n per tangent axis, degrees")
    p.add_argument("--model-error", default="p95",
                   help="extra pair tolerance: 'p95' or 'max' of the scan report's distance, or metres")
    p.add_argument("--max-gap", type=float, default=0.002, help="contacts only where the model is this close")
    p.add_argument("--surface-samples", type=int, default=200_000, help="samples of the true surface to draw from")
    p.add_argument("--seed", type=int, default=2003)
    p.add_argument("--model-cache", help="load the model from / save it to this .npz (reused when the mesh matches)")
    p.add_argument("--out", default="results/espresso")
    p.add_argument("--quick", action="store_true", help="20k -> 1,000 facets, coarser scan, 6 grasps")
    p.add_argument("--plot-only", action="store_true", help="redraw espresso.png from grasps.csv")
    args = p.parse_args(argv)
    if args.quick:
        args.true_faces, args.faces, args.views, args.resolution = 20_000, 1_000, 8, 96
        args.grasps, args.surface_samples = 6, 50_000
    return args


def make_model(args, times):
    """Generate, scan, reconstruct, crop and reduce; build the model.

    Returns (truth mesh, scan points, ScanResult, ObjectModel, whether it was built);
    writes the two meshes and fills ``times``.
    """
    clock = time.perf_counter()
    truth = espresso_machine(args.true_faces)
    times["generate"] = time.perf_counter() - clock
    truth.export(os.path.join(args.out, "espresso_true.ply"))
    clock = time.perf_counter()
    points, normals = scan(truth, np.random.default_rng([args.seed, 0]), n_views=args.views,
                           resolution=args.resolution, range_noise=args.range_noise)
    times["scan_simulated"] = time.perf_counter() - clock
    scanned = scan_to_mesh((points, normals), ScanOptions(faces=args.faces, crop=CROP))
    times["scan_pipeline"] = scanned.report.seconds
    write_mesh(scanned.mesh, os.path.join(args.out, f"espresso{args.faces}.ply"))
    print(scanned.report.format(), flush=True)
    clock = time.perf_counter()
    model, build_seconds = load_or_build(scanned.mesh, args.model_cache)
    built = build_seconds is not None
    key = "model_build" if built else "model_load"
    times[key] = build_seconds if built else time.perf_counter() - clock
    print(f"model: {model.describe()}, {'built' if built else 'loaded'} in {times[key]:.1f} s", flush=True)
    return truth, points, scanned, model, built


def run_grasps(model, pool, model_error, args, csv_path):
    """Simulate and localize ``args.grasps`` grasps; rows of grasps.csv (rewritten after each)."""
    rng = np.random.default_rng([args.seed, 1])
    rows = []
    for i in range(args.grasps):
        grasp, idx = simulate_grasp(pool, rng, args, model.diameter)
        row = {"grasp": i, "true_facets": " ".join(map(str, grasp.facets))}
        row |= localize_grasp(model, grasp, model_error, args)
        gap, angle = pool[3][idx], pool[4][idx]
        row |= {"model_gap_max_mm": 1000.0 * float(gap.max()), "model_normal_err_max_deg": float(angle.max()),
                "rot_threshold_deg": SUCCESS_ROT_DEG,
                "trans_threshold_mm": 1000.0 * SUCCESS_TRANS_FRAC * model.diameter}
        rows.append(row)
        print(f"grasp {i}: {row['status']}, {row['hypotheses']} hypotheses, {row['seconds']:.2f} s, "
              f"rotation {row['rot_err_deg']:.2f} deg, translation {row['trans_err_mm']:.1f} mm", flush=True)
        sweep.write_rows(csv_path, rows)
    return rows


def main(argv=None):
    args = parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    csv_path, png_path = os.path.join(args.out, "grasps.csv"), os.path.join(args.out, "espresso.png")
    if args.plot_only:
        print(f"figure: {plot(csv_path, png_path)}")
        return 0
    config = dict(vars(args), crop=CROP, noise="gaussian",
                  pose="uniform random rotation, translation within ±0.5 diameter",
                  success=f"rotation < {SUCCESS_ROT_DEG} deg and translation < {SUCCESS_TRANS_FRAC:.0%} of the "
                          "model's diameter (metrics.pose_success)")
    with open(os.path.join(args.out, "config.json"), "w") as fh:
        json.dump(config, fh, indent=1)
    times = {}
    truth, points, scanned, model, built = make_model(args, times)
    report = scanned.report
    model_error = {"p95": report.distance_p95, "max": report.distance_max}.get(args.model_error)
    model_error = float(args.model_error) if model_error is None else model_error
    tolerance = Tolerance.from_noise(args.position_noise, args.normal_noise_deg, model_error)
    pool = contact_pool(truth, scanned.mesh, args, args.seed)
    clock = time.perf_counter()
    rows = run_grasps(model, pool, model_error, args, csv_path)
    times["localize_all"] = time.perf_counter() - clock

    extra = {
        "true_faces": len(truth.faces), "model_faces": int(model.num_facets), "mesh": f"espresso{args.faces}.ply",
        "model": model.describe(), "model_bytes_in_memory": array_bytes(model), "model_built": built,
        "model_build_seconds": model.build_seconds or None,
        "model_error": model_error, "model_error_from": args.model_error,
        "pair_tolerance_mm": 1000.0 * tolerance.distance, "angle_tolerance_deg": math.degrees(tolerance.angle),
        "per_contact_angle_bound_deg": math.degrees(tolerance.per_contact_bounds()[1]),
        "contact_pool": int(len(pool[0])),
        "pool_model_gap_mm": spread(1000.0 * pool[3]), "pool_model_normal_err_deg": spread(pool[4]),
        "pool_model_normal_err_deg_p50_p75_p95": np.percentile(pool[4], [50, 75, 95]).tolist(),
        "scan_points": int(len(points)), "scan_report": report.to_dict(), "seconds": times,
    }
    summary = summarize(rows, extra)
    with open(os.path.join(args.out, "summary.json"), "w") as fh:
        json.dump(summary, fh, indent=1)
    plot(csv_path, png_path)
    r, t, s = summary["rot_err_deg"], summary["trans_err_mm"], summary["localize_seconds"]
    print(f"top-1 success {summary['success_rate']:.0%} of {len(rows)} grasps; rotation error median "
          f"{r['median']:.2f} / p90 {r['p90']:.2f} / max {r['max']:.1f} deg; translation error median "
          f"{t['median']:.1f} / p90 {t['p90']:.1f} / max {t['max']:.0f} mm; localize median {s['median']:.2f} s, "
          f"p90 {s['p90']:.1f} s, max {s['max']:.1f} s")
    print(f"wrote {args.out}/: {extra['mesh']}, grasps.csv, summary.json, config.json, espresso.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
