"""Where the realistic-contacts benchmark's failures lose the true placement, stage by stage.

Reads results/realistic_contacts/grasps.csv, draws the failing grasps of the default method
again (the same cell, the same random stream: ``realistic_contacts.draw``), and follows the
truth through the pipeline on a model of surface regions. The *true placement* is the best
ranked distinct pose within ADD-S 5 % of the diameter of the true pose (what the benchmark
calls found); the *true region tuple* holds, for each contact, the region of its touched
triangle (for an edge or vertex contact, of any incident triangle). The first that applies:

* ``first``: the true placement is ranked first, and its pose is off (strict failures);
* ``ranking``: the true placement fits within noise, another placement is first;
* ``fit``: the true placement is listed, and the fit test says it does not fit;
* ``grouping``: no listed pose is the true placement, but the true region tuple was posed
  (its pose fell outside 5 %, and the distinct-pose grouping kept another leader);
* ``table``: some finger pair's true region pair is not in S_ij;
* ``tree``: all six pairs are there, the tree does not join the tuple (the handedness test);
* ``cut``: joined, but not posed (the search's time limit).

For each grasp it also records the true region tuple's best row (its χ² and rotation error,
from ``distinct=False``) beside the listed best's, and the rotation error an efficient
estimator would make with these contacts (RMS, Cramér–Rao, each contact's location unknown
on a quadric: uncertainty.bounds), which says whether the grasp or the method limits the
pose. Failures: top-1 by ADD-S, and found (no listed pose within ADD-S 5 % though the best is
within 10 %), on every object; strict top-1 (rotation < 5°, translation < 5 % of the diameter)
on the asymmetric objects (on a symmetric one it fails by design).

Writes results/realistic_contacts/truth_stages.csv (the rows of objects and criteria not in
this run are kept) and truth_stages.md::

    .venv/bin/python experiments/truth_stages.py [--limit N]    # N strict failures per object and radius
        [--objects NAME ...] [--criteria adds found strict] [--out DIR]
"""

from __future__ import annotations

import argparse
import collections
import importlib.util
import json
import sys
import time
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from scipy.spatial import cKDTree

from contactpose.geometry import metrics
from contactpose.harness import sweep
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel, merged_mesh
from contactpose.search import find_pairs
from contactpose.search.tree import TripleTest, join_tuples
from contactpose.sim import ycb
from contactpose.uncertainty.bounds import rotation_bound_deg

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "results" / "realistic_contacts"
STAGES = ("first", "ranking", "fit", "grouping", "table", "tree", "cut")
#: Failure criteria, in the order a grasp is assigned to them (failures).
CRITERIA = ("adds", "found", "strict")
#: The true placement: a distinct pose within this ADD-S (fraction of the diameter) of the truth.
FOUND_FRAC = 0.05
#: Distinct poses, nearest the truth first, whose ADD-S placement_rank computes.
PLACEMENT_CHECKS = 200


def bench_module():
    spec = importlib.util.spec_from_file_location("experiment_realistic_contacts", HERE / "realistic_contacts.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def config():
    raw = json.loads((HERE / "configs" / "realistic_contacts.json").read_text())
    return {**raw["common"], **raw["full"]}


def failures(limit):
    """Failing default-method rows of grasps.csv, each under the first criterion it fails: every
    top-1 ADD-S failure ("adds"), every grasp whose listing holds no pose within ADD-S 5 %
    though its best is within 10 % ("found"), and up to ``limit`` strict failures per
    asymmetric object and radius ("strict")."""
    rows = [r for r in sweep.read_rows(OUT / "grasps.csv") if r["method"] == "fast"]
    picked, strict = [], collections.Counter()
    for r in rows:
        if r["top1_adds"] == "0":
            picked.append((r, "adds"))
        elif r["found"] == "0":
            picked.append((r, "found"))
        elif r["top1_strict"] == "0" and r["symmetry"] == "none":
            key = (r["object"], r["radius_frac"])
            if strict[key] < limit:
                strict[key] += 1
                picked.append((r, "strict"))
    return picked


def object_setup(name):
    """The benchmark's model (defaults), its vertex-merged mesh and region labels."""
    model = ObjectModel.from_mesh(ycb.load(name))
    mesh = merged_mesh(model.vertices, model.faces)
    labels = model.patches.labels if model.patch_table is not None else np.arange(model.num_facets)
    vertices = np.asarray(mesh.vertices)
    return SimpleNamespace(model=model, vertices=vertices, faces=np.asarray(mesh.faces), labels=labels,
                           tree=cKDTree(vertices))


def matching(labels, facets, keys):
    """(H,) bool: rows whose every contact's region is one of its true regions."""
    ok = np.ones(len(facets), dtype=bool)
    for k, key in enumerate(keys):
        ok &= (facets[:, k] >= 0) & np.isin(labels[np.maximum(facets[:, k], 0)], key)
    return ok


def placement_rank(s, poses, truth, limit):
    """Rank of the first pose within ADD-S ``limit`` of the truth (the true placement), or None.
    Poses are tried nearest first by the RMS displacement of the surface (an upper bound on
    ADD-S), up to PLACEMENT_CHECKS of them."""
    if not len(poses):
        return None
    moments = (s.model.surface_points.mean(axis=0), s.model.surface_points.T @ s.model.surface_points / len(s.model.surface_points))
    rms = np.linalg.norm(metrics.pose_embedding(poses, *moments) - metrics.pose_embedding(truth, *moments), axis=1)
    near = np.argsort(rms, kind="stable")[:PLACEMENT_CHECKS]
    adds = metrics.adds_many(poses[near], truth, s.model.surface_points, s.model.surface_tree)
    within = np.sort(near[adds < limit])
    return int(within[0]) if len(within) else None


def bound_rotation_deg(s, points, normals, noise):
    """RMS rotation error (degrees) of an efficient estimator for these contacts, the location
    of each unknown on a local quadric (uncertainty.bounds.rotation_bound_deg)."""
    return rotation_bound_deg(s.vertices, s.tree, s.model.diameter, points, normals, noise["position_noise"],
                              np.radians(noise["normal_noise_deg"]))


def stage_of(bench, s, contacts, pose, facets, points, normals, kinds, noise):
    """The stage that loses the true placement, and the figures behind it."""
    model, labels = s.model, s.labels
    keys = [np.unique(labels[f]) for f in (bench.incident_facets(s, f, p, k) for f, p, k in zip(facets, points, kinds))]
    listed = localize(model, contacts, **noise, keep="all", twins=True)  # the true tuple: every symmetric twin
    out = {"status": listed.status, "best_rot_deg": metrics.rotation_error_deg(listed.best.pose, pose),
           "best_chi2": float(listed.best.chi2), "bound_rot_deg": bound_rotation_deg(s, points, normals, noise)}
    rank = placement_rank(s, listed.hypotheses.arrays.poses, pose, FOUND_FRAC * model.diameter)
    out["placement_rank"] = rank
    every = localize(model, contacts, **noise, keep="all", distinct=False, twins=True)
    rows = np.flatnonzero(matching(labels, every.hypotheses.arrays.facets, keys))
    if len(rows):
        true_best = every.hypotheses[int(rows[0])]
        out.update(true_chi2=float(true_best.chi2), true_rot_deg=metrics.rotation_error_deg(true_best.pose, pose))
    if rank == 0:
        return "first", out
    if rank is not None:
        fits = any(rank in c.members for c in listed.classes)
        return ("ranking" if fits else "fit"), out
    if len(rows):
        return "grouping", out
    S = find_pairs(model, contacts, listed.tolerance)
    present = all(bool(S[(i, j)].contains(np.repeat(keys[i], len(keys[j])), np.tile(keys[j], len(keys[i]))).any())
                  for (i, j) in S)
    if not present:
        return "table", out
    triple = TripleTest(model.patches.normals, contacts.object_normals,
                        listed.tolerance.per_contact_bounds()[1], slack=model.patches.cone)
    if not matching(np.arange(model.patches.count), join_tuples(S, contacts.n, triple), keys).any():
        return "tree", out
    return "cut", out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--limit", type=int, default=10, help="strict failures per asymmetric object and radius")
    parser.add_argument("--objects", nargs="*", help="only these objects (default: every object in grasps.csv)")
    parser.add_argument("--out", default=str(OUT), help="where truth_stages.csv and .md go (default: %(default)s)")
    parser.add_argument("--criteria", nargs="*", choices=CRITERIA, default=list(CRITERIA),
                        help="only failures under these criteria (default: all)")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    bench, cfg = bench_module(), config()
    picked = [(r, c) for r, c in failures(args.limit)
              if (not args.objects or r["object"] in args.objects) and c in args.criteria]
    print(f"truth_stages: {len(picked)} failing grasps", flush=True)
    by_object = collections.defaultdict(list)
    for row, crit in picked:
        by_object[row["object"]].append((row, crit))
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "truth_stages.csv"
    redone = lambda r: r["object"] in by_object and r["criterion"] in args.criteria  # noqa: E731
    kept = [r for r in sweep.read_rows(path) if not redone(r)] if path.exists() else []
    out = []
    for name, items in by_object.items():
        start = time.perf_counter()
        s = object_setup(name)
        cells = {c.cell: c for c in bench.make_sweep(cfg, name, cfg["model_cache"]).cells()}
        noise = dict(position_noise=cfg["position_noise_frac"] * s.model.diameter,
                     normal_noise_deg=cfg["normal_noise_deg"])
        for row, crit in items:
            cell = cells[row["cell"]]
            rng = np.random.default_rng(cell.seed_sequence(cfg["base_seed"], ("object",)))
            pose, contacts, points, normals, facets, features, _ = bench.draw(s, rng, float(row["radius_frac"]), cfg)
            kinds = [str(f) for f in features]
            stage, figures = stage_of(bench, s, contacts, pose, facets, points, normals, kinds, noise)
            redrawn = abs(figures["best_rot_deg"] - float(row["rot_err_deg"])) < 1e-6
            out.append({"object": name, "radius_frac": row["radius_frac"], "seed": row["seed"], "criterion": crit,
                        "stage": stage, "recorded_stage": row["truth_stage"], "same_answer": redrawn,
                        "face_only": row["face_only"], **figures})
        print(f"{name}: {len(items)} grasps, {time.perf_counter() - start:.0f} s", flush=True)
        sweep.write_rows(path, kept + out)
    rows = sweep.read_rows(path)
    (out_dir / "truth_stages.md").write_text(table(rows))
    print(table(rows))
    return 0


def table(rows):
    lines = ["| r (% diam.) | criterion | failures | " + " | ".join(STAGES) + " | same answer as the run |",
             "|---:|---|---:|" + "---:|" * len(STAGES) + "---:|"]
    for frac in sorted({r["radius_frac"] for r in rows}, key=float):
        for crit in CRITERIA:
            sel = [r for r in rows if r["radius_frac"] == frac and r["criterion"] == crit]
            if sel:
                counts = collections.Counter(r["stage"] for r in sel)
                lines.append(f"| {100 * float(frac):g} | {crit} | {len(sel)} | "
                             + " | ".join(str(counts[s]) for s in STAGES)
                             + f" | {sum(r['same_answer'] in ('1', 'True') for r in sel)} |")
    lines += ["", "Strict failures whose true placement is first (stage `first`): the best pose's rotation error "
              "against the Cramér–Rao RMS rotation error of the grasp, and the true region tuple's own best row "
              "(distinct=False) against the listed best.", "",
              "| r (% diam.) | grasps | best rotation error, median (°) | bound, median (°) | error / bound, median | "
              "true tuple posed closer, with a higher χ² |", "|---:|---:|---:|---:|---:|---:|"]
    for frac in sorted({r["radius_frac"] for r in rows}, key=float):
        sel = [r for r in rows if r["radius_frac"] == frac and r["criterion"] == "strict" and r["stage"] == "first"]
        if not sel:
            continue
        err, bound = (np.array([float(r[c]) for r in sel]) for c in ("best_rot_deg", "bound_rot_deg"))
        closer = sum(r["true_rot_deg"] != "" and float(r["true_rot_deg"]) < float(r["best_rot_deg"])
                     and float(r["true_chi2"]) > float(r["best_chi2"]) for r in sel)
        lines.append(f"| {100 * float(frac):g} | {len(sel)} | {np.median(err):.1f} | {np.median(bound):.1f} | "
                     f"{np.median(err / bound):.1f} | {closer} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
