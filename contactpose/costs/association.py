"""Association: which facet explains a contact under a pose.

A contact (object-frame point p, outward normal ν) fits facet f with the whitened cost

    c_f = dist(p, V_f)² + w |n_f - ν|²,   w = σ_x²/σ_n²    (in units of σ_x², :func:`fit_cost`),

the facet model's χ² of that contact (costs.facet) at the contact's own closest point on the
triangle; on a model with crease edges its normal may also lie on an edge's arc of normals
(costs.smooth.arc_misfits). A contact takes the facet of least cost:

* :func:`nearest_fit_facets`: over the whole mesh, under one pose or many, with the pose's
  uncertainty in the weight (:func:`association_weights`); the tracks and the factor graph's
  prior rescue use it;
* :func:`fitting_members`, :func:`nearest_members`: within a hypothesised patch (a unit of the
  search on fine meshes), the ranking's and the factor graph's choice of member;
  :func:`fitting_facets` moves refined hypotheses' contacts to it.
"""

from __future__ import annotations

from itertools import chain

import numba
import numpy as np
from numba import njit

from contactpose.costs.frame import object_frame
from contactpose.costs.smooth import NO_ARCS, arc_misfits
from contactpose.costs.surface import facet_surface_cost
from contactpose.geometry.kernels import _d2, _point_triangle_d2, _t, point_triangle_dist2, segment_d2
from contactpose.geometry.se3 import hat


@njit(cache=True)
def normal_misfit(facet_normal, normal, weight):
    """weight · |n_f - n|²: the normal part of a contact's fit to a facet (normal n outward, in
    the facet's frame), in units of σ_x² when weight = σ_x²/σ_n²."""
    d = 0.0
    for a in range(3):
        d += (facet_normal[a] - normal[a]) ** 2
    return weight * d


@njit(cache=True)
def fit_cost(point, normal, triangle, facet_normal, weight):
    """A contact's whitened fit to a facet, times σ_x²: its squared distance to the triangle
    (3, 3) plus :func:`normal_misfit` (weight = σ_x²/σ_n²). The rule by which a contact takes
    its facet (:func:`nearest_fit_facets`, :func:`nearest_members`)."""
    return (_point_triangle_d2(_t(point), _t(triangle[0]), _t(triangle[1]), _t(triangle[2]))
            + normal_misfit(facet_normal, normal, weight))


def nearest_fit_facets(model, contacts, pose, tolerance, pose_covariance=None, creases=False, surface=False):
    """Each contact's best facet under a pose: least whitened point-to-triangle distance²
    plus normal residual². pose : (4, 4) -> (n,) int, or (H, 4, 4) -> (H, n) int, the poses
    searched together in one pass (valid facets only). pose_covariance : None, or the poses'
    (6, 6) / (H, 6, 6) covariance (rotation first, right perturbation), whose spread of each
    contact's object-frame point and normal joins the sensor's (:func:`association_weights`).
    creases : also score each facet's crease edges (ObjectModel.crease_edges) as the smooth
    contact model reads them, the squared distance to the edge plus the normal's to the
    edge's arc of normals (costs.smooth.arc_misfits), a contact on an edge taking that facet.
    surface : score each facet by the surface contact model instead, its face, convex edges
    and vertices with their normal cones (costs.surface.facet_surface_cost): the facet from
    which the contact lands on the feature of least cost of the whole mesh. A rounded
    fingertip on a vertex of a rough scan has a normal between its faces'; by their planes
    alone it takes a facet whose normal matches, millimetres away, and lands near there.

    The NEAREST_CANDIDATES facets of nearest centroid are scored first. A facet lies at least
    (its centroid's distance - the largest facet radius) from the contact, so one whose centroid
    lies farther than the best candidate's cost, as a distance, plus that radius cannot beat
    it; where the candidates do not reach that far, the contact is scored against every facet
    within it (one ball query for all such contacts). The answer is the brute force's either
    way."""
    poses = np.asarray(pose, dtype=np.float64)
    single = poses.ndim == 2
    poses = poses.reshape(-1, 4, 4)
    H, n = len(poses), contacts.n
    tree, valid, radius = model.centroid_tree
    p, normals = object_frame(poses[:, :3, :3], poses[:, :3, 3], contacts.points, contacts.finger_normals)
    p, normals = p.reshape(-1, 3), normals.reshape(-1, 3)  # (H·n, 3), pose by pose
    weight = association_weights(p.reshape(H, n, 3), normals.reshape(H, n, 3), tolerance, pose_covariance).reshape(-1)

    def scored(points, outward, candidates, starts, ends, found=None, found_cost=None, weights=weight):
        if found is None:
            found, found_cost = np.full(len(points), -1), np.full(len(points), np.inf)
        if surface:
            return _best_surface_fits(points, outward, candidates, starts, ends, model.triangles,
                                      model.planes.normals, model.facet_radii, weights, found, found_cost,
                                      model.topology.arrays, model.topology.spread)
        return _best_fits(points, outward, candidates, starts, ends, model.triangles, model.planes.normals,
                          model.facet_radii, weights, found, found_cost, edges)

    edges = model.crease_edges if creases else np.full((1, 3, 12), np.nan)

    if len(valid) <= SCORE_ALL_BELOW:  # a coarse mesh: score every facet
        best, _ = scored(p, normals, valid, np.zeros(H * n, np.int64), np.full(H * n, len(valid)))
    else:
        dist, near = tree.query(p, NEAREST_CANDIDATES)
        starts = NEAREST_CANDIDATES * np.arange(len(p))
        best, cost = scored(p, normals, valid[near].ravel(), starts, starts + NEAREST_CANDIDATES)
        reach = np.sqrt(cost) + radius  # a facet whose centroid lies farther costs more
        short = np.flatnonzero(dist[:, -1] < reach)
        if short.size:
            balls, offsets = _flat(tree.query_ball_point(p[short], reach[short]))
            best[short] = scored(p[short], normals[short], valid[balls], offsets[:-1], offsets[1:], best[short],
                                 cost[short], weight[short])[0]
    return best.reshape(n) if single else best.reshape(H, n)


def association_weights(p, normals, tolerance, pose_covariance=None):
    """Each contact's weight w = σ_p²/σ_r² of its normal misfit in the fit to a facet
    (:func:`fit_cost`): σ_p² = σ_x² plus the mean variance per axis of its object-frame
    point p under the pose's uncertainty, σ_r² = σ_n² plus that of its normal n per tangent
    axis; without a covariance, σ_x²/σ_n². A pose perturbed by ξ = (ω, v) on the right moves
    p by [p]× ω - v and n by [n]× ω, so a predicted pose a slip away, whose point errs by
    millimetres while its normal errs by about a degree, leans on the normal to pick the facet
    (research/tracking.md, "A covariance that carries the association").
    p, normals : (H, n, 3) object frame; pose_covariance : None, (6, 6) or (H, 6, 6). -> (H, n)"""
    base = (tolerance.position_noise / tolerance.normal_noise) ** 2
    if pose_covariance is None:
        return np.full(p.shape[:2], base)
    P = np.broadcast_to(np.asarray(pose_covariance, dtype=np.float64), (len(p), 6, 6))
    Jp = np.concatenate([hat(p), np.broadcast_to(-np.eye(3), p.shape + (3,))], axis=-1)  # (H, n, 3, 6)
    point_var = np.einsum("hcij,hjk,hcik->hc", Jp, P, Jp) / 3.0
    Jn = hat(normals)
    normal_var = np.einsum("hcij,hjk,hcik->hc", Jn, P[:, :3, :3], Jn) / 2.0
    return (tolerance.position_noise ** 2 + point_var) / (tolerance.normal_noise ** 2 + normal_var)


#: nearest_fit_facets scores this many facets of nearest centroid before it looks further (a
#: fine mesh's contacts mostly look further, in one ball query: cheaper than more neighbours).
NEAREST_CANDIDATES = 48
#: ... and scores every facet of a mesh with at most this many valid facets.
SCORE_ALL_BELOW = 1024


def _flat(lists):
    """Ragged index lists -> (indices (Σ,) int64, offsets (m + 1,) int64): list i at
    offsets[i]:offsets[i + 1]."""
    offsets = np.zeros(len(lists) + 1, dtype=np.int64)
    np.cumsum([len(a) for a in lists], out=offsets[1:])
    return np.fromiter(chain.from_iterable(lists), dtype=np.int64, count=int(offsets[-1])), offsets


@njit(cache=True)
def _best_fits(p, normals, candidates, starts, ends, triangles, facet_normals, radii, weight, found, found_cost,
               edges):
    """Each contact's candidate of least fit_cost (the first on a tie), or its ``found`` facet
    of cost ``found_cost`` (m,) when no candidate costs less (-1 and inf: none yet). p, normals
    : (m, 3) object-frame points and outward normals; candidates (Σ,) int, contact i's at
    starts[i]:ends[i] (starts, ends (m,); rows may share them); radii : (F,)
    the facets' radii; weight : (m,) each contact's σ_x²/σ_n² (association_weights); edges :
    ObjectModel.crease_edges, whose edges of a candidate compete with its face
    (costs.smooth.arc_misfits), or one NaN row: none. A candidate whose normal misfit plus (centroid
    distance - radius)² already reaches the least cost so far is not scored further.
    -> (facets (m,) int, their costs (m,), length²: the whitened cost times σ_x²)"""
    m = p.shape[0]
    best, cost = np.empty(m, np.int64), np.empty(m)
    creases = len(edges) > 1
    for i in range(m):
        least, pick = found_cost[i], found[i]
        for j in range(starts[i], ends[i]):
            f = candidates[j]
            c = normal_misfit(facet_normals[f], normals[i], weight[i])
            arcs = arc_misfits(normals[i], facet_normals[f], edges[f], weight[i]) if creases else NO_ARCS
            lower = min(c, arcs[0], arcs[1], arcs[2])
            if lower >= least:
                continue
            gap = 0.0
            for a in range(3):
                gap += (p[i, a] - (triangles[f, 0, a] + triangles[f, 1, a] + triangles[f, 2, a]) / 3.0) ** 2
            gap = max(np.sqrt(gap) - radii[f], 0.0)
            if lower + gap * gap >= least:
                continue
            c = fit_cost(p[i], normals[i], triangles[f], facet_normals[f], weight[i])
            for k in range(3):
                if arcs[k] < least:
                    c = min(c, arcs[k] + segment_d2(p[i], triangles[f, k], triangles[f, (k + 1) % 3]))
            if c < least:
                least, pick = c, f
        best[i], cost[i] = pick, least
    return best, cost


@njit(cache=True)
def _best_surface_fits(p, normals, candidates, starts, ends, triangles, facet_normals, radii, weight, found,
                       found_cost, topology, spread):
    """As :func:`_best_fits`, each candidate scored by costs.surface.facet_surface_cost (its
    face, convex edges and vertices). A candidate is not scored when a lower bound already
    reaches the least cost so far: (centroid distance - radius)² plus the normal misfit at
    the angle by which the contact's normal lies beyond the facet's spread (the widest its
    features admit). topology : model.surface.SurfaceTopology.arrays; spread : its spread (m,)."""
    fv, vpos, edge_nbr, edge_convex, vf_ptr, vf, cone_ptr, cone_rays, cone_bound = topology
    m = p.shape[0]
    best, cost = np.empty(m, np.int64), np.empty(m)
    for i in range(m):
        least, pick = found_cost[i], found[i]
        for j in range(starts[i], ends[i]):  # the faces first: a cheap upper bound to prune by
            f = candidates[j]
            c = fit_cost(p[i], normals[i], triangles[f], facet_normals[f], weight[i])
            if c < least:
                least, pick = c, f
        x, n = _t(p[i]), _t(normals[i])
        for j in range(starts[i], ends[i]):
            f = candidates[j]
            gap = 0.0
            for a in range(3):
                gap += (p[i, a] - (triangles[f, 0, a] + triangles[f, 1, a] + triangles[f, 2, a]) / 3.0) ** 2
            gap = max(np.sqrt(gap) - radii[f], 0.0)
            if gap * gap >= least:
                continue
            cos = normals[i, 0] * facet_normals[f, 0] + normals[i, 1] * facet_normals[f, 1] \
                + normals[i, 2] * facet_normals[f, 2]
            beyond = max(np.arccos(max(-1.0, min(1.0, cos))) - spread[f], 0.0)
            if gap * gap + weight[i] * (2.0 - 2.0 * np.cos(beyond)) >= least:
                continue
            c = facet_surface_cost(x, n, f, fv, vpos, edge_nbr, edge_convex, cone_ptr, cone_rays, cone_bound, vf_ptr,
                                   vf, triangles, facet_normals, weight[i])
            if c < least:
                least, pick = c, f
        best[i], cost[i] = pick, least
    return best, cost


def fitting_facets(model, contacts, facets, poses, tolerance):
    """Each contact's facet moved to the member of its patch that fits it best under the pose.

    With patches (connected facets searched as one unit) a hypothesis's facet within a patch
    depends on the pose, and the residuals of the wrong member would hold the contact to it.
    The member is the one of least whitened distance² plus normal residual²
    (:func:`fitting_members`, as in the ranking): on a fine mesh of a curved surface
    neighbouring members differ in normal by more than σ_n, and the nearest member alone
    biased the rotation (research/uncertainty.md, "Fine meshes"). Without patches in the
    model, ``facets`` unchanged.
    facets : (H, n) int (-1: unassigned, kept), poses : (H, 4, 4)  ->  (H, n) int
    """
    patches = getattr(model, "patches", None)
    labels = None if patches is None else patches.labels[np.maximum(facets, 0)]
    if patches is None or not np.any(np.diff(patches.indptr)[labels] > 1):
        return facets  # no patches, or every contact's patch is a single facet
    members = fitting_members(model, contacts, np.ascontiguousarray(labels), poses[:, :3, :3], poses[:, :3, 3],
                               tolerance)
    return np.where(facets >= 0, members, -1)


def fitting_members(model, contacts, tuples, R, t, tolerance):
    """The member facet of each hypothesised patch that fits its contact best under the pose
    (R (H, 3, 3), t (H, 3)): least whitened distance and normal residual
    (:func:`nearest_members`): the ranking's and the factor graph's choice of member.
    tuples : (H, n) patch indices  ->  (H, n) facets"""
    p, normals = object_frame(R, t, contacts.points, contacts.finger_normals)
    weight = (tolerance.position_noise / tolerance.normal_noise) ** 2
    return nearest_members(model.member_groups, model.triangles, tuples, p, (model.planes.normals, normals, weight),
                           (model.centroids, model.facet_radii))


def nearest_members(groups, triangles, tuples, p_obj, normals=None, spheres=None):
    """The member facet of each hypothesised region nearest to its contact.

    groups : MemberGroups of the regions; tuples : (Hp, n) region indices; p_obj : (Hp, n, 3)
    contacts in the object frame under each tuple's pose; triangles : (m, 3, 3); normals :
    None (nearest by distance), or (facet_normals (m, 3), contact normals (Hp, n, 3) outward
    in the object frame, σ_x²/σ_n²): the member with the least d²/σ_x² + |n_f - n|²/σ_n², the
    whitened χ² of that contact, so that on a curved region a contact takes the member whose
    normal it carries, not only the closest one. Runs whose sphere rules them out are
    skipped; spheres : (centres (m, 3), radii (m,)) holding each facet: members whose sphere
    rules them out skip the exact distance too (same answer).  ->  (Hp, n) int64 facet indices
    """
    if normals is None:
        facet_normals, obj_normals, weight = np.zeros((1, 3)), np.zeros((1, 1, 3)), 0.0
    else:
        facet_normals, obj_normals, weight = normals
    centres, radii = (np.zeros((1, 3)), np.full(1, -1.0)) if spheres is None else spheres
    return _nearest(groups.grp_ptr, groups.grp_mem, groups.members, groups.centre, groups.radius, triangles, tuples,
                    p_obj, np.ascontiguousarray(facet_normals, dtype=np.float64),
                    np.ascontiguousarray(obj_normals, dtype=np.float64), float(weight),
                    np.ascontiguousarray(centres, dtype=np.float64), np.ascontiguousarray(radii, dtype=np.float64))


@numba.njit(cache=True)
def _nearest(grp_ptr, grp_mem, members, grp_centre, grp_radius, triangles, tuples, p_obj, facet_normals,
             obj_normals, weight, centres, radii):
    """Least whitened cost over each region's members; a run's sphere bounds the distance of
    all its members from below (the normal term is >= 0), so a run it rules out is skipped.
    The run nearest the contact goes first, so that the others meet a low bound."""
    hp, n = tuples.shape
    out = np.empty((hp, n), dtype=np.int64)
    prune = radii[0] >= 0.0
    for h in range(hp):
        for i in range(n):
            q = tuples[h, i]
            x = _t(p_obj[h, i])
            best = np.inf
            lo, hi = grp_ptr[q], grp_ptr[q + 1]
            first = lo
            if hi - lo > 1:
                nearest = np.inf
                for g in range(lo, hi):
                    gap = np.sqrt(_d2(x, _t(grp_centre[g]))) - grp_radius[g]
                    if gap < nearest:
                        nearest, first = gap, g
            for j in range(hi - lo):
                g = lo + (first - lo + j) % (hi - lo)
                if j > 0:
                    gap = np.sqrt(_d2(x, _t(grp_centre[g]))) - grp_radius[g]
                    if gap > 0.0 and gap * gap >= best:
                        continue
                for e in range(grp_mem[g], grp_mem[g + 1]):
                    f = members[e]
                    d = normal_misfit(facet_normals[f], obj_normals[h, i], weight) if weight > 0.0 else 0.0
                    if prune:
                        gap = np.sqrt(_d2(x, _t(centres[f]))) - radii[f]
                        if gap > 0.0 and d + gap * gap >= best:
                            continue
                    d += point_triangle_dist2(p_obj[h, i], triangles[f, 0], triangles[f, 1], triangles[f, 2])
                    if d < best:
                        best = d
                        out[h, i] = f
    return out
