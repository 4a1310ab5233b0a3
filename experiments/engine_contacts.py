"""The default method on a physics engine's contacts: PyBullet's sphere-against-mesh contact
points and normals (its collision margin and narrow phase, not ours) on the built-in coarse
objects, beside our own fingertip simulator's on the same aims.

Each grasp is drawn as in experiments/regions_check.py (a uniformly random pose, 4 fingertips of
radius r aimed within 30° of inward facet normals); our simulator (``fingertip.approach``)
gives each finger's first touch along its approach. PyBullet (a static concave triangle mesh, a
sphere of radius r and mass 1, no gravity) then moves the ball along the same approach, from 2 %
of the diameter before our touch at 0.05 % of the diameter per time step (240 Hz), until its
contact query reports a contact at zero or negative distance; that contact's point on the mesh
and its normal (contactNormalOnB) are the engine's contact (its narrow phase and discrete steps,
not our sweep). Both sets get the same Gaussian noise (0.25 % D, 1°) and go through localize with
``finger_radius`` = r. Writes results/engine_contacts/grasps.csv and summary.md. Needs
pybullet (``pip install pybullet``; not a dependency of the package)::

    .venv/bin/python experiments/engine_contacts.py                 # 4 objects x 2 radii x 30 grasps
    .venv/bin/python experiments/engine_contacts.py banana512 --grasps 5
"""

from __future__ import annotations

import sys
import time
import warnings
from importlib.metadata import version
from pathlib import Path

import numpy as np
from coarse_edges import RADII, arguments, cells, outcomes, write
from regions_check import CONFIG

from contactpose import Contacts, ObjectModel, localize
from contactpose.geometry.metrics import SUCCESS_ROT_DEG, SUCCESS_TRANS_FRAC
from contactpose.geometry.sampling import perturb_normals
from contactpose.model.object_model import merged_mesh
from contactpose.model.symmetry import symmetry
from contactpose.sim import fingertip, objects
from contactpose.sim import grasps as simulate

ROOT = Path(__file__).resolve().parent.parent
FIELDS = ("object", "radius_frac", "grasp", "source", "face_only", "engine_gap", "engine_angle_deg", "status",
          "hypotheses", "best_right", "any_right", "rot_err_deg", "seconds")
#: The ball starts this many diameters before our touch and moves this many per time step.
RUN_UP, STEP = 0.02, 0.0005
#: The engine's time step: its default, 240 Hz.
STEPS_PER_SECOND = 240.0


class Engine:
    """A PyBullet world holding the object's mesh (static, concave) and one sphere."""

    def __init__(self, pybullet, vertices, faces, radius):
        self.p = pybullet
        self.client = pybullet.connect(pybullet.DIRECT)
        pybullet.setGravity(0, 0, 0, physicsClientId=self.client)
        shape = pybullet.createCollisionShape(pybullet.GEOM_MESH, vertices=vertices.tolist(),
                                              indices=faces.ravel().tolist(),
                                              flags=pybullet.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=self.client)
        self.body = pybullet.createMultiBody(0, shape, physicsClientId=self.client)
        ball = pybullet.createCollisionShape(pybullet.GEOM_SPHERE, radius=radius, physicsClientId=self.client)
        self.ball = pybullet.createMultiBody(1.0, ball, physicsClientId=self.client)
        self.radius = radius

    def touch(self, start, direction, travel, diameter):
        """The engine's first contact of the ball moving along ``direction``: started RUN_UP
        diameters before our touch at ``travel``, at STEP diameters per time step, without
        gravity, stepped until the engine reports a contact at zero or negative distance (its
        narrow phase, contact threshold and discrete steps, not our sweep). -> (point on the
        mesh, unit normal from the mesh toward the ball) or None."""
        p, c = self.p, self.client
        centre = start + (travel - RUN_UP * diameter) * direction
        p.resetBasePositionAndOrientation(self.ball, centre.tolist(), [0, 0, 0, 1], physicsClientId=c)
        p.resetBaseVelocity(self.ball, (direction * STEP * diameter * STEPS_PER_SECOND).tolist(), [0, 0, 0],
                            physicsClientId=c)
        for _ in range(int(3 * RUN_UP / STEP)):
            p.stepSimulation(physicsClientId=c)
            found = [row for row in p.getContactPoints(self.ball, self.body, physicsClientId=c) if row[8] <= 0.0]
            if found:
                row = min(found, key=lambda r: r[8])
                return np.array(row[6]), np.array(row[7]) / np.linalg.norm(row[7])
        return None


def run_object(pybullet, name, grasps, radii):
    model = ObjectModel.from_mesh(objects.load(name))
    merged = merged_mesh(model.vertices, model.faces)
    vertices, faces = np.asarray(merged.vertices), np.asarray(merged.faces)
    group, D = symmetry(model), model.diameter
    rows = []
    for k, frac in enumerate(radii):
        radius = frac * D
        engine = Engine(pybullet, vertices, faces, radius)
        rng = np.random.default_rng(CONFIG["base_seed"] + 100 + k)
        for g in range(grasps):
            pose = simulate.random_pose(rng, max_translation=CONFIG["translation_frac"] * D)
            while True:
                got = fingertip.approach(vertices, faces, rng, CONFIG["fingers"], radius, cone_deg=CONFIG["cone_deg"],
                                         mode=CONFIG["mode"])
                if got.hit.all():
                    touches = [engine.touch(s, d, t, D) for s, d, t in zip(got.starts, got.directions, got.travel)]
                    if all(touch is not None for touch in touches):
                        break
            engine_points = np.array([t[0] for t in touches])
            engine_normals = np.array([t[1] for t in touches])
            gap = np.linalg.norm(engine_points - got.points, axis=1).max() / D
            angle = np.degrees(np.max(np.arccos(np.clip(np.einsum("ij,ij->i", engine_normals, got.normals), -1, 1))))
            noise_x = rng.normal(0.0, CONFIG["position_noise_frac"] * D, got.points.shape)
            noise_seed = int(rng.integers(1 << 31))  # the same normal noise for both sources
            face_only = all(str(f) == fingertip.FACE for f in got.features)
            for source, points, normals in (("simulator", got.points, got.normals),
                                            ("engine", engine_points, engine_normals)):
                R, t = pose[:3, :3], pose[:3, 3]
                world = points @ R.T + t + noise_x
                finger = perturb_normals(-(normals @ R.T), np.radians(CONFIG["normal_noise_deg"]),
                                         np.random.default_rng(noise_seed))
                result = localize(model, Contacts(world, finger_normals=finger),
                                  position_noise=CONFIG["position_noise_frac"] * D,
                                  normal_noise_deg=CONFIG["normal_noise_deg"], finger_radius=radius, diagnose=False)
                poses = result.hypotheses.arrays.poses
                rot, trans = group.errors(poses, pose) if len(poses) else (np.array([np.inf]), np.array([np.inf]))
                right = (rot < SUCCESS_ROT_DEG) & (trans < SUCCESS_TRANS_FRAC * D)
                rows.append(dict(object=name, radius_frac=frac, grasp=g, source=source, face_only=face_only,
                                 engine_gap=gap, engine_angle_deg=angle, status=result.status,
                                 hypotheses=len(poses), best_right=bool(right[0]), any_right=bool(right.any()),
                                 rot_err_deg=float(rot[0]), seconds=result.timing["total"]))
    return rows


def summary(rows):
    lines = ["| object | r | contacts | grasps | engine vs simulator: point gap max (% D), normal angle max, "
             "medians | no hypothesis | any listed right | best right | online median / p95 |",
             "|---|---:|---|---:|---|---:|---:|---:|---:|"]
    for name, frac, cell in cells(rows):
        for source in ("simulator", "engine"):
            sel = [r for r in cell if r["source"] == source]
            t = 1e3 * np.array([r["seconds"] for r in sel])
            lines.append(
                f"| {name} | {100 * frac:g} % | {source} | {len(sel)} | "
                f"{100 * np.median([r['engine_gap'] for r in sel]):.2f} %, "
                f"{np.median([r['engine_angle_deg'] for r in sel]):.1f}° | "
                f"{outcomes(sel)} | {np.median(t):.0f} / {np.percentile(t, 95):.0f} ms |")
    return lines


def main(argv=None):
    args = arguments(argv, __doc__, 30, "engine_contacts")
    try:
        import pybullet
    except ImportError:
        print("engine_contacts needs pybullet: .venv/bin/pip install pybullet", file=sys.stderr)
        return 2
    warnings.simplefilter("ignore")
    args.out.mkdir(parents=True, exist_ok=True)
    start, rows = time.perf_counter(), []
    for name in args.objects:
        rows += run_object(pybullet, name, args.grasps, RADII)
        print(f"{name}: {len(rows)} rows, {time.perf_counter() - start:.0f} s", flush=True)
    write(args.out, FIELDS, rows,
          f"# The default method on a physics engine's contacts (PyBullet {version('pybullet')})\n\n"
          f"{len(rows) // 2} grasps, each with our simulator's contacts and the engine's on the same aims, the same "
          f"noise", f"engine_contacts.py --grasps {args.grasps}", time.perf_counter() - start, summary(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
