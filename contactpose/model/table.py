"""The 3-D hash table K3 of facet pairs (paper eqs. 3–5, errata 2).

Pairs are binned on (Δmax, Δmin, α) with p equal-width bins per axis (eq. 3,
hash functions eq. 4, clamped to [0, p-1]). The layout is compact: the pair
features sorted by flat bin key, plus an offsets array with one entry per bin,
so bin (a, b, c) holds entries ``offsets[key] : offsets[key + 1]``.

A query (eq. 5, read ∪ for ∩) visits the union of admissible bins, then applies
the exact interval test to each stored pair, and returns ordered pairs.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba
import numpy as np

from contactpose import tol
from contactpose.errors import ContactPoseError, ModelFileError
from contactpose.io.modelfile import OPTIONAL_TABLE, STORED_FEATURES, STORED_TABLE, check_arrays, check_pointers
from contactpose.model.features import CHUNK_PAIRS, PairFeatures

#: Default bins (p_dmax, p_dmin, p_alpha). α bins of 180°/64 ≈ 2.8° sit just below the
#: pair angle tolerance at 1° normal noise (4.2°), so an angle query touches 2–4 α bins;
#: 32 distance bins keep the number of visited bins (≈ p_dmax·p_dmin/4 segments) small
#: while the exact test removes the bins' excess. research/design.md ("Table layout") and results/bin_sweep/ give the measurements.
DEFAULT_BINS = (32, 32, 64)
#: Bytes per stored unordered pair: k, l (int32), Δmax, Δmin exact, Δmin vertex, α and the
#: two direction intervals (float32).
STORED_BYTES_PER_PAIR = 8 + 16 + 16
#: Extra bytes per pair at the build's peak: the int64 sort key and permutation, and one
#: permuted field (at most 8 bytes) while the table is sorted.
SORT_BYTES_PER_PAIR = 8 + 8 + 8


def check_bins(bins):
    """Validate bins=(p_dmax, p_dmin, p_alpha): three positive integers."""
    try:
        values = tuple(int(b) for b in bins)
        ok = len(values) == 3 and all(v >= 1 and v == b for v, b in zip(values, bins))
    except (TypeError, ValueError):
        ok = False
    if not ok or any(v > 4096 for v in values):
        raise ContactPoseError(f"bins must be three integers in [1, 4096] (p_dmax, p_dmin, p_alpha), got {bins!r}")
    return values


#: Temporaries per pair while a chunk of pair features is computed (int64 indices,
#: float64 distances, cosines and direction intervals before rounding to float32); measured.
CHUNK_TEMP_BYTES_PER_PAIR = 90
#: Bytes per patch pair at the patch table's peak (patches.PatchPairs): candidate indices
#: (int32) and work estimate (int64), the float32 features, their copy kept within the span,
#: and the sort into K3 (int64 key and permutation, one permuted field); measured.
PATCH_PAIR_BYTES = 16 + 36 + 44 + 24


def estimate_bytes(num_pairs, num_patch_pairs=0):
    """Peak memory of building a model's pair tables, in bytes.

    Facet table: the larger of the chunk phase (stored pairs so far plus one chunk's
    temporaries) and the sort into K3 (stored pairs plus key and permutation). Patch table:
    PATCH_PAIR_BYTES per candidate patch pair. num_pairs : unordered facet pairs kept
    (0 without a facet table); num_patch_pairs : candidate patch pairs (0 without patches).
    """
    stored = num_pairs * STORED_BYTES_PER_PAIR
    chunk = min(num_pairs, CHUNK_PAIRS) * CHUNK_TEMP_BYTES_PER_PAIR
    sort = num_pairs * SORT_BYTES_PER_PAIR
    return max(stored + chunk, stored + sort) + num_patch_pairs * PATCH_PAIR_BYTES


@dataclass
class PairTable:
    """K3: features sorted by bin key, with per-bin offsets.

    features : PairFeatures in key order; offsets : (p1·p2·p3 + 1,) int64;
    bins : (3,) int; mins, widths : (3,) float (Min and q of eq. 3 per axis);
    max_span : pairs with Δmin above it are not stored (None: all pairs).
    Angles are binned on the interval's lower end; ``alpha_width`` is the widest interval,
    by which a query widens its lower α bin.
    """

    features: PairFeatures
    offsets: np.ndarray
    bins: tuple
    mins: np.ndarray
    widths: np.ndarray
    max_span: float | None = None

    @cached_property
    def alpha_width(self):
        """The widest angle interval α_hi - α of a pair (0 without intervals); stored in model files."""
        f = self.features
        return 0.0 if f.alpha_hi is None or len(f.alpha) == 0 else float(np.max(f.alpha_hi - f.alpha))

    @classmethod
    def build(cls, features, bins, max_span=None):
        """Sort the pairs into K3 (eqs. 3–4). features : PairFeatures (any order)."""
        dmin = features.dmin_exact if features.dmin_exact is not None else features.dmin_vertex
        axes = (features.dmax, dmin, features.alpha)
        mins = np.array([float(a.min()) for a in axes])
        widths = np.array([(float(a.max()) - lo) / p for a, lo, p in zip(axes, mins, bins)])
        widths[widths <= 0] = 1.0  # a constant axis: everything falls into bin 0
        key = _flat_key(*(bin_index(a, lo, q, p) for a, lo, q, p in zip(axes, mins, widths, bins)), bins)
        order = np.argsort(key, kind="stable")
        counts = np.bincount(key, minlength=int(np.prod(bins)))
        del key
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return cls(features.permuted(order), offsets, tuple(bins), mins, widths, max_span)

    def to_arrays(self):
        span = np.nan if self.max_span is None else self.max_span
        return {"offsets": self.offsets, "bins": np.array(self.bins), "mins": self.mins, "widths": self.widths,
                "max_span": np.array(span), "alpha_width": np.array(self.alpha_width)}

    @classmethod
    def from_arrays(cls, arrays, features, sizes, prefixes=("table_", "features_"), values=True):
        """The table of a model file. arrays : the table's arrays; features : its PairFeatures;
        sizes : {"n": (facets or patches the pairs index, array that says so)};
        prefixes : of the table's and the features' arrays in the file (for messages);
        values : scan the values too (io.modelfile.check_arrays)."""
        check_arrays(features.to_arrays(), STORED_FEATURES, sizes, prefixes[1], ("dmin_exact", "alpha_hi"), values)
        check_arrays(arrays, STORED_TABLE, sizes, prefixes[0], OPTIONAL_TABLE)
        bins = tuple(int(b) for b in arrays["bins"])
        check_arrays(arrays, {"offsets": ("i", ("B",))}, {"B": (int(np.prod(bins)) + 1, prefixes[0] + "bins")},
                     prefixes[0])
        check_pointers(prefixes[0] + "offsets", arrays["offsets"], len(features.k))
        if not np.all(arrays["widths"] > 0):
            raise ModelFileError(f"array {prefixes[0] + 'widths'!r} must be positive, got {arrays['widths'].tolist()}")
        span = float(arrays["max_span"])
        if not (np.isnan(span) or 0 < span < np.inf):
            raise ModelFileError(f"array {prefixes[0] + 'max_span'!r} must be a positive length or NaN, got {span}")
        table = cls(features, arrays["offsets"], bins, arrays["mins"], arrays["widths"], None if np.isnan(span) else span)
        if "alpha_width" in arrays:
            width = float(arrays["alpha_width"])
            if not 0 <= width <= np.pi:
                raise ModelFileError(f"array {prefixes[0] + 'alpha_width'!r} must be an angle in [0, pi], got {width}")
            table.__dict__["alpha_width"] = width  # as cached_property keeps it
        return table

    def query(self, distance, angle, sigma_distance, sigma_angle, bounds="exact"):
        """Admissible unordered pairs for one finger pair (eq. 5 plus the exact test).

        distance Δ̃ and angle α̃ (radians) of the finger pair, tolerances σ_Δ and σ_α.
        Returns indices (s,) int64 into ``self.features`` of the pairs with
        Δmin - σ_Δ <= Δ̃ <= Δmax + σ_Δ and |α - α̃| <= σ_α.
        """
        limits = query_limits(distance, angle, sigma_distance, sigma_angle)
        f = self.features
        return _gather(self.offsets, np.asarray(self.bins), self.mins, self.widths,
                       f.dmax, f.dmin(bounds), f.alpha, f.alpha_upper, self.alpha_width, *limits)

    def query_pairs(self, distance, angle, sigma_distance, sigma_angle, bounds="exact", direction=None):
        """Like :meth:`query`, expanded to ordered pairs: (first (s,) int64, second (s,) int64).

        direction : None, or (h_ij, h_ji, σ_h): measured signed distances of contact j from
        contact i's tangent plane and back; an ordered pair (k, l) is kept only if
        h_ij ∈ h_kl ± σ_h and h_ji ∈ h_lk ± σ_h (the direction constraint).
        """
        idx = self.query(distance, angle, sigma_distance, sigma_angle, bounds)
        return self.ordered_pairs(idx, direction)

    def query_all(self, conditions, tolerance, bounds="exact", direction=True):
        """Ordered admissible pairs of every finger pair in one kernel call.

        conditions : PairConditions; tolerance : Tolerance. Returns first, second :
        (s,) int64 concatenated over finger pairs, and bounds (P + 1,) int64 delimiting them.
        """
        c = conditions
        sigma_h = tolerance.direction(c.distance)
        f = self.features
        return _query_all(self.offsets, np.asarray(self.bins), self.mins, self.widths, f.dmax, f.dmin(bounds),
                          f.alpha, f.alpha_upper, self.alpha_width, f.k, f.l, f.h_kl, f.h_lk,
                          c.distance, c.angle, c.h_ij, c.h_ji, sigma_h,
                          tolerance.distance, tolerance.angle, direction,
                          tol.LENGTH_SLACK_REL, tol.ANGLE_SLACK)

    def ordered_pairs(self, indices, direction=None):
        """Expand unordered entries to ordered pairs (k, l) and (l, k). indices : (s,) int."""
        f = self.features
        use = direction is not None
        h_ij, h_ji, sigma_h = direction if use else (0.0, 0.0, 0.0)
        return _expand_ordered(f.k, f.l, indices, f.h_kl, f.h_lk, use, h_ij, h_ji, sigma_h)


def query_limits(distance, angle, sigma_distance, sigma_angle):
    """Interval limits of the exact test, with slack for float32 storage."""
    slack_d = tol.LENGTH_SLACK_REL * max(distance, sigma_distance)
    lo_d = distance - sigma_distance - slack_d
    hi_d = distance + sigma_distance + slack_d
    return lo_d, hi_d, angle - sigma_angle - tol.ANGLE_SLACK, angle + sigma_angle + tol.ANGLE_SLACK


def bin_index(values, lo, width, p):
    """Hash functions t1, t2, t3 (eq. 4), clamped to [0, p-1] (erratum 2)."""
    t = np.floor((np.asarray(values, dtype=np.float64) - lo) / width)
    return np.clip(t, 0, p - 1).astype(np.int64)


def _flat_key(a, b, c, bins):
    _, p2, p3 = bins
    return (a * p2 + b) * p3 + c


@numba.njit(cache=True)
def _bin(value, lo, width, p):
    """Scalar hash function t (eq. 4), clamped to [0, p-1]."""
    t = np.floor((value - lo) / width)
    return int(min(max(t, 0.0), p - 1.0))


@numba.njit(cache=True)
def _gather(offsets, bins, mins, widths, dmax, dmin, alpha, alpha_hi, alpha_width, lo_d, hi_d, lo_a, hi_a):
    """Union of the admissible bins of eq. (5), then the exact interval test.

    Bins: a in [t1(Δ̃ - σ_Δ), p1 - 1], b in [0, t2(Δ̃ + σ_Δ)], c in [t3(α̃ - σ_α - w), t3(α̃ + σ_α)],
    w the widest stored angle interval (0 for facets).
    """
    p1, p2, p3 = bins[0], bins[1], bins[2]
    a0 = _bin(lo_d, mins[0], widths[0], p1)
    b1 = _bin(hi_d, mins[1], widths[1], p2)
    c0 = _bin(lo_a - alpha_width, mins[2], widths[2], p3)
    c1 = _bin(hi_a, mins[2], widths[2], p3)
    total = 0
    for a in range(a0, p1):
        for b in range(0, b1 + 1):
            base = (a * p2 + b) * p3
            total += offsets[base + c1 + 1] - offsets[base + c0]
    out = np.empty(total, np.int64)
    count = 0
    for a in range(a0, p1):
        for b in range(0, b1 + 1):
            base = (a * p2 + b) * p3
            for e in range(offsets[base + c0], offsets[base + c1 + 1]):
                if dmax[e] >= lo_d and dmin[e] <= hi_d and alpha_hi[e] >= lo_a and alpha[e] <= hi_a:
                    out[count] = e
                    count += 1
    return out[:count]


@numba.njit(cache=True)
def _query_all(offsets, bins, mins, widths, dmax, dmin, alpha, alpha_hi, alpha_width, k, l, h_kl, h_lk,
               distance, angle, h_ij, h_ji, sigma_h, sigma_d, sigma_a, use_direction, slack_rel, slack_angle):
    """:meth:`PairTable.query_pairs` for every finger pair; results concatenated."""
    parts_first = []
    parts_second = []
    bounds = np.zeros(len(distance) + 1, np.int64)
    for e in range(len(distance)):
        slack_d = slack_rel * max(distance[e], sigma_d)
        idx = _gather(offsets, bins, mins, widths, dmax, dmin, alpha, alpha_hi, alpha_width,
                      distance[e] - sigma_d - slack_d, distance[e] + sigma_d + slack_d,
                      angle[e] - sigma_a - slack_angle, angle[e] + sigma_a + slack_angle)
        first, second = _expand_ordered(k, l, idx, h_kl, h_lk, use_direction, h_ij[e], h_ji[e], sigma_h[e])
        parts_first.append(first)
        parts_second.append(second)
        bounds[e + 1] = bounds[e] + len(first)
    out_first = np.empty(bounds[-1], np.int64)
    out_second = np.empty(bounds[-1], np.int64)
    for e in range(len(distance)):
        out_first[bounds[e]:bounds[e + 1]] = parts_first[e]
        out_second[bounds[e]:bounds[e + 1]] = parts_second[e]
    return out_first, out_second, bounds


@numba.njit(cache=True)
def _within(value, interval, slack):
    return interval[0] - slack <= value <= interval[1] + slack


@numba.njit(cache=True)
def _expand_ordered(k, l, indices, h_kl, h_lk, use_direction, h_ij, h_ji, sigma_h):
    """(k, l) and, off the diagonal, (l, k) for each stored unordered pair,
    optionally kept only where the direction intervals admit (h_ij, h_ji)."""
    s = len(indices)
    first = np.empty(2 * s, np.int64)
    second = np.empty(2 * s, np.int64)
    count = 0
    for e in indices:
        if not use_direction or (_within(h_ij, h_kl[e], sigma_h) and _within(h_ji, h_lk[e], sigma_h)):
            first[count] = k[e]
            second[count] = l[e]
            count += 1
        if k[e] != l[e] and (not use_direction or (_within(h_ij, h_lk[e], sigma_h) and _within(h_ji, h_kl[e], sigma_h))):
            first[count] = l[e]
            second[count] = k[e]
            count += 1
    return first[:count], second[:count]
