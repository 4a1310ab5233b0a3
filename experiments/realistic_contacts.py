"""Realistic contacts on the YCB benchmark objects: rounded fingertips, sensor noise, mm and degrees.

A grasp: a uniformly random object pose (``simulate.random_pose``: rotation uniform, translation
within ±``translation_frac`` diameter), then 4 fingertips from ``fingertip.approach`` on the
object-frame mesh (mode "cone", 30°: each ball of radius r aims at an area-uniform surface point
along a direction within 30° of the inward facet normal and stops at its first touch, which may
be a face, an edge or a vertex). A finger that misses is drawn again (``redraws`` counts them).
r = 0, 1, 2 and 5 % of the model's diameter. Contacts to the world: points R p + t, finger
normals −(R n) (n: from the contact toward the ball centre, outward); then Gaussian sensor
noise, σ_x = 0.25 % of the diameter per axis and σ_n = 1° (``perturb_normals``); ``localize``
is told that noise. One sweep cell is one grasp; its generator makes every draw, in this
order: pose, fingertips (and redraws), position noise, normal noise, then the baselines'
own draws. The cells of one object share their stream across radii (``seed_axes``): grasp k
has the same pose and the same aims at every radius.

Methods on the same grasps: ``fast`` (the default method) on every grasp; ``paper``
(``method="paper"``, LM from the identity) on the first ``paper_grasps`` grasps per object and
radius, counted as run only when it finishes within ``paper_time_limit`` seconds (its status is
not ``time_limit``); where the object's model has no facet table, the paper's own workflow: the
mesh decimated to about ``paper_facets`` facets (``objects.decimate``, the paper's banana went
from 512 to 53), its facet table built, the contacts searched there and the pose scored
against the full mesh's truth (``paper_model_facets`` says on how many facets); ``icp-multistart`` (32
random starts) and ``scaling-series`` (2000 particles) from contactpose/peers/ with their
default budgets and ICP's default pad radius and correspondence distance (not tuned per object
as experiments/baselines.py does), on the first ``baseline_grasps`` grasps; the Scaling Series as
published (``peers.scaling_series_published``, ``published_per_neighbourhood`` particles per
neighbourhood) on the first ``published_grasps``: ``ss-published`` with its whole schedule,
``ss-published-timed`` within the time the default method took on that grasp.

Per grasp and method: found (some returned hypothesis places the surface within ADD-S
``found_adds_frac`` = 5 % of the diameter; exact over all hypotheses, see :func:`any_within`),
top-1 by ADD-S (< ``top1_adds_frac`` = 10 %) and strict (``metrics.pose_success``:
rotation < 5°, translation < 5 % of the diameter), the best pose's rotation and translation errors and
ADD-S (mm), its MSSD (``mssd_mm``: the BOP challenge's maximum symmetry-aware surface distance
over the mesh's vertices, the symmetries ``model.symmetry`` finds in the mesh), status,
hypothesis count, online time (``result.timing["total"]``; wall time for the baselines). The
summary gives each method's AR_MSSD: the recall of the MSSD averaged over thresholds of
5 %, 10 %, ..., 50 % of the diameter (a grasp without a pose counts as a miss). For ``fast`` also where
the true assignment is lost (``truth_stage``, the first that applies): ``table`` (some finger
pair's true facet pair is not in S_ij), ``tree`` (every pair is there, no distinct pose holds
the tuple: not joined, or on a model of regions also grouped under a near-copy;
experiments/truth_stages.py tells them apart), ``fit`` (the tuple is found but no pose near its
closed form fits within noise), ``ranking`` (it fits, another tuple is first) or ``first`` (it
is ranked first). The true facet of a contact is the triangle it touched, or on an edge or a
vertex any triangle incident to it (``pairs_present_touched`` counts the pairs with the touched
triangles only).

Models: each object's model is built once, in a child process that records its build time and
peak RSS, and kept as .npz (with the baselines' surface samples) under ``model_cache``
(results/realistic_contacts/_scratch/models/); the workers load it. A model with its facet table
is 5.4 GB on disk, so with ``keep_models`` false (full run) each is deleted once its object's
grasps are done. Objects run one after the other, each its own sweep in
_scratch/sweeps/<object>/ (a rerun resumes there; ``--fresh`` starts afresh), and the results
are published after each object.

Writes results/realistic_contacts/: grasps.csv (one row per grasp and method; timings.csv the
same with the ``time_*`` columns), models.csv (build time, peak RSS, size per object),
summary.csv (per object × radius × method, all grasps and the face-only / edge-vertex splits),
summary.md, config.json, run.json and realistic_contacts.png/pdf (drawn from the CSVs alone)::

    .venv/bin/python experiments/realistic_contacts.py               # 12 objects x 4 radii x 100 grasps
    .venv/bin/python experiments/realistic_contacts.py --quick       # 2 objects x 2 radii x 3 grasps
    .venv/bin/python experiments/realistic_contacts.py --plot-only   # summary and figures from the CSVs

A run of some methods only (config ``methods``) draws the same grasps, so CHSEL, which needs the
optional extra and takes minutes a grasp, can run in a pass of its own and join the others
(``merge_runs``: the ``--out`` roots of the other passes; their rows are published beside
this run's)::

    ALL='["fast","paper","icp-multistart","scaling-series","ss-published","ss-published-timed"]'
    .venv/bin/python experiments/realistic_contacts.py --out results/_scratch/a --set "methods=$ALL"
    python experiments/realistic_contacts.py --out results/_scratch/b --set 'methods=["chsel"]' --set seeds=20
    .venv/bin/python experiments/realistic_contacts.py --out results/_scratch/a --set "methods=$ALL" \
        --set 'merge_runs=["results/_scratch/b"]'

``seeds`` is a count (grasps 0 .. seeds-1) or a list of grasp indices: ``--set
'seeds=[15,16,17]'`` draws the grasps 15-17 of a longer run, the same draws, so a sample can
be extended (into another ``--out``) without running its first grasps again.
"""

from __future__ import annotations

import functools
import json
import logging
import resource
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from contactpose import peers as bl
from contactpose.contacts import Contacts, FreeSpace
from contactpose.geometry import metrics
from contactpose.geometry.raycast import raycaster
from contactpose.geometry.sampling import perturb_normals
from contactpose.harness import sweep
from contactpose.harness.ceiling import truth_share
from contactpose.io.modelfile import FORMAT_VERSION
from contactpose.localize import DEFAULT_TIME_LIMIT, localize
from contactpose.localize import warm_up as warm_localize
from contactpose.model.object_model import ObjectModel, merged_mesh
from contactpose.model.symmetry import symmetry
from contactpose.model.table import estimate_bytes
from contactpose.options import STATUSES, fit_threshold
from contactpose.peers import chsel as chsel_peer
from contactpose.scoring.infacet import within_noise
from contactpose.search import find_pairs
from contactpose.sim import fingertip, objects, ycb
from contactpose.sim import grasps as simulate
from contactpose.stages import listed_rows

NAME = "realistic_contacts"
log = logging.getLogger(NAME)
METHODS = ("fast", "fast-free", "fast-samples", "paper", "icp-multistart", "scaling-series", "ss-published",
           "ss-published-timed", "chsel")
#: The default method's variants on the same grasps: given the free space the fingertips swept
#: (the points CHSEL gets), and with the search by hypothesize and verify.
VARIANTS = {"fast-free": "free_space", "fast-samples": "search"}
#: The methods of this library: status and hypothesis columns in the summary.
OURS = ("fast", "fast-free", "fast-samples", "paper")
#: Where the true assignment is lost, in pipeline order; "first": it is ranked first.
STAGES = ("table", "tree", "fit", "ranking", "first")
STAGE_TEXT = {"table": "table: a true pair not in S_ij", "tree": "tree: pairs there, tuple not listed",
              "fit": "fit test: tuple found, judged not to fit", "ranking": "ranking: tuple fits, another first",
              "first": "true tuple first, its pose off"}
#: Row subsets of summary.csv: every grasp, face-only and edge/vertex contacts, and the grasps
#: that every method of the run was given (the methods are compared there).
SPLITS = ("all", "face-only", "edge/vertex", "same grasps")
EDGES = ((0, 1), (1, 2), (2, 0))
GiB = 2.0**30


# --------------------------------------------------------------------------- models

def stem(name):
    return ycb.resolve(name)[len(ycb.PREFIX):]


def model_files(cache, name):
    s = stem(name)
    return {"model": Path(cache) / f"{s}.npz", "surface": Path(cache) / f"{s}_surface.npz",
            "meta": Path(cache) / f"{s}.json"}


def build_model_files(name, cache):
    """Build an object's model, save it, sample the baselines' surface, save it, and write the
    meta json with the build time and the peak RSS of this process after the build. Runs in a
    child process of its own (:func:`prepare`), so the peak is this object's."""
    files = model_files(cache, name)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = ObjectModel.from_mesh(ycb.load(name))
    build_s = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux
    model.save(files["model"])
    v = int(model.planes.valid.sum())
    meta = {"object": name, "facets": model.num_facets, "valid_facets": v, "diameter_m": model.diameter,
            "facet_table": model.table is not None, "patches": None if model.patches is None else model.patches.count,
            "patch_table": model.patch_table is not None, "ordered_pairs": int(model.num_pairs),
            "facet_table_gib": estimate_bytes(v * (v + 1) // 2) / GiB, "build_s": build_s,
            "build_stage_s": model.build_seconds, "build_peak_rss_gib": peak / GiB,
            "model_file_gib": files["model"].stat().st_size / GiB, "warnings": [str(w.message) for w in caught],
            "library": library_version()}
    model.table = None  # saved; the surface samples need the facets only, and the memory
    start = time.perf_counter()
    surface = bl.sample_surface(model)
    meta["surface_s"] = time.perf_counter() - start
    meta["surface_neighbours"] = int(surface.neighbours.shape[1])
    np.savez(files["surface"], points=surface.points, normals=surface.normals, facets=surface.facets,
             center=surface.center, radius=surface.radius, neighbours=surface.neighbours)
    files["meta"].write_text(json.dumps(meta, indent=1) + "\n")


def library_version():
    """git HEAD of the repository and whether contactpose/ differs from it (other engineers edit it)."""
    def git(*cmd):
        out = subprocess.run(["git", *cmd], cwd=sweep.ROOT, capture_output=True, text=True, check=False)
        return out.stdout.strip()
    return {"commit": git("rev-parse", "HEAD"), "contactpose_dirty": bool(git("status", "--porcelain", "contactpose"))}


def prepare(name, cache):
    """The meta dict of an object's cached model, building it first (in a child process) if
    it is not there."""
    files = model_files(cache, name)
    if all(f.exists() for f in files.values()) and current(files["model"]):
        return json.loads(files["meta"].read_text())
    Path(cache).mkdir(parents=True, exist_ok=True)
    log.info("%s: building the model (one at a time: with a facet table a 16,384-facet build peaks near 13 GiB)", name)
    code = ("import importlib.util, sys; spec = importlib.util.spec_from_file_location('realistic_build', sys.argv[1]); "
            "m = sys.modules['realistic_build'] = importlib.util.module_from_spec(spec); spec.loader.exec_module(m); "
            "m.build_model_files(*sys.argv[2:])")
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", code, str(Path(__file__).resolve()), name, str(cache)], check=True)
    meta = json.loads(files["meta"].read_text())
    log.info("%s: built in %.0f s (peak RSS %.1f GiB, file %.1f GiB), surface samples %.0f s; %.0f s in all",
             name, meta["build_s"], meta["build_peak_rss_gib"], meta["model_file_gib"], meta["surface_s"],
             time.perf_counter() - start)
    return meta


def current(path):
    """Whether a model file has this library's format version (others may change it meanwhile)."""
    with np.load(path) as data:
        return int(data["format_version"]) == FORMAT_VERSION


@dataclass
class Setup:
    """What a worker holds per object: model, vertex-merged mesh, baselines' surface and ICP
    target, the 12-D embedding of poses for ADD bounds (:func:`embed`), the mesh's vertices on
    its convex hull and its symmetry group (for the MSSD)."""

    model: ObjectModel
    vertices: np.ndarray
    faces: np.ndarray
    surface: bl.Surface
    target: object
    moments: tuple
    labels: np.ndarray
    hull: np.ndarray
    group: object


def setup(name, cache, cfg):
    def load():
        files = model_files(cache, name)
        model = ObjectModel.load(files["model"])
        mesh = merged_mesh(model.vertices, model.faces)
        vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        if not np.allclose(vertices[faces], model.triangles):
            raise RuntimeError(f"{name}: merging the vertices changed the face order")
        s = np.load(files["surface"])
        surface = bl.Surface(s["points"], s["normals"], s["facets"], s["center"], float(s["radius"]), s["neighbours"],
                             raycaster(model))
        p = model.surface_points
        labels = model.patches.labels if model.patch_table is not None else np.arange(model.num_facets)
        warm_up()
        return Setup(model, vertices, faces, surface, bl.icp_target(surface, cfg["icp_target_points"]),
                     (p.mean(axis=0), p.T @ p / len(p)), labels, metrics.hull_points(vertices), symmetry(model))
    return sweep.cached((NAME, name, str(cache)), load)


def paper_model(name, cache, cfg):
    """The paper's workflow where the full mesh has no facet table: the mesh decimated to about
    ``paper_facets`` facets, in its own frame, and built with the facet table (one per worker)."""
    def load():
        model = setup(name, cache, cfg).model
        small = objects.decimate(merged_mesh(model.vertices, model.faces), cfg["paper_facets"])
        return ObjectModel.from_mesh(small, facet_pairs=True)
    return sweep.cached((NAME, "paper", name, str(cache), cfg["paper_facets"]), load)


def warm_up():
    """One untimed call of everything timed, on the 53-facet banana (numba and Open3D load lazily)."""
    model = ObjectModel.from_mesh(objects.load("banana"))
    rng = np.random.default_rng(0)
    g = simulate.grasp(model, rng, n=4, position_noise=0.0005, normal_noise_deg=1.0)
    for method in ("fast", "paper"):
        warm_localize(model, g.contacts, position_noise=0.0005, normal_noise_deg=1.0, method=method)
    surface = bl.sample_surface(model)
    noise = dict(position_noise=0.0005, normal_noise_deg=1.0)
    bl.icp_multistart(model, surface, bl.icp_target(surface, 500), g.contacts, rng, starts=2, **noise)
    bl.scaling_series(model, surface, g.contacts, rng, initial=50, per_ball=4, max_particles=50, **noise)
    fingertip.approach(model.vertices, model.faces, rng, 4, 0.005)


# --------------------------------------------------------------------------- the grasp

def fingertips(s, rng, radius, cfg):
    """4 fingertip contacts on the object-frame mesh; a finger that misses is drawn again.
    -> (points, outward normals, facets, features, redraws, the sweeps (FingertipContacts))"""
    n = cfg["fingers"]
    kw = dict(cone_deg=cfg["cone_deg"], mode=cfg["mode"])
    got = fingertip.approach(s.vertices, s.faces, rng, n, radius, **kw)
    sweeps = [got]
    points, normals, facets, features = got.points.copy(), got.normals.copy(), got.facets.copy(), got.features.copy()
    missing, redraws = np.flatnonzero(~got.hit), 0
    while len(missing):
        if redraws >= cfg["max_redraws"]:
            raise RuntimeError(f"{redraws} fingertip redraws and still {len(missing)} misses")
        again = fingertip.approach(s.vertices, s.faces, rng, len(missing), radius, **kw)
        sweeps.append(again)
        redraws += len(missing)
        hit = missing[again.hit]
        points[hit], normals[hit] = again.points[again.hit], again.normals[again.hit]
        facets[hit], features[hit] = again.facets[again.hit], again.features[again.hit]
        missing = missing[~again.hit]
    return points, normals, facets, features, redraws, sweeps


def incident_facets(s, facet, point, feature):
    """The facets a contact may rightly be assigned to: its triangle on a face; on an edge the
    triangles sharing that edge; on a vertex the triangles around it (vertex-merged mesh)."""
    ids = s.faces[facet]
    tri = s.vertices[ids]
    if feature == fingertip.VERTEX:
        v = ids[np.argmin(np.linalg.norm(tri - point, axis=1))]
        around = np.flatnonzero((s.faces == v).any(axis=1))
    elif feature == fingertip.EDGE:
        dist = []
        for i, j in EDGES:
            e = tri[j] - tri[i]
            t = np.clip(np.dot(point - tri[i], e) / np.dot(e, e), 0.0, 1.0)
            dist.append(np.linalg.norm(point - tri[i] - t * e))
        i, j = EDGES[int(np.argmin(dist))]
        around = np.flatnonzero((s.faces == ids[i]).any(axis=1) & (s.faces == ids[j]).any(axis=1))
    else:
        around = np.zeros(0, dtype=np.int64)
    return np.union1d(around, [facet])


def embed(s, poses):
    """Poses (..., 4, 4) as 12-vectors whose distances are the RMS displacements of the
    model's surface points (metrics.pose_embedding). RMS ≥ ADD ≥ ADD-S."""
    return metrics.pose_embedding(poses, *s.moments)


def adds(s, pose, truth):
    return metrics.adds(pose, truth, s.model.surface_points, s.model.surface_tree)


def any_within(s, poses, truth, limit, max_anchors):
    """Whether some pose has ADD-S to truth below limit, exactly, without an ADD-S per pose:
    a pose within RMS `limit` of the truth is one (ADD-S ≤ ADD ≤ RMS); else anchors, nearest
    the truth first, each get their ADD-S a, which decides every pose within RMS a − limit of
    them (|ADD-S(h) − ADD-S(anchor)| ≤ ADD(h, anchor) ≤ RMS). -> (found, anchors, exact)"""
    if len(poses) == 0:
        return False, 0, True
    v = embed(s, poses)
    near = np.linalg.norm(v - embed(s, truth), axis=1)
    if near.min() < limit:
        return True, 0, True
    tree = cKDTree(v)
    open_ = np.ones(len(v), dtype=bool)
    order = np.argsort(near)
    pos = 0
    for anchors in range(1, max_anchors + 1):
        while pos < len(order) and not open_[order[pos]]:
            pos += 1
        if pos == len(order):
            return False, anchors - 1, True
        a = order[pos]
        value = adds(s, poses[a], truth)
        if value < limit:
            return True, anchors, True
        open_[a] = False
        open_[tree.query_ball_point(v[a], value - limit)] = False
    return False, max_anchors, not open_.any()


def truth_columns(s, contacts, result, true_sets, touched, cfg):
    """Where the true assignment is lost (see the module docstring) and what shows it."""
    labels = s.labels
    S = find_pairs(s.model, contacts, result.tolerance)
    keys = [np.unique(labels[c]) for c in true_sets]
    present = present_touched = 0
    for (i, j), pairs in S.items():
        a, b = np.repeat(keys[i], len(keys[j])), np.tile(keys[j], len(keys[i]))
        present += bool(pairs.contains(a, b).any())
        present_touched += bool(pairs.contains(labels[touched[[i]]], labels[touched[[j]]])[0])
    arrays = result.hypotheses.arrays
    facets = arrays.facets
    match = np.ones(len(facets), dtype=bool)
    for k, key in enumerate(keys):
        match &= np.isin(labels[np.maximum(facets[:, k], 0)], key) & (facets[:, k] >= 0)
    ranks = np.flatnonzero(match)
    fits = bool(len(ranks)) and bool(within_noise(s.model, contacts, arrays.take(ranks[:cfg["truth_fit_checks"]]),
                                                  result.tolerance, fit_threshold(contacts.n)).any())
    if len(ranks):
        stage = "first" if ranks[0] == 0 else ("ranking" if fits else "fit")
    else:
        stage = "table" if present < len(S) else "tree"
    return {"pairs_present": present, "pairs_present_touched": present_touched, "true_tuples": len(ranks),
            "true_rank": int(ranks[0]) if len(ranks) else None, "true_fits": fits, "truth_stage": stage}


def score(s, poses, truth, cfg, max_anchors=1):
    """Accuracy columns: found (any of poses), and of poses[0] (the best) top-1 and errors."""
    D = s.model.diameter
    if len(poses) == 0:
        return {"found": False, "found_exact": True, "anchors": 0, "top1_adds": False, "top1_strict": False,
                "rot_err_deg": None, "trans_err_mm": None, "adds_mm": None, "mssd_mm": None}
    found, anchors, exact = any_within(s, poses, truth, cfg["found_adds_frac"] * D, max_anchors)
    best = poses[0]
    a = adds(s, best, truth)
    return {"found": found, "found_exact": exact, "anchors": anchors, "top1_adds": bool(a < cfg["top1_adds_frac"] * D),
            "top1_strict": bool(metrics.pose_success(best, truth, D)),
            "rot_err_deg": float(metrics.rotation_error_deg(best, truth)),
            "trans_err_mm": 1e3 * float(metrics.translation_error(best, truth)), "adds_mm": 1e3 * a,
            "mssd_mm": 1e3 * s.group.mssd(best, truth, s.hull)}


def ours(s, contacts, truth, noise, cfg, model=None, **options):
    """localize (on ``model``, default the object's), scored on the hypotheses the default
    listing returns (keep="fitting", localize.listed_rows); the result keeps every distinct
    pose, for truth_columns. Warnings (the explosion estimate) are recorded, not printed."""
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = localize(s.model if model is None else model, contacts, **noise, **options, keep="all",
                     diagnose=False)  # wall: the search alone
    wall = time.perf_counter() - start
    poses = r.hypotheses.arrays.poses
    if r.method == "fast" and r.status != "time_limit":
        poses = poses[listed_rows(r.classes, len(poses))]
    row = {"ran": True, "note": "", "status": r.status, "num_hypotheses": r.num_hypotheses,
           "num_returned": len(poses), "classes": len(r.classes),
           "best_underdetermined": bool(r.best is not None and r.best.underdetermined),
           "widened": "widened" in r.hint, "warned_explosion": any("explode" in str(w.message) for w in caught),
           "time_online_ms": 1e3 * r.timing["total"], "time_wall_ms": 1e3 * wall}
    row.update(score(s, poses, truth, cfg, cfg["max_anchors"]))
    row.update(placement_columns(s, r, truth))
    return r, row


def placement_columns(s, result, truth):
    """How sure the answer says it is, against the truth: its confidence (the probability
    that the best pose is strictly right), the best pose strictly right modulo the object's
    symmetry group (``strict_sym``), how many distinct placements it weighed, and whether one
    of them is strictly right (``truth_listed``); and each placement's χ², probability and
    whether it is strictly right, space-separated in the placements' order
    (``placement_chi2``, ``placement_probability``, ``placement_right``), so other weightings
    of the same placements can be judged from the rows; and the share the truth would hold
    had the search found it at its own floor (``truth_share``, harness.ceiling.truth_share,
    with the truth's own χ²_S, ``truth_chi2``; empty for the paper's method)."""
    best = [] if result.best is None else [result.best.pose]
    listed = [p.pose for p in result.placements]
    right = strict_modulo_symmetry(s, listed, truth)
    oracle = ("", "") if result.confidence is None else truth_share(s.model, result.contacts, result, truth, s.group)
    return {"truth_share": oracle[0], "truth_chi2": oracle[1],
            "confidence": result.confidence, "strict_sym": bool(strict_modulo_symmetry(s, best, truth).any()),
            "placements": len(listed), "truth_listed": bool(right.any()),
            "placement_chi2": " ".join(f"{p.chi2:.4g}" for p in result.placements),
            "placement_probability": " ".join(f"{p.probability:.4g}" for p in result.placements),
            "placement_right": " ".join(str(int(x)) for x in right)}


def strict_modulo_symmetry(s, poses, truth):
    """(K,) bool: each pose strictly right (metrics.pose_success's thresholds) modulo the
    object's symmetry group. poses : list of (4, 4)."""
    if not len(poses):
        return np.zeros(0, dtype=bool)
    rot, trans = s.group.errors(np.stack(poses), truth)
    return (rot < metrics.SUCCESS_ROT_DEG) & (trans < metrics.SUCCESS_TRANS_FRAC * s.model.diameter)


def draw(s, rng, frac, cfg):
    """One grasp's draws, in the cell's order: pose, fingertips of radius frac x diameter,
    position noise, normal noise. -> (true pose, Contacts (world), object-frame points,
    outward normals, facets, features, redraws)"""
    return draw_with_free_space(s, rng, frac, cfg)[:7]


def draw_with_free_space(s, rng, frac, cfg):
    """:func:`draw`, and the free space the hitting fingertips swept before they touched
    (world frame, ``free_spacing_frac`` of the diameter apart, without noise: the outside
    peers' free points; it draws nothing)."""
    D = s.model.diameter
    pose = simulate.random_pose(rng, max_translation=cfg["translation_frac"] * D)
    points, normals, facets, features, redraws, sweeps = fingertips(s, rng, frac * D, cfg)
    R, t = pose[:3, :3], pose[:3, 3]
    world = points @ R.T + t + rng.normal(0.0, cfg["position_noise_frac"] * D, points.shape)
    finger = perturb_normals(-(normals @ R.T), np.radians(cfg["normal_noise_deg"]), rng)
    free = np.concatenate([fingertip.swept_free_points(w, cfg["free_spacing_frac"] * D) for w in sweeps])
    return (pose, Contacts(world, finger_normals=finger), points, normals, facets, features, redraws,
            free @ R.T + t)


def task(settings, rng, *, cfg, cache):
    name, frac, seed = settings["object"], settings["radius_frac"], settings["seed"]
    s = setup(name, cache, cfg)
    model = s.model
    D = model.diameter
    pose, contacts, points, normals, facets, features, redraws, free = draw_with_free_space(s, rng, frac, cfg)
    noise = dict(position_noise=cfg["position_noise_frac"] * D, normal_noise_deg=cfg["normal_noise_deg"])
    kinds = [str(f) for f in features]
    grasp = {"symmetry": ycb.symmetry(name) or "none", "diameter_mm": 1e3 * D, "radius_mm": 1e3 * frac * D,
             "features": " ".join(kinds), "n_face": kinds.count(fingertip.FACE), "n_edge": kinds.count(fingertip.EDGE),
             "n_vertex": kinds.count(fingertip.VERTEX), "face_only": all(k == fingertip.FACE for k in kinds),
             "redraws": redraws, "spread_mm": 1e3 * contacts.spread}
    rows, run = [], set(cfg["methods"])
    # the default method, with where the truth is lost
    if "fast" in run:
        r, row = ours(s, contacts, pose, noise, cfg)
        true_sets = [incident_facets(s, f, p, k) for f, p, k in zip(facets, points, kinds)]
        row.update(truth_columns(s, contacts, r, true_sets, facets, cfg))
        rows.append({"method": "fast", **grasp, **row})
    for method, option in VARIANTS.items():
        if method in run:
            value = FreeSpace(points=free) if option == "free_space" else "samples"
            rows.append({"method": method, **grasp, **ours(s, contacts, pose, noise, cfg, **{option: value})[1]})
    # the paper's method, within its time cap
    if "paper" in run and seed < cfg["paper_grasps"]:
        small = model if model.table is not None else paper_model(name, cache, cfg)
        r, row = ours(s, contacts, pose, noise, cfg, model=small, method="paper", time_limit=cfg["paper_time_limit"])
        if r.status == "time_limit":
            row = {"ran": False, "note": f"not finished within {cfg['paper_time_limit']:g} s",
                   "status": r.status, "num_hypotheses": r.num_hypotheses, "time_wall_ms": row["time_wall_ms"]}
        rows.append({"method": "paper", **grasp, **row, "paper_model_facets": small.num_facets})
    # the baselines, default budgets
    if seed < cfg["baseline_grasps"]:
        for method, call in (("icp-multistart", lambda: bl.icp_multistart(model, s.surface, s.target, contacts, rng,
                                                                            **noise)),
                             ("scaling-series", lambda: bl.scaling_series(model, s.surface, contacts, rng, **noise))):
            if method not in run:
                continue
            start = time.perf_counter()
            b = call()
            rows.append({"method": method, **grasp, **peer_row(s, b, start, pose, cfg)})
    if seed < cfg["published_grasps"]:
        ours_seconds = rows[0]["time_online_ms"] / 1e3 if "fast" in run else None
        rows += [{"method": r.pop("method"), **grasp, **r}
                 for r in published_series(s, contacts, pose, noise, cfg, rng, ours_seconds, run)]
    if "chsel" in run and seed < cfg["chsel_grasps"]:
        rows.append({"method": "chsel", **grasp, **outside_peer(name, cache, cfg, s, contacts, free, pose, rng)})
    return rows


def published_series(s, contacts, truth, noise, cfg, rng, ours_seconds, run=METHODS):
    """The Scaling Series as published (peers.scaling_series_published) with
    ``published_per_neighbourhood`` particles per δ-neighbourhood: its whole schedule
    (``ss-published``), and within the time ours took on the grasp (``ss-published-timed``),
    those of them in ``run``. -> rows; ``note`` says where a series stopped early."""
    rows = []
    m = cfg["published_per_neighbourhood"]
    for method, seconds in (("ss-published", None), ("ss-published-timed", ours_seconds)):
        if method not in run:
            continue
        start = time.perf_counter()
        b = bl.scaling_series_published(s.model, s.surface, contacts, rng, per_neighbourhood=m, seconds=seconds,
                                        **noise)
        note = "; ".join(filter(None, (f"M = {m}, {b.iterations} of {b.planned} scales", b.stopped)))
        rows.append({"method": method, **peer_row(s, b, start, truth, cfg, note)})
    return rows


def peer_row(s, b, start, truth, cfg, note=""):
    """A peer's row from its BaselineResult b, begun at perf_counter ``start``: cost, work,
    wall time (its online time) and the scores of its one pose."""
    ms = 1e3 * (time.perf_counter() - start)
    return {"ran": True, "note": note, "cost": b.cost, "evaluations": b.evaluations, "time_online_ms": ms,
            "time_wall_ms": ms, **score(s, b.pose[None], truth, cfg)}


def outside_peer(name, cache, cfg, s, contacts, free, truth, rng):
    """CHSEL's row on one grasp (contactpose.peers.chsel, its README's settings), or a row that
    says why it did not run. found: over its whole returned set, sorted by its RMSE."""
    version = chsel_peer.available()
    if version is None:
        return {"ran": False, "note": "not run: CHSEL not installed (pip install contactpose[peers])"}
    peer = sweep.cached((NAME, "chsel", name, str(cache)), lambda: chsel_peer.ChselPeer(s.vertices, s.faces))
    start = time.perf_counter()
    best, poses, rmse = peer.localize(contacts.points, free, rng, scale=cfg["translation_frac"] * s.model.diameter)
    row = {"ran": True, "note": f"chsel {version}, batch {chsel_peer.BATCH}, {chsel_peer.ITERATIONS} iterations, CPU",
           "cost": best.cost, "evaluations": best.evaluations, "free_points": len(free),
           "time_online_ms": 1e3 * (time.perf_counter() - start)}
    row["time_wall_ms"] = row["time_online_ms"]
    row.update(score(s, poses, truth, cfg))
    return row


def make_sweep(cfg, name, cache):
    fixed = {k: v for k, v in cfg.items() if k not in ("objects", "estimate", "keep_models", "workers", "merge_runs")}
    return sweep.Sweep(f"{NAME}:{stem(name)}", functools.partial(task, cfg=cfg, cache=str(cache)),
                       {"object": [name], "radius_frac": cfg["radius_fracs"]}, seeds=seed_list(cfg),
                       base_seed=cfg["base_seed"], seed_axes=("object",), config=fixed)


def finished(sw, stage):
    """Whether every cell of a sweep already has its rows in stage/ from the same config."""
    try:
        old = json.loads((Path(stage) / sweep.CONFIG_JSON).read_text())
        done = {r[sweep.CELL_COLUMN] for r in sweep.read_rows(Path(stage) / sweep.TIMINGS_CSV)}
    except (OSError, ValueError):
        return False
    record = sw.config_record()
    same = all(old.get(k) == record[k] for k in ("experiment", "config", "base_seed", "seed_axes"))
    return same and {c.cell for c in sw.cells()} <= done


# --------------------------------------------------------------------------- publishing

def publish(out, cfg, stages, metas, seconds, *, workers, ran_here, earlier):
    """grasps.csv / timings.csv (the objects' sweeps concatenated), models.csv, config.json, run.json.

    ``earlier`` is (run.json, models.csv rows by object) as ``out`` held them before this call
    ran anything: an object none of whose grasps ran here (``ran_here``) keeps its model row, and
    a call that ran no grasp at all (a re-publication, say with another pass merged) keeps the
    record of the run that made the rows (library commit, machine, seconds, workers) and adds its
    own as ``republished``. run.json also carries each merged pass's run.json."""
    for src, dst in ((sweep.RESULTS_CSV, "grasps.csv"), (sweep.TIMINGS_CSV, "timings.csv")):
        rows = [r for st in stages if (Path(st) / src).exists() for r in sweep.read_rows(Path(st) / src)]
        sweep.write_rows(out / dst, rows)
    earlier_run, earlier_models = earlier
    sweep.write_rows(out / "models.csv", [earlier_models[m["object"]]
                                           if m["object"] in earlier_models and m["object"] not in ran_here
                                           else model_row(m) for m in metas])
    (out / "config.json").write_text(json.dumps(cfg, indent=1) + "\n")
    record = {"experiment": NAME, "seconds": round(seconds, 1), "workers": workers,
              "library": library_version(), "machine": sweep.machine_description()}
    if earlier_run and not ran_here:
        record = {**earlier_run, "republished": {k: record[k] for k in ("library", "machine")}}
    record |= {"objects_done": [m["object"] for m in metas],
               "merged_runs": {root: sweep.read_run(sweep.ROOT / root / NAME) for root in cfg["merge_runs"]}}
    (out / "run.json").write_text(json.dumps(record, indent=1) + "\n")


def model_row(meta):
    """models.csv row of an object's model meta: its numbers and the commit that built it."""
    return ({k: v for k, v in meta.items() if k not in ("build_stage_s", "warnings", "library")}
            | {"commit": meta["library"]["commit"][:12]})


def earlier_publication(out):
    """(run.json, models.csv rows by object) of what ``out`` holds now ({} each if nothing)."""
    models = out / "models.csv"
    return sweep.read_run(out), {r["object"]: r for r in sweep.read_rows(models)} if models.exists() else {}


def expected_minutes(cfg, cache, workers):
    """(model-build minutes, grasp minutes, builds to make) this run expects: each method of
    ``methods`` on its grasps at its seconds a grasp (config ``estimate``; CHSEL only when
    installed), the grasps spread over ``workers`` (0 or None: one, in process)."""
    e = cfg["estimate"]
    builds = sum(not (model_files(cache, n)["model"].exists() and current(model_files(cache, n)["model"]))
                 for n in cfg["objects"])
    run = [m for m in cfg["methods"] if m != "chsel" or chsel_peer.available()]
    per_cell = sum(grasps_of(cfg, m) * e["seconds"][m] for m in run)
    per_cell += len(seed_list(cfg)) * e["check_seconds"] if "fast" in run else 0.0
    work = len(cfg["objects"]) * len(cfg["radius_fracs"]) * per_cell
    return builds * e["build_minutes"], work / 60.0 / max(workers or 1, 1), builds


# --------------------------------------------------------------------------- summary

def pct(x, q):
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if len(x) else np.nan


def summarize(c):
    """summary.csv rows: object × radius × method × split (SPLITS)."""
    rows, same = [], same_grasps(c)
    for obj in dict.fromkeys(c["object"]):
        for frac in sorted(set(c["radius_frac"][c["object"] == obj])):
            for method in METHODS:
                cell = (c["object"] == obj) & (c["radius_frac"] == frac) & (c["method"] == method)
                if not cell.any():
                    continue
                for split in SPLITS:
                    sel = cell & {"all": True, "face-only": c["face_only"] == 1, "edge/vertex": c["face_only"] == 0,
                                  "same grasps": same}[split]
                    rows.append(summary_row(c, sel, obj, frac, method, split))
    return rows


def same_grasps(c):
    """Mask of the rows whose grasp (object, radius, seed) every method in ``c`` was given."""
    keys = list(zip(c["object"], c["radius_frac"], c["seed"]))
    given = [{k for k, m in zip(keys, c["method"]) if m == method} for method in dict.fromkeys(c["method"])]
    common = set.intersection(*given) if given else set()
    return np.array([k in common for k in keys], dtype=bool)


def summary_row(c, sel, obj, frac, method, split):
    ran = sel & (c["ran"] == 1)
    n, k = int(sel.sum()), int(ran.sum())
    share = (lambda col: float(np.mean(c[col][ran] == 1)) if k else np.nan)
    row = {"object": obj, "symmetry": c["symmetry"][sel][0] if n else "", "radius_frac": frac,
           "radius_mm": float(c["radius_mm"][sel][0]) if n else np.nan, "method": method, "split": split,
           "grasps": n, "ran": k, "found": share("found"), "top1_adds": share("top1_adds"),
           "top1_strict": share("top1_strict")}
    for col in ("rot_err_deg", "trans_err_mm", "adds_mm"):
        row[f"{col}_median"], row[f"{col}_p90"] = pct(c[col][ran], 50), pct(c[col][ran], 90)
    mssd = c.get("mssd_mm")  # runs before it had no MSSD
    row["ar_mssd"] = metrics.ar_mssd(mssd[ran], float(c["diameter_mm"][sel][0])) if k and mssd is not None else np.nan
    for st in STATUSES:
        row[f"status_{st}"] = int(np.sum(c["status"][ran] == st)) if method in OURS else ""
    row["no_hypothesis"] = row["hypotheses_median"] = row["returned_median"] = np.nan
    if method in OURS:   # a run of peers alone has no hypothesis columns
        row["no_hypothesis"] = float(np.mean(c["num_hypotheses"][ran] == 0)) if k else np.nan
        row["hypotheses_median"] = pct(c["num_hypotheses"][ran], 50)
        returned = c.get("num_returned", c["num_hypotheses"])   # runs before keep="fitting" listed every hypothesis
        row["returned_median"] = pct(returned[ran], 50)
    row["online_ms_median"], row["online_ms_p95"] = pct(c["time_online_ms"][ran], 50), pct(c["time_online_ms"][ran], 95)
    row["redraws"] = int(np.nansum(c["redraws"][sel]))
    row["found_inexact"] = int(np.sum(c["found_exact"][ran] == 0))
    if method == "fast":
        for crit in ("top1_adds", "top1_strict"):
            fail = ran & (c[crit] == 0)
            for stage in STAGES:
                row[f"fail_{crit}_{stage}"] = int(np.sum(c["truth_stage"][fail] == stage))
        row["pairs_present_median"] = pct(c["pairs_present"][ran], 50)
    return row


def fmt(x, spec=".0f", scale=1.0):
    return "–" if x == "" or not np.isfinite(float(x)) else format(scale * float(x), spec)


def short(name):
    return stem(name).split("_", 1)[1]


def summary_markdown(rows, models, cfg_text, cfg=None):
    by = {(r["object"], float(r["radius_frac"]), r["method"], r["split"]): r for r in rows}
    objs = list(dict.fromkeys(r["object"] for r in rows))
    fracs = sorted({float(r["radius_frac"]) for r in rows})
    lines = ["# Realistic contacts on YCB objects", "", cfg_text, "",
             "Default method (`fast`). found: some hypothesis within ADD-S 5 % of the diameter; top-1 ADD-S: the best "
             "within 10 %; strict: rotation < 5° and translation < 5 % of the diameter. Errors of the best pose "
             "(median / p90; for symmetric objects the ADD-S in mm is the fair one). no-hyp: no hypothesis. "
             "face / e-v: top-1 ADD-S of the face-only grasps and of those with an edge or vertex contact (grasps). "
             "AR_MSSD: the best pose's MSSD recall averaged over thresholds of 5-50 % of the diameter (BOP).", "",
             "| object | sym. | r (% diam.) | grasps | found % | top-1 ADD-S % | top-1 strict % | AR_MSSD % | "
             "rot med / p90 (°) | "
             "trans med / p90 (mm) | ADD-S med / p90 (mm) | no-hyp % | hyp. found / listed (median) | online med / p95 (ms) | "
             "face (n) / e-v (n) top-1 % |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for obj in objs:
        for frac in fracs:
            r = by.get((obj, frac, "fast", "all"))
            if r is None:
                continue
            f, e = by[(obj, frac, "fast", "face-only")], by[(obj, frac, "fast", "edge/vertex")]
            lines.append(
                f"| {short(obj)} | {r['symmetry'] if r['symmetry'] != 'none' else ''} | {100 * frac:g} | {r['grasps']} | "
                f"{fmt(r['found'], '.0f', 100)} | {fmt(r['top1_adds'], '.0f', 100)} | {fmt(r['top1_strict'], '.0f', 100)} | "
                f"{fmt(r.get('ar_mssd', ''), '.0f', 100)} | "
                f"{fmt(r['rot_err_deg_median'], '.1f')} / {fmt(r['rot_err_deg_p90'], '.0f')} | "
                f"{fmt(r['trans_err_mm_median'], '.1f')} / {fmt(r['trans_err_mm_p90'], '.0f')} | "
                f"{fmt(r['adds_mm_median'], '.1f')} / {fmt(r['adds_mm_p90'], '.0f')} | "
                f"{fmt(r['no_hypothesis'], '.0f', 100)} | {fmt(r['hypotheses_median'], '.0f')} / "
                f"{fmt(r['returned_median'], '.0f')} | "
                f"{fmt(r['online_ms_median'], '.0f')} / {fmt(r['online_ms_p95'], '.0f')} | "
                f"{fmt(f['top1_adds'], '.0f', 100)} ({f['grasps']}) / {fmt(e['top1_adds'], '.0f', 100)} ({e['grasps']}) |")
    lines += ["", "## All objects, by radius (default method)", "",
              "| r (% diam.) | grasps | found % | top-1 ADD-S % | top-1 strict % | face-only top-1 % (n) | "
              "edge/vertex top-1 % (n) | statuses | redraws |", "|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    for frac in fracs:
        tot = pooled(rows, frac, "fast")
        lines.append(f"| {100 * frac:g} | {tot['all']['n']} | {fmt(tot['all']['found'], '.0f', 100)} | "
                     f"{fmt(tot['all']['top1_adds'], '.0f', 100)} | {fmt(tot['all']['top1_strict'], '.0f', 100)} | "
                     f"{fmt(tot['face-only']['top1_adds'], '.0f', 100)} ({tot['face-only']['n']}) | "
                     f"{fmt(tot['edge/vertex']['top1_adds'], '.0f', 100)} ({tot['edge/vertex']['n']}) | "
                     + ", ".join(f"{st} {tot['status'][st]}" for st in STATUSES if tot["status"][st]) +
                     f" | {tot['redraws']} |")
    lines += ["", "## Where the true assignment is lost (default method, grasps whose top-1 fails)", "",
              "Stage: the first that loses the true facet tuple (an edge or vertex contact's true facets are all the "
              "triangles incident to the touched feature). On a model of regions a tuple is \"listed\" when some "
              "distinct pose holds the true region of every contact: \"tree\" then also counts a true tuple that was "
              "joined and posed but grouped under a near-copy led by other regions. experiments/truth_stages.py draws "
              "the failures again and follows the true placement instead, into truth_stages.md beside this file.", "",
              "| r (% diam.) | criterion | failures | " + " | ".join(STAGE_TEXT[s] for s in STAGES) + " |",
              "|---:|---|---:|" + "---:|" * len(STAGES)]
    for frac in fracs:
        for crit in ("top1_adds", "top1_strict"):
            counts = [sum(int(r[f"fail_{crit}_{st}"]) for r in rows if float(r["radius_frac"]) == frac
                          and r["method"] == "fast" and r["split"] == "all") for st in STAGES]
            lines.append(f"| {100 * frac:g} | {'ADD-S 10 %' if crit == 'top1_adds' else 'strict'} | {sum(counts)} | "
                         + " | ".join(str(x) for x in counts) + " |")
    lines += ["", "## Methods on the same grasps (all objects)", "",
              "Baselines and the paper's method run on the first grasps of each object and radius (config "
              "`baseline_grasps`, `paper_grasps`, `published_grasps`, `chsel_grasps`); every method is counted here on "
              "the grasps that every method was given (the default method's on all grasps: the tables above). `ran` "
              "counts the grasps where a method gave an answer (the paper's: finished within its time cap).", "",
              "| r (% diam.) | method | ran / grasps | found % | top-1 ADD-S % | top-1 strict % | AR_MSSD % | "
              "rot med (°) | trans med (mm) | online med / p95 (ms) | budget | note |",
              "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for frac in fracs:
        for method in METHODS:
            tot = pooled(rows, frac, method)["same grasps"]
            if tot["n"]:
                lines.append(f"| {100 * frac:g} | {method} | {tot['ran']} / {tot['n']} | {fmt(tot['found'], '.0f', 100)} | "
                             f"{fmt(tot['top1_adds'], '.0f', 100)} | {fmt(tot['top1_strict'], '.0f', 100)} | "
                             f"{fmt(tot['ar_mssd'], '.0f', 100)} | "
                             f"{fmt(tot['rot'], '.1f')} | {fmt(tot['trans'], '.1f')} | {fmt(tot['ms'], '.0f')} / "
                             f"{fmt(tot['ms95'], '.0f')} | {budget(method, cfg or {})} | {tot['note']} |")
    lines += ["", "## Models (built once per object)", "",
              "| object | facets | patches | facet table | build (s) | peak RSS (GiB) | model file (GiB) | "
              "surface samples (s) |", "|---|---:|---:|---|---:|---:|---:|---:|"]
    for m in models:
        lines.append(f"| {short(m['object'])} | {m['facets']} | {m['patches']} | {m['facet_table']} | "
                     f"{fmt(m['build_s'], '.0f')} | {fmt(m['build_peak_rss_gib'], '.1f')} | "
                     f"{fmt(m['model_file_gib'], '.1f')} | {fmt(m['surface_s'], '.0f')} |")
    return "\n".join(lines) + "\n"


def budget(method, cfg):
    """The time or work each method was given per grasp, in words."""
    return {"fast": f"time limit {DEFAULT_TIME_LIMIT:g} s",
            "fast-free": f"time limit {DEFAULT_TIME_LIMIT:g} s, the swept free space",
            "fast-samples": f"time limit {DEFAULT_TIME_LIMIT:g} s, search=\"samples\"",
            "paper": f"time limit {cfg.get('paper_time_limit', float('nan')):g} s",
            "icp-multistart": "32 starts", "scaling-series": "2,000 particles",
            "ss-published": f"M = {cfg.get('published_per_neighbourhood')}, its whole schedule",
            "ss-published-timed": f"M = {cfg.get('published_per_neighbourhood')}, the time ours took",
            "chsel": f"{chsel_peer.BATCH} transforms x {chsel_peer.ITERATIONS} iterations"}[method]


def pooled(rows, frac, method):
    """Grasp-weighted pooling of summary rows over objects (shares and counts; medians of the
    per-object medians for errors and times)."""
    out = {}
    for split in SPLITS:
        sel = [r for r in rows if float(r["radius_frac"]) == frac and r["method"] == method and r["split"] == split]
        n, k = sum(int(r["grasps"]) for r in sel), sum(int(r["ran"]) for r in sel)
        mean = (lambda col: sum(float(r[col]) * int(r["ran"]) for r in sel if int(r["ran"])) / k if k else np.nan)
        med = (lambda col: float(np.nanmedian([float(r[col]) for r in sel if int(r["ran"])])) if k else np.nan)
        out[split] = {"n": n, "ran": k, "found": mean("found"), "top1_adds": mean("top1_adds"),
                      "top1_strict": mean("top1_strict"), "ar_mssd": mean("ar_mssd"), "rot": med("rot_err_deg_median"),
                      "trans": med("trans_err_mm_median"), "ms": med("online_ms_median"), "ms95": med("online_ms_p95"),
                      "note": "" if k == n else f"{n - k} not run or not finished"}
    sel = [r for r in rows if float(r["radius_frac"]) == frac and r["method"] == method and r["split"] == "all"]
    out["status"] = {st: sum(int(r[f"status_{st}"] or 0) for r in sel) for st in STATUSES}
    out["redraws"] = sum(int(r["redraws"]) for r in sel)
    return out


def write_summary(out):
    c = sweep.read_columns(out / "timings.csv")
    rows = summarize(c)
    sweep.write_rows(out / "summary.csv", rows)
    rows = sweep.read_rows(out / "summary.csv")
    models = sweep.read_rows(out / "models.csv") if (out / "models.csv").exists() else []
    cfg = json.loads((out / "config.json").read_text()) if (out / "config.json").exists() else {}
    text = (f"{len(set(c['object']))} objects, radii {', '.join(f'{100 * f:g}' for f in sorted(set(c['radius_frac'])))} % "
            f"of the diameter, {int(np.max(c['seed'])) + 1} grasps per object and radius, 4 fingers (cone 30°), "
            f"noise σ_x = {100 * cfg.get('position_noise_frac', np.nan):g} % of the diameter, "
            f"σ_n = {cfg.get('normal_noise_deg', np.nan):g}°, Gaussian; localize told the noise.")
    (out / "summary.md").write_text(summary_markdown(rows, models, text, cfg))
    return rows


# --------------------------------------------------------------------------- figure

def plot(out_dir):
    """realistic_contacts.png/pdf from timings.csv (through summary.csv): top-1 against radius
    per object, face-only against edge/vertex, where the truth is lost, and the methods."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    rows = write_summary(out)
    objs = list(dict.fromkeys(r["object"] for r in rows))
    fracs = sorted({float(r["radius_frac"]) for r in rows})
    x = 100 * np.array(fracs)
    get = {(r["object"], float(r["radius_frac"]), r["method"], r["split"]): r for r in rows}
    with plt.rc_context(sweep.PAPER_RC):
        fig, axes = plt.subplots(2, 2, figsize=(sweep.PAGE_WIDTH, 5.6))
        ax = axes[0, 0]
        colors = plt.cm.tab10(np.arange(len(objs))) if len(objs) <= 10 else plt.cm.tab20(np.arange(len(objs)) % 20)
        for obj, color in zip(objs, colors):
            y = [float(get[(obj, f, "fast", "all")]["top1_adds"]) if (obj, f, "fast", "all") in get else np.nan
                 for f in fracs]
            ys = [float(get[(obj, f, "fast", "all")]["top1_strict"]) if (obj, f, "fast", "all") in get else np.nan
                  for f in fracs]
            sym = next(r["symmetry"] for r in rows if r["object"] == obj)   # a run of peers alone has no "fast"
            ax.plot(x, y, "-o", color=color, ms=3, label=short(obj) + ("*" if sym != "none" else ""))
            ax.plot(x, ys, ":", color=color, lw=0.8)
        ax.set_xlabel("fingertip radius (% of diameter)")
        ax.set_ylabel("top-1 success (share of grasps)")
        ax.set_title("top-1: ADD-S < 10 % (solid), strict (dotted); * symmetric")
        ax.set_ylim(-0.03, 1.03)
        ax.legend(fontsize=5, ncol=2, frameon=False, loc="lower left")
        ax = axes[0, 1]
        width = 0.35 * (x[1] - x[0] if len(x) > 1 else 1.0)
        for k, (split, color) in enumerate((("face-only", "tab:blue"), ("edge/vertex", "tab:orange"))):
            tot = [pooled(rows, f, "fast")[split] for f in fracs]
            pos = x + (k - 0.5) * width
            ax.bar(pos, [t["top1_adds"] for t in tot], width, color=color, label=f"{split}, ADD-S")
            ax.plot(pos, [t["top1_strict"] for t in tot], "k_", ms=6, mew=1.2, label="strict" if k == 0 else None)
            for p, t in zip(pos, tot):
                ax.annotate(str(t["n"]), (p, 0.02), ha="center", fontsize=5, color="white")
        ax.set_xticks(x)
        ax.set_xlabel("fingertip radius (% of diameter)")
        ax.set_ylabel("top-1 success, all objects")
        ax.set_title("face contacts only vs an edge/vertex contact (n in bars)")
        ax.set_ylim(0, 1.15)
        ax.legend(fontsize=6, frameon=False, ncol=3, loc="upper center")
        ax = axes[1, 0]
        stage_colors = dict(zip(STAGES, ("tab:red", "tab:orange", "gold", "tab:cyan", "tab:gray")))
        n = np.array([pooled(rows, f, "fast")["all"]["n"] for f in fracs], dtype=float)
        tallest = 0.0
        for k, crit in enumerate(("top1_adds", "top1_strict")):
            bottom = np.zeros(len(fracs))
            for stage in STAGES:
                v = np.array([sum(int(r[f"fail_{crit}_{stage}"]) for r in rows if float(r["radius_frac"]) == f
                                  and r["method"] == "fast" and r["split"] == "all") for f in fracs]) / np.maximum(n, 1)
                ax.bar(x + (k - 0.5) * width, v, width, bottom=bottom, color=stage_colors[stage],
                       hatch="//" if k else None, edgecolor="white", lw=0.3, label=STAGE_TEXT[stage] if k == 0 else None)
                bottom += v
            tallest = max(tallest, bottom.max())
        ax.set_xticks(x)
        ax.set_xlabel("fingertip radius (% of diameter)")
        ax.set_ylabel("top-1 misses, share of grasps")
        ax.set_ylim(0, 1.6 * tallest or 1)  # headroom for the legend
        ax.set_title("where the truth is lost: ADD-S (left), strict (hatched)")
        ax.legend(fontsize=5.5, frameon=False, loc="upper left")
        ax = axes[1, 1]
        method_style = {"fast": ("o", "tab:blue"), "fast-free": ("o", "tab:brown"), "fast-samples": ("*", "tab:pink"),
                        "paper": ("s", "tab:cyan"), "icp-multistart": ("v", "tab:red"),
                        "scaling-series": ("D", "tab:green"), "ss-published": ("P", "olive"),
                        "ss-published-timed": ("X", "tab:olive"), "chsel": ("^", "tab:purple")}
        grasps = sweep.read_columns(out / "timings.csv")
        for method, (marker, color) in method_style.items():
            tot = [pooled(rows, f, method)["same grasps"] for f in fracs]
            if not any(t["n"] for t in tot):
                continue
            notes = grasps["note"][(grasps["method"] == method) & (grasps["ran"] == 0)]
            label = method_label(method, tot, str(notes[0]) if len(notes) else "")
            if not any(t["ran"] for t in tot):  # a method that never ran has no success rate, not one of 0 %
                ax.plot([], [], marker, color=color, mfc="none", ls="none", label=label)
                continue
            y = [t["top1_adds"] * t["ran"] / t["n"] if t["ran"] else np.nan for t in tot]  # unfinished: a miss
            ax.plot(x, y, "-" + marker, color=color, label=label)
            ar = [t["ar_mssd"] * t["ran"] / t["n"] if t["ran"] else np.nan for t in tot]
            ax.plot(x, ar, "--" + marker, color=color, mfc="none")
            for xi, t in zip(x, tot):
                if t["n"] and not t["ran"]:
                    ax.annotate("not run", (xi, 0.02), ha="center", fontsize=5, color=color)
        ax.set_xlabel("fingertip radius (% of diameter)")
        ax.set_ylabel("top-1 ADD-S (solid), AR_MSSD (dashed)")
        ax.set_title("methods on the same grasps (unfinished: a miss)")
        ax.set_ylim(-0.03, 1.03)
        ax.legend(fontsize=5.5, frameon=False, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.16))
        return sweep.save_figure(fig, out, NAME)


def method_label(method, tot, note=""):
    """The methods panel's legend entry: the grasps a method was given and, when fewer ran,
    how many did; a method that ran on none is "not run", with the reason its rows give
    (note: the first such row's note, e.g. "not run: CHSEL not installed (pip ...)").
    tot: one dict per radius with "n" (grasps given) and "ran"."""
    n, ran = sum(t["n"] for t in tot), sum(t["ran"] for t in tot)
    if not ran:
        why = note.removeprefix("not run: ").split(" (")[0]
        return f"{method}: not run" + (f" ({why})" if why else "")
    return f"{method} ({n} grasps" + (f", {ran} ran)" if ran < n else ")")


def summary(out_dir):
    return (Path(out_dir) / "summary.md").read_text()


# --------------------------------------------------------------------------- driver

#: Config key of the grasps each method runs on (the default method: every grasp).
GRASPS_KEY = {"fast": "seeds", "fast-free": "seeds", "fast-samples": "seeds", "paper": "paper_grasps", "icp-multistart": "baseline_grasps",
              "scaling-series": "baseline_grasps", "ss-published": "published_grasps",
              "ss-published-timed": "published_grasps", "chsel": "chsel_grasps"}


def seed_list(cfg):
    """The grasp indices a run draws: ``seeds`` a count (0 .. seeds-1) or a list (say
    ``list(range(15, 30))``, to extend a run of the first 15 without drawing them again)."""
    seeds = cfg["seeds"]
    return list(range(seeds)) if isinstance(seeds, int) else [int(s) for s in seeds]


def grasps_of(cfg, method):
    """How many of the run's grasps ``method`` runs on (the peers run on the first N grasps only)."""
    key = GRASPS_KEY[method]
    return len([s for s in seed_list(cfg) if key == "seeds" or s < cfg[key]])


def methods_problem(cfg):
    """Why the config's ``methods`` cannot run (one line), or None. A run of some methods only
    (e.g. CHSEL in a pass of its own) draws the same grasps; every grasp needs some method."""
    methods = cfg["methods"]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        return f"methods {methods!r}: expected a non-empty list of {', '.join(METHODS)}"
    if "ss-published-timed" in methods and "fast" not in methods:
        return "methods: ss-published-timed takes the time of the default method, so it needs \"fast\" too"
    seeds = cfg["seeds"]
    if not (isinstance(seeds, int) and seeds > 0 or isinstance(seeds, list) and seeds
            and all(isinstance(x, int) and x >= 0 for x in seeds) and len(set(seeds)) == len(seeds)):
        return f"seeds {seeds!r}: expected a positive count or a list of distinct grasp indices >= 0"
    most = max(grasps_of(cfg, m) for m in methods)
    if most < len(seed_list(cfg)):
        fix = (f"lower seeds to {most}" if isinstance(seeds, int)
               else f"keep seeds below {max(cfg[GRASPS_KEY[m]] for m in methods)}")
        return f"methods {methods!r} run on fewer grasps than seeds = {seeds}: {fix}"
    return None


#: Config keys in which a merged run may differ: which methods ran, on how many grasps.
MERGE_FREE = ("methods", "seeds", "paper_grasps", "baseline_grasps", "published_grasps", "chsel_grasps")


def merge_dir(name, root):
    """Stage directory of object ``name`` in the run written with ``--out root``."""
    return sweep.ROOT / root / NAME / "_scratch" / "sweeps" / stem(name)


def merge_problem(cfg, cache):
    """Why the runs of ``merge_runs`` cannot join this one (one line), or None. Each must hold
    every object, drawn alike (the same config but for MERGE_FREE, the same seeds), with none
    of this run's methods."""
    for root in cfg["merge_runs"]:
        for name in cfg["objects"]:
            path = merge_dir(name, root) / sweep.CONFIG_JSON
            if not path.exists():
                return f"merge_runs: no run of {name} in {path.parent}"
            other, mine = json.loads(path.read_text()), make_sweep(cfg, name, cache).config_record()
            a, b = ({k: v for k, v in r["config"].items() if k not in MERGE_FREE} for r in (mine, other))
            differ = sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))
            if differ or other["base_seed"] != mine["base_seed"] or other["seed_axes"] != mine["seed_axes"]:
                return f"merge_runs: {path.parent} drew other grasps ({', '.join(differ) or 'seeds'} differ)"
            both = set(other["config"]["methods"]) & set(cfg["methods"])
            if both:
                return f"merge_runs: {path.parent} also ran {', '.join(sorted(both))}"
    return None


def main(argv=None):
    args, cfg, out = sweep.start(NAME, __doc__, argv)
    problem = methods_problem(cfg) or merge_problem(cfg, sweep.ROOT / cfg["model_cache"])
    if problem:
        print(f"{NAME}: {problem}", file=sys.stderr)
        return 2
    cache = sweep.ROOT / cfg["model_cache"]
    if not args.plot_only:
        out.mkdir(parents=True, exist_ok=True)
        workers = sweep.workers_for(args, cfg)
        sweeps = {n: make_sweep(cfg, n, cache) for n in cfg["objects"]}
        stage_of = {n: out / "_scratch" / "sweeps" / stem(n) for n in cfg["objects"]}
        todo = [n for n, sw in sweeps.items() if args.fresh or not finished(sw, stage_of[n])]
        builds, sweeping, missing = expected_minutes({**cfg, "objects": todo}, cache, workers)
        print(f"{NAME}: {len(cfg['objects'])} objects ({len(todo)} to run) x {len(cfg['radius_fracs'])} radii x "
              f"{len(seed_list(cfg))} grasps; "
              f"expected about {builds + sweeping:.0f} min ({missing} model builds, {builds:.0f} min, one at a time; "
              f"grasps {sweeping:.0f} min " + (f"on {workers} workers)" if workers else "in process)"), flush=True)
        start = time.perf_counter()
        stages, metas, ran_here, earlier = [], [], set(), earlier_publication(out)
        for name, sw in sweeps.items():
            stage = stage_of[name]
            stages.append(stage)
            done = name not in todo
            meta = model_files(cache, name)["meta"]
            metas.append(json.loads(meta.read_text()) if done and meta.exists() else prepare(name, cache))
            if not done:
                ran_here.add(name)
                sweep.run_logged(sw, stage, args, cfg)
                if not cfg["keep_models"]:
                    model_files(cache, name)["model"].unlink(missing_ok=True)
            stages += [merge_dir(name, root) for root in cfg["merge_runs"]]
            publish(out, cfg, stages, metas, time.perf_counter() - start, workers=workers, ran_here=ran_here,
                    earlier=earlier)
            plot(out)
            log.info("%s: done, %.0f min so far", name, (time.perf_counter() - start) / 60)
    return sweep.finish(out, plot, summary)


if __name__ == "__main__":
    sys.exit(main())
