"""Simulated grasps: random poses, contacts on facets, sensor noise. Every function takes ``rng``.

Noise model (research/noise_model.md): a contact point gets isotropic Gaussian
noise of per-axis σ_x; a normal is rotated by a tangent-plane Gaussian of per-axis
σ_n. ``noise="bounded"`` redraws any contact whose error exceeds half the pair
tolerance, so every pair lies within the stated tolerance ("noise inside the
tolerance", the condition under which the search must be complete).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.contacts import Contacts, Tolerance
from contactpose.errors import ContactPoseError
from contactpose.geometry.sampling import bounded_gaussian, perturb_normals, uniform_in_triangles

WHERE = ("area", "centroid")
NOISE = ("gaussian", "bounded")


@dataclass
class Grasp:
    """A simulated grasp: measured contacts, the true pose and the true facets.

    contacts : Contacts (world); pose : (4, 4) true T_world_object; facets : (n,) int;
    points_object : (n, 3) exact contact points in the object frame.
    """

    contacts: Contacts
    pose: np.ndarray
    facets: np.ndarray
    points_object: np.ndarray


def pose_from(rotvec=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)):
    """(4, 4) T_world_object from a rotation vector (radians) and a translation."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = translation
    return T


def random_pose(rng, *, max_translation=0.0, rotation="uniform"):
    """A random pose: uniform rotation (or identity with rotation=None), translation in a cube."""
    T = np.eye(4)
    if rotation == "uniform":
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-max_translation, max_translation, 3)
    return T


def paper_pose():
    """The §5 protocol pose: roll 5.7° about x, shifted 10 mm in x, y and z."""
    return pose_from((np.radians(5.7), 0.0, 0.0), (0.01, 0.01, 0.01))


def choose_facets(model, n, rng, *, weight="area"):
    """n random valid facets: area-weighted with repeats (uniform on the surface), or
    uniform by facet and distinct (the §5 protocol, one finger per facet)."""
    valid = np.flatnonzero(model.planes.valid)
    if weight == "area":
        return rng.choice(valid, size=n, replace=True, p=model.planes.areas[valid] / model.planes.areas[valid].sum())
    return rng.choice(valid, size=n, replace=False)


def points_on_facets(model, facets, rng, *, where="area"):
    """Object-frame points on the given facets: uniform inside each triangle, or its centroid.

    facets : (n,) int  ->  (n, 3) float
    """
    tri = model.triangles[facets]
    if where == "centroid":
        return tri.mean(axis=1)
    return uniform_in_triangles(tri, rng)


def grasp(model, rng, *, n=4, pose=None, facets=None, where="area", position_noise=0.0,
          normal_noise_deg=0.0, noise="gaussian", max_translation=None):
    """Simulate one grasp of n fingers on the model.

    pose : (4, 4) true pose (default: uniform random rotation, translation within
    ±max_translation, default 0.5 diameter); facets : (n,) given facets (default: random,
    area-weighted for where="area", uniform for where="centroid"); noise : "gaussian" |
    "bounded" (each pair within the tolerance of Tolerance.from_noise(σ_x, σ_n)).
    """
    if where not in WHERE or noise not in NOISE:
        raise ContactPoseError(f"where must be in {WHERE} and noise in {NOISE}, got {where!r}, {noise!r}")
    if pose is None:
        span = 0.5 * model.diameter if max_translation is None else max_translation
        pose = random_pose(rng, max_translation=span)
    if facets is None:
        facets = choose_facets(model, n, rng, weight="area" if where == "area" else "uniform")
    facets = np.asarray(facets)
    p_obj = points_on_facets(model, facets, rng, where=where)
    pos_bound, ang_bound = np.inf, np.inf
    if noise == "bounded" and position_noise > 0 and normal_noise_deg > 0:
        pos_bound, ang_bound = Tolerance.from_noise(position_noise, normal_noise_deg).per_contact_bounds()
    R, t = pose[:3, :3], pose[:3, 3]
    points = p_obj @ R.T + t + bounded_gaussian(rng, len(facets), 3, position_noise, pos_bound)
    normals = perturb_normals(model.planes.normals[facets] @ R.T, np.radians(normal_noise_deg), rng, ang_bound)
    return Grasp(Contacts(points, object_normals=normals), pose, facets, p_obj)


def touch_sequence(model, rng, steps, *, first=4, hand_rot=0.1, hand_trans=0.02, sigma_rot_deg=1.0,
                   sigma_trans=0.001, **noise):
    """A SEQ.json document (``contactpose track --sequence``): a first grasp of ``first``
    contacts, then ``steps`` touches of 1 and 2 contacts in turn, each after a hand motion
    drawn with per-axis σ ``hand_rot`` (radians) and ``hand_trans`` (length), stated with
    ``sigma_rot_deg`` and ``sigma_trans``; every step with its true pose. noise : as for
    :func:`grasp`. -> (document dict, the last true pose (4, 4))"""
    def step(g):
        return {"contacts": [{"point": p.tolist(), "finger_normal": n.tolist()}
                             for p, n in zip(g.contacts.points, g.contacts.finger_normals)],
                "true_pose": g.pose.tolist()}

    g = grasp(model, rng, n=first, **noise)
    pose, out = g.pose, [step(g)]
    for k in range(steps):
        delta = pose_from(rotvec=hand_rot * rng.normal(size=3), translation=hand_trans * rng.normal(size=3))
        pose = delta @ pose
        out.append(dict(step(grasp(model, rng, n=1 + k % 2, pose=pose, **noise)),
                        hand_motion={"delta": delta.tolist(), "sigma_rot_deg": sigma_rot_deg, "sigma_trans": sigma_trans}))
    return {"steps": out}, pose


def scan(mesh, rng, **options):
    """Simulated range scan of a mesh (see :func:`contactpose.sim.range_scanner.scan`); needs Open3D."""
    from contactpose.sim.range_scanner import scan as _scan

    return _scan(mesh, rng, **options)
