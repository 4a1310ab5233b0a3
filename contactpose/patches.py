"""Patches: connected facets of (nearly) one plane, searched as one unit.

A flat region made of many facets makes the facet-level tree explode: four
contacts on one face of a box admit every tuple of its facets. A patch is a
connected set of valid facets whose normals lie within ``tol_deg`` of the
patch's first facet (``tol_deg=0``: exactly coplanar). The pair table over
patches stores *interval* bounds, each the exact union of its member facet
pairs' intervals (Δmin, Δmax, [α_min, α_max], direction intervals), so a search
over patches admits every tuple the facet-level search admits: it stays complete.
A hypothesis over patches is expanded to facets where the pose needs them:
each contact takes the member facet nearest to it (research/design.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from contactpose.features import PairFeatures
from contactpose.geometry import point_triangle_dist2

#: Normals closer than this (radians) count as exactly parallel for tol_deg = 0.
COPLANAR_ANGLE = 1e-9
#: The default method searches patches when they number at most this fraction of the
#: valid facets; with fewer merges the facet-level search is faster.
PATCH_GAIN = 0.9


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
    def from_arrays(cls, a):
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


class PatchReducer:
    """Accumulates patch-pair features from chunks of facet-pair features.

    Call it with each chunk's PairFeatures (exact bounds), then :meth:`features`.
    Dense upper-triangle accumulators: 64 bytes per patch pair.
    """

    def __init__(self, patches):
        self.patches = patches
        self.acc = _empty_accumulators(patches.count)

    def __call__(self, f):
        _reduce(self.acc, self.patches.labels, self.patches.count, f.k, f.l, f.dmax, f.dmin_exact, f.alpha,
                f.h_kl, f.h_lk)

    def features(self):
        """PairFeatures with k <= l patch indices and α as [alpha, alpha_hi]."""
        present = np.flatnonzero(np.isfinite(self.acc[:, 0]))
        pk, pl = _unrank(present, self.patches.count)
        acc = self.acc[present].astype(np.float32)
        return PairFeatures(k=pk.astype(np.int32), l=pl.astype(np.int32), dmax=acc[:, 1], dmin_vertex=acc[:, 0],
                            dmin_exact=acc[:, 0], alpha=acc[:, 2], h_kl=acc[:, 4:6].copy(),
                            h_lk=acc[:, 6:8].copy(), alpha_hi=acc[:, 3])


def patch_features(facet_features, patches):
    """Pair features over patches, each the union of its member facet pairs' intervals."""
    reducer = PatchReducer(patches)
    reducer(facet_features)
    return reducer.features()


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


def nearest_members(patches, triangles, tuples, p_obj):
    """The member facet of each hypothesised patch nearest to its contact.

    tuples : (Hp, n) patch indices; p_obj : (Hp, n, 3) contacts in the object frame under
    each tuple's pose; triangles : (m, 3, 3).  ->  (Hp, n) int64 facet indices
    """
    return _nearest(patches.indptr, patches.members, triangles, tuples, p_obj)


@numba.njit(cache=True)
def _nearest(indptr, members, triangles, tuples, p_obj):
    hp, n = tuples.shape
    out = np.empty((hp, n), dtype=np.int64)
    for h in range(hp):
        for i in range(n):
            q = tuples[h, i]
            best = np.inf
            for e in range(indptr[q], indptr[q + 1]):
                f = members[e]
                d = point_triangle_dist2(p_obj[h, i], triangles[f, 0], triangles[f, 1], triangles[f, 2])
                if d < best:
                    best = d
                    out[h, i] = f
    return out
