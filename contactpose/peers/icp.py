"""Point-to-plane ICP from a pose prior (Open3D), a peer of the contact search.

:func:`icp` aligns *finger pads* (each contact point plus a ring of points on a disc of
``patch_radius`` in the measured tangent plane) to dense surface samples with Open3D's
point-to-plane ICP. Four bare points leave point-to-plane ICP with 4 equations for 6
unknowns; the pads carry the measured normals into the fit. :func:`icp_multistart` runs
it from random starts when there is no prior and keeps the lowest contact cost
(peers.surface.contact_cost). research/baselines.md says how it was tuned.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.errors import ContactPoseError
from contactpose.peers.surface import BaselineResult, contact_cost


def finger_pads(contacts, radius, points=6):
    """Each contact point and a ring of ``points`` points at ``radius`` in its measured
    tangent plane. -> (n * (points + 1), 3) world points (just the contacts for radius 0)."""
    if radius <= 0:
        return np.array(contacts.points, dtype=np.float64)
    n = contacts.object_normals
    helper = np.where(np.abs(n[:, [0]]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    phi = 2 * np.pi * np.arange(points) / points
    ring = radius * (np.cos(phi)[None, :, None] * e1[:, None] + np.sin(phi)[None, :, None] * e2[:, None])
    pads = np.concatenate([contacts.points[:, None], contacts.points[:, None] + ring], axis=1)
    return pads.reshape(-1, 3)


def icp_target(surface, count=None):
    """Open3D point cloud of the surface samples with their facet normals (object frame)."""
    import open3d as o3d

    pts, nrm = surface.points, surface.normals
    if count is not None and count < len(pts):
        keep = np.linspace(0, len(pts) - 1, count).round().astype(int)  # spread over all facets
        pts, nrm = pts[keep], nrm[keep]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(pts)))
    cloud.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(nrm))
    return cloud


def icp(model, surface, target, contacts, init, *, position_noise, normal_noise_deg, patch_radius=0.004,
        patch_points=6, max_correspondence=0.01, iterations=30):
    """Point-to-plane ICP of the finger pads onto the surface, from init (4, 4) T_world_object.

    target : :func:`icp_target` of ``surface``. Open3D finds T_object_world (pads -> surface);
    the returned pose is its inverse, scored with :func:`contact_cost`.
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(finger_pads(contacts, patch_radius, patch_points)))
    out = reg.registration_icp(source, target, max_correspondence, np.linalg.inv(init),
                               reg.TransformationEstimationPointToPlane(),
                               reg.ICPConvergenceCriteria(max_iteration=iterations))
    pose = np.linalg.inv(np.asarray(out.transformation))
    pose[3] = (0.0, 0.0, 0.0, 1.0)
    cost = float(contact_cost(model, surface, contacts, pose[None], position_noise, normal_noise_deg)[0])
    return BaselineResult(pose, cost, 1, 1)


def centered_start(surface, contacts, rotation):
    """T_world_object with the given rotation (3, 3) and the surface centre at the contacts' centroid."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = contacts.points.mean(axis=0) - rotation @ surface.center
    return T


def icp_multistart(model, surface, target, contacts, rng, *, starts=32, **options):
    """ICP from ``starts`` uniformly random rotations, the surface centre at the contacts'
    centroid (no prior); the start with the lowest contact cost wins."""
    if starts < 1:
        raise ContactPoseError(f"starts must be >= 1, got {starts}")
    rotations = Rotation.random(starts, random_state=rng).as_matrix()
    best = None
    for R in rotations:
        r = icp(model, surface, target, contacts, centered_start(surface, contacts, R), **options)
        if best is None or r.cost < best.cost:
            best = r
    return BaselineResult(best.pose, best.cost, starts, starts)
