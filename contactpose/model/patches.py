"""Patches: connected facets of (nearly) one plane, searched as one unit.

A flat region made of many facets makes the facet-level tree explode: four
contacts on one face of a box admit every tuple of its facets. A patch is a
connected set of valid facets whose normals lie within ``tol_deg`` of the
patch's first facet (``tol_deg=0``: exactly coplanar). The pair table over
patches stores *interval* bounds, each containing the union of its member facet
pairs' intervals (Δmin, Δmax, [α_min, α_max], direction intervals), so a search
over patches admits every tuple the facet-level search admits: it stays complete.
It is built patch pair by patch pair (:class:`PatchPairs`), never through a table
of facet pairs (research/scale.md).
A hypothesis over patches is expanded to facets where the pose needs them:
each contact takes the member facet nearest to it (research/design.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from contactpose.geometry.kernels import _t, _triangle_triangle_d2
from contactpose.io.modelfile import STORED_PATCHES, check_arrays, check_pointers
from contactpose.model.features import NearPairs, PairFeatures, round_down32, round_up32
from contactpose.progress import progress_bar

#: Normals closer than this (radians) count as exactly parallel for tol_deg = 0.
COPLANAR_ANGLE = 1e-9
#: The default method searches patches when they number at most this fraction of the
#: valid facets. Measured on the scanned 6,767-facet espresso mesh (research/scale.md):
#: at 0.61 patches build 1.7x and search 3.5x faster (median); at 0.74 build and median
#: search tie and the p95 is worse; at 0.87 the patch build costs 1.3x more for no gain.
PATCH_GAIN = 0.65


@dataclass
class Patches:
    """A partition of the valid facets into patches.

    labels : (m,) int, the patch of each facet (-1 for degenerate facets);
    normals : (p, 3) area-weighted unit normals; offsets : (p,) plane offsets through the
    area-weighted centroid centres : (p, 3); cone : (p,) largest angle (radians) of a member normal from
    the patch normal; indptr (p + 1,), members : facets of each patch in CSR form;
    tol_deg : the tolerance they were grown with.
    """

    labels: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    centres: np.ndarray
    cone: np.ndarray
    indptr: np.ndarray
    members: np.ndarray
    tol_deg: float

    @property
    def count(self):
        return len(self.normals)

    @property
    def worthwhile(self):
        """True when patches shrink the search: at most PATCH_GAIN of the valid facets."""
        return self.count <= PATCH_GAIN * len(self.members)

    def of(self, patch):
        """Member facets of one patch, (k,) int."""
        return self.members[self.indptr[patch]:self.indptr[patch + 1]]

    def to_arrays(self):
        return {"labels": self.labels, "normals": self.normals, "offsets": self.offsets, "centres": self.centres,
                "cone": self.cone, "indptr": self.indptr, "members": self.members, "tol_deg": np.array(self.tol_deg)}

    @classmethod
    def from_arrays(cls, a, sizes=None, prefix="patches_", values=True):
        """Patches of a model file. a : their arrays; sizes : sizes known already, as
        {"m": (facets, array that says so)}; prefix : of their names in the file (for messages);
        values : scan the values too (io.modelfile.check_arrays)."""
        sizes = {} if sizes is None else sizes
        check_arrays(a, STORED_PATCHES, sizes, prefix, values=values)
        check_pointers(prefix + "indptr", a["indptr"], len(a["members"]))
        return cls(a["labels"], a["normals"], a["offsets"], a["centres"], a["cone"], a["indptr"], a["members"],
                   float(a["tol_deg"]))


def find_patches(merged, planes, tol_deg):
    """Grow patches over edge adjacency in facet order (deterministic).

    merged : trimesh.Trimesh with coincident vertices merged (face order as the model's);
    planes : FacetPlanes; tol_deg >= 0.
    """
    adjacency = np.asarray(merged.face_adjacency, dtype=np.int64).reshape(-1, 2)
    m = len(merged.faces)
    nbr_ptr = np.zeros(m + 1, dtype=np.int64)
    both = np.concatenate([adjacency, adjacency[:, ::-1]])
    both = both[np.lexsort((both[:, 1], both[:, 0]))]
    np.cumsum(np.bincount(both[:, 0], minlength=m), out=nbr_ptr[1:])
    cos_tol = np.cos(max(np.radians(tol_deg), COPLANAR_ANGLE))
    labels = _grow(nbr_ptr, both[:, 1], planes.normals, planes.valid, cos_tol)
    return _summarise(labels, planes, merged.triangles.mean(axis=1), tol_deg)


@numba.njit(cache=True)
def _grow(nbr_ptr, nbr, normals, valid, cos_tol):
    """Breadth-first region growing: a facet joins its neighbour's patch when its normal is
    within the tolerance of the patch's seed normal."""
    m = len(valid)
    labels = -np.ones(m, dtype=np.int64)
    queue = np.empty(m, dtype=np.int64)
    count = 0
    for seed in range(m):
        if not valid[seed] or labels[seed] >= 0:
            continue
        labels[seed] = count
        head, tail = 0, 1
        queue[0] = seed
        while head < tail:
            f = queue[head]
            head += 1
            for e in range(nbr_ptr[f], nbr_ptr[f + 1]):
                g = nbr[e]
                if valid[g] and labels[g] < 0 and normals[g] @ normals[seed] >= cos_tol:
                    labels[g] = count
                    queue[tail] = g
                    tail += 1
        count += 1
    return labels


def _summarise(labels, planes, centroids, tol_deg):
    """Patch planes (area-weighted), cones and member lists from the labels. centroids : (m, 3)"""
    valid = labels >= 0
    p = int(labels.max()) + 1
    lab, area = labels[valid], planes.areas[valid]
    sums = np.zeros((p, 3))
    np.add.at(sums, lab, planes.normals[valid] * area[:, None])
    normals = sums / np.linalg.norm(sums, axis=1, keepdims=True)
    centre = np.zeros((p, 3))
    np.add.at(centre, lab, centroids[valid] * area[:, None])
    centre /= np.bincount(lab, area, minlength=p)[:, None]
    offsets = -np.einsum("ij,ij->i", normals, centre)  # plane through the area-weighted centroid
    cos = np.clip(np.einsum("ij,ij->i", planes.normals[valid], normals[lab]), -1.0, 1.0)
    cone = np.zeros(p)
    np.maximum.at(cone, lab, np.arccos(cos))
    order = np.argsort(labels, kind="stable")[np.count_nonzero(~valid):]
    indptr = np.zeros(p + 1, dtype=np.int64)
    np.cumsum(np.bincount(lab, minlength=p), out=indptr[1:])
    return Patches(labels, normals, offsets, centre, cone, indptr, order, float(tol_deg))


def patch_features(facet_features, patches):
    """Pair features over patches, each the exact union of its member facet pairs' intervals:
    the reference for :func:`patch_pair_features`. facet_features : PairFeatures (exact bounds)."""
    f, p = facet_features, patches.count
    acc = _empty_accumulators(p)
    _reduce(acc, patches.labels, p, f.k, f.l, f.dmax, f.dmin_exact, f.alpha, f.h_kl, f.h_lk)
    present = np.flatnonzero(np.isfinite(acc[:, 0]))
    pk, pl = _unrank(present, p)
    acc = acc[present].astype(np.float32)
    return PairFeatures(k=pk.astype(np.int32), l=pl.astype(np.int32), dmax=acc[:, 1], dmin_vertex=acc[:, 0],
                        dmin_exact=acc[:, 0], alpha=acc[:, 2], h_kl=acc[:, 4:6].copy(),
                        h_lk=acc[:, 6:8].copy(), alpha_hi=acc[:, 3])


def _empty_accumulators(p):
    """Columns Δmin, Δmax, α_lo, α_hi, h_PQ lo/hi, h_QP lo/hi, as identities of min/max."""
    acc = np.empty((p * (p + 1) // 2, 8))
    acc[:, 0::2] = np.inf
    acc[:, 1::2] = -np.inf
    return acc


@numba.njit(cache=True)
def _reduce(acc, labels, p, k, l, dmax, dmin, alpha, h_kl, h_lk):
    """Fold facet pairs into the dense patch-pair accumulators (P <= Q); see _empty_accumulators."""
    for e in range(len(k)):
        a, b = labels[k[e]], labels[l[e]]
        fwd, back = h_kl[e], h_lk[e]
        if a > b:
            a, b = b, a
            fwd, back = back, fwd
        r = a * p - a * (a - 1) // 2 + (b - a)
        acc[r, 0] = min(acc[r, 0], dmin[e])
        acc[r, 1] = max(acc[r, 1], dmax[e])
        acc[r, 2] = min(acc[r, 2], alpha[e])
        acc[r, 3] = max(acc[r, 3], alpha[e])
        _widen(acc, r, 4, fwd)
        _widen(acc, r, 6, back)
        if a == b:  # either finger may sit on either member: both orientations
            _widen(acc, r, 4, back)
            _widen(acc, r, 6, fwd)


@numba.njit(cache=True)
def _widen(acc, r, col, interval):
    acc[r, col] = min(acc[r, col], interval[0])
    acc[r, col + 1] = max(acc[r, col + 1], interval[1])


def _unrank(rank, p):
    """Upper-triangle rank (row-major, diagonal included) -> (P, Q) with P <= Q."""
    starts = np.arange(p) * p - np.arange(p) * (np.arange(p) - 1) // 2
    a = np.searchsorted(starts, rank, side="right") - 1
    return a, a + (rank - starts[a])


@dataclass
class MemberGroups:
    """The members of each region (patch, or one facet) in Morton order, in runs of at most
    GROUP_FACETS nearby facets, each run with a sphere holding its vertices: a query near one
    part of a large region (a box face of a thousand facets) skips the runs whose sphere
    rules them out instead of testing every member.

    indptr (r + 1,), members (M,) : each region's member facets, Morton order within it;
    grp_ptr (r + 1,) : each region's runs; grp_mem (g + 1,) : where each run starts in
    ``members``; centre (g, 3), radius (g,) : the runs' spheres; spread (g,) : the largest
    facet sphere radius (centroid to farthest vertex) in each run.
    """

    indptr: np.ndarray
    members: np.ndarray
    grp_ptr: np.ndarray
    grp_mem: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    spread: np.ndarray

    @classmethod
    def of(cls, triangles, facet_radii, patches=None, run=None):
        """triangles : (m, 3, 3); facet_radii : (m,); patches : Patches, or None for one region
        per facet; run : facets per run (default GROUP_FACETS)."""
        run = GROUP_FACETS if run is None else run
        if patches is None:
            m = len(triangles)
            members, indptr = np.arange(m, dtype=np.int64), np.arange(m + 1, dtype=np.int64)
        else:
            members, indptr = _morton_members(triangles, patches), patches.indptr.astype(np.int64)
        sizes = np.diff(indptr)
        grp_ptr = np.concatenate([[0], np.cumsum(-(-sizes // run))]).astype(np.int64)
        starts = [np.arange(s, e, run) for s, e in zip(indptr[:-1], indptr[1:])]
        grp_mem = np.concatenate(starts + [[len(members)]]).astype(np.int64)
        centre, radius = _spheres(triangles[members].reshape(-1, 3), 3 * grp_mem)
        spread = np.maximum.reduceat(facet_radii[members], grp_mem[:-1]) if len(members) else np.zeros(0)
        return cls(indptr, members, grp_ptr, grp_mem, centre, radius, spread)


# ------------------------------------------------- patch-first pair features ---
#
# The pair table over patches, built patch pair by patch pair without visiting facet
# pairs through the exact triangle distance: Δmax, α and the direction intervals come
# exactly from the members' vertices and planes (cheap products), and Δmin from a branch
# and bound that computes exact triangle distances only where the cheap lower bounds
# (plane separation, bounding spheres) are further than DMIN_GAP_REL · diameter below the
# closest vertex pair. Every stored interval contains the union of its member pairs'.

#: The stored patch-pair Δmin lies within this fraction of the diameter below the exact
#: minimum over member facet pairs (never above it).
DMIN_GAP_REL = 1e-4
#: Member facets per group in the Δmin branch and bound.
GROUP_FACETS = 16
#: Member-pair work per chunk of patch pairs (one progress-bar step).
CHUNK_WORK = 100_000_000


@dataclass
class PatchLayout:
    """Patch members in a spatially coherent order, split into groups, with each patch's
    distinct vertices and bounding spheres of facets, groups and patches.

    mem_ptr (p + 1,), mem : member facets per patch (Morton order); grp_ptr (p + 1,) : the
    groups of each patch; grp_mem (g + 1,) : their runs in ``mem``; vtx_ptr (p + 1,),
    vtx (V, 3) : distinct vertex positions per patch; *_centre, *_radius : spheres holding
    every vertex of a facet (indexed by facet), a group and a patch.
    """

    mem_ptr: np.ndarray
    mem: np.ndarray
    grp_ptr: np.ndarray
    grp_mem: np.ndarray
    grp_centre: np.ndarray
    grp_radius: np.ndarray
    vtx_ptr: np.ndarray
    vtx: np.ndarray
    facet_centre: np.ndarray
    facet_radius: np.ndarray
    centre: np.ndarray
    radius: np.ndarray

    @classmethod
    def of(cls, triangles, patches):
        """triangles : (m, 3, 3) float; patches : Patches."""
        lab = patches.labels
        mem = _morton_members(triangles, patches)
        sizes = np.diff(patches.indptr)
        grp_ptr = np.concatenate([[0], np.cumsum(-(-sizes // GROUP_FACETS))])
        grp_mem = np.concatenate([np.arange(s, e, GROUP_FACETS) for s, e in zip(patches.indptr[:-1], patches.indptr[1:])]
                                 + [[len(mem)]]).astype(np.int64)
        vtx_ptr, vtx = _patch_vertices(triangles, lab, patches.count)
        fc, fr = _spheres(triangles.reshape(-1, 3), np.arange(0, 3 * len(triangles) + 1, 3))
        gc, gr = _spheres(triangles[mem].reshape(-1, 3), 3 * grp_mem)
        pc, pr = _spheres(vtx, vtx_ptr)
        return cls(patches.indptr, mem, grp_ptr, grp_mem, gc, gr, vtx_ptr, vtx, fc, fr, pc, pr)

    def work(self, a, b):
        """Estimated member-level operations of patch pairs (a, b). a, b : (n,) int."""
        na, nb = np.diff(self.mem_ptr)[a], np.diff(self.mem_ptr)[b]
        va, vb = np.diff(self.vtx_ptr)[a], np.diff(self.vtx_ptr)[b]
        return na * nb + va * vb + na * vb + nb * va + 64


def _morton_members(triangles, patches):
    """Members of each patch sorted by the Morton code of their centroids (10 bits per axis),
    so consecutive members are near each other. -> (M,) int64"""
    c = triangles[patches.members].mean(axis=1)
    lo, span = c.min(axis=0), np.ptp(c, axis=0).max()
    q = np.clip((c - lo) / (span if span > 0 else 1.0) * 1023, 0, 1023).astype(np.uint64)
    code = np.zeros(len(c), dtype=np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    order = np.lexsort((code, patches.labels[patches.members]))
    return patches.members[order].astype(np.int64)


def _patch_vertices(triangles, labels, p):
    """Distinct vertex positions of each patch. -> vtx_ptr (p + 1,), vtx (V, 3)"""
    valid = labels >= 0
    corners = triangles[valid].reshape(-1, 3)
    uniq, inv = np.unique(corners, axis=0, return_inverse=True)
    key = np.unique(np.repeat(labels[valid], 3).astype(np.int64) * len(uniq) + inv.ravel())
    vtx_ptr = np.concatenate([[0], np.cumsum(np.bincount(key // len(uniq), minlength=p))])
    return vtx_ptr, uniq[key % len(uniq)]


def patch_spheres(triangles, patches):
    """Bounding spheres of the patches, as :class:`PatchLayout` has them, without the layout:
    the same corner positions give the same box centres and farthest points.
    -> centres (p, 3), radii (p,)"""
    return _spheres(triangles[patches.members].reshape(-1, 3), 3 * patches.indptr)


def _spheres(points, ptr):
    """Bounding spheres (bounding-box centre, farthest point) of runs points[ptr[i]:ptr[i+1]]."""
    lo = np.minimum.reduceat(points, ptr[:-1], axis=0)
    hi = np.maximum.reduceat(points, ptr[:-1], axis=0)
    centre = 0.5 * (lo + hi)
    d = np.linalg.norm(points - np.repeat(centre, np.diff(ptr), axis=0), axis=1)
    return centre, np.maximum.reduceat(d, ptr[:-1])


class PatchPairs:
    """The patch-pair features of a model, built patch pair by patch pair.

    triangles : (m, 3, 3) float; planes : FacetPlanes; patches : Patches; diameter : float;
    max_span : keep only pairs with Δmin <= max_span (None: all pairs). The candidate pairs
    (``count`` of them) are listed first, so the memory they need is known before building.
    """

    def __init__(self, triangles, planes, patches, diameter, max_span=None):
        self.triangles, self.planes, self.max_span = triangles, planes, max_span
        self.gap = DMIN_GAP_REL * diameter
        self.layout = PatchLayout.of(triangles, patches)
        self.a, self.b = _candidates(self.layout, max_span)

    @property
    def count(self):
        """Candidate patch pairs P <= Q (bounding spheres within the span)."""
        return len(self.a)

    def features(self, progress=None):
        """PairFeatures over patch pairs (P <= Q), each interval containing the union of its
        member facet pairs' (Δmin within DMIN_GAP_REL · diameter below exact, never above).
        progress : tqdm bar (None: on a terminal once the work has taken a second)."""
        lay, a, b = self.layout, self.a, self.b
        work = lay.work(a, b)
        total = int(work.sum())
        order = np.random.default_rng(0).permutation(len(a))  # spreads the costly pairs over threads
        cuts = np.searchsorted(np.cumsum(work[order]), np.arange(CHUNK_WORK, total, CHUNK_WORK))
        del work
        out = _PatchPairOutput(len(a))
        with progress_bar(total=len(a), desc="patch pairs", unit="patch pair", show=progress) as bar:
            for idx in np.split(order, cuts):
                raw = np.empty((len(idx), 8))
                _patch_pair_kernel(a[idx], b[idx], lay.mem_ptr, lay.mem, lay.grp_ptr, lay.grp_mem, lay.grp_centre,
                                   lay.grp_radius, lay.vtx_ptr, lay.vtx, lay.facet_centre, lay.facet_radius,
                                   self.triangles, self.planes.normals, self.planes.offsets, self.gap, raw)
                out.put(idx, raw)
                bar.update(len(idx))
        if self.max_span is None:
            return out.features(a, b, slice(None))
        return out.features(a, b, np.flatnonzero(out.dmin <= self.max_span))


def _candidates(layout, max_span):
    """Patch pairs P <= Q whose bounding spheres come within max_span (all for None). -> (a, b) int32"""
    p = len(layout.radius)
    if max_span is None:
        counts = p - np.arange(p)
        a = np.repeat(np.arange(p, dtype=np.int32), counts)
        first = np.repeat(np.cumsum(counts) - counts, counts)
        return a, (np.arange(len(a)) - first + a).astype(np.int32)
    return NearPairs(layout.centre, layout.radius, max_span).all_rows()


class _PatchPairOutput:
    """float32 patch-pair features, rounded outward as the chunks arrive."""

    def __init__(self, n):
        self.dmin, self.dmax = np.empty(n, np.float32), np.empty(n, np.float32)
        self.alpha, self.alpha_hi = np.empty(n, np.float32), np.empty(n, np.float32)
        self.h_kl, self.h_lk = np.empty((n, 2), np.float32), np.empty((n, 2), np.float32)

    def put(self, idx, raw):
        """raw : (len(idx), 8) float64 columns Δmin, Δmax, cos max, cos min, h_PQ lo/hi, h_QP lo/hi."""
        self.dmin[idx] = round_down32(raw[:, 0])
        self.dmax[idx] = round_up32(raw[:, 1])
        self.alpha[idx] = round_down32(np.arccos(np.clip(raw[:, 2], -1.0, 1.0)))
        self.alpha_hi[idx] = round_up32(np.arccos(np.clip(raw[:, 3], -1.0, 1.0)))
        for col, h in ((4, self.h_kl), (6, self.h_lk)):
            h[idx, 0], h[idx, 1] = round_down32(raw[:, col]), round_up32(raw[:, col + 1])

    def features(self, a, b, keep):
        dmin = self.dmin[keep]
        return PairFeatures(k=a[keep], l=b[keep], dmax=self.dmax[keep], dmin_vertex=dmin, dmin_exact=dmin,
                            alpha=self.alpha[keep], h_kl=self.h_kl[keep], h_lk=self.h_lk[keep],
                            alpha_hi=self.alpha_hi[keep])


@numba.njit(cache=True, parallel=True)
def _patch_pair_kernel(a, b, mem_ptr, mem, grp_ptr, grp_mem, grp_centre, grp_radius, vtx_ptr, vtx,
                       facet_centre, facet_radius, tri, normals, offsets, gap, out):
    """Features of patch pairs (a[i], b[i]) into out[i] (see _PatchPairOutput.put)."""
    for i in numba.prange(len(a)):
        p, q = a[i], b[i]
        lo2, hi2 = _vertex_range(vtx, vtx_ptr, p, q)
        out[i, 2], out[i, 3] = _cos_range(normals, mem, mem_ptr, p, q)
        out[i, 4], out[i, 5] = _plane_range(normals, offsets, mem, mem_ptr, p, vtx, vtx_ptr, q)
        out[i, 6], out[i, 7] = _plane_range(normals, offsets, mem, mem_ptr, q, vtx, vtx_ptr, p)
        out[i, 1] = np.sqrt(hi2)
        best = np.sqrt(lo2)
        # every point of Q lies at least this far from every member plane of P, and back
        floor = max(0.0, out[i, 4], -out[i, 5], out[i, 6], -out[i, 7])
        if best - floor > gap:
            floor = max(floor, _dmin_search(p, q, best, gap, grp_ptr, grp_mem, grp_centre, grp_radius, mem,
                                            facet_centre, facet_radius, tri, normals, offsets))
        out[i, 0] = min(floor, best)


@numba.njit(cache=True)
def _vertex_range(vtx, vtx_ptr, p, q):
    """Smallest and largest squared distance between a vertex of patch p and one of q."""
    lo, hi = np.inf, 0.0
    for u in range(vtx_ptr[p], vtx_ptr[p + 1]):
        x0, x1, x2 = vtx[u, 0], vtx[u, 1], vtx[u, 2]
        for v in range(vtx_ptr[q], vtx_ptr[q + 1]):
            d = (vtx[v, 0] - x0) ** 2 + (vtx[v, 1] - x1) ** 2 + (vtx[v, 2] - x2) ** 2
            lo = min(lo, d)
            hi = max(hi, d)
    return lo, hi


@numba.njit(cache=True)
def _cos_range(normals, mem, mem_ptr, p, q):
    """Largest and smallest n_kᵀn_l over member facets k of p and l of q."""
    hi, lo = -np.inf, np.inf
    for e in range(mem_ptr[p], mem_ptr[p + 1]):
        k = mem[e]
        n0, n1, n2 = normals[k, 0], normals[k, 1], normals[k, 2]
        for f in range(mem_ptr[q], mem_ptr[q + 1]):
            l = mem[f]
            c = n0 * normals[l, 0] + n1 * normals[l, 1] + n2 * normals[l, 2]
            hi = max(hi, c)
            lo = min(lo, c)
    return hi, lo


@numba.njit(cache=True)
def _plane_range(normals, offsets, mem, mem_ptr, p, vtx, vtx_ptr, q):
    """[min, max] of n_kᵀx + d_k over member facets k of p and vertices x of q."""
    lo, hi = np.inf, -np.inf
    for e in range(mem_ptr[p], mem_ptr[p + 1]):
        k = mem[e]
        n0, n1, n2, d = normals[k, 0], normals[k, 1], normals[k, 2], offsets[k]
        for v in range(vtx_ptr[q], vtx_ptr[q + 1]):
            s = n0 * vtx[v, 0] + n1 * vtx[v, 1] + n2 * vtx[v, 2] + d
            lo = min(lo, s)
            hi = max(hi, s)
    return lo, hi


@numba.njit(cache=True)
def _sphere_gap(c, r, i, d, s, j):
    """Lower bound on the distance between what spheres (c[i], r[i]) and (d[j], s[j]) hold."""
    return np.sqrt((c[i, 0] - d[j, 0]) ** 2 + (c[i, 1] - d[j, 1]) ** 2 + (c[i, 2] - d[j, 2]) ** 2) - r[i] - s[j]


@numba.njit(cache=True)
def _plane_gap(tri, normals, offsets, k, l):
    """Distance by which facet l lies wholly on one side of facet k's plane (0 if it crosses)."""
    lo, hi = np.inf, -np.inf
    for v in range(3):
        s = normals[k, 0] * tri[l, v, 0] + normals[k, 1] * tri[l, v, 1] + normals[k, 2] * tri[l, v, 2] + offsets[k]
        lo = min(lo, s)
        hi = max(hi, s)
    return max(0.0, lo, -hi)


@numba.njit(cache=True)
def _separation(tri, normals, offsets, centre, k, l):
    """Lower bound on the distance between facets k and l: their separation along either
    facet's normal and along the line through their centres (projections shrink distances)."""
    u0, u1, u2 = centre[l, 0] - centre[k, 0], centre[l, 1] - centre[k, 1], centre[l, 2] - centre[k, 2]
    norm = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    axis = 0.0
    if norm > 0.0:
        top, bottom = -np.inf, np.inf
        for v in range(3):
            top = max(top, (u0 * tri[k, v, 0] + u1 * tri[k, v, 1] + u2 * tri[k, v, 2]) / norm)
            bottom = min(bottom, (u0 * tri[l, v, 0] + u1 * tri[l, v, 1] + u2 * tri[l, v, 2]) / norm)
        axis = bottom - top
    return max(axis, _plane_gap(tri, normals, offsets, k, l), _plane_gap(tri, normals, offsets, l, k))


@numba.njit(cache=True)
def _dmin_search(p, q, best, gap, grp_ptr, grp_mem, gc, gr, mem, fc, fr, tri, normals, offsets):
    """Branch and bound over group pairs, then member pairs, of patches p and q: a lower
    bound on the exact member-pair Δmin, at least min(exact, best) - gap. best : an upper bound."""
    g0, g1, h0, h1 = grp_ptr[p], grp_ptr[p + 1], grp_ptr[q], grp_ptr[q + 1]
    nh = h1 - h0
    if (g1 - g0) * nh == 1:  # one group each: no ordering to do
        best, floor = _group_pair(g0, h0, best, np.inf, gap, grp_mem, mem, fc, tri, normals, offsets)
        return min(best, floor)
    bound = np.empty((g1 - g0) * nh)
    for g in range(g0, g1):
        for h in range(h0, h1):
            bound[(g - g0) * nh + h - h0] = _sphere_gap(gc, gr, g, gc, gr, h)
    floor = np.inf  # smallest lower bound of anything left unvisited
    for e in np.argsort(bound):
        if bound[e] >= best - gap:
            floor = min(floor, bound[e])
            break
        best, floor = _group_pair(g0 + e // nh, h0 + e % nh, best, floor, gap, grp_mem, mem, fc, tri, normals, offsets)
        if best <= 0.0:
            return 0.0
    return min(best, floor)


@numba.njit(cache=True)
def _group_pair(g, h, best, floor, gap, grp_mem, mem, fc, tri, normals, offsets):
    """Exact distances of the member pairs of groups g and h whose separation bound is
    below best - gap. -> (best, floor): the smallest exact distance and skipped bound."""
    for u in range(grp_mem[g], grp_mem[g + 1]):
        k = mem[u]
        for v in range(grp_mem[h], grp_mem[h + 1]):
            l = mem[v]
            lb = _separation(tri, normals, offsets, fc, k, l)
            if lb >= best - gap:
                floor = min(floor, lb)
                continue
            best = min(best, np.sqrt(_triangle_triangle_d2(_t(tri[k, 0]), _t(tri[k, 1]), _t(tri[k, 2]),
                                                           _t(tri[l, 0]), _t(tri[l, 1]), _t(tri[l, 2]))))
    return best, floor
