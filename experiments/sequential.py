"""Tracking an object held in a moving hand, touch after touch: PoseTrack (iSAM2) against
re-localizing from scratch and batch LM, on the same sequences (first part of the
"sequential" experiment; the particle-filter baseline and active localization are not yet
in).

A sequence: the object at a uniformly random pose; a first grasp of 4 rounded fingertips
(sim.fingertip.approach, cone 30°) that ``localize`` answers; then ``steps`` touches, each after
a known random hand motion (rotation N(0, hand_rot_deg²) per axis, translation N(0,
(hand_trans_frac·D)²) per axis) and a slip of N(0, slip_deg²) and N(0, (slip_trans_frac·D)²)
per axis, with 2 new fingertip contacts. Sensor noise as in the realistic-contacts benchmark.
Per touch, three estimates of the current pose:

* ``track``: a ``TrackSet`` (iSAM2 per track, at most 20) started from every distinct pose
  that localize lists for the first grasp (``keep="all"``), told the hand motions and the slip
  sigmas; each contact takes its best-fitting facet under each track's predicted pose; one
  iSAM2 update per track and touch; the best track's pose (least sequential χ²);
* ``batch``: Levenberg–Marquardt on the best track's graph from the same initial values,
  every touch;
* ``relocalize``: ``localize`` from scratch on the last 4 contacts (this touch's 2 and the
  previous touch's 2, moved by the known hand motion), its best.

Rotation error (°) and translation error (mm) per touch; a track is lost when the last touch's
error exceeds ``lost_deg`` or ``lost_frac`` of the diameter. Writes
results/sequential/steps.csv (one row per sequence, touch and method) and summary.md::

    .venv/bin/python experiments/sequential.py ycb:011_banana ycb:037_scissors --sequences 30
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose import Contacts, ObjectModel, localize, sweep
from contactpose.contacts import Tolerance
from contactpose.geometry import metrics
from contactpose.geometry.sampling import perturb_normals
from contactpose.model.object_model import merged_mesh
from contactpose.sim import fingertip, objects
from contactpose.sim import grasps as simulate
from contactpose.solvers.track import TrackSet

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "results" / "sequential"
SETTINGS = dict(steps=30, radius_frac=0.02, position_noise_frac=0.0025, normal_noise_deg=1.0, hand_rot_deg=10.0,
                hand_trans_frac=0.1, slip_deg=1.0, slip_trans_frac=0.005, lost_deg=10.0, lost_frac=0.1, seed=18)
METHODS = ("track", "batch", "relocalize")


def motion(rng, rot_deg, trans):
    """A random rigid motion: rotation vector N(0, rot_deg²) per axis, translation N(0, trans²). -> (4, 4)"""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(rot_deg) * rng.normal(size=3)).as_matrix()
    T[:3, 3] = trans * rng.normal(size=3)
    return T


def touch(model, vertices, faces, rng, pose, n, s):
    """n rounded-fingertip contacts on the object at ``pose``, with sensor noise. -> Contacts"""
    d = model.diameter
    got = fingertip.approach(vertices, faces, rng, n, s["radius_frac"] * d, cone_deg=30.0)
    while not got.hit.all():
        got = fingertip.approach(vertices, faces, rng, n, s["radius_frac"] * d, cone_deg=30.0)
    R, t = pose[:3, :3], pose[:3, 3]
    points = got.points @ R.T + t + rng.normal(0.0, s["position_noise_frac"] * d, got.points.shape)
    finger = perturb_normals(-(got.normals @ R.T), np.radians(s["normal_noise_deg"]), rng)
    return Contacts(points, finger_normals=finger)


def sequence(model, mesh, rng, s, seq):
    """The rows of one sequence: (sequence, touch, method, rotation error °, translation error
    mm, milliseconds) for every touch and method."""
    d = model.diameter
    tol = Tolerance.from_noise(s["position_noise_frac"] * d, s["normal_noise_deg"])
    noise = dict(position_noise=tol.position_noise, normal_noise_deg=s["normal_noise_deg"])
    X = simulate.random_pose(rng, max_translation=0.5 * d)
    first = touch(model, *mesh, rng, X, 4, s)
    r = localize(model, first, keep="all", **noise)
    if r.best is None:
        return []
    tracks = TrackSet(model, first, [(h.facets, h.pose) for h in r.hypotheses], tol)
    rows, last = [], first
    for k in range(1, s["steps"] + 1):
        delta = motion(rng, s["hand_rot_deg"], s["hand_trans_frac"] * d)
        X = delta @ X @ motion(rng, s["slip_deg"], s["slip_trans_frac"] * d)
        contacts = touch(model, *mesh, rng, X, 2, s)
        clock = time.perf_counter()
        est = {"track": tracks.add(contacts, hand_motion=(delta, s["slip_deg"], s["slip_trans_frac"] * d))}
        ms = {"track": 1e3 * (time.perf_counter() - clock)}
        clock = time.perf_counter()
        est["batch"] = tracks.best.batch()[-1]
        ms["batch"] = 1e3 * (time.perf_counter() - clock)
        moved = last.transformed(delta)
        both = Contacts(np.vstack([moved.points[-2:], contacts.points]),
                        finger_normals=np.vstack([moved.finger_normals[-2:], contacts.finger_normals]))
        clock = time.perf_counter()
        again = localize(model, both, **noise)
        ms["relocalize"] = 1e3 * (time.perf_counter() - clock)
        est["relocalize"] = None if again.best is None else again.best.pose
        for m in METHODS:
            T = est[m]
            rot = np.nan if T is None else metrics.rotation_error_deg(T, X)
            trans = np.nan if T is None else 1e3 * metrics.translation_error(T, X)
            rows.append(dict(sequence=seq, touch=k, method=m, rot_deg=rot, trans_mm=trans, ms=ms[m]))
        last = contacts
    return rows


def summary(rows, d, s):
    """Per method: error over all touches after the first (median, p90), the share of lost
    tracks, and the time per touch (median, p95)."""
    lines = ["| method | touches | rotation median / p90 (°) | translation median / p90 (mm) | lost | ms per touch median / p95 |",
             "|---|---:|---:|---:|---:|---:|"]
    for m in METHODS:
        sel = [r for r in rows if r["method"] == m]
        rot = np.array([float(r["rot_deg"]) for r in sel])
        trans = np.array([float(r["trans_mm"]) for r in sel])
        ms = np.array([float(r["ms"]) for r in sel])
        last = {}
        for r in sel:
            last[r["sequence"]] = r
        lost = np.mean([not (float(r["rot_deg"]) <= s["lost_deg"] and float(r["trans_mm"]) <= 1e3 * s["lost_frac"] * d)
                        for r in last.values()])
        lines.append(f"| {m} | {len(sel)} | {np.nanmedian(rot):.2f} / {np.nanpercentile(rot, 90):.2f} | "
                     f"{np.nanmedian(trans):.2f} / {np.nanpercentile(trans, 90):.2f} | {lost:.1%} of {len(last)} | "
                     f"{np.median(ms):.2f} / {np.percentile(ms, 95):.2f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("objects", nargs="+")
    parser.add_argument("--sequences", type=int, default=30)
    parser.add_argument("--steps", type=int, default=SETTINGS["steps"], help="touches after the first grasp")
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    s, text, all_rows = dict(SETTINGS, steps=args.steps), [], []
    for index, name in enumerate(args.objects):
        model = ObjectModel.from_mesh(objects.load(name))
        merged = merged_mesh(model.vertices, model.faces)
        mesh = (np.asarray(merged.vertices), np.asarray(merged.faces))
        rng = np.random.default_rng([s["seed"], index])
        clock = time.perf_counter()
        rows = [dict(object=name, **r) for q in range(args.sequences) for r in sequence(model, mesh, rng, s, q)]
        all_rows += rows
        text += [f"## {name}: {args.sequences} sequences of {s['steps']} touches, {time.perf_counter() - clock:.0f} s",
                 "", summary(rows, model.diameter, s), ""]
        print("\n".join(text[-4:]), flush=True)
        sweep.write_rows(out / "steps.csv", all_rows)
    settings = ", ".join(f"{k} {v}" for k, v in s.items())
    (out / "summary.md").write_text(f"Settings: {settings}.\n\n" + "\n".join(text))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
