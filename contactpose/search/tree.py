"""The tree T (§3.2): admissible facet pairs S_ij (search.pairs) joined into n-tuples.

The tree joins the pairs into hypotheses h = (γ_1, ..., γ_n), tuples that satisfy
every finger pair.

Two joins give the same set:

* :func:`join_tuples`, the default: level by level over all nodes in one compiled
  pass, starting from the most selective finger pair; each node expands from the placed
  finger with the fewest candidates, membership by binary search in sorted adjacency rows.
* :func:`join_tuples_paper`: the paper's tree, node by node in finger order.

:func:`extend_tuples` grows a tree of the first k fingers by more fingers, from the pairs
of the new fingers alone: the same set as :func:`join_tuples` over all of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import accumulate

import numba
import numpy as np

from contactpose.progress import progress_bar


@dataclass(frozen=True)
class SearchTree:
    """A complete tree T, kept so that more contacts can extend it (:func:`extend_tuples`).

    contacts : the Contacts it was grown for (world frame); tolerance : the Tolerance of its
    pair sets; units : "patches" or "facets", what ``tuples`` index; tuples : (H, n) int64,
    every admissible tuple, rows in lexicographic order (:func:`sorted_rows`).
    """

    contacts: object
    tolerance: object
    units: str
    tuples: np.ndarray


def tilt_chord(angle):
    """|m - n| = 2 sin(θ/2) for unit vectors θ apart (θ capped at π): the most a unit normal
    tilted by at most ``angle`` can move. angle : float or array."""
    return 2.0 * np.sin(np.minimum(angle, np.pi) / 2.0)


def triple_tolerance(angle_bound):
    """Bound on |det[m_a, m_b, m_c] - det[n_a, n_b, n_c]| when each unit vector m is n tilted
    by at most ``angle_bound``: det[m] - det[n] = det[m_a - n_a, m_b, m_c] + det[n_a, m_b - n_b,
    m_c] + det[n_a, n_b, m_c - n_c], each term at most |m - n| = δ = 2 sin(angle/2) by
    Hadamard's inequality (the other two vectors are unit), so the change is at most 3δ.
    :class:`TripleTest` sums the three δ of units tilted by different bounds."""
    return 3.0 * tilt_chord(angle_bound)


class TripleTest:
    """Handedness test for triples of fingers: pairwise angles cannot tell three normals
    from their mirror image, the triple product can.

    facet_normals : (m, 3) unit normals of the search units; measured : (n, 3) measured
    object normals (-ñ); angle_bound : per-contact tilt bound (radians); slack : (m,) extra
    tilt of each unit (a region's cone half-angle: its surface normals lie that far from
    its normal), or None. A triple passes when its determinants differ by at most the sum
    of its three units' chords δ (:func:`triple_tolerance`).
    """

    def __init__(self, facet_normals, measured, angle_bound, slack=None):
        self.facet_normals = facet_normals
        self.measured = measured
        extra = np.zeros(len(facet_normals)) if slack is None else np.asarray(slack, dtype=np.float64)
        self.delta = tilt_chord(angle_bound + extra)


@numba.njit(cache=True)
def _det3(a, b, c):
    return (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
            + a[2] * (b[0] * c[1] - b[1] * c[0]))


def join_tuples(S, n, triple=None, *, deadline=None, progress=None):
    """All n-tuples admissible for every finger pair (the tree T), level by level over all
    nodes, starting from the most selective finger pair.

    Each node places the next finger from the placed finger that admits the fewest facets
    for it, then tests the others by binary search in their sorted adjacency rows.
    S : dict (i, j) -> PairSet for i < j; triple : optional TripleTest applied to every
    triple of fingers as soon as it is placed. Returns (H, n) int64 in finger order, each
    node's children in ascending facet order.

    deadline : a progress.Deadline; the start nodes go through every level START_CHUNK at a
    time, and once it has passed (and some tuple is complete) the rest are left out, so a
    truncated answer of complete tuples comes back fast and ``deadline.hit`` says so.
    progress : show a bar (None: on a terminal, after a second).
    """
    pairs = sorted(S)
    pair_of = np.full((n, n), -1, dtype=np.int64)
    for e, (i, j) in enumerate(pairs):
        pair_of[i, j] = pair_of[j, i] = e
    order, _ = placement_order(S, n)
    m = S[pairs[0]].m
    first, second, cut = getattr(S, "flat", None) or _flat_pairs(S, pairs)
    normals, measured, delta = _triple_arrays(triple, n)
    e0 = pair_of[order[0], order[1]]
    if cut[e0 + 1] - cut[e0] <= START_CHUNK:  # one chunk: the whole tree in one compiled call
        return _join(first, second, cut, m, order, pair_of, normals, measured, delta)
    start = np.stack(_directed(first, second, cut, e0, order[0] < order[1]), axis=1).astype(np.int64).reshape(-1, 2)
    rows = [_level_adjacency(first, second, cut, m, order, pair_of, level) for level in range(2, n)]
    nodes = _grow_chunks(start, n, rows, order, (normals, measured, delta), deadline, progress, "start")
    out = np.empty((len(nodes), n), dtype=np.int64)
    out[:, order] = nodes
    return out


#: Start nodes (first finger pair) taken through every level at a time: the grain of the
#: deadline checks. Each start node's tuples are contiguous, so the order is the same.
START_CHUNK = 1024
#: Start nodes grown to estimate the size of a tree (expected_tuples).
ESTIMATE_SAMPLE = 256


def _grow_all(start, n, rows, order, normals, measured, delta):
    """Every complete tuple under the start nodes (K, k), k = n - len(rows) fingers placed:
    (H, n) int64 in placement order."""
    k = start.shape[1]
    nodes = np.zeros((len(start), n), dtype=np.int64)
    nodes[:, :k] = start
    count = len(nodes)
    for level, (indptr, targets) in enumerate(rows, start=k):
        if not count:
            break
        nodes, count = _grow(nodes, count, level, indptr, targets, order, normals, measured, delta)
    return nodes[:count]


def extend_tuples(tuples, S, n, triple=None, *, deadline=None, progress=None):
    """The tree of n fingers from the tree of its first k: every tuple (H, k) of ``tuples``
    grows by fingers k, ..., n-1 in turn, each kept where every placed finger admits it and
    every new triple passes, as in :func:`join_tuples`, whose set this is (a tuple admissible
    for all n fingers is admissible for the first k). S : dict (i, j) -> PairSet holding at
    least the pairs i < j with j >= k, the only ones queried. triple : TripleTest over all n
    fingers' measured normals. deadline, progress : as in :func:`join_tuples`, START_CHUNK
    tuples at a time. Returns (H', n) int64 in finger order, in the order of ``tuples``, each
    node's children in ascending facet order."""
    tuples = np.asarray(tuples, dtype=np.int64)
    k = tuples.shape[1]
    if k >= n:
        raise ValueError(f"a tree of {k} fingers cannot grow to {n}")
    pairs = sorted(p for p in S if p[1] >= k)
    pair_of = np.full((n, n), -1, dtype=np.int64)
    for e, (i, j) in enumerate(pairs):
        pair_of[i, j] = pair_of[j, i] = e
    first, second, cut = _flat_pairs(S, pairs)
    m, order = S[pairs[0]].m, np.arange(n, dtype=np.int64)
    normals, measured, delta = _triple_arrays(triple, n)
    rows = [_level_adjacency(first, second, cut, m, order, pair_of, level) for level in range(k, n)]
    return _grow_chunks(tuples, n, rows, order, (normals, measured, delta), deadline, progress, "node")


def _grow_chunks(start, n, rows, order, triple, deadline, progress, unit):
    """:func:`_grow_all` over the start nodes START_CHUNK at a time, until the deadline passes
    (once some tuple is complete); the bar counts ``unit``. -> (H, n) int64 in placement order"""
    parts = []
    with progress_bar(total=len(start), desc="tree", unit=unit, show=progress) as bar:
        for lo in range(0, len(start), START_CHUNK):
            if any(len(p) for p in parts) and deadline is not None and deadline.passed:
                break
            parts.append(_grow_all(start[lo:lo + START_CHUNK], n, rows, order, *triple))
            bar.update(min(START_CHUNK, len(start) - lo))
    return np.concatenate(parts) if parts else np.zeros((0, n), dtype=np.int64)


def _triple_arrays(triple, n):
    """(unit normals, measured normals, δ) of a TripleTest, contiguous; a pass-all stand-in for None."""
    if triple is None:
        return np.zeros((1, 3)), np.zeros((n, 3)), np.full(1, np.inf)
    return (np.ascontiguousarray(triple.facet_normals, dtype=np.float64),
            np.ascontiguousarray(triple.measured, dtype=np.float64), triple.delta)


def _level_adjacency(first, second, cut, m, order, pair_of, level):
    """CSR rows from every placed finger to finger order[level]: indptr (level, m + 1),
    targets (level, pairs)."""
    indptr = np.empty((level, m + 1), dtype=np.int64)
    targets = np.empty((level, max(int(cut[-1]), 1)), dtype=np.int64)
    for b in range(level):
        e = pair_of[order[b], order[level]]
        src, dst = _directed(first, second, cut, e, order[b] < order[level])
        _adjacency(src, dst, m, indptr[b], targets[b])
    return indptr, targets


def expected_tuples(S, n, triple=None, sample=ESTIMATE_SAMPLE):
    """Estimate of the tree's output size before it runs in full: the tree grown from
    ``sample`` of its start nodes (the first finger pair's facet pairs, drawn evenly with
    a fixed seed), scaled by their share. Unbiased; exact when there are no more start
    nodes than ``sample``. The pair sets are far from independent (geometry ties them),
    so their sizes alone would miss the count by orders of magnitude."""
    pairs = sorted(S)
    order, _ = placement_order(S, n)
    a, b = sorted(order[:2])
    starts = len(S[(a, b)])
    if starts <= sample:
        return float(len(join_tuples(S, n, triple)))
    keep = np.sort(np.random.default_rng(0).choice(starts, size=sample, replace=False))
    sub = {pair: S[pair] for pair in pairs}
    first = S[(a, b)]
    sub[(a, b)] = type(first)(first.first[keep], first.second[keep], first.m)
    return len(join_tuples(sub, n, triple)) * starts / sample


def _flat_pairs(S, pairs):
    """(first, second, (P + 1,) offsets): the facet pairs of ``pairs`` concatenated."""
    cut = np.zeros(len(pairs) + 1, dtype=np.int64)
    cut[1:] = list(accumulate(len(S[p]) for p in pairs))
    join = lambda arrays: np.concatenate(arrays + [np.empty(0, np.int64)]).astype(np.int64)
    return join([S[p].first for p in pairs]), join([S[p].second for p in pairs]), cut


def placement_order(S, n):
    """Fingers in the order the tree places them, and for each the position (in that
    order) of the placed finger it is expanded from: first the most selective pair, then
    always the (new, placed) finger pair with the fewest admissible facet pairs.
    Returns (order (n,) int64, parent (n,) int64; parent of the first two is -1)."""
    size = {pair: len(S[pair]) for pair in S}
    order, parent = list(min(size, key=size.get)), [-1, -1]
    while len(order) < n:
        best = (np.inf, -1, -1)  # (size, new finger, position of the placed one); ties: first
        for f in range(n):
            for b, a in enumerate(order if f not in order else ()):
                if size[(min(a, f), max(a, f))] < best[0]:
                    best = (size[(min(a, f), max(a, f))], f, b)
        order.append(best[1])
        parent.append(best[2])
    return np.array(order, dtype=np.int64), np.array(parent, dtype=np.int64)


@numba.njit(cache=True)
def _join(first, second, cut, m, order, pair_of, normals, measured, delta):
    """The whole tree T in one compiled pass (level by level over every node), for trees
    with at most START_CHUNK start nodes: as :func:`join_tuples`, without the chunks."""
    n = len(order)
    e0 = pair_of[order[0], order[1]]
    start_a, start_b = _directed(first, second, cut, e0, order[0] < order[1])
    nodes = np.zeros((len(start_a), n), dtype=np.int64)
    nodes[:, 0], nodes[:, 1] = start_a, start_b
    count = len(nodes)
    for level in range(2, n):
        indptr = np.empty((level, m + 1), dtype=np.int64)
        targets = np.empty((level, max(cut[-1], 1)), dtype=np.int64)
        for b in range(level):
            e = pair_of[order[b], order[level]]
            src, dst = _directed(first, second, cut, e, order[b] < order[level])
            _adjacency(src, dst, m, indptr[b], targets[b])
        nodes, count = _grow(nodes, count, level, indptr, targets, order, normals, measured, delta)
    out = np.empty((count, n), dtype=np.int64)
    for c in range(n):
        out[:, order[c]] = nodes[:count, c]
    return out


@numba.njit(cache=True)
def _directed(first, second, cut, e, forward):
    """Finger pair e's facet pairs as (from, to): (first, second), or reversed."""
    a, b = first[cut[e]:cut[e + 1]], second[cut[e]:cut[e + 1]]
    return (a, b) if forward else (b, a)


@numba.njit(cache=True)
def _adjacency(src, dst, m, indptr, targets):
    """CSR adjacency src -> dst into indptr (m + 1,) and targets (first len(src) entries),
    each row in ascending order: counting sort by dst, then a stable one by src."""
    s = len(src)
    by_dst = np.empty(s, dtype=np.int64)
    pos = np.zeros(m + 1, dtype=np.int64)
    for q in range(s):
        pos[dst[q] + 1] += 1
    for f in range(m):
        pos[f + 1] += pos[f]
    for q in range(s):
        by_dst[pos[dst[q]]] = q
        pos[dst[q]] += 1
    indptr[:] = 0
    for q in range(s):
        indptr[src[q] + 1] += 1
    for f in range(m):
        indptr[f + 1] += indptr[f]
    pos[:m] = indptr[:m]
    for q in by_dst:
        targets[pos[src[q]]] = dst[q]
        pos[src[q]] += 1


@numba.njit(cache=True)
def _grow(nodes, count, level, indptr, targets, order, normals, measured, delta):
    """Place finger order[level] under every node: each facet that the placed finger with
    the fewest candidates admits, kept if every other placed finger admits it too (binary
    search in its sorted row) and every new triple passes."""
    want = _measured_triples(measured, order, level)
    test = delta[0] < np.inf
    out = np.empty((max(count, 16), nodes.shape[1]), dtype=np.int64)
    k = 0
    for r in range(count):
        a, fewest = 0, np.iinfo(np.int64).max
        for b in range(level):
            size = indptr[b, nodes[r, b] + 1] - indptr[b, nodes[r, b]]
            if size < fewest:
                a, fewest = b, size
        for q in range(indptr[a, nodes[r, a]], indptr[a, nodes[r, a] + 1]):
            facet = targets[a, q]
            if not _admitted(nodes[r], facet, level, a, indptr, targets):
                continue
            if test and not _triples_pass(normals, nodes[r], facet, level, want, delta):
                continue
            if k == len(out):
                out = _doubled(out)
            out[k, :level] = nodes[r, :level]
            out[k, level] = facet
            k += 1
    return out, k


@numba.njit(cache=True)
def _admitted(node, facet, level, skip, indptr, targets):
    """Whether every placed finger but ``skip`` admits the new finger on ``facet``."""
    for b in range(level):
        if b == skip:
            continue
        lo, hi = indptr[b, node[b]], indptr[b, node[b] + 1]
        pos = lo + np.searchsorted(targets[b, lo:hi], facet)
        if pos == hi or targets[b, pos] != facet:
            return False
    return True


@numba.njit(cache=True)
def _measured_triples(measured, order, level):
    """det[ñ_a, ñ_b, ñ_new] of the measured normals for placed pairs a < b (row-major)."""
    want = np.empty(level * (level - 1) // 2)
    t = 0
    for a in range(level):
        for b in range(a + 1, level):
            want[t] = _det3(measured[order[a]], measured[order[b]], measured[order[level]])
            t += 1
    return want


@numba.njit(cache=True)
def _triples_pass(normals, node, facet, level, want, delta):
    t = 0
    for a in range(level):
        for b in range(a + 1, level):
            tol = delta[node[a]] + delta[node[b]] + delta[facet]
            if abs(_det3(normals[node[a]], normals[node[b]], normals[facet]) - want[t]) > tol:
                return False
            t += 1
    return True


@numba.njit(cache=True)
def _doubled(a):
    out = np.empty((2 * len(a), a.shape[1]), dtype=a.dtype)
    out[:len(a)] = a
    return out


def join_tuples_paper(S, n, *, deadline=None, progress=None):
    """The paper's tree T (§3.2, fig. 7): insert S_12, then grow each node in finger order.

    A node on level f (fingers 0..f-1 placed) gets a child γ_f for every facet that
    S_0f, ..., S_(f-1)f all admit with the node's ancestors. Returns (H, n) int64.
    deadline, progress : as in :func:`join_tuples`, PAPER_START_CHUNK start paths at a time.
    """
    first = S[(0, 1)]
    starts = [[int(k), int(l)] for k, l in zip(first.first, first.second)]
    done = []
    with progress_bar(total=len(starts), desc="paper tree", unit="start", show=progress) as bar:
        for lo in range(0, len(starts), PAPER_START_CHUNK):
            if done and deadline is not None and deadline.passed:
                break
            paths = starts[lo:lo + PAPER_START_CHUNK]
            for f in range(2, n):
                paths = [path + [int(c)] for path in paths for c in _paper_children(S, path, f)]
            done.extend(paths)
            bar.update(len(starts[lo:lo + PAPER_START_CHUNK]))
    return np.array(done, dtype=np.int64).reshape(-1, n)


#: Start paths of the paper's tree taken through every level at a time.
PAPER_START_CHUNK = 64


def _paper_children(S, path, f):
    """Facets for finger f that every placed finger of ``path`` admits."""
    children = None
    for a, facet in enumerate(path):
        indptr, targets = S[(a, f)].neighbours()
        allowed = targets[indptr[facet]:indptr[facet + 1]]
        children = allowed if children is None else np.intersect1d(children, allowed, assume_unique=True)
        if len(children) == 0:
            break
    return children


def sorted_rows(tuples):
    """Rows in lexicographic order, so joins can be compared as sets. tuples : (H, n) int."""
    if len(tuples) == 0:
        return tuples
    return tuples[np.lexsort(tuples.T[::-1])]
