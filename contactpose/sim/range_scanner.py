"""A simulated range scanner: ray-cast a triangle mesh from viewpoints around it.

It stands in for the paper's hand-guided laser scanner in tests and experiments.
Each view is a square pinhole image of ``resolution x resolution`` rays cast with
the mesh's :class:`~contactpose.geometry.raycast.Raycaster`; every hit becomes one point with range
noise along its ray, and the normal of the hit triangle turned towards the
sensor. The result is a partial cloud (surfaces that no view sees, or sees only
at grazing angles, are missing), like a real scan.

Range noise model: ``range_noise`` is relative to the measured range. A hit at
range ``r`` is moved along its ray by ``N(0, (range_noise * r)**2)``; so
``range_noise=0.005`` is "0.5 % range noise". With the default stand-off
(viewpoints at ``standoff=1.0`` bounding-box diagonals from the centre) the
ranges are 0.5 to 1.0 diagonals, so the noise is 0.25 % to 0.5 % of the diagonal.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh

from contactpose.errors import ContactPoseError
from contactpose.geometry.raycast import Raycaster

log = logging.getLogger(__name__)

__all__ = ["scan", "viewpoints"]


def viewpoints(mesh: trimesh.Trimesh, n_views: int = 8, standoff: float = 1.0) -> np.ndarray:
    """Sensor positions spread evenly on a sphere around a mesh.

    Parameters
    ----------
    mesh : trimesh.Trimesh
      The object; its bounding-box centre is the target of every view.
    n_views : int
      Number of viewpoints, on a Fibonacci sphere (so top and bottom are seen).
    standoff : float
      Distance from the centre, in bounding-box diagonals.

    Returns
    -------
    eyes : (n_views, 3) float
      Sensor positions.
    """
    if int(n_views) < 1:
        raise ContactPoseError(f"n_views is {n_views}; need at least 1 view")
    if not standoff > 0.5:
        raise ContactPoseError(
            f"standoff is {standoff}; need more than 0.5 bounding-box diagonals "
            "so the sensor is outside the object")
    centre, diagonal = _centre_and_diagonal(mesh)
    n = int(n_views)
    # Fibonacci lattice: z evenly spaced in (-1, 1), golden-angle azimuths
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    rho = np.sqrt(1.0 - z ** 2)
    directions = np.column_stack([rho * np.cos(phi), rho * np.sin(phi), z])
    return centre + standoff * diagonal * directions


def scan(
    mesh: trimesh.Trimesh,
    rng: np.random.Generator,
    *,
    n_views: int = 8,
    range_noise: float = 0.005,
    resolution: int = 96,
    standoff: float = 1.0,
    max_incidence_deg: float = 80.0,
    outlier_fraction: float = 0.0,
    eyes: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Simulate a multi-view range scan of a mesh.

    Parameters
    ----------
    mesh : trimesh.Trimesh
      The object surface, outward wound.
    rng : numpy.random.Generator
      Source of the range noise and the outliers.
    n_views : int
      Number of viewpoints (see :func:`viewpoints`); ignored when ``eyes`` is given.
    range_noise : float
      Standard deviation of the range error as a fraction of the measured range:
      0.005 means 0.5 % of the range. 0 gives exact hits.
    resolution : int
      Rays per image side; each view casts ``resolution**2`` rays through a
      square field of view that just contains the object's bounding sphere.
    standoff : float
      Sensor distance from the bounding-box centre, in bounding-box diagonals.
    max_incidence_deg : float
      Hits whose ray meets the surface more obliquely than this (angle between
      the ray and the surface normal) return nothing, as on a real scanner.
    outlier_fraction : float
      Fraction of extra points scattered uniformly in the bounding box grown by
      10 %, with random unit normals: spurious returns for testing filters.
    eyes : (k, 3) float, optional
      Explicit sensor positions instead of the Fibonacci sphere.

    Returns
    -------
    points : (n, 3) float
      Measured points (plus any outliers).
    normals : (n, 3) float
      Unit normals of the hit triangles, turned towards the sensor that saw them.
    """
    if not isinstance(rng, np.random.Generator):
        raise ContactPoseError(f"rng is {type(rng).__name__}; expected numpy.random.Generator")
    if not 0.0 <= range_noise < 0.5:
        raise ContactPoseError(f"range_noise is {range_noise}; expected a fraction in [0, 0.5)")
    if int(resolution) < 2:
        raise ContactPoseError(f"resolution is {resolution}; need at least 2 rays per side")
    if not 0.0 <= outlier_fraction < 1.0:
        raise ContactPoseError(f"outlier_fraction is {outlier_fraction}; expected [0, 1)")
    centre, diagonal = _centre_and_diagonal(mesh)
    if eyes is None:
        eyes = viewpoints(mesh, n_views, standoff)
    eyes = np.asanyarray(eyes, dtype=np.float64).reshape(-1, 3)

    caster = Raycaster.of_mesh(mesh)

    cos_max = np.cos(np.radians(max_incidence_deg))
    points, normals = [], []
    for eye in eyes:
        directions = _pinhole_directions(eye, centre, 0.5 * diagonal, int(resolution))
        t, facet = caster.first_hits(np.broadcast_to(eye, directions.shape), directions)
        hit = facet >= 0
        t, n, d = t[hit], caster.normals[facet[hit]], directions[hit]
        # turn each triangle normal towards the sensor
        cos = np.einsum("ij,ij->i", n, d)
        n[cos > 0] *= -1.0
        # drop grazing hits: |cos| between ray and normal below the limit
        keep = np.abs(cos) >= cos_max
        t, n, d = t[keep], n[keep], d[keep]
        # range noise proportional to the range (directions are unit, so t is the range)
        t = t + rng.normal(0.0, 1.0, t.shape) * range_noise * t
        points.append(eye + t[:, None] * d)
        normals.append(n)
    points = np.concatenate(points) if points else np.zeros((0, 3))
    normals = np.concatenate(normals) if normals else np.zeros((0, 3))

    n_out = int(round(outlier_fraction / (1.0 - outlier_fraction) * len(points)))
    if n_out:
        lo, hi = mesh.bounds
        pad = 0.1 * (hi - lo)
        points = np.vstack([points, rng.uniform(lo - pad, hi + pad, (n_out, 3))])
        random_normals = rng.normal(size=(n_out, 3))
        random_normals /= np.linalg.norm(random_normals, axis=1, keepdims=True)
        normals = np.vstack([normals, random_normals])
    log.debug("scan: %d views, %d points (%d outliers)", len(eyes), len(points), n_out)
    return points, normals


def _centre_and_diagonal(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """Bounding-box centre (3,) and diagonal of a non-empty mesh."""
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ContactPoseError("mesh to scan is empty or not a trimesh.Trimesh; need at least one facet")
    lo, hi = mesh.bounds
    return 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))


def _pinhole_directions(eye: np.ndarray, target: np.ndarray, radius: float, res: int) -> np.ndarray:
    """Unit ray directions (res*res, 3) of a square pinhole view of a sphere."""
    forward = target - eye
    dist = np.linalg.norm(forward)
    forward = forward / dist
    # any vector not parallel to forward makes the image axes
    helper = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(forward, helper)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    # half field of view that just contains the bounding sphere
    half = np.tan(np.arcsin(min(radius / dist, 0.999)))
    s = np.linspace(-half, half, res)
    u, v = np.meshgrid(s, s)
    d = forward + u.reshape(-1, 1) * right + v.reshape(-1, 1) * up
    return d / np.linalg.norm(d, axis=1, keepdims=True)
