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
stored interval always contains the exact one. The vertex-only Δmin and the direction
intervals are cheap and exact to recompute: model files leave them out, and
:func:`derived_features` rebuilds them on load, bit for bit as the build made them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from contactpose.geometry.kernels import _vertex_minmax, triangle_pair_bounds, triangle_pair_vertex_bounds
from contactpose.progress import progress_bar

#: Number of facet pairs computed per chunk; bounds the temporary memory.
CHUNK_PAIRS = 2_000_000
#: Rows of a NearPairs sample: count estimates from this many rows are within about 5 %
#: on meshes of even density, and cost at most this many KD-tree ball queries.
SAMPLE_ROWS = 512
#: The fields that model files leave out and :func:`derived_features` recomputes.
DERIVED_FIELDS = ("dmin_vertex", "h_kl", "h_lk")


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
        self._sample = None

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

    def count_estimate(self, span=None):
        """Estimated number of pairs (k <= l) :meth:`rows` lists for a span (default: max_span).

        Each row's ball query (radius span + r_k + r_max) is counted exactly on SAMPLE_ROWS
        random rows (all rows when there are fewer), scaled to all rows and halved for k <= l.
        Costs SAMPLE_ROWS queries, however large the count.
        """
        span = self.max_span if span is None else span
        rows = self._sample_rows()
        hits = self.tree.query_ball_point(self.centres[rows], span + self.radii[rows] + self.radii.max(),
                                          return_length=True)
        n = len(self.centres)
        return int((hits.sum() * n / len(rows) + n) // 2)

    def _sample_rows(self):
        n = len(self.centres)
        if self._sample is None:
            self._sample = np.arange(n) if n <= SAMPLE_ROWS else np.sort(
                np.random.default_rng(0).choice(n, SAMPLE_ROWS, replace=False))
        return self._sample

    def all_rows(self, chunk_pairs=CHUNK_PAIRS):
        """:meth:`rows` of every row, listed in blocks of about chunk_pairs pairs so the
        query's Python lists stay small. -> (k, l) int32 facet (or item) indices."""
        n = len(self.centres)
        per_row = max(1.0, 2.0 * self.count_estimate() / n)
        step = max(1, int(chunk_pairs / per_row))
        parts = [self.rows(start, min(n, start + step)) for start in range(0, n, step)]
        k = np.concatenate([p[0].astype(np.int32) for p in parts]) if parts else np.empty(0, np.int32)
        l = np.concatenate([p[1].astype(np.int32) for p in parts]) if parts else np.empty(0, np.int32)
        return k, l

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
    progress : None shows a bar on a terminal once the work has taken a second (progress.progress_bar).
    """
    valid_idx = np.flatnonzero(planes.valid)
    v = len(valid_idx)
    near = None if max_span is None else NearPairs.of_facets(triangles, valid_idx, max_span)
    # rows of the upper triangle; with a span, rows hold fewer candidates each
    chunks = row_chunks(v - np.arange(v), CHUNK_PAIRS if near is None else CHUNK_PAIRS * 4)
    parts = []
    with progress_bar(total=v, desc="pair features", unit="facet", show=progress) as bar:
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


def derived_features(triangles, normals, k, l):
    """The fields model files leave out (DERIVED_FIELDS), recomputed for facet pairs (k, l).

    triangles : (m, 3, 3) float64; normals : (m, 3) float64 (the model's planes);
    k, l : (P,) int. -> {"dmin_vertex": (P,) float32, "h_kl", "h_lk": (P, 2) float32},
    equal bit for bit to what the build stores (same products, same outward rounding).
    """
    k, l = np.ascontiguousarray(k), np.ascontiguousarray(l)
    dmin_v, h_kl, h_lk = np.empty(len(k), np.float32), np.empty(2 * len(k), np.float32), np.empty(2 * len(k), np.float32)
    _derived_kernel(np.ascontiguousarray(triangles, dtype=np.float64), np.ascontiguousarray(normals, dtype=np.float64),
                    k, l, dmin_v, dmin_v.view(np.int32), h_kl, h_kl.view(np.int32), h_lk, h_lk.view(np.int32))
    return {"dmin_vertex": dmin_v, "h_kl": h_kl.reshape(-1, 2), "h_lk": h_lk.reshape(-1, 2)}


#: Pairs per task of the derived-fields kernel.
DERIVED_BLOCK = 65536
#: The smallest positive float32 (a subnormal).
_TINY32 = np.float32(2.0**-149)


@numba.njit(cache=True, parallel=True)
def _derived_kernel(tri, normals, k, l, dmin_v, dmin_bits, h_kl, h_kl_bits, h_lk, h_lk_bits):
    """dmin_vertex (P,) and the flat direction intervals (2P,) [lo, hi, lo, hi, ...] of pairs
    (k, l); each *_bits is the int32 view of its float32 array, for the outward steps."""
    for block in numba.prange((len(k) + DERIVED_BLOCK - 1) // DERIVED_BLOCK):
        for e in range(block * DERIVED_BLOCK, min(len(k), (block + 1) * DERIVED_BLOCK)):
            lo2, _ = _vertex_minmax(tri, k[e], l[e])
            _put_outward(dmin_v, dmin_bits, e, np.sqrt(lo2), False)
            lo, hi = _signed_bounds(normals[k[e]], tri[k[e], 0], tri[l[e]])
            _put_outward(h_kl, h_kl_bits, 2 * e, lo, False)
            _put_outward(h_kl, h_kl_bits, 2 * e + 1, hi, True)
            lo, hi = _signed_bounds(normals[l[e]], tri[l[e], 0], tri[k[e]])
            _put_outward(h_lk, h_lk_bits, 2 * e, lo, False)
            _put_outward(h_lk, h_lk_bits, 2 * e + 1, hi, True)


@numba.njit(cache=True, inline="always")
def _put_outward(out, bits, i, x, up):
    """out[i] = round_up32(x) (up) or round_down32(x), for finite x: the nearest float32,
    stepped one ulp outward through its bits when on the wrong side of x. Branch-free but for
    values that round to zero (|x| < 2⁻¹⁵⁰), four times faster than np.nextafter here."""
    y = np.float32(x)
    out[i] = y
    wrong = np.int32(np.float64(y) < x) if up else np.int32(np.float64(y) > x)
    positive = np.int32(y > 0)
    bits[i] += wrong * ((2 * positive - 1) if up else (1 - 2 * positive))  # away from zero or toward it
    if wrong and y == 0:
        out[i] = _TINY32 if up else -_TINY32


@numba.njit(cache=True)
def _direction_intervals(triangles, normals, k, l):
    """h_kl, h_lk : (P, 2) [min, max] of n_kᵀ q + d_k over facet l's vertices q, and swapped."""
    p = len(k)
    h_kl = np.empty((p, 2))
    h_lk = np.empty((p, 2))
    for e in range(p):
        h_kl[e, 0], h_kl[e, 1] = _signed_bounds(normals[k[e]], triangles[k[e], 0], triangles[l[e]])
        h_lk[e, 0], h_lk[e, 1] = _signed_bounds(normals[l[e]], triangles[l[e], 0], triangles[k[e]])
    return h_kl, h_lk


@numba.njit(cache=True)
def _signed_bounds(normal, origin, tri):
    """(min, max) over tri's vertices of the signed distance nᵀ(q - origin)."""
    lo, hi = np.inf, -np.inf
    for v in range(3):
        d = 0.0
        for c in range(3):
            d += normal[c] * (tri[v, c] - origin[c])
        lo = min(lo, d)
        hi = max(hi, d)
    return lo, hi
