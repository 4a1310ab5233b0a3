"""Touch after touch: tracking an object held in a moving hand (TrackSet with iSAM2, batch
LM, re-localizing from scratch, a particle filter, on the same sequences), and active
localization of a static object (suggested touches against random ones).

**Tracking** (``--part tracking``).

A sequence: the object at a uniformly random pose; a first grasp of 4 rounded fingertips
(sim.fingertip.approach, cone 30°) that ``localize`` answers; then ``steps`` touches, each after
a known random hand motion (rotation N(0, hand_rot_deg²) per axis, translation N(0,
(hand_trans_frac·D)²) per axis) and a slip of N(0, slip_deg²) and N(0, (slip_trans_frac·D)²)
per axis, with 2 new fingertip contacts. Sensor noise as in the realistic-contacts benchmark.
Per touch, three estimates of the current pose:

* ``track``: a ``TrackSet`` (iSAM2 per track, at most 20) started from every distinct pose
  that localize lists for the first grasp (``keep="all"``), told the hand motions and the slip
  sigmas, with the contact model of ``--contact-model`` (default "auto": smooth normals on the
  YCB meshes, PoseTrack); each contact takes its best-fitting facet under each track's predicted pose; one
  iSAM2 update per track and touch; the best track's pose (least sequential χ²). A touch that
  no track explains (TrackSet.SURPRISE_P) adds tracks localized afresh from the last 4
  contacts, each replayed over the sequence (session.relocalizer; ``--no-reseed``: none);
* ``batch``: Levenberg–Marquardt on the best track's graph from the same initial values,
  every touch;
* ``relocalize``: ``localize`` from scratch on the last 4 contacts (this touch's 2 and the
  previous touch's 2, moved by the known hand motion), its best;
* ``pf``: baselines.MemoryParticleFilter, 1,000 particles started around localize's distinct
  poses of the first grasp, told the hand motions and the slip sigmas, with a memory of the
  last 4 contacts; its estimate.

Rotation error (°) and translation error (mm) per touch, raw (``rot_deg``, ``trans_mm``) and
modulo the object's symmetry (``rot_sym_deg``, ``trans_sym_mm``: against the nearest of the
poses that place the surface as the truth does, model.symmetry; equal to the raw ones on an
object without symmetry), and, on the track method's rows, the
number of tracks held after it (column ``tracks``) and the reseeds so far (``reseeds``); a track is lost when the last touch's
error exceeds ``lost_deg`` or ``lost_frac`` of the diameter. The pose counts as determined from the first touch after
which one track is left (the session's status "ok"), and the summary gives the worst touch's
median over all touches and over those once determined; the summary's errors are those modulo
the symmetry (the raw ones for rows written before those columns). Writes
results/sequential/steps.csv (one row per sequence, touch and method) and summary.md;
``--methods`` runs some of the methods and keeps the other methods' rows of steps.csv (the
sequences are drawn from their own stream, so they are the same)::

    .venv/bin/python experiments/sequential.py ycb:011_banana ycb:037_scissors --sequences 100

**Active localization** (``--part active``). A static object at a random pose, one contact per
touch through a TouchSession: the first two touches are fingertip-free point contacts at
random surface points (one contact has no pose classes to separate), then each touch is the
probe that ``TouchSession.suggest_touch`` picks, or a random candidate probe
(touch.random_touch), measured by touch.simulate_touch with the same noise. A probe that
touches nothing counts as a touch. Touches until a single pose class (and until that class
holds the truth) are counted, up to ``--max-touches``; writes active.csv and active.md::

    .venv/bin/python experiments/sequential.py rock banana --part active --sequences 200

**Covariance of a track** (``--part coverage``). One ``PoseTrack`` started at the true pose
on the true facets of a first grasp of 4 contacts, then ``--steps`` touches as above (hand
motion, slip) of 2 contacts each at random facet points with their facets' normals and the
sensor noise (the protocol of the paper, whose contacts have true facets). Each touch's
facets are the true ones (``given``) or the track's own association (``associated``, as a
tracker works), on the same sequences. At the last touch: the level of the truth under the
track's 95 % (68 %, 50 %) region, and the rotation error and the covariance's standard
deviation about the object's principal axes (longest first); the same level under
``PoseTrack.association_covariance`` (20 trajectories drawn per sequence). Writes
coverage.csv and coverage.md::

    .venv/bin/python experiments/sequential.py ycb:011_banana rock --part coverage --sequences 200 --steps 10

**Speed** (``--part speed``). The time to add one contact to ``max_tracks`` (20) tracks of a
held object: 20 ``PoseTrack`` s started from the true pose of a 4-contact grasp moved by a
random slip each (so that none coincide), then ``--steps`` touches of one contact each (hand
motion and slip as above, contacts at facet points), associated by each track. Per touch: the
wall time of all 20 updates (association, iSAM2 update, re-association), one process.
Writes speed.csv and speed.md::

    .venv/bin/python experiments/sequential.py ycb:011_banana rock --part speed --sequences 10 --steps 30
"""

from __future__ import annotations

import argparse
import os
import time
import warnings
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from contactpose import Contacts, ObjectModel, TouchSession, localize
from contactpose.contacts import Tolerance
from contactpose.geometry import metrics
from contactpose.geometry.sampling import perturb_normals
from contactpose.harness import sweep
from contactpose.model.object_model import merged_mesh
from contactpose.model.symmetry import symmetry
from contactpose.peers import MemoryParticleFilter, random_touch, sample_surface
from contactpose.sim import fingertip, objects
from contactpose.sim import grasps as simulate
from contactpose.sim.touch import simulate_touch
from contactpose.tracking.session import relocalizer
from contactpose.tracking.track import CONTACT_MODELS, MAX_TRACKS, PoseTrack, TrackSet, add_touch, checked_motion

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "results" / "sequential"
SETTINGS = dict(steps=30, radius_frac=0.02, position_noise_frac=0.0025, normal_noise_deg=1.0, hand_rot_deg=10.0,
                hand_trans_frac=0.1, slip_deg=1.0, slip_trans_frac=0.005, lost_deg=10.0, lost_frac=0.1, seed=18,
                contact_model="auto", reseed=True)
METHODS = ("track", "batch", "relocalize", "pf")
STRATEGIES = ("suggested", "random")
#: Particles of the particle-filter baseline.
PARTICLES = 1000



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


def sequence(model, mesh, rng, s, seq, methods=METHODS, surface=None):
    """The rows of one sequence: (sequence, touch, method, rotation error °, translation error
    mm, milliseconds) for every touch and each of ``methods``. The sequence's draws come from
    ``rng`` alone (the particle filter has its own stream), whatever the methods."""
    d = model.diameter
    tol = Tolerance.from_noise(s["position_noise_frac"] * d, s["normal_noise_deg"])
    noise = dict(position_noise=tol.position_noise, normal_noise_deg=s["normal_noise_deg"])
    X = simulate.random_pose(rng, max_translation=0.5 * d)
    first = touch(model, *mesh, rng, X, 4, s)
    r = localize(model, first, keep="all", **noise)
    if r.best is None:
        return []
    starts = [(h.facets, h.pose) for h in r.hypotheses]
    tracks = (TrackSet(model, first, starts, tol, contact_model=s["contact_model"],
                       seeder=relocalizer(model, tol) if s["reseed"] else None)
              if {"track", "batch"} & set(methods) else None)
    pf = None
    if "pf" in methods:
        pf = MemoryParticleFilter(model, surface, [p for _, p in starts], first, np.random.default_rng([s["seed"], seq]),
                                  particles=PARTICLES, **noise)
    rows, last, group = [], first, symmetry(model)
    for k in range(1, s["steps"] + 1):
        delta = motion(rng, s["hand_rot_deg"], s["hand_trans_frac"] * d)
        X = delta @ X @ motion(rng, s["slip_deg"], s["slip_trans_frac"] * d)
        contacts = touch(model, *mesh, rng, X, 2, s)
        hand = (delta, s["slip_deg"], s["slip_trans_frac"] * d)
        est, ms = {}, {}
        for m in methods:
            clock = time.perf_counter()
            est[m] = _estimate(m, model, tracks, pf, last, contacts, hand, noise)
            ms[m] = 1e3 * (time.perf_counter() - clock)
        for m in methods:
            T = est[m]
            rot = np.nan if T is None else metrics.rotation_error_deg(T, X)
            trans = np.nan if T is None else 1e3 * metrics.translation_error(T, X)
            rot_sym, trans_sym = (np.nan, np.nan) if T is None else group.errors(T, X)
            rows.append(dict(sequence=seq, touch=k, method=m, rot_deg=rot, trans_mm=trans, rot_sym_deg=float(rot_sym),
                             trans_sym_mm=1e3 * float(trans_sym), ms=ms[m],
                             tracks=len(tracks.tracks) if m == "track" else "",
                             reseeds=tracks.reseeds if m == "track" else ""))
        last = contacts
    return rows


def _estimate(method, model, tracks, pf, last, contacts, hand, noise):
    """One method's pose after a touch (None: no answer). Track before batch: batch solves the
    best track's graph, touch included."""
    if method == "track":
        return tracks.add(contacts, hand_motion=hand)
    if method == "batch":
        return tracks.best.batch()[-1]
    if method == "pf":
        return pf.add(contacts, hand)
    moved = last.transformed(hand[0])
    again = localize(model, moved.permuted([moved.n - 2, moved.n - 1]).joined(contacts), **noise)
    return None if again.best is None else again.best.pose


def summary(rows, d, s):
    """Per method: error modulo the object's symmetry over all touches (median, p90), the
    worst touch's median (over the sequences), the same over the touches once the pose is
    determined (:func:`determined`), the share of lost tracks, and the time per touch (median,
    p95). Rows without the modulo-symmetry columns (written before them) give their raw errors."""
    lines = ["| method | touches | rotation median / p90 (°) | translation median / p90 (mm) | worst touch's median "
             "(° / mm) | once determined: touches, worst touch's median (° / mm) | lost | ms per touch median / p95 |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    since = determined(rows)
    for m in [m for m in METHODS if any(r["method"] == m for r in rows)]:
        sel = [r for r in rows if r["method"] == m]
        rot, trans = (np.array([float(r.get(c) if str(r.get(c, "")) != "" else r[raw]) for r in sel])
                      for c, raw in (("rot_sym_deg", "rot_deg"), ("trans_sym_mm", "trans_mm")))
        ms, step = (np.array([float(r[c]) for r in sel]) for c in ("ms", "touch"))
        known = np.array([int(r["touch"]) >= since.get(int(r["sequence"]), np.inf) for r in sel], dtype=bool)
        last = {r["sequence"]: (a, b) for r, a, b in zip(sel, rot, trans)}
        lost = np.mean([not (a <= s["lost_deg"] and b <= 1e3 * s["lost_frac"] * d) for a, b in last.values()])
        lines.append(f"| {m} | {len(sel)} | {np.nanmedian(rot):.2f} / {np.nanpercentile(rot, 90):.2f} | "
                     f"{np.nanmedian(trans):.2f} / {np.nanpercentile(trans, 90):.2f} | "
                     f"{_worst_median(rot, trans, step)} | {known.sum()}, {_worst_median(rot[known], trans[known], step[known])} | "
                     f"{lost:.1%} of {len(last)} | {np.median(ms):.2f} / {np.percentile(ms, 95):.2f} |")
    return "\n".join(lines + ["", "Errors modulo the object's symmetry (model.symmetry; raw where it has none)."]
                     + reseeded(rows))


def reseeded(rows):
    """A line on the track method's reseeds (touches that no track explained: TrackSet), from
    the ``reseeds`` column, or none when the rows do not have it."""
    track = [r for r in rows if r["method"] == "track" and str(r.get("reseeds", "")) != ""]
    if not track:
        return []
    so_far, ms = {}, []
    for r in track:  # each sequence's rows in touch order
        if int(r["reseeds"]) > so_far.get(r["sequence"], 0):
            ms.append(float(r["ms"]))
        so_far[r["sequence"]] = int(r["reseeds"])
    timing = f", {np.median(ms):.0f} ms per reseeding touch (median)" if ms else ""
    return ["", f"track: {len(ms)} reseeds in {sum(v > 0 for v in so_far.values())} of {len(so_far)} sequences "
                f"({len(track)} touches){timing}."]


def determined(rows):
    """{sequence: the first touch after which the tracker holds a single track} (the session's
    status "ok", one pose left; the "tracks" column of the track method's rows), the sequences
    that get there: the issue's "after the pose is first determined", judged by the tracker
    itself, not by the truth."""
    since = {}
    for r in rows:
        if r["method"] == "track" and str(r.get("tracks", "")) == "1":
            q = int(r["sequence"])
            since[q] = min(since.get(q, np.inf), int(r["touch"]))
    return since


def _worst_median(rot, trans, step):
    """'° / mm': the largest over touches of the median over sequences, of each error."""
    if not len(step):
        return "– / –"
    touches = np.unique(step)
    return (f"{max(np.nanmedian(rot[step == k]) for k in touches):.2f} / "
            f"{max(np.nanmedian(trans[step == k]) for k in touches):.2f}")


# ------------------------------------------------------------------ active localization

def active_sequence(model, rng, s, strategy, max_touches):
    """One static object localized touch by touch with one strategy. -> dict(touches until a
    single pose class, touches until a single class holding the truth, misses, ms per plan);
    counts are max_touches + 1 when not reached."""
    d = model.diameter
    noise = dict(position_noise=s["position_noise_frac"] * d, normal_noise_deg=s["normal_noise_deg"])
    X = simulate.random_pose(rng, max_translation=0.5 * d)
    session = TouchSession(model, **noise)
    single = true = max_touches + 1
    misses, plan_ms = 0, []
    for k in range(1, max_touches + 1):
        if session.contacts is None or session.contacts.n < 2:
            r = session.add(simulate.grasp(model, rng, n=1, pose=X, **noise).contacts)
        else:
            clock = time.perf_counter()
            probe = (session.suggest_touch(rng=rng) if strategy == "suggested"
                     else random_touch(model, session.result, rng=rng, contacts=session.contacts))
            plan_ms.append(1e3 * (time.perf_counter() - clock))
            measured = simulate_touch(model, X, probe, rng, **noise)
            if measured is None:
                misses += 1
                continue
            r = session.add(Contacts(measured[0][None], object_normals=measured[1][None]))
        if session.contacts.n >= 2 and len(r.classes) == 1:
            single = min(single, k)
            if _holds_truth(model, r, X):
                true = k
                break
    return dict(touches_single=single, touches_true=true, misses=misses,
                plan_ms=float(np.median(plan_ms)) if plan_ms else np.nan)


def _holds_truth(model, result, X):
    """Whether the single class's pose places the surface as the truth does (ADD-S)."""
    adds = metrics.adds(result.classes[0].pose, X, model.surface_points, model.surface_tree)
    return adds < metrics.SAME_CLASS_ADDS_FRAC * model.diameter


def active_summary(rows, max_touches):
    """Per object and strategy: touches to a single class and to the true one (median, p90,
    mean; a sequence that never got there counts max_touches + 1)."""
    lines = [f"| object | strategy | sequences | touches to one class, median / p90 / mean | to the true class, median / p90 / mean | "
             f"not reached in {max_touches} | misses per sequence | ms per plan, median |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for name in dict.fromkeys(r["object"] for r in rows):
        for strategy in STRATEGIES:
            sel = [r for r in rows if r["object"] == name and r["strategy"] == strategy]
            one, true = (np.array([float(r[c]) for r in sel]) for c in ("touches_single", "touches_true"))
            lines.append(f"| {name} | {strategy} | {len(sel)} | {np.median(one):g} / {np.percentile(one, 90):g} / "
                         f"{np.mean(one):.2f} | {np.median(true):g} / {np.percentile(true, 90):g} / {np.mean(true):.2f} | "
                         f"{np.mean(true > max_touches):.1%} | "
                         f"{np.mean([float(r['misses']) for r in sel]):.2f} | "
                         f"{np.nanmedian([float(r['plan_ms']) for r in sel]):.0f} |")
    return "\n".join(lines)


def run_active(names, args, s, out):
    """Both strategies on the same objects at the same poses (the same first two touches)."""
    rows = []
    for index, name in enumerate(names):
        model = ObjectModel.from_mesh(objects.load(name))
        for strategy in STRATEGIES:
            for q in range(args.sequences):
                rng = np.random.default_rng([s["seed"], index, q])
                rows.append(dict(object=name, sequence=q, strategy=strategy,
                                 **active_sequence(model, rng, s, strategy, args.max_touches)))
        sweep.write_rows(out / "active.csv", rows)
    text = active_summary(rows, args.max_touches)
    print(text, flush=True)
    settings = ", ".join(f"{k} {s[k]}" for k in ("position_noise_frac", "normal_noise_deg", "seed"))
    (out / "active.md").write_text(f"Settings: {settings}, max touches {args.max_touches}.\n\n{text}\n")


# ------------------------------------------------------------------ coverage

def facet_sequence(model, rng, s, per_touch):
    """A held object touched at facet points (the paper's protocol): a first grasp of 4
    contacts, then s["steps"] hand motions with slip and ``per_touch`` contacts each.
    -> (Tolerance, first Grasp, [(ΔT (4, 4), Grasp)], the last true pose (4, 4))"""
    d = model.diameter
    tol = Tolerance.from_noise(s["position_noise_frac"] * d, s["normal_noise_deg"])
    noise = dict(position_noise=tol.position_noise, normal_noise_deg=s["normal_noise_deg"])
    X = simulate.random_pose(rng, max_translation=0.5 * d)
    first = simulate.grasp(model, rng, n=4, pose=X, **noise)
    touches = []
    for _ in range(s["steps"]):
        delta = motion(rng, s["hand_rot_deg"], s["hand_trans_frac"] * d)
        X = delta @ X @ motion(rng, s["slip_deg"], s["slip_trans_frac"] * d)
        touches.append((delta, simulate.grasp(model, rng, n=per_touch, pose=X, **noise)))
    return tol, first, touches, X


def coverage_sequence(model, rng, s, axes, draws):
    """One sequence tracked twice, on given and on associated facets; the level of the truth
    under the track's covariance and under its association_covariance (``draws``: its
    numpy.random.Generator). -> list of two dicts"""
    d = model.diameter
    tol, first, touches, X = facet_sequence(model, rng, s, 2)
    rows = []
    for facets in ("given", "associated"):
        track = PoseTrack(model, first.contacts, first.facets, first.pose, tol, contact_model=s["contact_model"])
        for delta, g in touches:
            track.add(g.contacts, facets=g.facets if facets == "given" else None,
                      hand_motion=(delta, s["slip_deg"], s["slip_trans_frac"] * d))
        cov = track.covariance
        xi = gtsam.Pose3(track.pose).localCoordinates(gtsam.Pose3(X))
        wider = track.association_covariance(draws)
        err = np.degrees(np.abs(axes.T @ xi[:3]))
        sd = np.degrees(np.sqrt(np.diag(axes.T @ cov[:3, :3] @ axes)))
        rows.append(dict(facets=facets, level=_level(xi, cov), level_association=_level(xi, wider),
                         rot_deg=float(np.degrees(np.linalg.norm(xi[:3]))),
                         trans_mm=1e3 * float(np.linalg.norm(xi[3:])),
                         **{f"err_axis{i}_deg": float(err[i]) for i in range(3)},
                         **{f"sd_axis{i}_deg": float(sd[i]) for i in range(3)}))
    return rows


def _level(xi, cov):
    """The level of the region of ``cov`` (6, 6) whose boundary passes through ``xi`` (6,)."""
    return float(chi2.cdf(float(xi @ np.linalg.solve(cov, xi)), 6))


def principal_axes(model):
    """(3, 3) the object's principal axes (columns, longest first), from its vertices."""
    v = model.vertices - model.vertices.mean(axis=0)
    return np.linalg.eigh(v.T @ v)[1][:, ::-1]


def coverage_summary(rows):
    """Per object and facets: coverage at 50 / 68 / 95 % under the covariance and the
    association covariance, errors and sds (of the covariance) about the axes."""
    lines = ["| object | facets | sequences | covariance: covered at 50 / 68 / 95 % | association covariance: "
             "covered at 50 / 68 / 95 % | rotation error, median | error about the axes, median (°, longest first) "
             "| sd about the axes, median (°) |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for name in dict.fromkeys(r["object"] for r in rows):
        for facets in ("given", "associated"):
            sel = [r for r in rows if r["object"] == name and r["facets"] == facets]
            covered = [" / ".join(f"{np.mean(np.array([float(r[c]) for r in sel]) <= a):.1%}" for a in (0.5, 0.68, 0.95))
                       for c in ("level", "level_association")]
            med = {c: np.median([float(r[c]) for r in sel]) for c in sel[0] if c.startswith(("err_", "sd_", "rot_"))}
            lines.append(f"| {name} | {facets} | {len(sel)} | {covered[0]} | {covered[1]} | {med['rot_deg']:.2f}° | "
                         + " / ".join(f"{med[f'err_axis{i}_deg']:.2f}" for i in range(3)) + " | "
                         + " / ".join(f"{med[f'sd_axis{i}_deg']:.2f}" for i in range(3)) + " |")
    return "\n".join(lines)


def run_coverage(names, args, s, out):
    """The covariance part: given and associated facets on the same sequences."""
    rows = []
    for index, name in enumerate(names):
        model = ObjectModel.from_mesh(objects.load(name))
        axes = principal_axes(model)
        for q in range(args.sequences):
            rng = np.random.default_rng([s["seed"], 100 + index, q])
            draws = np.random.default_rng([s["seed"], 200 + index, q])
            rows += [dict(object=name, sequence=q, **r) for r in coverage_sequence(model, rng, s, axes, draws)]
        sweep.write_rows(out / "coverage.csv", rows)
    text = coverage_summary(rows)
    print(text, flush=True)
    settings = ", ".join(f"{k} {s[k]}" for k in ("steps", "position_noise_frac", "normal_noise_deg", "hand_rot_deg",
                                                 "hand_trans_frac", "slip_deg", "slip_trans_frac", "seed"))
    (out / "coverage.md").write_text(f"Settings: {settings}.\n\n{text}\n")


# ------------------------------------------------------------------ speed

def speed_sequence(model, rng, s, n_tracks):
    """Milliseconds per touch of one contact added to n_tracks tracks. -> list of floats"""
    d = model.diameter
    tol, first, touches, _ = facet_sequence(model, rng, s, 1)
    tracks = [PoseTrack(model, first.contacts, first.facets,
                        first.pose @ motion(rng, s["slip_deg"], s["slip_trans_frac"] * d), tol,
                        contact_model=s["contact_model"])
              for _ in range(n_tracks)]
    ms = []
    for delta, g in touches:
        clock = time.perf_counter()
        hand = checked_motion((delta, s["slip_deg"], s["slip_trans_frac"] * d))  # once per touch, as TrackSet.add
        add_touch(tracks, g.contacts, hand)
        ms.append(1e3 * (time.perf_counter() - clock))
    return ms


def run_speed(names, args, s, out):
    """The speed part: ms per touch of one contact with MAX_TRACKS tracks."""
    rows, lines = [], ["| object | facets | tracks | touches | ms per touch, median / p95 | ms per track, median |",
                       "|---|---:|---:|---:|---:|---:|"]
    for index, name in enumerate(names):
        model = ObjectModel.from_mesh(objects.load(name))
        speed_sequence(model, np.random.default_rng(0), dict(s, steps=2), 2)  # compile and warm up
        ms = []
        for q in range(args.sequences):
            got = speed_sequence(model, np.random.default_rng([s["seed"], 200 + index, q]), s, MAX_TRACKS)
            rows += [dict(object=name, sequence=q, touch=k + 1, ms=m) for k, m in enumerate(got)]
            ms += got
        lines.append(f"| {name} | {model.num_facets} | {MAX_TRACKS} | {len(ms)} | {np.median(ms):.1f} / "
                     f"{np.percentile(ms, 95):.1f} | {np.median(ms) / MAX_TRACKS:.2f} |")
        sweep.write_rows(out / "speed.csv", rows)
    text = "\n".join(lines)
    print(text, flush=True)
    (out / "speed.md").write_text(f"One process; load average at the end {os.getloadavg()[0]:.2f} on "
                                  f"{os.cpu_count()} CPUs.\n\n{text}\n")


# ------------------------------------------------------------------ tracking

def run_tracking(names, args, s, out):
    """The tracking part; with a subset of methods, steps.csv keeps the other methods' rows."""
    methods = tuple(args.methods)
    old = sweep.read_rows(out / "steps.csv") if (out / "steps.csv").exists() and set(methods) != set(METHODS) else []
    kept = [r for r in old if r["method"] not in methods]
    text, all_rows = [], []
    for index, name in enumerate(names):
        model = ObjectModel.from_mesh(objects.load(name))
        merged = merged_mesh(model.vertices, model.faces)
        mesh = (np.asarray(merged.vertices), np.asarray(merged.faces))
        surface = sample_surface(model, neighbour_radius=None) if "pf" in methods else None
        rng = np.random.default_rng([s["seed"], index])
        clock = time.perf_counter()
        rows = [dict(object=name, **r) for q in range(args.sequences)
                for r in sequence(model, mesh, rng, s, q, methods, surface)]
        all_rows += rows
        mine = rows + [r for r in kept if r["object"] == name and int(r["sequence"]) < args.sequences]
        text += [f"## {name}: {args.sequences} sequences of {s['steps']} touches, {time.perf_counter() - clock:.0f} s",
                 "", summary(mine, model.diameter, s), ""]
        print("\n".join(text[-4:]), flush=True)
        sweep.write_rows(out / "steps.csv", kept + all_rows)
    settings = ", ".join(f"{k} {v}" for k, v in s.items())
    (out / "summary.md").write_text(f"Settings: {settings}.\n\n" + "\n".join(text))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("objects", nargs="+")
    parser.add_argument("--part", choices=("tracking", "active", "coverage", "speed"), default="tracking")
    parser.add_argument("--sequences", type=int, default=30)
    parser.add_argument("--steps", type=int, default=SETTINGS["steps"], help="touches after the first grasp")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS), help="tracking methods to run")
    parser.add_argument("--max-touches", type=int, default=15, help="active: touches per sequence at most")
    parser.add_argument("--contact-model", default=SETTINGS["contact_model"], choices=CONTACT_MODELS,
                        help="the tracks' contact model (PoseTrack)")
    parser.add_argument("--no-reseed", action="store_true",
                        help="tracking: no new tracks on a touch that no track explains")
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    s = dict(SETTINGS, steps=args.steps, contact_model=args.contact_model, reseed=not args.no_reseed)
    {"active": run_active, "coverage": run_coverage, "speed": run_speed, "tracking": run_tracking}[args.part](args.objects, args, s, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
