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
  q_a) / d, the angles ∠(m_a, u), ∠(m_b, u), ∠(m_a, m_b), grouped by d in bins a quarter of
  the spacing wide, so that one distance range is one slice. Computed (compiled, a counting
  sort) when first used, not stored in the model file: the YCB mug's 5,695 samples make 16 M
  pairs, about 1.5 s and 390 MB.
* **Field**: a voxel grid over the object's box padded by FIELD_PAD_FRAC of the diameter,
  each voxel naming the sample nearest its centre; a point's nearest sample then lies within
  the covering radius plus a voxel's diagonal of it, wherever it is on the surface.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit
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
#: The pair features' distance bins, as a fraction of the sample spacing.
PAIR_BIN_FRAC = 0.25


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
        """SamplePairs: the features of every unordered sample pair, grouped by distance in
        bins of PAIR_BIN_FRAC of the spacing."""
        return SamplePairs.of(self.points, self.normals, PAIR_BIN_FRAC * self.spacing)

    def nearest_samples(self, x):
        """(K,) int: the field's sample for each point x (K, 3), -1 outside the field."""
        idx = np.floor((x - self.origin) / self.cell + 0.5).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < np.array(self.nearest.shape)), axis=1)
        out = np.full(len(x), -1, dtype=np.int64)
        i = idx[inside]
        out[inside] = self.nearest[i[:, 0], i[:, 1], i[:, 2]]
        return out


@dataclass(frozen=True)
class SamplePairs:
    """first, second (P,) int32 sample indices (first < second); distance (P,) float32;
    angle_first, angle_second, angle_normals (P,) float32: ∠(m_a, u), ∠(m_b, u), ∠(m_a, m_b)
    in radians, u from the first to the second. The pairs are grouped by distance in bins of
    width ``bin``: offsets (B + 1,) int64, bin k's pairs at offsets[k]:offsets[k + 1]."""

    first: np.ndarray
    second: np.ndarray
    distance: np.ndarray
    angle_first: np.ndarray
    angle_second: np.ndarray
    angle_normals: np.ndarray
    offsets: np.ndarray
    bin: float

    @classmethod
    def of(cls, points, normals, bin):
        """The features of every unordered pair of the samples (points (N, 3), unit normals
        (N, 3)), grouped by distance in bins of width ``bin`` (compiled, a counting sort)."""
        n = len(points)
        count = n * (n - 1) // 2
        check_fits(PAIR_BYTES * count, f"the pair features of {n:,} surface samples", "use a larger spacing")
        points, normals = np.ascontiguousarray(points, np.float64), np.ascontiguousarray(normals, np.float64)
        bins = int(np.ceil(np.ptp(points, axis=0).dot(np.ones(3)) / bin)) + 1  # Σ extents ≥ any distance
        offsets = _bin_offsets(points, bin, bins)
        out = (np.empty(count, np.int32), np.empty(count, np.int32), *(np.empty(count, np.float32) for _ in range(4)))
        _fill_pairs(points, normals, bin, offsets.copy(), *out)
        return cls(*out, offsets, float(bin))

    def within(self, lo, hi):
        """The slice of pairs in the bins that [lo, hi] overlaps: every pair whose distance
        lies in [lo, hi], and others within one bin of it."""
        last = len(self.offsets) - 2
        k0, k1 = (min(last, max(0, int(np.floor(x / self.bin)))) for x in (lo, hi))
        return slice(int(self.offsets[k0]), int(self.offsets[k1 + 1]))


@njit(cache=True)
def _bin_offsets(points, bin, bins):
    """(bins + 1,) int64: where each distance bin of the sample pairs starts."""
    n = points.shape[0]
    offsets = np.zeros(bins + 1, np.int64)
    for a in range(n):
        for b in range(a + 1, n):
            d0, d1, d2 = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
            offsets[int(np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) / bin) + 1] += 1
    return np.cumsum(offsets)


@njit(cache=True, inline="always")
def _angle(x0, x1, x2, y0, y1, y2):
    """The angle between the unit vectors x and y (radians)."""
    return np.arccos(min(1.0, max(-1.0, x0 * y0 + x1 * y1 + x2 * y2)))


@njit(cache=True)
def _fill_pairs(points, normals, bin, cursor, first, second, distance, angle_first, angle_second, angle_normals):
    """Write each pair's features at the next free row of its distance bin (cursor (B + 1,):
    each bin's next free row)."""
    n = points.shape[0]
    for a in range(n):
        for b in range(a + 1, n):
            d0, d1, d2 = points[b, 0] - points[a, 0], points[b, 1] - points[a, 1], points[b, 2] - points[a, 2]
            d = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
            k = int(d / bin)
            row = cursor[k]
            cursor[k] += 1
            u0, u1, u2 = (d0 / d, d1 / d, d2 / d) if d > 0 else (0.0, 0.0, 0.0)
            first[row], second[row], distance[row] = a, b, d
            angle_first[row] = _angle(normals[a, 0], normals[a, 1], normals[a, 2], u0, u1, u2)
            angle_second[row] = _angle(normals[b, 0], normals[b, 1], normals[b, 2], u0, u1, u2)
            angle_normals[row] = _angle(normals[a, 0], normals[a, 1], normals[a, 2], normals[b, 0], normals[b, 1],
                                        normals[b, 2])


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
