"""The in-facet check: can some pose within noise put every contact on its facet *triangle*?

The closed form poses a hypothesis on the facet *planes*; the lateral residual r_l (how far a
contact lies outside its triangle, residuals.py) is measured at that pose. Testing the full χ²
there drops true hypotheses: the best pose for planes and triangles together slides a contact
near an edge back inside (research/discrimination.md). So the test bounds the best full χ²
from below instead, and rejects a hypothesis only when that bound exceeds the fit threshold.

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
from scipy.spatial.transform import Rotation

from contactpose.geometry import closest_point_triangle

#: Alternating-minimisation steps before the bound is taken (it is valid after any number).
STEPS = 6
#: Bounds above the threshold but within this factor of it (and every failing underdetermined
#: hypothesis) are taken again about the pose the minimisation reached, up to RELINEARISE
#: times: the first-order error (~1 % measured) could matter there.
RELINEARISE_BAND = 1.5
RELINEARISE = 3


def within_noise(model, contacts, arrays, tolerance, threshold):
    """(H,) bool: the hypotheses whose best full χ² (triangles included) may be within
    ``threshold``, by the lower bound above. arrays : HypothesisArrays."""
    chi2 = arrays.chi2
    lateral = np.nan_to_num(arrays.residuals[..., 4])
    plane = chi2 - np.sum(lateral**2, axis=1) / tolerance.position_noise**2
    ok = chi2 <= threshold
    check = np.flatnonzero(~ok & (plane <= threshold))
    if len(check):
        ok[check] = lowest_chi2_bound(model, contacts, arrays, check, tolerance, threshold) <= threshold
    return ok


def lowest_chi2_bound(model, contacts, arrays, rows, tolerance, threshold=None, steps=STEPS):
    """Lower bound on the full χ² of hypotheses ``rows`` over poses near their closed form
    (to first order). Bounds within RELINEARISE_BAND of ``threshold`` (all, when None) are
    taken again about the pose the alternating minimisation reached, which shrinks their
    first-order error. rows : (K,) int  ->  (K,)"""
    facets = arrays.facets[rows]
    used = (facets >= 0).astype(float)                      # unassigned fingers (outliers) drop out
    f = np.maximum(facets, 0)
    R, t = arrays.fit.R[rows], arrays.fit.t[rows]
    regions, indptr, members = _regions(model, f)
    planes = model.planes.normals[f], model.planes.offsets[f], regions
    weights = used / tolerance.normal_noise**2, used / tolerance.position_noise**2
    # the tangent bound needs a convex region: one triangle, and a pose with no free direction
    determined = ~arrays.fit.underdetermined[rows] & (np.diff(indptr)[regions] == 1).all(axis=1)
    free = arrays.fit.underdetermined[rows]
    shape = (model.triangles, model.centroids, _facet_radii(model), indptr, members,
             np.inf if threshold is None else float(threshold))
    bound, xi = _bounds(R, t, *planes, contacts, *weights, determined, free, shape, steps)
    for _ in range(RELINEARISE):
        again = (np.ones(len(bound), dtype=bool) if threshold is None else
                 (bound > threshold) & ((bound <= RELINEARISE_BAND * threshold) | ~determined))
        if not again.any():
            break
        R[again] = R[again] @ Rotation.from_rotvec(xi[again, :3]).as_matrix()
        t[again] += np.einsum("kij,kj->ki", R[again], xi[again, 3:])
        bound[again], xi[again] = _bounds(R[again], t[again], *(a[again] for a in planes), contacts,
                                          *(w[again] for w in weights), determined[again], free[again], shape, steps)
    return bound


def _regions(model, facets):
    """Where each contact may lie: its facet, or with patches all members of its facet's
    patch (the search picked one member only by the closed-form pose). Returns the region
    of each (K, n) facet, and CSR (indptr, members) of facet indices per region."""
    if model.patch_table is None:
        return facets, np.arange(model.num_facets + 1), np.arange(model.num_facets)
    return model.patches.labels[facets], model.patches.indptr, model.patches.members


def _facet_radii(model):
    """(m,) distance from each facet's centroid to its farthest vertex."""
    return np.linalg.norm(model.triangles - model.centroids[:, None], axis=2).max(axis=1)


def _bounds(R, t, normals, offsets, regions, contacts, wn, wx, determined, free, shape, steps):
    """The bound about (R, t) and the ξ the alternating minimisation reached: (K,), (K, 6)."""
    bound, xi = np.empty(len(R)), np.empty((len(R), 6))
    _bound_kernel(*(np.ascontiguousarray(a, dtype=np.float64) for a in
                    (R, t, normals, offsets, contacts.points, contacts.finger_normals, wn, wx)),
                  regions, *shape, determined, free, steps, bound, xi)
    return bound, xi


@numba.njit(cache=True)
def _bound_kernel(R, t, normals, offsets, points, finger_normals, wn, wx, regions, triangles, centres, radii,
                  indptr, members, threshold, determined, free, steps, bound, xi_out):
    """Per hypothesis: the plane quadratic (A, g, χ²_0), alternating minimisation of the
    linearised χ² from ξ = 0, and the closed-form minimum of the lower bound there. Where
    that bound does not hold (``determined`` false: a free direction, or a patch of several
    triangles, which need not be convex) the linearised χ² the minimisation reached."""
    n = points.shape[0]
    for k in range(R.shape[0]):
        A, g, H, g_n, A_n = np.zeros((6, 6)), np.zeros(6), np.zeros((6, 6)), np.zeros(6), np.zeros((3, 3))
        chi2_0 = 0.0
        p, G = np.empty((n, 3)), np.empty((n, 3, 6))
        for i in range(n):
            nrm = normals[k, i]
            p[i] = R[k].T @ (points[i] - t[k])
            G[i] = _motion(p[i])
            r_n = R[k] @ nrm + finger_normals[i]
            r_o = nrm @ p[i] + offsets[k, i]
            chi2_0 += wn[k, i] * (r_n @ r_n) + wx[k, i] * r_o**2
            # normal term: J_n = -R[n]×, J_nᵀJ_n = I - n nᵀ, J_nᵀ r_n = n × Rᵀ r_n
            A_n += wn[k, i] * (np.eye(3) - np.outer(nrm, nrm))
            g_n[:3] += wn[k, i] * np.cross(nrm, R[k].T @ r_n)
            j_o = nrm @ G[i]
            A += wx[k, i] * np.outer(j_o, j_o)
            g += wx[k, i] * r_o * j_o
            H += wx[k, i] * (G[i].T @ G[i])
        A[:3, :3] += A_n
        H[:3, :3] += A_n
        g += g_n
        H += 1e-12 * np.trace(H) * np.eye(6)
        many = np.any(indptr[regions[k] + 1] - indptr[regions[k]] > 1)
        reach = _reach(A, g, chi2_0, G, threshold) if many and not free[k] else np.full(n, np.inf)
        cand, count = _candidates(p, reach, regions[k], centres, radii, indptr, members)
        xi, last = _alternate(p, G, cand, count, triangles, centres, radii, wx[k], np.linalg.inv(H), g_n,
                              steps if determined[k] else 4 * steps)
        h, const, reached = np.zeros(6), chi2_0, 0.0
        for i in range(n):
            q = p[i] + G[i] @ xi
            d = q - _closest_of(q, cand[i, :count[i]], triangles, centres, radii, last[i])[0]
            u = d - (d @ normals[k, i]) * normals[k, i]      # in-plane: |u| = r_l at q
            h += wx[k, i] * (G[i].T @ u)
            const += wx[k, i] * (u @ u)
            r_n = R[k] @ (normals[k, i] + np.cross(xi[:3], normals[k, i])) + finger_normals[i]
            reached += wn[k, i] * (r_n @ r_n) + wx[k, i] * (d @ d)
        gh = g + h
        bound[k] = const - 2.0 * (h @ xi) - gh @ np.linalg.solve(A, gh) if determined[k] else reached
        xi_out[k] = xi


@numba.njit(cache=True)
def _alternate(p, G, cand, count, triangles, centres, radii, wx, H_inv, g_n, steps):
    """Minimise the linearised χ² over ξ, alternating closest points c_i in the contacts'
    regions with the ξ that best meets them: H ξ = -(g_n + Σ_i wx G_iᵀ (p_i - c_i)).
    Returns ξ (6,) and where each contact's closest triangle sits in its candidates."""
    xi, last = np.zeros(6), np.zeros(len(p), dtype=np.int64)
    for _ in range(steps):
        rhs = g_n.copy()
        for i in range(len(p)):
            c, last[i] = _closest_of(p[i] + G[i] @ xi, cand[i, :count[i]], triangles, centres, radii, last[i])
            rhs += wx[i] * (G[i].T @ (p[i] - c))
        xi = -(H_inv @ rhs)
    return xi, last


@numba.njit(cache=True)
def _reach(A, g, chi2_0, G, threshold):
    """How far each contact can move, to first order, among the poses whose plane χ² is
    within ``threshold``: |G_i ξ*| + sqrt(b · trace(G_i A⁻¹ G_iᵀ)), b = threshold - χ²_min."""
    A_inv = np.linalg.pinv(A)
    step = -(A_inv @ g)
    budget = max(threshold - (chi2_0 + g @ step), 0.0)
    reach = np.empty(len(G))
    for i in range(len(G)):
        reach[i] = np.sqrt(np.sum((G[i] @ step) ** 2)) + np.sqrt(budget * np.trace(G[i] @ A_inv @ G[i].T))
    return reach


@numba.njit(cache=True)
def _candidates(p, reach, regions, centres, radii, indptr, members):
    """Per contact, the facets of its region that a pose within noise can bring it to: those
    whose bounding sphere lies within (distance to the region) + reach of it. -> (n, s), (n,)"""
    size = 1
    for i in range(len(p)):
        size = max(size, indptr[regions[i] + 1] - indptr[regions[i]])
    cand, count = np.empty((len(p), size), dtype=np.int64), np.zeros(len(p), dtype=np.int64)
    for i in range(len(p)):
        lo, hi = indptr[regions[i]], indptr[regions[i] + 1]
        near = np.inf  # an upper bound on the distance from p_i to the region
        for e in range(lo, hi):
            near = min(near, np.sqrt(np.sum((p[i] - centres[members[e]]) ** 2)) + radii[members[e]])
        for e in range(lo, hi):
            f = members[e]
            if np.sqrt(np.sum((p[i] - centres[f]) ** 2)) - radii[f] <= near + reach[i]:
                cand[i, count[i]] = f
                count[i] += 1
    return cand, count


@numba.njit(cache=True)
def _closest_of(q, facets, triangles, centres, radii, start):
    """Closest point to q on the given triangles, and its position in ``facets``. facets[start]
    (the last answer) goes first, so the bounding spheres of most others rule them out."""
    best, out, at = np.inf, q, start
    for j in range(len(facets)):
        e = (start + j) % len(facets)
        f = facets[e]
        gap = np.sqrt(np.sum((q - centres[f]) ** 2)) - radii[f]
        if gap > 0.0 and gap * gap >= best:
            continue
        tri = triangles[f]
        c = closest_point_triangle(q, tri[0], tri[1], tri[2])
        d = (q - c) @ (q - c)
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
