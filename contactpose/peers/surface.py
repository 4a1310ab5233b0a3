"""The peers' shared view of the object: area-uniform surface samples, each facet's
neighbours, and the contact likelihood every peer scores a pose with (:func:`contact_cost`):
for each contact, its distance to the mesh surface over σ_x and the angle between its
measured normal and the normal of the nearest facet over σ_n, squared and summed (a
whitened χ², 3 dof per contact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactpose.costs.facet import angle_chi2
from contactpose.costs.frame import object_frame
from contactpose.geometry.kernels import triangle_pair_bounds
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
#: Contact-facet pairs scored at once by :func:`contact_cost` (about 150 bytes each, so near
#: 300 MB), whatever the number of poses and of neighbours per facet (157 on the YCB mug).
PAIRS_PER_BLOCK = 2_000_000


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
    the number of poses scored and of iterations (ICP runs or Scaling Series scales); a method
    with a schedule also gives the iterations it planned and, when it stopped early, why."""

    pose: np.ndarray
    cost: float
    evaluations: int
    iterations: int
    planned: int = 0
    stopped: str = ""


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
    p, nu = object_frame(poses[:, :3, :3], poses[:, :3, 3], contacts.points, contacts.finger_normals)
    flat, nflat = p.reshape(-1, 3), nu.reshape(-1, 3)
    if not len(flat):
        return np.zeros(len(poses))
    step = max(PAIRS_PER_BLOCK // surface.neighbours.shape[1], 1)
    chi2 = np.concatenate([_block_chi2(model, surface, flat[i:i + step], nflat[i:i + step], position_noise,
                                       normal_noise_deg) for i in range(0, len(flat), step)])
    return chi2.reshape(len(poses), -1).sum(axis=1)


def _block_chi2(model, surface, points, normals, position_noise, normal_noise_deg):
    """χ² of object-frame contact points and normals (k, 3) -> (k,), one block of contact_cost."""
    # candidates: the facet of the exact closest surface point and its neighbours  -> (k, D); each
    # contact takes the one that explains it best (near an edge the nearest facet by distance may
    # be the neighbour with the wrong normal)
    candidates = surface.neighbours[surface.closest_facets(points)]
    return angle_chi2(points, normals, candidates, model.triangles, model.planes.normals, position_noise,
                      np.radians(normal_noise_deg))
