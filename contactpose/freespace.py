"""Free-space check: a finger sits outside the object (issue 9, item 5).

A hypothesis puts contact i on facet k under the pose T = (R, t). In the object frame
the contact is p_i = Rᵀ(x̃_i - t) and the finger comes from the direction
u_i = -Rᵀñ_i, away from the object. If a ray from the surface along u_i enters the
object again within the finger radius r, the contact lies in a concavity too narrow
for the finger, and the hypothesis is rejected.

* The ray starts on facet k's plane (the foot of p_i), ``START_REL`` · diameter off it.
* Only *entering* hits count (the ray meets a facet from its outer side, u·n < 0).
  A ray that starts just inside the surface, through noise, first leaves the object:
  that exit is not a violation, so the test never depends on the sign of the noise.
* ``fingertip="ball"`` also checks the fingertip sphere of radius r resting on the
  contact: its centre p_i + r·u_i must be at least r - ``slack`` from the surface.
  This catches a finger at the bottom of a narrow slot, where the ray runs out of the
  slot freely. A true contact of a spherical fingertip of radius >= r passes both
  tests when the noise (``slack``) is accounted for: the ray segment of length r lies
  inside the fingertip's ball as long as the normal error is below 60°.

Ray casting uses Open3D's ``RaycastingScene`` (about 10⁶ rays/s; trimesh's
``ray_triangle`` took 3.5 s for 4,000 rays on the 980-facet rock, Open3D under 1 ms),
with trimesh as the fallback when Open3D is missing. One caster is kept per model
(:func:`raycaster`).
"""

from __future__ import annotations

import logging
import weakref

import numpy as np

from contactpose.errors import ContactPoseError

log = logging.getLogger(__name__)

#: Rays start this fraction of the object diameter off the facet plane.
START_REL = 1e-6
FINGERTIPS = ("ray", "ball")
#: Default clearance allowance of the "ball" test, as a fraction of the finger radius:
#: a true fingertip's centre sits r·cos θ from its facet for a normal error θ, and
#: 0.1 r covers θ up to 25° plus position error up to a tenth of the radius.
BALL_SLACK_REL = 0.1

_CASTERS: dict = {}


class Raycaster:
    """Rays against one model's mesh, in the object frame.

    vertices : (V, 3) float; faces : (F, 3) int; facet ids returned are face indices.
    """

    def __init__(self, vertices, faces):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        tri = self.vertices[self.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normal, axis=1, keepdims=True)
        self.normals = normal / np.where(length > 0, length, 1.0)
        try:
            import open3d as o3d
        except ImportError:  # pragma: no cover - open3d is a dependency
            import trimesh

            log.info("open3d missing: free-space rays use trimesh (slow)")
            self._o3d = None
            self._mesh = trimesh.Trimesh(self.vertices, self.faces, process=False)
            self._intersector = trimesh.ray.ray_triangle.RayMeshIntersector(self._mesh)
            return
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                  o3d.core.Tensor(self.faces.astype(np.uint32)))

    def _rays(self, origins, directions):
        return self._o3d.core.Tensor(np.hstack([origins, directions]).astype(np.float32))

    def first_hits(self, origins, directions):
        """First hit of each ray. origins, directions (unit) : (N, 3) ->
        (t (N,) float, inf on a miss; facet (N,) int, -1 on a miss)."""
        origins, directions = _rays_in(origins, directions)
        if self._o3d is None:  # pragma: no cover
            return self._first_hits_trimesh(origins, directions)
        ans = self._scene.cast_rays(self._rays(origins, directions))
        t = ans["t_hit"].numpy().astype(np.float64)
        facet = ans["primitive_ids"].numpy().astype(np.int64)
        miss = ~np.isfinite(t)
        facet[miss] = -1
        return t, facet

    def all_hits(self, origins, directions):
        """Every hit of every ray: (ray (K,) int, t (K,) float, facet (K,) int)."""
        origins, directions = _rays_in(origins, directions)
        if self._o3d is None:  # pragma: no cover
            facet, ray, loc = self._intersector.intersects_id(origins, directions, multiple_hits=True,
                                                              return_locations=True)
            t = np.einsum("ki,ki->k", loc - origins[ray], directions[ray])
            return ray.astype(np.int64), t, facet.astype(np.int64)
        ans = self._scene.list_intersections(self._rays(origins, directions))
        return (ans["ray_ids"].numpy().astype(np.int64), ans["t_hit"].numpy().astype(np.float64),
                ans["primitive_ids"].numpy().astype(np.int64))

    def entering_within(self, origins, directions, length):
        """(N,) bool: the ray enters the mesh (hits a facet from its outer side) at
        0 < t <= length. length : float or (N,) float."""
        origins, directions = _rays_in(origins, directions)
        length = np.broadcast_to(np.asarray(length, dtype=np.float64), (len(origins),))
        ray, t, facet = self.all_hits(origins, directions)
        # entering: the ray runs against the facet's outward normal
        entering = np.einsum("ki,ki->k", directions[ray], self.normals[facet]) < 0
        hit = entering & (t > 0) & (t <= length[ray])
        out = np.zeros(len(origins), dtype=bool)
        out[ray[hit]] = True
        return out

    def distance(self, points):
        """(N,) unsigned distance of each point (N, 3) to the mesh."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self._o3d is None:  # pragma: no cover
            import trimesh

            return trimesh.proximity.closest_point(self._mesh, points)[1]
        query = self._o3d.core.Tensor(points.astype(np.float32))
        return self._scene.compute_distance(query).numpy().astype(np.float64)

    def _first_hits_trimesh(self, origins, directions):  # pragma: no cover
        facet, ray = self._intersector.intersects_id(origins, directions, multiple_hits=False)
        t = np.full(len(origins), np.inf)
        out = -np.ones(len(origins), dtype=np.int64)
        loc = self._intersector.intersects_location(origins[ray], directions[ray], multiple_hits=False)[0]
        t[ray] = np.einsum("ki,ki->k", loc - origins[ray], directions[ray])
        out[ray] = facet
        return t, out


def _rays_in(origins, directions):
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if origins.shape != directions.shape:
        raise ValueError(f"origins and directions must have the same shape (N, 3), got {origins.shape} "
                         f"and {directions.shape}")
    return origins, directions


def raycaster(model):
    """The :class:`Raycaster` of a model, built once and kept while the model lives."""
    key = id(model)
    entry = _CASTERS.get(key)
    if entry is not None and entry[0]() is model and entry[1] == model.mesh_hash:
        return entry[2]
    caster = Raycaster(model.vertices, model.faces)
    _CASTERS[key] = (weakref.ref(model, lambda _, key=key: _CASTERS.pop(key, None)), model.mesh_hash, caster)
    return caster


def free_space_violations(model, facets, poses, contacts, finger_radius, *, per_contact=False,
                          fingertip="ray", slack=None):
    """Which hypotheses put a contact where no finger fits.

    model : ObjectModel; facets : (H, n) int, the facet of each contact (-1: unassigned
    finger, never a violation); poses : (H, 4, 4) T_world_object; contacts : Contacts
    (world frame); finger_radius : r > 0, length units; fingertip : "ray" (the outward
    normal ray of length r re-enters the object) or "ball" (also: the fingertip sphere of
    radius r on the contact comes closer than r - slack to the surface); slack : length,
    the noise allowance of the "ball" test (default BALL_SLACK_REL · r).
    Returns (H,) bool, True where some contact is violated, or (H, n) bool with
    ``per_contact=True``.
    """
    facets = np.asarray(facets)
    poses = np.asarray(poses, dtype=np.float64)
    if facets.ndim != 2 or facets.shape[1] != contacts.n:
        raise ContactPoseError(f"facets must have shape (H, {contacts.n}), got {facets.shape}")
    if poses.shape != (len(facets), 4, 4):
        raise ContactPoseError(f"poses must have shape ({len(facets)}, 4, 4), got {poses.shape}")
    if not (np.isfinite(finger_radius) and finger_radius > 0):
        raise ContactPoseError(f"finger_radius must be a positive length, got {finger_radius!r}")
    if fingertip not in FINGERTIPS:
        raise ContactPoseError(f"fingertip must be one of {FINGERTIPS}, got {fingertip!r}")
    h, n = facets.shape
    if h == 0:
        return np.zeros((0, n) if per_contact else 0, dtype=bool)
    assigned = facets >= 0
    k = np.where(assigned, facets, 0)
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    # contacts and outward finger directions in each hypothesis' object frame: (H, n, 3)
    p = np.einsum("hji,hnj->hni", R, contacts.points[None] - t[:, None])
    u = -np.einsum("hji,nj->hni", R, contacts.finger_normals)
    # foot of each contact on its facet's plane, then a hair outward
    n_k = model.planes.normals[k]
    foot = p - (np.einsum("hni,hni->hn", n_k, p) + model.planes.offsets[k])[..., None] * n_k
    origins = foot + START_REL * model.diameter * u
    caster = raycaster(model)
    bad = caster.entering_within(origins.reshape(-1, 3), u.reshape(-1, 3), finger_radius).reshape(h, n)
    if fingertip == "ball":
        slack = BALL_SLACK_REL * finger_radius if slack is None else float(slack)
        # fingertip sphere resting on the contact: centre r along u, clearance r - slack
        centres = foot + finger_radius * u
        bad |= caster.distance(centres.reshape(-1, 3)).reshape(h, n) < finger_radius - slack
    bad &= assigned
    return bad if per_contact else bad.any(axis=1)
