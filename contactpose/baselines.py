"""Baselines a user might pick instead of the contact search: point-to-plane ICP from a pose
prior (Open3D), and a particle-filter global localization in the style of the Scaling
Series (Petrovskaya & Khatib, "Global localization of objects via touch", IEEE T-RO 2011).

Both see exactly what :func:`contactpose.localize` sees, the n measured contacts (point and
normal, world frame) and the mesh, and return one pose T_world_object. Both score a pose
with the same contact likelihood (:func:`contact_cost`): for each contact, its distance to
the mesh surface over σ_x and the angle between its measured normal and the normal of the
nearest facet over σ_n, squared and summed (a whitened χ², 3 dof per contact).

* :func:`icp` aligns *finger pads* (each contact point plus a ring of points on a disc of
  ``patch_radius`` in the measured tangent plane) to dense surface samples with Open3D's
  point-to-plane ICP. Four bare points leave point-to-plane ICP with 4 equations for 6
  unknowns; the pads carry the measured normals into the fit. :func:`icp_multistart` runs
  it from random starts when there is no prior and keeps the lowest contact cost.
* :func:`scaling_series`: particles in SE(3), refined over a sequence of shrinking
  neighbourhoods δ_k = δ_0 · zoom^k; at each scale, ``per_ball`` samples are drawn uniformly
  in the δ-ball of every surviving particle (Even Density Cover), weighted by the contact
  likelihood annealed to the scale (σ² inflated by τ = (δ_k/δ*)²), and pruned by importance
  resampling. The scales stop at δ*, the resolution the measurement noise supports.
* :class:`MemoryParticleFilter` tracks an object held in a moving hand, in the spirit of the
  memory unscented particle filter (Vezzani et al., 2017): particles move with the hand and a
  sampled slip, and each touch weights them by the contact likelihood of the last ``memory``
  contacts.

research/baselines.md says how each was tuned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.errors import ContactPoseError
from contactpose.geometry.kernels import point_triangle_distance, triangle_pair_bounds
from contactpose.geometry.raycast import raycaster
from contactpose.geometry.sampling import barycentric_uniform, points_in_triangles

#: Surface samples for the nearest-facet look-up of the contact likelihood.
SURFACE_SAMPLES = 20_000
#: Fewest samples on any facet (its centroid and random points).
MIN_PER_FACET = 4
#: Facets within this distance (m) of a contact's closest facet are also tested for it, so a
#: contact pushed by noise past an edge or onto the far side of a thin part still finds the
#: facet that explains its normal (6 sigma at 0.5 mm position noise).
NEIGHBOUR_RADIUS = 0.003
#: Dimension of the pose space (for the Scaling Series zoom factor 2^(-1/dim)).
POSE_DIM = 6


@dataclass(frozen=True)
class Surface:
    """Area-uniform samples of a model's surface, object frame.

    points, normals : (N, 3) float; facets : (N,) int (each sample's facet);
    center : (3,) mean of the samples; radius : largest distance of a sample from center;
    neighbours : (m, D) int, for each facet the facets within ``neighbour_radius`` of it
    (exact triangle distance, itself included), padded by repeating the facet;
    scene : the model's Raycaster, for exact closest points.
    """

    points: np.ndarray
    normals: np.ndarray
    facets: np.ndarray
    center: np.ndarray
    radius: float
    neighbours: np.ndarray
    scene: object = None

    def closest_facets(self, points):
        """Facet of the exact closest surface point (the model's raycaster). points : (N, 3) -> (N,) int"""
        return self.scene.closest_points(points)[1]


def sample_surface(model, count=SURFACE_SAMPLES, seed=0, min_per_facet=MIN_PER_FACET,
                   neighbour_radius=NEIGHBOUR_RADIUS):
    """Surface samples of a model's valid facets (deterministic for a seed): about ``count``
    area-uniform points, and at least ``min_per_facet`` on every facet (the centroid and
    random points), so that small facets are found by the nearest-sample look-up.
    neighbour_radius None: each facet's only candidate is itself (the neighbour search tests
    every facet pair, too many on a fine mesh)."""
    rng = np.random.default_rng(seed)
    valid = np.flatnonzero(model.planes.valid)
    areas = model.planes.areas[valid]
    per_facet = np.maximum(rng.multinomial(count, areas / areas.sum()), min_per_facet)
    facets = np.repeat(valid, per_facet)
    u, v = barycentric_uniform(rng, len(facets))
    first = np.concatenate([[0], np.cumsum(per_facet)[:-1]])
    u[first], v[first] = 1 / 3, 1 / 3                    # the centroid of every facet
    points = points_in_triangles(model.triangles[facets], u, v)
    center = points.mean(axis=0)
    radius = float(np.linalg.norm(points - center, axis=1).max())
    neighbours = (np.arange(model.num_facets)[:, None] if neighbour_radius is None
                  else facet_neighbours(model, neighbour_radius))
    return Surface(points, model.planes.normals[facets], facets, center, radius, neighbours, raycaster(model))


def facet_neighbours(model, radius):
    """(m, D) int: for each facet, the valid facets within ``radius`` of it (exact
    triangle-triangle distance), itself first, rows padded by repeating the facet."""
    m = model.num_facets
    k, l = np.triu_indices(m, 1)
    dmin, _, _ = triangle_pair_bounds(model.triangles, k, l)
    valid = model.planes.valid
    near = (dmin <= radius) & valid[k] & valid[l]
    k, l = np.concatenate([k[near], l[near]]), np.concatenate([l[near], k[near]])
    order = np.lexsort((l, k))
    k, l = k[order], l[order]
    counts = np.bincount(k, minlength=m)
    out = np.repeat(np.arange(m)[:, None], counts.max() + 1, axis=1)
    # position of each neighbour within its facet's row, after the facet itself
    within = np.arange(len(k)) - np.repeat(np.cumsum(counts) - counts, counts)
    out[k, within + 1] = l
    return out


@dataclass
class BaselineResult:
    """One baseline estimate: pose (4, 4) T_world_object, its contact cost (whitened χ²),
    the number of poses scored and of iterations (ICP runs or Scaling Series scales)."""

    pose: np.ndarray
    cost: float
    evaluations: int
    iterations: int


# --------------------------------------------------------------------------- likelihood

def contact_cost(model, surface, contacts, poses, position_noise, normal_noise_deg):
    """Whitened χ² of the contacts under each pose.

    poses : (P, 4, 4) T_world_object  ->  (P,) float: Σ_i d_i²/σ_x² + θ_i²/σ_n², with d_i the
    distance of contact i (moved into the object frame) to a facet and θ_i the angle between
    its measured outward normal and that facet's normal, for the facet with the lowest
    d²/σ_x² + θ²/σ_n² among the facet of the exact closest surface point and the facets
    within NEIGHBOUR_RADIUS of it.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    # object-frame contact points and outward normals: Rᵀ(x - t), Rᵀ n  -> (P, n, 3)
    p = np.einsum("pji,pnj->pni", R, contacts.points[None] - t[:, None])
    nrm = np.einsum("pji,nj->pni", R, contacts.object_normals)
    flat, nflat = p.reshape(-1, 3), nrm.reshape(-1, 3)
    # candidates: the facet of the exact closest surface point and its neighbours  -> (Pn, D)
    facets = surface.neighbours[surface.closest_facets(flat)]
    D = facets.shape[1]
    d = point_triangle_distance(np.repeat(flat, D, axis=0), model.triangles[facets.ravel()]).reshape(-1, D)
    cos = np.einsum("ij,ikj->ik", nflat, model.planes.normals[facets])
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    # each contact takes the candidate facet that explains it best (near an edge the
    # nearest facet by distance may be the neighbour with the wrong normal)
    chi2 = ((d / position_noise) ** 2 + (angle / np.radians(normal_noise_deg)) ** 2).min(axis=1)
    return chi2.reshape(len(poses), -1).sum(axis=1)


# --------------------------------------------------------------------------- ICP

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


# --------------------------------------------------------------------------- Scaling Series

def _ball(rng, count, dim=POSE_DIM):
    """count points uniform in the unit ball of R^dim -> (count, dim)."""
    g = rng.normal(size=(count, dim))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    return g * rng.random((count, 1)) ** (1.0 / dim)


def _perturb(R, c, u, delta, radius):
    """Move particles (R (P, 3, 3), object-centre position c (P, 3)) by u (P, 6) in the unit
    ball scaled to delta: rotation vector δ·u[:3]/radius about the centre (world frame), shift δ·u[3:]."""
    dR = Rotation.from_rotvec(delta * u[:, :3] / radius).as_matrix()
    return np.einsum("pij,pjk->pik", dR, R), c + delta * u[:, 3:]


def _poses(R, c, center):
    """T_world_object of particles given their rotation and the world position of the surface centre."""
    T = np.zeros((len(R), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = c - R @ center
    T[:, 3, 3] = 1.0
    return T


def scaling_series(model, surface, contacts, rng, *, position_noise, normal_noise_deg, prior=None,
                   initial=2000, per_ball=8, max_particles=2000, delta_final=None, zoom=2.0 ** (-1.0 / POSE_DIM)):
    """Scaling-Series pose estimate from contacts, with a prior (PosePrior) or globally.

    Pose metric: translation of the surface centre plus rotation angle times the surface
    radius ρ, so a δ-ball moves no surface point by more than about 2δ. Start: ``initial``
    particles from the prior (Gaussian) with δ_0 = 3·max(σ_t, ρ·σ_rot), or uniform rotations
    with the centre uniform in the ρ-ball around the contacts' centroid (every contact lies
    within ρ of the centre) with δ_0 = π·ρ. Each scale: δ ← zoom·δ, τ = max(1, (δ/δ*)²);
    ``per_ball`` uniform samples in the previous δ-ball of each survivor (survivors capped at
    max_particles / per_ball); weights exp(-χ²/(2τ)); importance resampling, duplicates
    removed. δ* (default: max(σ_x, ρ·σ_n)·3) is where the scales stop. The estimate is the
    lowest-χ² particle of the last scale.
    """
    rho = surface.radius
    sigma_n = np.radians(normal_noise_deg)
    if delta_final is None:
        delta_final = 3.0 * max(position_noise, rho * sigma_n)
    # initial particles: rotation R (P, 3, 3) and world position of the surface centre c (P, 3)
    if prior is not None:
        cov = prior.covariance_matrix()
        xi = rng.multivariate_normal(np.zeros(6), cov, size=initial)
        R = Rotation.from_rotvec(xi[:, :3]).as_matrix() @ prior.pose[:3, :3]
        c = (prior.pose[:3, :3] @ surface.center + prior.pose[:3, 3]) + xi[:, 3:]
        delta = 3.0 * max(np.sqrt(np.max(np.diag(cov)[3:])), rho * np.sqrt(np.max(np.diag(cov)[:3])))
    else:
        R = Rotation.random(initial, random_state=rng).as_matrix()
        c = contacts.points.mean(axis=0) + rho * _ball(rng, initial, 3)
        delta = np.pi * rho
    cost = contact_cost(model, surface, contacts, _poses(R, c, surface.center), position_noise, normal_noise_deg)
    evaluations, scales = initial, 0
    R, c, cost = _prune(rng, R, c, cost, max(delta / delta_final, 1.0) ** 2, max_particles // per_ball)
    while delta > delta_final:
        new_delta = max(zoom * delta, delta_final)
        tau = (new_delta / delta_final) ** 2
        # even density cover: per_ball samples in the δ-ball of each survivor
        Rs = np.repeat(R, per_ball, axis=0)
        cs = np.repeat(c, per_ball, axis=0)
        Rs, cs = _perturb(Rs, cs, _ball(rng, len(Rs)), delta, rho)
        cost = contact_cost(model, surface, contacts, _poses(Rs, cs, surface.center), position_noise, normal_noise_deg)
        evaluations += len(Rs)
        scales += 1
        delta = new_delta
        keep = max_particles // per_ball
        if delta <= delta_final:
            R, c = Rs, cs  # the last scale: keep every particle for the estimate
            break
        R, c, cost = _prune(rng, Rs, cs, cost, tau, keep)
    best = int(np.argmin(cost))
    return BaselineResult(_poses(R[best:best + 1], c[best:best + 1], surface.center)[0], float(cost[best]),
                          evaluations, scales)


def _prune(rng, R, c, cost, tau, keep):
    """Importance resampling with weights exp(-cost/(2τ)), duplicates removed; at most keep survivors."""
    logw = -0.5 * (cost - cost.min()) / tau
    w = np.exp(logw)
    w /= w.sum()
    # systematic resampling: keep draws, one uniform offset
    positions = (rng.random() + np.arange(keep)) / keep
    idx = np.unique(np.searchsorted(np.cumsum(w), positions).clip(0, len(w) - 1))
    return R[idx], c[idx], cost[idx]


# --------------------------------------------------------------------------- tracking

class MemoryParticleFilter:
    """The pose of an object held in a moving hand, as particles.

    model : ObjectModel; surface : its Surface (:func:`sample_surface`); starts : (S, 4, 4)
    poses to start from (for example localize's distinct poses of a first grasp), the
    particles split evenly among them and spread by N(0, spread_deg²) of rotation and
    N(0, spread²) of translation per axis (default 1 % of the diameter); contacts : the first
    grasp's Contacts; rng : numpy Generator; position_noise, normal_noise_deg : the contact
    likelihood's σ (:func:`contact_cost`); memory : contacts kept for the likelihood.

    Each :meth:`add` moves the particles with the hand, X ← ΔT X S, with a slip S drawn from
    the slip's sigmas (rotation vector and translation in the object frame), moves the
    remembered contacts with the hand (x ← ΔT x), weights every particle by exp(-χ²/2) of
    the last ``memory`` contacts (recomputed each touch, not multiplied over touches: the
    memory stands for the history), and resamples (systematic). The estimate is the weighted
    mean of the particles within ESTIMATE_DEG and ESTIMATE_FRAC of the diameter of the most
    probable one. A bootstrap filter: the proposal is the motion model, not an unscented one.
    """

    #: The estimate averages the particles this close to the most probable one.
    ESTIMATE_DEG = 10.0
    ESTIMATE_FRAC = 0.1

    def __init__(self, model, surface, starts, contacts, rng, *, position_noise, normal_noise_deg, particles=1000,
                 spread_deg=2.0, spread=None, memory=4):
        starts = np.asarray(starts, dtype=np.float64).reshape(-1, 4, 4)
        if len(starts) == 0:
            raise ContactPoseError("a particle filter needs at least one start pose")
        self.model, self.surface, self.rng, self.memory = model, surface, rng, memory
        self.noise = (position_noise, normal_noise_deg)
        spread = 0.01 * model.diameter if spread is None else spread
        X = starts[np.arange(particles) % len(starts)]
        self.X = X @ _slips(rng, particles, spread_deg, spread)
        self.remembered = contacts
        self._weigh_and_resample()

    def add(self, contacts, hand_motion):
        """One touch after the hand moved: hand_motion (ΔT (4, 4), σ_rot in degrees, σ_trans).
        -> the estimate (4, 4)"""
        delta, sigma_rot_deg, sigma_trans = hand_motion
        self.X = delta @ self.X @ _slips(self.rng, len(self.X), sigma_rot_deg, sigma_trans)
        joined = self.remembered.transformed(delta).joined(contacts)
        self.remembered = joined.permuted(np.arange(max(0, joined.n - self.memory), joined.n))
        return self._weigh_and_resample()

    def _weigh_and_resample(self):
        chi2 = contact_cost(self.model, self.surface, self.remembered, self.X, *self.noise)
        w = np.exp(-0.5 * (chi2 - chi2.min()))
        w /= w.sum()
        self.pose = _local_mean(self.X, w, self.X[np.argmax(w)], self.ESTIMATE_DEG,
                                self.ESTIMATE_FRAC * self.model.diameter)
        positions = (self.rng.random() + np.arange(len(w))) / len(w)
        self.X = self.X[np.searchsorted(np.cumsum(w), positions).clip(0, len(w) - 1)]
        return self.pose


def _slips(rng, count, sigma_rot_deg, sigma_trans):
    """count random rigid transforms: rotation vector N(0, σ_r²), translation N(0, σ_t²) per
    axis. -> (count, 4, 4)"""
    S = np.zeros((count, 4, 4))
    S[:, :3, :3] = Rotation.from_rotvec(np.radians(sigma_rot_deg) * rng.normal(size=(count, 3))).as_matrix()
    S[:, :3, 3] = sigma_trans * rng.normal(size=(count, 3))
    S[:, 3, 3] = 1.0
    return S


def _local_mean(X, w, best, max_deg, max_trans):
    """Weighted mean pose of the particles X (P, 4, 4) within max_deg and max_trans of
    ``best`` (rotations by scipy's weighted mean). -> (4, 4)"""
    rel = Rotation.from_matrix(np.einsum("ji,pjk->pik", best[:3, :3], X[:, :3, :3]))
    near = (np.degrees(rel.magnitude()) <= max_deg) & (np.linalg.norm(X[:, :3, 3] - best[:3, 3], axis=1) <= max_trans)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_matrix(X[near, :3, :3]).mean(weights=w[near]).as_matrix()
    T[:3, 3] = np.average(X[near, :3, 3], axis=0, weights=w[near])
    return T
