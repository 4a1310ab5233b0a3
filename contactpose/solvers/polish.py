"""The full χ² (planes and triangles) about a hypothesis's pose, linearised: its minimisation,
which polishes poses (:func:`polished_poses`), and a lower bound on its minimum, the in-facet
test of scoring.infacet (:func:`lowest_chi2_bound`).

The closed form poses a hypothesis on the facet *planes*; the lateral residual r_l (how far a
contact lies outside its triangle, costs.facet) is measured at that pose. The best pose for
planes and triangles together slides a contact near an edge back inside
(research/discrimination.md).

To first order about the closed form, in the right perturbation ξ = (ω, v) of T_world_object
(rotation first), the contact moves in the object frame to q_i(ξ) = p_i + G_i ξ with
G_i = [[p_i]×, -I], and

    χ²(ξ) = Σ_i |r_n,i + J_n,i ξ|²/σ_n² + dist²(q_i(ξ), triangle_i)/σ_x²,

which is convex in ξ (a distance to a convex set, composed with an affine map). Splitting
dist² = r_o² + r_l², the plane part P(ξ) = χ²_0 + 2gᵀξ + ξᵀAξ is quadratic and r_l² is convex,
so for any ξ_k, with u_i the in-plane vector from the triangle to q_i(ξ_k),

    χ²(ξ) >= P(ξ) + Σ_i (|u_i|² + 2 u_iᵀ G_i (ξ - ξ_k)) / σ_x²,

whose minimum over ξ is closed-form: a lower bound on min χ². It is tight when ξ_k is the
minimiser, which alternating minimisation (closest points on the triangles, then a 6×6 linear
solve) approaches in a few steps; bounds near the threshold are taken again about that pose.

Two cases get the linearised χ² the minimisation reaches instead (with four times the steps),
which approaches the minimum from above, so they are complete as far as it converges:
underdetermined hypotheses (A singular: the bound is unbounded below), and, on models with
patches, contacts whose region is their patch (all its member triangles: the search chose one
member by the closed-form pose only), a union that need not be convex.
"""

from __future__ import annotations

import numba
import numpy as np

from contactpose.costs.association import fitting_members
from contactpose.costs.facet import in_plane, normal_residual, plane_terms
from contactpose.geometry.kernels import (  # 3-tuple kernels
    _closest_on_triangle,
    _d2,
    _t,
)
from contactpose.geometry.se3 import retract
from contactpose.options import fit_threshold

#: Alternating-minimisation steps before the bound is taken (it is valid after any number).
STEPS = 6
#: Bounds above the threshold but within this factor of it (and every failing underdetermined
#: hypothesis) are taken again about the pose the minimisation reached, up to RELINEARISE
#: times: the first-order error (~1 % measured) could matter there.
RELINEARISE_BAND = 1.5
RELINEARISE = 3
#: A plane quadratic this ill-conditioned leaves a direction free (a hypothesis whose contacts
#: landed on facets of parallel normals, solvers.surface): its bound is the χ² reached.
SINGULAR_COND = 1e12
#: Relinearisations of polished_poses.
POLISH_ROUNDS = 2
#: The default method moves the poses of at most this many hypotheses toward the least
#: full χ² (:func:`polished`), those whose plane χ² is at least POLISH_GAIN below the best.
POLISH = 256
POLISH_GAIN = 0.5


def polished(model, contacts, arrays, tolerance):
    """The ranked hypotheses (HypothesisArrays) that could beat the best, their poses moved
    toward the least full χ² (:func:`polished_poses`).

    The closed form fits the planes only, the ranking cost includes the triangles: a
    hypothesis whose plane χ² is at least POLISH_GAIN below the best full χ² (the best
    itself, when a contact lies outside its triangle) is moved, up to POLISH of them, best
    plane fit first. With patches, each moved contact gets the member facet that fits it
    best again (costs.association.fitting_members). -> (rows (K,) int, PoseFit of the moved
    poses, facets (K, n) int); K = 0 when every contact lies inside its triangle."""
    rows = np.zeros(0, dtype=np.int64)
    lateral = arrays.residuals[..., 4]
    if lateral.any():  # else every contact lies inside its triangle: the plane χ² is the full χ²
        plane = arrays.chi2 - np.sum(lateral**2, axis=1) / tolerance.position_noise**2
        rows = np.flatnonzero(plane <= arrays.chi2.min() - POLISH_GAIN)
        rows = rows[np.argsort(plane[rows], kind="stable")[:POLISH]]
    fit = arrays.fit.take(rows)
    if not len(rows):
        return rows, fit, arrays.facets[rows]
    fit.R, fit.t = polished_poses(model, contacts, arrays, rows, tolerance, fit_threshold(contacts.n))
    facets = arrays.facets[rows]
    if model.patch_table is not None:
        facets = fitting_members(model, contacts, np.ascontiguousarray(model.patches.labels[facets]), fit.R, fit.t,
                                 tolerance)
    return rows, fit, facets


def lowest_chi2_bound(model, contacts, arrays, rows, tolerance, threshold=None, steps=STEPS):
    """Lower bound on the full χ² of hypotheses ``rows`` over poses near their closed form
    (to first order). Bounds within RELINEARISE_BAND of ``threshold`` (all, when None) are
    taken again about the pose the alternating minimisation reached, which shrinks their
    first-order error. rows : (K,) int  ->  (K,)"""
    R, t, planes, weights, determined, free, shape = _problem(model, contacts, arrays, rows, tolerance, threshold)
    bound, xi = _bounds(R, t, *planes, contacts, *weights, determined, free, shape, steps)
    for _ in range(RELINEARISE):
        again = (np.ones(len(bound), dtype=bool) if threshold is None else
                 (bound > threshold) & ((bound <= RELINEARISE_BAND * threshold) | ~determined))
        if not again.any():
            break
        R[again], t[again] = retract(R[again], t[again], xi[again])
        bound[again], xi[again] = _bounds(R[again], t[again], *(a[again] for a in planes), contacts,
                                          *(w[again] for w in weights), determined[again], free[again], shape, steps)
    return bound


def polished_poses(model, contacts, arrays, rows, tolerance, threshold, rounds=POLISH_ROUNDS):
    """Poses of hypotheses ``rows`` moved from their closed form toward the least full χ²
    (triangles included): where the alternating minimisation above leads, taken again about
    each pose it reaches, ``rounds`` times. Contacts move over the facets a pose with plane
    χ² within ``threshold`` can reach. rows : (K,) int  ->  R (K, 3, 3), t (K, 3)"""
    R, t, planes, weights, determined, free, shape = _problem(model, contacts, arrays, rows, tolerance, threshold)
    for _ in range(rounds):
        xi = _bounds(R, t, *planes, contacts, *weights, determined, free, shape, STEPS)[1]
        R, t = retract(R, t, xi)
    return R, t


def _problem(model, contacts, arrays, rows, tolerance, threshold):
    """The kernel's inputs for hypotheses ``rows``: (R, t, planes, weights, determined,
    free, shape) as _bounds takes them; R and t are copies."""
    facets = arrays.facets[rows]
    used = (facets >= 0).astype(float)                      # unassigned fingers (outliers) drop out
    f = np.maximum(facets, 0)
    regions = _regions(model, f)
    groups = model.facet_groups if model.patch_table is None else model.member_groups
    planes = model.planes.normals[f], model.planes.offsets[f], regions
    weights = used / tolerance.normal_noise**2, used / tolerance.position_noise**2
    # the tangent bound needs a convex region: one triangle, and a pose with no free direction
    free = arrays.fit.underdetermined[rows]
    determined = ~free & (np.diff(groups.indptr)[regions] == 1).all(axis=1)
    runs = (groups.grp_ptr, groups.grp_mem, groups.centre, groups.radius, groups.spread)
    shape = (model.triangles, model.centroids, model.facet_radii, groups.indptr, groups.members, runs,
             np.inf if threshold is None else float(threshold))
    return arrays.fit.R[rows], arrays.fit.t[rows], planes, weights, determined, free, shape


def _regions(model, facets):
    """Where each contact may lie: its facet, or with patches all members of its facet's
    patch (the search picked one member only by the closed-form pose). Returns the region
    of each (K, n) facet, an index into model.member_groups."""
    if model.patch_table is None:
        return facets
    return model.patches.labels[facets]


def _bounds(R, t, normals, offsets, regions, contacts, wn, wx, determined, free, shape, steps):
    """The bound about (R, t) and the ξ the alternating minimisation reached: (K,), (K, 6)."""
    bound, xi = np.empty(len(R)), np.empty((len(R), 6))
    _bound_kernel(*(np.ascontiguousarray(a, dtype=np.float64) for a in
                    (R, t, normals, offsets, contacts.points, contacts.finger_normals, wn, wx)),
                  regions, *shape, determined, free, steps, bound, xi)
    return bound, xi


@numba.njit(cache=True)
def _bound_kernel(R, t, normals, offsets, points, finger_normals, wn, wx, regions, triangles, centres, radii,
                  indptr, members, runs, threshold, determined, free, steps, bound, xi_out):
    """Per hypothesis: the plane quadratic (A, g, χ²_0), alternating minimisation of the
    linearised χ² from ξ = 0, and the closed-form minimum of the lower bound there. Where
    that bound does not hold (``determined`` false: a free direction, or a patch of several
    triangles, which need not be convex) the linearised χ² the minimisation reached.

    In the object frame G_i ξ = p_i × ω - v and G_iᵀ u = (u × p_i, -u), so
    G_iᵀG_i = [[|p|²I - ppᵀ, [p]×], [-[p]×, I]]; the offset row is j_o = (n × p, -n)."""
    n = points.shape[0]
    A, H, chol = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6))
    g, g_n, p = np.empty(6), np.empty(6), np.empty((n, 3))
    for k in range(R.shape[0]):
        A[:], H[:], g[:], g_n[:] = 0.0, 0.0, 0.0, 0.0
        chi2_0 = 0.0
        for i in range(n):
            # normal term: J_nᵀJ_n = I - n nᵀ, J_nᵀ r_n = n × Rᵀ r_n; offset term: j_o = (n × p, -n)
            pi, r_n, r_o, gn, j_o = plane_terms(R[k], t[k], normals[k, i], offsets[k, i], points[i], finger_normals[i])
            p[i, 0], p[i, 1], p[i, 2] = pi
            nrm = normals[k, i]
            chi2_0 += wn[k, i] * (r_n[0] * r_n[0] + r_n[1] * r_n[1] + r_n[2] * r_n[2]) + wx[k, i] * r_o * r_o
            pp = pi[0] * pi[0] + pi[1] * pi[1] + pi[2] * pi[2]
            for a in range(3):
                g_n[a] += wn[k, i] * gn[a]
                g[a] += wx[k, i] * r_o * j_o[a]
                g[a + 3] -= wx[k, i] * r_o * nrm[a]
                for b in range(3):
                    a_n = wn[k, i] * ((a == b) - nrm[a] * nrm[b])
                    A[a, b] += a_n + wx[k, i] * j_o[a] * j_o[b]
                    A[a, b + 3] -= wx[k, i] * j_o[a] * nrm[b]
                    A[a + 3, b] -= wx[k, i] * nrm[a] * j_o[b]
                    A[a + 3, b + 3] += wx[k, i] * nrm[a] * nrm[b]
                    H[a, b] += a_n + wx[k, i] * ((a == b) * pp - pi[a] * pi[b])
                    H[a + 3, b + 3] += wx[k, i] * (a == b)
            skew = ((0.0, -pi[2], pi[1]), (pi[2], 0.0, -pi[0]), (-pi[1], pi[0], 0.0))
            for a in range(3):  # the off-diagonal blocks of GᵀG: ±w [p]×
                for b in range(3):
                    H[a, b + 3] += wx[k, i] * skew[a][b]
                    H[a + 3, b] -= wx[k, i] * skew[a][b]
        for a in range(6):
            g[a] += g_n[a]
        # regularise each block by its own trace, so that the solve does not depend on units
        rot, trans = H[0, 0] + H[1, 1] + H[2, 2], H[3, 3] + H[4, 4] + H[5, 5]
        for a in range(3):
            H[a, a] += 1e-12 * rot
            H[a + 3, a + 3] += 1e-12 * trans
        _cholesky(H, chol)
        many = np.any(indptr[regions[k] + 1] - indptr[regions[k]] > 1)
        reach = _reach(A, g, chi2_0, p, threshold) if many and not free[k] else np.full(n, np.inf)
        cand = _candidates(p, reach, regions[k], centres, radii, members, runs)
        xi, last = _alternate(p, cand, runs, triangles, centres, radii, wx[k], chol, g_n,
                              steps if determined[k] else 4 * steps)
        w, v = (xi[0], xi[1], xi[2]), (xi[3], xi[4], xi[5])
        h = np.zeros(6)
        const, reached = chi2_0, 0.0
        for i in range(n):
            p0, p1, p2 = p[i, 0], p[i, 1], p[i, 2]
            q = (p0 + (p1 * w[2] - p2 * w[1]) - v[0], p1 + (p2 * w[0] - p0 * w[2]) - v[1],
                 p2 + (p0 * w[1] - p1 * w[0]) - v[2])  # p + p × ω - v
            c = _closest_of(q, i, cand, runs, triangles, centres, radii, last[i])[0]
            d = (q[0] - c[0], q[1] - c[1], q[2] - c[2])
            n0, n1, n2 = normals[k, i, 0], normals[k, i, 1], normals[k, i, 2]
            u = in_plane(d, (n0, n1, n2))                    # |u| = r_l at q
            gu = (u[1] * p2 - u[2] * p1, u[2] * p0 - u[0] * p2, u[0] * p1 - u[1] * p0)  # u × p
            for a in range(3):
                h[a] += wx[k, i] * gu[a]
                h[a + 3] -= wx[k, i] * u[a]
            const += wx[k, i] * (u[0] * u[0] + u[1] * u[1] + u[2] * u[2])
            turned = (n0 + (w[1] * n2 - w[2] * n1), n1 + (w[2] * n0 - w[0] * n2), n2 + (w[0] * n1 - w[1] * n0))
            r_n = normal_residual(R[k], turned, finger_normals[i])  # at R (I + [ω]×): n + ω × n
            reached += (wn[k, i] * (r_n[0] * r_n[0] + r_n[1] * r_n[1] + r_n[2] * r_n[2])
                        + wx[k, i] * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
        if determined[k] and np.linalg.cond(A) < SINGULAR_COND:  # the facets may leave a direction free
            gh = g + h
            bound[k] = const - 2.0 * (h @ xi) - gh @ np.linalg.solve(A, gh)
        else:
            bound[k] = reached
        xi_out[k] = xi


@numba.njit(cache=True)
def _cholesky(H, L):
    """Lower Cholesky factor L of the symmetric positive definite (6, 6) H, in place."""
    L[:] = 0.0
    for j in range(6):
        s = H[j, j]
        for c in range(j):
            s -= L[j, c] * L[j, c]
        L[j, j] = np.sqrt(max(s, 1e-300))
        for r in range(j + 1, 6):
            s = H[r, j]
            for c in range(j):
                s -= L[r, c] * L[j, c]
            L[r, j] = s / L[j, j]


@numba.njit(cache=True)
def _cho_solve(L, b, x):
    """x = (L Lᵀ)⁻¹ b for the Cholesky factor L (6, 6)."""
    for r in range(6):
        s = b[r]
        for c in range(r):
            s -= L[r, c] * x[c]
        x[r] = s / L[r, r]
    for r in range(5, -1, -1):
        s = x[r]
        for c in range(r + 1, 6):
            s -= L[c, r] * x[c]
        x[r] = s / L[r, r]


@numba.njit(cache=True)
def _alternate(p, cand, runs, triangles, centres, radii, wx, chol, g_n, steps):
    """Minimise the linearised χ² over ξ, alternating closest points c_i in the contacts'
    regions with the ξ that best meets them: H ξ = -(g_n + Σ_i wx G_iᵀ (p_i - c_i)).
    Returns ξ (6,) and where each contact's closest triangle sits in its candidates."""
    xi, rhs, last = np.zeros(6), np.empty(6), np.zeros(len(p), dtype=np.int64)
    for _ in range(steps):
        rhs[:] = g_n
        w, v = (xi[0], xi[1], xi[2]), (xi[3], xi[4], xi[5])
        for i in range(len(p)):
            p0, p1, p2 = p[i, 0], p[i, 1], p[i, 2]
            q = (p0 + (p1 * w[2] - p2 * w[1]) - v[0], p1 + (p2 * w[0] - p0 * w[2]) - v[1],
                 p2 + (p0 * w[1] - p1 * w[0]) - v[2])  # p + p × ω - v
            c, last[i] = _closest_of(q, i, cand, runs, triangles, centres, radii, last[i])
            u = (p0 - c[0], p1 - c[1], p2 - c[2])
            gu = (u[1] * p2 - u[2] * p1, u[2] * p0 - u[0] * p2, u[0] * p1 - u[1] * p0)  # u × p
            for a in range(3):
                rhs[a] += wx[i] * gu[a]
                rhs[a + 3] -= wx[i] * u[a]
        _cho_solve(chol, rhs, xi)
        for a in range(6):
            xi[a] = -xi[a]
    return xi, last


@numba.njit(cache=True)
def _reach(A, g, chi2_0, p, threshold):
    """How far each contact can move, to first order, among the poses whose plane χ² is
    within ``threshold``: |G_i ξ*| + sqrt(b · trace(G_i A⁻¹ G_iᵀ)), b = threshold - χ²_min."""
    A_inv = np.linalg.pinv(A)
    step = -(A_inv @ g)
    budget = max(threshold - (chi2_0 + g @ step), 0.0)
    reach = np.empty(len(p))
    for i in range(len(p)):
        G = _motion(p[i])
        reach[i] = np.sqrt(np.sum((G @ step) ** 2)) + np.sqrt(budget * np.trace(G @ A_inv @ G.T))
    return reach


@numba.njit(cache=True)
def _candidates(p, reach, regions, centres, radii, members, runs):
    """Per contact, the facets of its region that a pose within noise can bring it to: those
    whose bounding sphere lies within (distance to the region) + reach of it, kept in runs
    (MemberGroups) so that closest-point queries can skip a run by its sphere. A facet's
    centroid lies in its run's sphere, so |p - c_f| >= |p - c_run| - r_run bounds whole runs.
    -> (facets (n, s), count (n,), run starts in facets (n, s + 1), run ids (n, s), runs (n,))"""
    grp_ptr, grp_mem, grp_centre, grp_radius, spread = runs
    n, size = len(p), 1
    for i in range(n):
        size = max(size, grp_mem[grp_ptr[regions[i] + 1]] - grp_mem[grp_ptr[regions[i]]])
    facets, count = np.empty((n, size), dtype=np.int64), np.zeros(n, dtype=np.int64)
    starts, ids, nruns = np.zeros((n, size + 1), dtype=np.int64), np.empty((n, size), dtype=np.int64), np.zeros(n, dtype=np.int64)
    for i in range(n):
        x = p[i]
        lo, hi = grp_ptr[regions[i]], grp_ptr[regions[i] + 1]
        near = np.inf  # an upper bound on the distance from p_i to the region
        for g in range(lo, hi):
            if _distance(x, grp_centre[g]) - grp_radius[g] >= near:
                continue
            for e in range(grp_mem[g], grp_mem[g + 1]):
                near = min(near, _distance(x, centres[members[e]]) + radii[members[e]])
        for g in range(lo, hi):
            if _distance(x, grp_centre[g]) - grp_radius[g] - spread[g] > near + reach[i]:
                continue
            before = count[i]
            for e in range(grp_mem[g], grp_mem[g + 1]):
                f = members[e]
                if _distance(x, centres[f]) - radii[f] <= near + reach[i]:
                    facets[i, count[i]] = f
                    count[i] += 1
            if count[i] > before:
                ids[i, nruns[i]] = g
                nruns[i] += 1
                starts[i, nruns[i]] = count[i]
    return facets, count, starts, ids, nruns


@numba.njit(cache=True)
def _distance(x, y):
    """|x - y| of two points (3,)."""
    d0, d1, d2 = x[0] - y[0], x[1] - y[1], x[2] - y[2]
    return np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)


@numba.njit(cache=True)
def _closest_of(q, i, cand, runs, triangles, centres, radii, start):
    """Closest point (3-tuple) to the 3-tuple q on contact i's candidate triangles (cand from
    :func:`_candidates`), and its position among them. The last answer, position ``start``,
    is tried first, so that the spheres of most runs and facets rule them out."""
    facets, count, starts, ids, nruns = cand
    grp_centre, grp_radius = runs[2], runs[3]
    if count[i] == 0:
        return q, 0
    at = min(start, count[i] - 1)
    tri = triangles[facets[i, at]]
    out = _closest_on_triangle(q, _t(tri[0]), _t(tri[1]), _t(tri[2]))
    best = _d2(q, out)
    for r in range(nruns[i]):
        g = ids[i, r]
        gap = np.sqrt(_d2(q, _t(grp_centre[g]))) - grp_radius[g]
        if gap > 0.0 and gap * gap >= best:
            continue
        for e in range(starts[i, r], starts[i, r + 1]):
            f = facets[i, e]
            gap = np.sqrt(_d2(q, _t(centres[f]))) - radii[f]
            if gap > 0.0 and gap * gap >= best:
                continue
            tri = triangles[f]
            c = _closest_on_triangle(q, _t(tri[0]), _t(tri[1]), _t(tri[2]))
            d = _d2(q, c)
            if d < best:
                best, out, at = d, c, e
    return out, at


@numba.njit(cache=True)
def _motion(p):
    """G = [[p]×, -I] (3, 6): how the object-frame contact p moves under ξ = (ω, v)."""
    G = np.zeros((3, 6))
    G[0, 1], G[0, 2], G[1, 0], G[1, 2], G[2, 0], G[2, 1] = -p[2], p[1], p[2], -p[0], -p[1], p[0]
    G[0, 3], G[1, 4], G[2, 5] = -1.0, -1.0, -1.0
    return G
