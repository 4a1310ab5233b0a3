"""Pair conditions and admissible facet pairs S_ij (§3.2, eq. 5).

The measured characteristics of every finger pair i < j (Δ̃_ij, α̃_ij and the signed
heights h_ij, h_ji of the direction constraint) query the model's pair table; ``S[(i, j)]``
holds the ordered facet pairs (k, l) admissible for finger i on facet k and finger j on l.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from itertools import combinations

import numpy as np

#: Membership tests use a dense bitmap up to this many facet pairs (bytes), else sorted keys.
BITMAP_MAX_CELLS = 16_000_000


@dataclass(frozen=True)
class PairConditions:
    """Δ̃_ij and α̃_ij for all finger pairs i < j.

    pairs : list of (i, j); distance, angle : (P,) float (angle in radians);
    h_ij, h_ji : (P,) float, signed distance of contact j from contact i's tangent
    plane, -ñ_iᵀ(x̃_j - x̃_i), and the reverse.
    """

    pairs: list
    distance: np.ndarray
    angle: np.ndarray
    h_ij: np.ndarray
    h_ji: np.ndarray


@lru_cache(maxsize=32)
def _finger_pairs(n):
    """All finger pairs i < j of n fingers: (list of (i, j), i (P,), j (P,))."""
    pairs = list(combinations(range(n), 2))
    i, j = np.array(pairs, dtype=np.int64).reshape(-1, 2).T
    return pairs, i, j


def pair_conditions(contacts, since=0):
    """Δ̃_ij = |x̃_j - x̃_i| and α̃_ij = arccos(ñ_i·ñ_j) for all i < j (§3, fig. 6) with
    j >= ``since`` (0: every pair; k: only the pairs of contacts k, k+1, ... with the others)."""
    pairs, i, j = _finger_pairs(contacts.n)
    if since:
        keep = j >= since
        pairs, i, j = [p for p, k in zip(pairs, keep) if k], i[keep], j[keep]
    nf, d = contacts.finger_normals, contacts.points[j] - contacts.points[i]
    distance = np.sqrt(np.einsum("ij,ij->i", d, d))
    cos = np.einsum("ij,ij->i", nf[i], nf[j])
    h_ij = -np.einsum("ij,ij->i", nf[i], d)
    h_ji = np.einsum("ij,ij->i", nf[j], d)
    return PairConditions(pairs, distance, np.arccos(np.clip(cos, -1.0, 1.0)), h_ij, h_ji)



class PairSet:
    """The admissible ordered pairs of one finger pair, indexed both ways.

    first, second : (s,) int facet indices; m : number of facets.
    """

    def __init__(self, first, second, m):
        self.first = np.asarray(first, dtype=np.int64)
        self.second = np.asarray(second, dtype=np.int64)
        self.m = m
        self._keys = None
        self._csr = {}

    def __len__(self):
        return len(self.first)

    def contains(self, a, b):
        """Whether each (a[r], b[r]) is in the set. a, b : (r,) int -> (r,) bool.

        A dense m×m bitmap answers when it is small, else binary search on sorted keys.
        """
        key = a * self.m + b
        if self.m * self.m <= BITMAP_MAX_CELLS:
            if self._keys is None:
                self._keys = np.zeros(self.m * self.m, dtype=bool)
                self._keys[self.first * self.m + self.second] = True
            return self._keys[key]
        if self._keys is None:
            self._keys = np.sort(self.first * self.m + self.second)
        if len(self._keys) == 0:
            return np.zeros(len(key), dtype=bool)
        pos = np.minimum(np.searchsorted(self._keys, key), len(self._keys) - 1)
        return self._keys[pos] == key

    def neighbours(self, reverse=False):
        """CSR adjacency (indptr (m+1,), targets) from first to second (or back)."""
        if reverse not in self._csr:
            src, dst = (self.second, self.first) if reverse else (self.first, self.second)
            order = np.lexsort((dst, src))
            indptr = np.zeros(self.m + 1, dtype=np.int64)
            np.cumsum(np.bincount(src, minlength=self.m), out=indptr[1:])
            self._csr[reverse] = (indptr, dst[order])
        return self._csr[reverse]


def admissible_pairs(model, conditions, tolerance, bounds="exact", direction=True, patches=False, edges=False):
    """S_ij for all finger pairs i < j (eq. 5 with ∪, then the exact interval test).

    direction : also apply the direction constraint (the default method; not the paper's);
    patches : over the model's patches instead of its facets; edges : over its facets, sharp
    edges and vertices (model.units).
    Returns dict (i, j) -> PairSet.
    """
    if edges:
        table, m = model.unit_table, len(model.units)
    else:
        table, m = (model.patch_table, model.patches.count) if patches else (model.facet_table(), model.num_facets)
    first, second, cut = table.query_all(conditions, tolerance, bounds, direction)
    S = PairSets({pair: PairSet(first[cut[e]:cut[e + 1]], second[cut[e]:cut[e + 1]], m)
                  for e, pair in enumerate(conditions.pairs)})
    S.flat = (first, second, cut)  # conditions.pairs is in sorted order
    return S


class PairSets(dict):
    """S_ij as a dict (i, j) -> PairSet, plus ``flat``: (first, second, (P + 1,) offsets),
    every finger pair's facet pairs concatenated in sorted pair order."""

    flat = None


def _pair(S, a, b):
    """(PairSet, reversed?) for fingers a, b in either order."""
    return (S[(a, b)], False) if a < b else (S[(b, a)], True)


def _contains(S, a, b, fa, fb):
    """Whether finger a on facet fa and finger b on fb is admissible. fa, fb : (r,) int."""
    pairs, rev = _pair(S, a, b)
    return pairs.contains(fb, fa) if rev else pairs.contains(fa, fb)
