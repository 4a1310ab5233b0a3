"""Hypotheses: admissible facet pairs S_ij (eq. 5) joined into n-tuples by the tree T (§3.2).

``S[(i, j)]`` holds the ordered facet pairs (k, l) admissible for fingers i < j:
finger i on facet k and finger j on facet l. The tree joins them into
hypotheses h = (γ_1, ..., γ_n), tuples that satisfy every finger pair.

Two joins give the same set:

* :func:`join_tuples`, the default: level by level, vectorized over all nodes,
  starting from the most selective finger pair.
* :func:`join_tuples_paper`: the paper's tree, node by node in finger order.
"""

from __future__ import annotations

import numba
import numpy as np

#: Membership tests use a dense bitmap up to this many facet pairs (bytes), else sorted keys.
BITMAP_MAX_CELLS = 16_000_000


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


def admissible_pairs(model, conditions, tolerance, bounds="exact", direction=True, patches=False):
    """S_ij for all finger pairs i < j (eq. 5 with ∪, then the exact interval test).

    direction : also apply the direction constraint (the default method; not the paper's);
    patches : over the model's patches instead of its facets.
    Returns dict (i, j) -> PairSet.
    """
    table, m = (model.patch_table, model.patches.count) if patches else (model.facet_table(), model.num_facets)
    first, second, cut = table.query_all(conditions, tolerance, bounds, direction)
    return {pair: PairSet(first[cut[e]:cut[e + 1]], second[cut[e]:cut[e + 1]], m)
            for e, pair in enumerate(conditions.pairs)}


def _pair(S, a, b):
    """(PairSet, reversed?) for fingers a, b in either order."""
    return (S[(a, b)], False) if a < b else (S[(b, a)], True)


def _contains(S, a, b, fa, fb):
    """Whether finger a on facet fa and finger b on fb is admissible. fa, fb : (r,) int."""
    pairs, rev = _pair(S, a, b)
    return pairs.contains(fb, fa) if rev else pairs.contains(fa, fb)


def _expand(S, a, f, facets_a):
    """All facets of finger f admissible with finger a on facets_a.

    facets_a : (r,) int. Returns (rows (q,) int into facets_a, facets_f (q,) int).
    """
    pairs, rev = _pair(S, a, f)
    indptr, targets = pairs.neighbours(reverse=rev)
    counts = indptr[facets_a + 1] - indptr[facets_a]
    rows = np.repeat(np.arange(len(facets_a)), counts)
    # position of each output within its row's neighbour list: 0..count-1
    starts = np.cumsum(counts) - counts
    within = np.arange(len(rows)) - np.repeat(starts, counts)
    return rows, targets[np.repeat(indptr[facets_a], counts) + within]


def triple_products(normals):
    """det[a, b, c] of three unit vectors. normals : (..., 3, 3) rows a, b, c -> (...)"""
    return np.linalg.det(normals)


def triple_tolerance(angle_bound):
    """Bound on |det[m_a, m_b, m_c] - det[n_a, n_b, n_c]| when each unit vector m is n tilted
    by at most ``angle_bound``: det is multilinear, |m - n| <= δ = 2 sin(angle/2), so the
    change is at most (1 + δ)³ - 1."""
    delta = 2.0 * np.sin(min(angle_bound, np.pi) / 2.0)
    return (1.0 + delta) ** 3 - 1.0


class TripleTest:
    """Handedness test for triples of fingers: pairwise angles cannot tell three normals
    from their mirror image, the triple product can.

    facet_normals : (m, 3); measured : (n, 3) measured object normals (-ñ);
    angle_bound : per-contact tilt bound (radians).
    """

    def __init__(self, facet_normals, measured, angle_bound):
        self.facet_normals = facet_normals
        self.measured = measured
        self.tol = triple_tolerance(angle_bound)

    def keep(self, tuples, assigned):
        """(r,) bool: tuples (r, c) whose every triple containing the last column passes.

        assigned : the finger of each column.
        """
        last = len(assigned) - 1
        cols = np.array([(a, b, last) for a in range(last) for b in range(a + 1, last)], dtype=np.int64)
        if len(cols) == 0:
            return np.ones(len(tuples), dtype=bool)
        want = triple_products(self.measured[np.asarray(assigned)[cols]])
        return _triples_within(self.facet_normals, tuples, cols, want, self.tol)


@numba.njit(cache=True)
def _det3(a, b, c):
    return (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
            + a[2] * (b[0] * c[1] - b[1] * c[0]))


@numba.njit(cache=True)
def _triples_within(normals, tuples, cols, want, tol):
    """Per row: all |det[n_a, n_b, n_c] - want| <= tol over the column triples ``cols``."""
    keep = np.ones(len(tuples), dtype=np.bool_)
    for r in range(len(tuples)):
        for t in range(len(cols)):
            got = _det3(normals[tuples[r, cols[t, 0]]], normals[tuples[r, cols[t, 1]]],
                        normals[tuples[r, cols[t, 2]]])
            if abs(got - want[t]) > tol:
                keep[r] = False
                break
    return keep


def join_tuples(S, n, triple=None):
    """All n-tuples admissible for every finger pair (the tree T), vectorized per level.

    S : dict (i, j) -> PairSet for i < j; triple : optional TripleTest applied to every
    triple of fingers as soon as it is placed. Returns (H, n) int64 in finger order.
    """
    start = min(S, key=lambda key: len(S[key]))
    assigned = list(start)
    tuples = np.stack([S[start].first, S[start].second], axis=1)
    while len(assigned) < n and len(tuples):
        # next finger and the assigned finger it is expanded from: the fewest candidate pairs
        f, a = min(((f, a) for f in range(n) if f not in assigned for a in assigned),
                   key=lambda fa: len(_pair(S, fa[1], fa[0])[0]))
        rows, new = _expand(S, a, f, tuples[:, assigned.index(a)])
        keep = np.ones(len(rows), dtype=bool)
        for b in assigned:
            if b != a:
                keep &= _contains(S, b, f, tuples[rows, assigned.index(b)], new)
        tuples = np.column_stack([tuples[rows[keep]], new[keep]])
        assigned.append(f)
        if triple is not None:
            tuples = tuples[triple.keep(tuples, assigned)]
    if len(assigned) < n:
        return np.empty((0, n), dtype=np.int64)
    return tuples[:, np.argsort(assigned)]


def join_tuples_paper(S, n):
    """The paper's tree T (§3.2, fig. 7): insert S_12, then grow each node in finger order.

    A node on level f (fingers 0..f-1 placed) gets a child γ_f for every facet that
    S_0f, ..., S_(f-1)f all admit with the node's ancestors. Returns (H, n) int64.
    """
    first = S[(0, 1)]
    paths = [[int(k), int(l)] for k, l in zip(first.first, first.second)]
    for f in range(2, n):
        grown = []
        for path in paths:
            children = None
            for a, facet in enumerate(path):
                indptr, targets = S[(a, f)].neighbours()
                allowed = targets[indptr[facet]:indptr[facet + 1]]
                children = allowed if children is None else np.intersect1d(children, allowed, assume_unique=True)
                if len(children) == 0:
                    break
            grown.extend(path + [int(c)] for c in children)
        paths = grown
    return np.array(paths, dtype=np.int64).reshape(-1, n)


def brute_force_tuples(S, n, m):
    """Reference twin: test every one of the m**n tuples against every S_ij. Small m only."""
    grid = np.stack(np.meshgrid(*[np.arange(m)] * n, indexing="ij"), axis=-1).reshape(-1, n)
    keep = np.ones(len(grid), dtype=bool)
    for (i, j) in S:
        keep &= _contains(S, i, j, grid[:, i], grid[:, j])
    return grid[keep]


def sorted_rows(tuples):
    """Rows in lexicographic order, so joins can be compared as sets. tuples : (H, n) int."""
    if len(tuples) == 0:
        return tuples
    return tuples[np.lexsort(tuples.T[::-1])]
