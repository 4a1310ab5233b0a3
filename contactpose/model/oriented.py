"""The offline half of the search by hypothesize and verify (research/verify_search.md):
oriented surface samples, the features of every pair of them, and a field that names each
point's nearest sample.

* **Samples** (model.samples.SurfaceSamples) at ``spacing``: each carries the smooth normal
  of the surface at its point (model.smooth_normals, which does not blend across a crease,
  so the two sides of a thin wall keep their own) and a *spread* s_a: the angle from that
  normal to the normal of any facet in its patch, bounded by ∠(m_a, n_a) + β_a. A contact
  within the covering radius of the sample, on a face, an edge or a vertex, has its normal
  within s_a of m_a.
* **Pair features** of every unordered pair (a, b), a < b: d = |q_b − q_a| and, u = (q_b −
  q_a) / d, the angles ∠(m_a, u), ∠(m_b, u), ∠(m_a, m_b), sorted by d, so that one distance
  range is one slice. Computed when first used, not stored in the model file: N = 2,000
  samples make 2 M pairs, about 0.1 s and 50 MB.
* **Field**: a voxel grid over the object's box padded by FIELD_PAD_FRAC of the diameter,
  each voxel naming the sample nearest its centre; a point's nearest sample then lies within
  the covering radius plus a voxel's diagonal of it, wherever it is on the surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from contactpose.model.memory import check_fits
from contactpose.model.samples import SurfaceSamples, _grid_points

#: Sample spacing as a fraction of the object's diameter.
SPACING_FRAC = 0.02
#: The field's voxel edge as a fraction of the diameter, and the padding around the box.
FIELD_CELL_FRAC = 0.01
FIELD_PAD_FRAC = 0.1
#: Dense points per spacing when the samples' spreads and radii are measured.
DENSE_DIVISOR = 6
#: Nearest samples searched for one on a point's own side of a thin wall.
SIDE_NEIGHBOURS = 16
#: Bytes per sample pair of the feature table (two indices, four float32 features).
PAIR_BYTES = 24


@dataclass(frozen=True)
class OrientedSamples:
    """points (N, 3), normals (N, 3) unit smooth normals, spreads (N,) radians, facets (N,)
    int: the samples, object frame; spacing, covering: lengths (model.samples); origin (3,),
    cell: the field's first voxel centre and edge; nearest (X, Y, Z) int32: each voxel's
    nearest sample."""

    points: np.ndarray
    normals: np.ndarray
    spreads: np.ndarray
    radii: np.ndarray
    facets: np.ndarray
    spacing: float
    covering: float
    origin: np.ndarray
    cell: float
    nearest: np.ndarray
    other_side: np.ndarray

    @classmethod
    def of(cls, model, spacing=None):
        """The oriented samples of ``model`` at ``spacing`` (default SPACING_FRAC of its
        diameter) and their field."""
        spacing = SPACING_FRAC * model.diameter if spacing is None else float(spacing)
        base = SurfaceSamples.of(model, spacing)
        normals = _smooth_normals(model, base.points, base.facets)
        spreads, radii = _voronoi_spreads(model, base.points, normals, spacing)
        origin, cell, nearest = _field(model, base.points)
        return cls(base.points, normals, spreads, radii, base.facets, base.spacing, base.covering, origin, cell,
                   nearest, _other_sides(base.points, normals, base.covering))

    def __len__(self):
        return len(self.points)

    @property
    def reach(self):
        """How far a surface point may lie from the sample the field names for it: the
        covering radius plus a voxel's full diagonal (length)."""
        return self.covering + np.sqrt(3.0) * self.cell

    @cached_property
    def pairs(self):
        """PairFeatures of every unordered sample pair, sorted by distance."""
        return PairFeatures.of(self.points, self.normals)

    def nearest_samples(self, x):
        """(K,) int: the field's sample for each point x (K, 3), -1 outside the field."""
        idx = np.floor((x - self.origin) / self.cell + 0.5).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < np.array(self.nearest.shape)), axis=1)
        out = np.full(len(x), -1, dtype=np.int64)
        i = idx[inside]
        out[inside] = self.nearest[i[:, 0], i[:, 1], i[:, 2]]
        return out


@dataclass(frozen=True)
class PairFeatures:
    """first, second (P,) int32 sample indices (first < second); distance (P,) float32,
    ascending; angle_first, angle_second, angle_normals (P,) float32: ∠(m_a, u), ∠(m_b, u),
    ∠(m_a, m_b) in radians, u from the first to the second."""

    first: np.ndarray
    second: np.ndarray
    distance: np.ndarray
    angle_first: np.ndarray
    angle_second: np.ndarray
    angle_normals: np.ndarray

    @classmethod
    def of(cls, points, normals):
        n = len(points)
        count = n * (n - 1) // 2
        check_fits(3 * PAIR_BYTES * count, f"the pair features of {n:,} surface samples", "use a larger spacing")
        a, b = np.triu_indices(n, 1)
        d = points[b] - points[a]
        dist = np.linalg.norm(d, axis=1)
        u = d / np.maximum(dist, 1e-300)[:, None]
        angles = [np.arccos(np.clip(np.einsum("ij,ij->i", x, y), -1.0, 1.0))
                  for x, y in ((normals[a], u), (normals[b], u), (normals[a], normals[b]))]
        order = np.argsort(dist, kind="stable")
        return cls(a[order].astype(np.int32), b[order].astype(np.int32), dist[order].astype(np.float32),
                   *(x[order].astype(np.float32) for x in angles))

    def within(self, lo, hi):
        """The slice of pairs whose distance lies in [lo, hi]."""
        return slice(int(np.searchsorted(self.distance, lo, "left")), int(np.searchsorted(self.distance, hi, "right")))


def _smooth_normals(model, points, facets):
    """(N, 3) the model's smooth normal (model.smooth_normals) at each point on its facet."""
    m = model.smooth_normal_at(points, facets)
    size = np.linalg.norm(m, axis=1, keepdims=True)
    fallback = model.planes.normals[facets]
    return np.where(np.isfinite(size) & (size > 0), m / np.where(size > 0, size, 1.0), fallback)


def _voronoi_spreads(model, points, normals, spacing):
    """(spreads (N,), radii (N,)): over dense points of the valid facets (a barycentric grid
    DENSE_DIVISOR times finer than the spacing), each given to its nearest sample on its own
    side (the sample's normal within a right angle of the facet's: a thin wall's other side
    is not its own), the largest angle from the sample's normal to a given point's facet
    normal, and the largest distance from the sample to a given point plus the grid's step."""
    valid = np.flatnonzero(model.planes.valid)
    dense, owner, step = _grid_points(model.triangles[valid], spacing / DENSE_DIVISOR)
    facet_normals = model.planes.normals[valid[owner]]
    dist, near = cKDTree(points).query(dense, k=SIDE_NEIGHBOURS)
    same = np.einsum("gkj,gj->gk", normals[near], facet_normals) > 0
    pick = np.where(same.any(axis=1), np.argmax(same, axis=1), 0)
    rows = np.arange(len(dense))
    sample, gap = near[rows, pick], dist[rows, pick]
    angle = np.arccos(np.clip(np.einsum("gj,gj->g", normals[sample], facet_normals), -1.0, 1.0))
    spreads, radii = np.zeros(len(points)), np.zeros(len(points))
    np.maximum.at(spreads, sample, angle)
    np.maximum.at(radii, sample, gap)
    return spreads, radii + step


def _other_sides(points, normals, covering):
    """(N,) int: each sample's nearest sample whose normal faces away from its own (a thin
    wall's other side), within SIDE_NEIGHBOURS neighbours; -1 where none is."""
    _, near = cKDTree(points).query(points, k=SIDE_NEIGHBOURS)
    away = np.einsum("nkj,nj->nk", normals[near], normals) < 0
    return np.where(away.any(axis=1), near[np.arange(len(points)), np.argmax(away, axis=1)], -1).astype(np.int32)


def _field(model, points):
    """(origin (3,), cell, nearest (X, Y, Z) int32): the sample nearest each voxel centre."""
    cell = FIELD_CELL_FRAC * model.diameter
    pad = FIELD_PAD_FRAC * model.diameter
    lo, hi = model.vertices.min(axis=0) - pad, model.vertices.max(axis=0) + pad
    shape = np.ceil((hi - lo) / cell).astype(np.int64) + 1
    check_fits(32 * int(np.prod(shape)), f"the verification field of {int(np.prod(shape)):,} voxels",
               "use a larger cell")
    axes = [lo[k] + cell * np.arange(shape[k]) for k in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    _, nearest = cKDTree(points).query(centres)
    return lo, cell, nearest.astype(np.int32).reshape(tuple(shape))
