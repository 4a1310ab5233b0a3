"""Pair characteristics of facets (paper §3.1): Δmin, Δmax and the normal angle α.

Each unordered pair {k, l} of valid facets (k = l included) is stored once;
the characteristics are symmetric, and the table answers as over ordered pairs.

* Δmax is the largest vertex–vertex distance (exact by convexity).
* Δmin is the exact triangle–triangle distance (0 when the facets touch or
  intersect). The paper's vertex-only Δmin (§3.1, erratum 4 in research/errata.md) is kept
  beside it for ``bounds="paper"``.
* α is the angle between the unit normals.
* Direction intervals (Grimson & Lozano-Pérez, *Model-based recognition and
  localization from sparse range or tactile data*, 1984; research/errata.md): h_kl is the
  interval of signed distances n_kᵀq + d_k of facet l's vertices q from facet k's
  plane, and h_lk the same with k and l swapped. Exact by linearity.

Distances are stored as float32 rounded outward (Δmin down, Δmax up), so the
stored interval always contains the exact one.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numba
import numpy as np
from tqdm.auto import tqdm

from contactpose.geometry.kernels import triangle_pair_bounds, triangle_pair_vertex_bounds

#: Number of facet pairs computed per chunk; bounds the temporary memory.
CHUNK_PAIRS = 2_000_000
#: Models with more pairs than this show a progress bar on a terminal.
PROGRESS_MIN_PAIRS = 5_000_000


def round_down32(x):
    """float64 -> float32, never above the input. x : (p,) float."""
    y = x.astype(np.float32)
    over = y.astype(np.float64) > x
    y[over] = np.nextafter(y[over], np.float32(-np.inf))
    return y


def round_up32(x):
    """float64 -> float32, never below the input. x : (p,) float."""
    y = x.astype(np.float32)
    under = y.astype(np.float64) < x
    y[under] = np.nextafter(y[under], np.float32(np.inf))
    return y


@dataclass
class PairFeatures:
    """Characteristics of the unordered valid facet pairs {k, l}, k <= l.

    k, l : (P,) int32; dmax, dmin_vertex, alpha : (P,) float32;
    dmin_exact : (P,) float32 or None (models built with ``bounds="paper"``);
    h_kl, h_lk : (P, 2) float32 direction intervals [lo, hi];
    alpha_hi : (P,) float32 or None: for pairs of patches, α is the interval
    [alpha, alpha_hi]; None for facets (a single angle).
    """

    k: np.ndarray
    l: np.ndarray
    dmax: np.ndarray
    dmin_vertex: np.ndarray
    dmin_exact: np.ndarray | None
    alpha: np.ndarray
    h_kl: np.ndarray
    h_lk: np.ndarray
    alpha_hi: np.ndarray | None = None

    @property
    def alpha_upper(self):
        """(P,) upper end of the angle interval (α itself for facet pairs)."""
        return self.alpha if self.alpha_hi is None else self.alpha_hi

    @property
    def num_ordered(self):
        """Ordered pairs (k, l) these stand for: both orders, the diagonal once."""
        return int(2 * len(self.k) - np.count_nonzero(self.k == self.l))

    def dmin(self, bounds):
        """The Δmin array for ``bounds`` "exact" or "paper"."""
        if bounds == "paper":
            return self.dmin_vertex
        if self.dmin_exact is None:
            from contactpose.errors import ModelFileError

            raise ModelFileError(
                "this model was built with bounds='paper' and has no exact Δmin; "
                "rebuild it with bounds='exact' to use the default method"
            )
        return self.dmin_exact

    def permuted(self, order):
        """These features in another order, permuted in place field by field. order : (P,) int."""
        for f in _FIELDS:
            value = getattr(self, f)
            if value is not None:
                setattr(self, f, value[order])
        return self

    def to_arrays(self):
        return {f: getattr(self, f) for f in _FIELDS if getattr(self, f) is not None}

    @classmethod
    def from_arrays(cls, arrays):
        return cls(*(arrays.get(f) for f in _FIELDS))


_FIELDS = ("k", "l", "dmax", "dmin_vertex", "dmin_exact", "alpha", "h_kl", "h_lk", "alpha_hi")


def unordered_pairs(valid_idx, start, stop):
    """Pairs (k, l), k <= l, whose first member is valid_idx[start:stop].

    valid_idx : (v,) int, sorted. Returns k, l : (p,) int64, row-major order.
    """
    v = len(valid_idx)
    rows = np.arange(start, stop)
    counts = v - rows
    row_of = np.repeat(rows, counts)
    # column offset within each row: 0..counts-1, shifted to start at the diagonal
    first = np.cumsum(counts) - counts
    col = np.arange(counts.sum()) - np.repeat(first, counts) + row_of
    return valid_idx[row_of], valid_idx[col]


def row_chunks(counts, chunk_pairs=CHUNK_PAIRS):
    """Split rows into runs of about chunk_pairs pairs. counts : (v,) pairs per row."""
    cum = np.cumsum(counts)
    if len(cum) == 0:
        return []
    bounds_at = np.searchsorted(cum, np.arange(chunk_pairs, cum[-1], chunk_pairs)) + 1
    edges = np.unique(np.concatenate([[0], bounds_at, [len(counts)]]))
    return list(zip(edges[:-1], edges[1:]))


class NearPairs:
    """Facet pairs (k, l), k <= l, that may lie within ``max_span`` of each other.

    Uses a KD-tree over bounding spheres (centres (n, 3), radii (n,)) of the items ids (n,):
    Δmin(k, l) >= |c_k - c_l| - r_k - r_l, so only centre pairs closer than
    max_span + r_k + r_l can qualify; no n² scan.
    """

    def __init__(self, centres, radii, max_span, ids=None):
        from scipy.spatial import cKDTree

        self.valid_idx = np.arange(len(centres)) if ids is None else ids
        self.centres, self.radii = centres, radii
        self.reach = max_span + self.radii + self.radii.max()
        self.tree = cKDTree(self.centres)
        self.max_span = max_span

    @classmethod
    def of_facets(cls, triangles, valid_idx, max_span):
        """Near pairs of the facets valid_idx of triangles (m, 3, 3)."""
        tri = triangles[valid_idx]
        centres = tri.mean(axis=1)
        return cls(centres, np.linalg.norm(tri - centres[:, None], axis=2).max(axis=1), max_span, valid_idx)

    def count_bound(self):
        """Upper bound on the number of candidate pairs (k <= l), without listing them."""
        both = self.tree.count_neighbors(self.tree, self.max_span + 2 * self.radii.max())
        return int((both + len(self.centres)) // 2)

    def rows(self, start, stop):
        """Candidate pairs whose first member is row start..stop-1: (k, l) int64 facet indices."""
        hits = self.tree.query_ball_point(self.centres[start:stop], self.reach[start:stop])
        counts = np.array([len(h) for h in hits])
        rows = np.repeat(np.arange(start, stop), counts)
        cols = np.concatenate(hits).astype(np.int64) if len(rows) else np.empty(0, np.int64)
        keep = cols >= rows
        return self.valid_idx[rows[keep]], self.valid_idx[cols[keep]]


def pair_features(triangles, planes, *, bounds="exact", progress=None, max_span=None):
    """Characteristics of the unordered valid facet pairs (§3.1, with erratum 4).

    triangles : (m, 3, 3) float; planes : FacetPlanes; bounds : "exact" | "paper";
    max_span : keep only pairs with Δmin <= max_span (None: all pairs);
    progress : None shows a bar on a terminal for large models.
    """
    valid_idx = np.flatnonzero(planes.valid)
    v = len(valid_idx)
    near = None if max_span is None else NearPairs.of_facets(triangles, valid_idx, max_span)
    total = v * (v + 1) // 2
    if progress is None:
        progress = total >= PROGRESS_MIN_PAIRS and sys.stderr.isatty()
    # rows of the upper triangle; with a span, rows hold about total/v candidates each
    chunks = row_chunks(v - np.arange(v), CHUNK_PAIRS if near is None else CHUNK_PAIRS * 4)
    parts = []
    with tqdm(total=v, unit="facet", disable=not progress, desc="pair features") as bar:
        for start, stop in chunks:
            k, l = unordered_pairs(valid_idx, start, stop) if near is None else near.rows(start, stop)
            part = _chunk_features(triangles, planes.normals, k, l, bounds)
            parts.append(part if near is None else _within_span(part, max_span, bounds))
            bar.update(stop - start)
    return PairFeatures(*_concat_fields(parts))


def _within_span(part, max_span, bounds):
    """Keep the pairs of a chunk whose Δmin (as the method uses it) is within max_span."""
    dmin = part[4] if bounds == "exact" else part[3]
    keep = dmin <= max_span
    return [None if a is None else a[keep] for a in part]


def _concat_fields(parts):
    """Concatenate chunk results field by field, releasing each field's chunks as it goes,
    so the peak is the result plus one field, not twice the result."""
    fields = []
    for f in range(len(parts[0])):
        column = [p[f] for p in parts]
        fields.append(None if column[0] is None else np.concatenate(column))
        for p in parts:
            p[f] = None
    return fields


def _chunk_features(triangles, normals, k, l, bounds):
    if bounds == "exact":
        dmin_exact, dmin_vertex, dmax = triangle_pair_bounds(triangles, k, l)
    else:
        (dmin_vertex, dmax), dmin_exact = triangle_pair_vertex_bounds(triangles, k, l), None
    cos = np.clip(np.einsum("ij,ij->i", normals[k], normals[l]), -1.0, 1.0)
    h_kl, h_lk = _direction_intervals(triangles, normals, k, l)
    return [
        k.astype(np.int32),
        l.astype(np.int32),
        round_up32(dmax),
        round_down32(dmin_vertex),
        None if dmin_exact is None else round_down32(dmin_exact),
        np.arccos(cos).astype(np.float32),
        _round_interval32(h_kl),
        _round_interval32(h_lk),
    ]


def _round_interval32(h):
    """(P, 2) float64 [lo, hi] -> float32 rounded outward."""
    return np.stack([round_down32(h[:, 0]), round_up32(h[:, 1])], axis=1)


@numba.njit(cache=True)
def _direction_intervals(triangles, normals, k, l):
    """h_kl, h_lk : (P, 2) [min, max] of n_kᵀ q + d_k over facet l's vertices q, and swapped."""
    p = len(k)
    h_kl = np.empty((p, 2))
    h_lk = np.empty((p, 2))
    for e in range(p):
        _signed_range(normals[k[e]], triangles[k[e], 0], triangles[l[e]], h_kl[e])
        _signed_range(normals[l[e]], triangles[l[e], 0], triangles[k[e]], h_lk[e])
    return h_kl, h_lk


@numba.njit(cache=True)
def _signed_range(normal, origin, tri, out):
    """[min, max] over tri's vertices of the signed distance nᵀ(q - origin)."""
    lo, hi = np.inf, -np.inf
    for v in range(3):
        d = 0.0
        for c in range(3):
            d += normal[c] * (tri[v, c] - origin[c])
        lo = min(lo, d)
        hi = max(hi, d)
    out[0] = lo
    out[1] = hi
