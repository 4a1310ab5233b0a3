"""Touch until sure: suggested probes against random ones, until localize answers "ok".

A grasp as in the realistic-contacts benchmark (experiments/realistic_contacts.py): a uniformly
random object pose (translation within ±0.5 diameter), 4 fingertips of radius r = ``radius``
× diameter from ``fingertip.approach`` (cone 30°; a finger that misses is drawn again), sensor
noise σ_x = 0.25 % of the diameter per axis and σ_n = 1°, localize told that noise. Then
``tracking.touch_until_sure`` twice on the same grasp: ``suggested`` probes
(``next_touch.suggest_touch``) and ``random`` ones (``sure.random_probe``: a random surface point
of the best pose's object). A probe is measured by one ball of the same radius swept on the true
posed object (``fingertip.sweep_spheres`` in the object frame: the probe carried there by the
true pose, the contact carried back), with the same sensor noise; a miss counts as a touch. At
most ``--max-touches`` touches after the grasp.

Per grasp and policy (touches.csv): touches made, misses, status after the grasp and at the
end, touches until "ok" (empty: never), whether "ok" came within 3 touches, the final
confidence, and the best pose's errors modulo the object's symmetry (model.symmetry) and
whether it is strictly right (rotation < 5°, translation < 5 % of the diameter). summary.md:
per object, radius and policy the share that reached "ok" within 3 touches, the share of
"ok" answers that are strictly right, the mean touches; and the paired comparison on the same
grasps (touches until "ok", never counted as max + 1: suggested fewer / equal / more)::

    .venv/bin/python experiments/touch_until_sure.py --quick                 # the mug, 3 grasps
    .venv/bin/python experiments/touch_until_sure.py --objects ycb:025_mug ycb:042_adjustable_wrench \
        --radii 0.02 --grasps 5 --out results/_scratch/touch_until_sure
    .venv/bin/python experiments/touch_until_sure.py                         # 5 objects x 2 radii x 50 grasps

Models: the realistic-contacts cache (results/realistic_contacts/_scratch/models/<stem>.npz)
when there, else built from the YCB mesh (1-3 min each; not saved).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from contactpose import Contacts, ObjectModel
from contactpose.geometry.sampling import perturb_normals
from contactpose.harness import sweep
from contactpose.model.object_model import merged_mesh
from contactpose.model.symmetry import symmetry
from contactpose.sim import fingertip, ycb
from contactpose.sim import grasps as simulate
from contactpose.tracking import touch_until_sure

NAME = "touch_until_sure"
ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "results" / NAME
CACHE = ROOT / "results" / "realistic_contacts" / "_scratch" / "models"
OBJECTS = ("ycb:025_mug", "ycb:042_adjustable_wrench", "ycb:048_hammer", "ycb:040_large_marker",
           "ycb:052_extra_large_clamp")
SETTINGS = dict(fingers=4, cone_deg=30.0, translation_frac=0.5, position_noise_frac=0.0025, normal_noise_deg=1.0,
                max_redraws=100, within=3, seed=2026)
POLICIES = ("suggested", "random")
log = logging.getLogger(NAME)


def load_model(name):
    """The cached realistic-contacts model of a YCB object, else one built from its mesh."""
    path = CACHE / f"{ycb.resolve(name)[len(ycb.PREFIX):]}.npz"
    if path.exists():
        try:
            return ObjectModel.load(path)
        except Exception as error:  # another format version, or a file being written
            log.warning("%s: cached model not usable (%s); building it", name, error)
    return ObjectModel.from_mesh(ycb.load(name))


def draw(model, mesh, rng, radius):
    """A grasp: true pose, 4 fingertip contacts (world, noisy, finger normals)."""
    D = model.diameter
    pose = simulate.random_pose(rng, max_translation=SETTINGS["translation_frac"] * D)
    kw = dict(cone_deg=SETTINGS["cone_deg"], mode="cone")
    got = fingertip.approach(*mesh, rng, SETTINGS["fingers"], radius, **kw)
    points, normals = got.points.copy(), got.normals.copy()
    missing, redraws = np.flatnonzero(~got.hit), 0
    while len(missing):
        if redraws >= SETTINGS["max_redraws"]:
            raise RuntimeError(f"{redraws} fingertip redraws and still {len(missing)} misses")
        again = fingertip.approach(*mesh, rng, len(missing), radius, **kw)
        redraws += len(missing)
        hit = missing[again.hit]
        points[hit], normals[hit] = again.points[again.hit], again.normals[again.hit]
        missing = missing[~again.hit]
    return pose, Contacts(*measure(pose, points, normals, rng, D))


def measure(pose, points, normals, rng, D):
    """Object-frame contacts (points, outward normals) as the sensor reports them: world frame,
    finger normals, Gaussian noise."""
    R, t = pose[:3, :3], pose[:3, 3]
    world = points @ R.T + t + rng.normal(0.0, SETTINGS["position_noise_frac"] * D, points.shape)
    return world, perturb_normals(-(normals @ R.T), np.radians(SETTINGS["normal_noise_deg"]), rng)


def toucher(model, mesh, pose, rng, radius):
    """touch(origin, direction): one ball of the grasp's radius swept on the true posed object."""
    R, t = pose[:3, :3], pose[:3, 3]

    def touch(origin, direction):
        got = fingertip.sweep_spheres(*mesh, ((origin - t) @ R)[None], (direction @ R)[None], radius)
        if not got.hit[0]:
            return None
        world, finger = measure(pose, got.points, got.normals, rng, model.diameter)
        return world[0], finger[0]
    return touch


def run_grasp(model, mesh, group, name, frac, k, max_touches):
    """Both policies on grasp k of an object at one radius. -> two rows"""
    D = model.diameter
    radius = frac * D
    index = OBJECTS.index(name) if name in OBJECTS else len(OBJECTS)
    pose, contacts = draw(model, mesh, np.random.default_rng([SETTINGS["seed"], index, int(1e4 * frac), k]), radius)
    noise = dict(position_noise=SETTINGS["position_noise_frac"] * D, normal_noise_deg=SETTINGS["normal_noise_deg"])
    rows = []
    for p, policy in enumerate(POLICIES):
        rng = np.random.default_rng([SETTINGS["seed"], index, int(1e4 * frac), k, p])
        clock = time.perf_counter()
        run = touch_until_sure(model, contacts, toucher(model, mesh, pose, rng, radius), rng=rng,
                               max_touches=max_touches, policy=policy, **noise)
        best = run.result.best
        rot, trans = group.errors(best.pose, pose) if best is not None else (np.nan, np.nan)
        strict = bool(rot < 5.0 and trans < 0.05 * D)
        to_ok = run.touches_to_ok()
        rows.append(dict(object=name, radius_frac=frac, grasp=k, policy=policy, grasp_status=run.statuses[0],
                         touches=run.touches, misses=run.misses, final_status=run.result.status,
                         touches_to_ok="" if to_ok is None else to_ok,
                         ok_within=bool(to_ok is not None and to_ok <= SETTINGS["within"]),
                         confidence="" if run.result.confidence is None else f"{run.result.confidence:.4f}",
                         placements=len(run.result.placements), rot_deg=f"{rot:.3f}", trans_frac=f"{trans / D:.5f}",
                         strict=strict, ok_strict=bool(run.result.status == "ok" and strict),
                         statuses=" ".join(run.statuses),
                         plan_ms=f"{1e3 * np.mean([s.plan_s for s in run.steps]):.0f}" if run.steps else "",
                         time_s=f"{time.perf_counter() - clock:.2f}"))
        log.info("%s r=%g grasp %d %s: %s", name, frac, k, policy, rows[-1]["statuses"])
    return rows


def summary(rows, max_touches):
    """summary.md's tables from the rows (str or typed values)."""
    def num(v):
        return float(v) if v not in ("", None) else np.nan

    def yes(v):
        return str(v) == "True"
    within = SETTINGS["within"]
    lines = [f"| object | r (D) | policy | grasps | ok at the grasp | ok within {within} touches | ok strictly right "
             f"| mean touches | mean touches to ok (reached) | misses per grasp |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    pairs = ["", f"Paired on the same grasps: touches until ok (never: {max_touches + 1}).", "",
             "| object | r (D) | grasps | suggested fewer / equal / more | mean suggested − random | "
             f"ok within {within}: suggested only / random only |", "|---|---:|---:|---:|---:|---:|"]
    cells = dict.fromkeys((r["object"], float(r["radius_frac"])) for r in rows)
    for name, frac in cells:
        sel = [r for r in rows if r["object"] == name and float(r["radius_frac"]) == frac]
        by = {}
        for policy in POLICIES:
            part = sorted((r for r in sel if r["policy"] == policy), key=lambda r: int(r["grasp"]))
            by[policy] = part
            if not part:
                continue
            oks = [r for r in part if r["final_status"] == "ok"]
            right = f"{np.mean([yes(r['strict']) for r in oks]):.0%} of {len(oks)}" if oks else "–"
            reached = [num(r["touches_to_ok"]) for r in part if r["touches_to_ok"] not in ("", None)]
            lines.append(f"| {name} | {frac:g} | {policy} | {len(part)} | "
                         f"{np.mean([r['grasp_status'] == 'ok' for r in part]):.0%} | "
                         f"{np.mean([yes(r['ok_within']) for r in part]):.0%} | {right} | "
                         f"{np.mean([num(r['touches']) for r in part]):.2f} | "
                         f"{np.mean(reached) if reached else np.nan:.2f} | "
                         f"{np.mean([num(r['misses']) for r in part]):.2f} |")
        a = {int(r["grasp"]): r for r in by["suggested"]}
        b = {int(r["grasp"]): r for r in by["random"]}
        both = sorted(set(a) & set(b))
        if both:
            def to_ok(r):
                return num(r["touches_to_ok"]) if r["touches_to_ok"] not in ("", None) else max_touches + 1
            d = np.array([to_ok(a[g]) - to_ok(b[g]) for g in both])
            only_s = sum(yes(a[g]["ok_within"]) and not yes(b[g]["ok_within"]) for g in both)
            only_r = sum(yes(b[g]["ok_within"]) and not yes(a[g]["ok_within"]) for g in both)
            pairs.append(f"| {name} | {frac:g} | {len(both)} | {int((d < 0).sum())} / {int((d == 0).sum())} / "
                         f"{int((d > 0).sum())} | {d.mean():+.2f} | {only_s} / {only_r} |")
    return "\n".join(lines + pairs)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", nargs="+", default=list(OBJECTS))
    parser.add_argument("--radii", nargs="+", type=float, default=[0.0, 0.02], help="fingertip radii, fractions of D")
    parser.add_argument("--grasps", type=int, default=50)
    parser.add_argument("--max-touches", type=int, default=6)
    parser.add_argument("--quick", action="store_true", help="the mug, r = 2 %%, 3 grasps")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.quick:
        args.objects, args.radii, args.grasps = ["ycb:025_mug"], [0.02], 3
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.objects:
        clock = time.perf_counter()
        model = load_model(name)
        merged = merged_mesh(model.vertices, model.faces)
        mesh = (np.asarray(merged.vertices), np.asarray(merged.faces))
        log.info("%s: model ready in %.0f s", name, time.perf_counter() - clock)
        group = symmetry(model)
        for frac in args.radii:
            for k in range(args.grasps):
                rows += run_grasp(model, mesh, group, name, frac, k, args.max_touches)
                sweep.write_rows(args.out / "touches.csv", rows)
        del model
    text = summary(rows, args.max_touches)
    settings = ", ".join(f"{k} {v}" for k, v in SETTINGS.items())
    (args.out / "summary.md").write_text(f"# Touch until sure\n\nSettings: {settings}, max touches {args.max_touches}, "
                                         f"objects {' '.join(args.objects)}, radii {args.radii}, "
                                         f"{args.grasps} grasps each.\n\n{text}\n")
    print(text, flush=True)


if __name__ == "__main__":
    main()
