"""The smooth-normal model of a contact, for fine tessellations of smooth surfaces.

On a mesh whose facets are a few sensor sigmas wide a contact's facet is ambiguous, and the
facets' own normals jump from facet to facet. Here a contact's normal residual is taken
against the normal interpolated over its facet from its corners' normals
(ObjectModel.smooth_normals) at the contact's place p = Rᵀ(x̃ - t): n(p) = m/|m|,
m = n_a + M (p - a), in the object frame,

    r_n = W_f (n(p) + Rᵀ ñ),    W_f = C_f^(-1/2),   C_f = σ_n² I + S_f + σ_x² Dn Dnᵀ,

whitened by the sensor's normal noise, the mesh's own normals straying from n(p) (S_f,
ObjectModel.normal_scatter) and the contact's position noise along the surface (Dn at the
facet's centroid; ObjectModel.normal_whitening). The offset and lateral rows are the facet
model's (costs.facet), and so is the per-contact robust kernel.

Where a rounded fingertip sits on a crease (a convex edge the smooth normals do not blend
across, ObjectModel.crease_edges), its normal lies on the edge's arc of normals: the contact
then reads the edge when it fits better than the face (:func:`_crease_rows`); the
association scores the arcs alike (:func:`arc_misfits`; research/tracking.md, "Contacts on
creases").
"""

from __future__ import annotations

import numpy as np
from numba import njit

from contactpose.costs.facet import contact_rows, pack_contacts, robust_rows
from contactpose.costs.frame import object_normal, object_point
from contactpose.geometry.kernels import _axpy, _cross, _dot, _t
from contactpose.geometry.se3 import hat3

#: Columns of :func:`smooth_data`'s per-contact rows.
SMOOTH_COLUMNS = 61


def smooth_data(model, contacts, facets, tolerance):
    """The smooth factor's inputs: (pack_contacts data (..., n, 20), smooth (..., n, 61): per
    contact M (9, row-major), a (3), n_a (3), assigned (1.0 or 0.0), W_f (9, row-major) of
    ObjectModel.normal_whitening, then its facet's three ObjectModel.crease_edges (3 × 12, NaN
    where an edge is no crease)). facets : (..., n) int, as for costs.facet.pack_contacts."""
    facets = np.asarray(facets)
    safe = np.maximum(facets, 0)
    M, corner = model.smooth_normals
    smooth = np.empty(facets.shape + (SMOOTH_COLUMNS,))
    smooth[..., 0:9] = M[safe].reshape(facets.shape + (9,))
    smooth[..., 9:12] = model.triangles[safe, 0]
    smooth[..., 12:15] = corner[safe]
    smooth[..., 15] = facets >= 0
    W = model.normal_whitening(tolerance.normal_noise, tolerance.position_noise)
    smooth[..., 16:25] = W[safe].reshape(facets.shape + (9,))
    smooth[..., 25:61] = model.crease_edges[safe].reshape(facets.shape + (36,))
    return pack_contacts(model, contacts, facets), smooth


@njit(cache=True)
def smooth_rows(T, data, params, smooth, place, e, J):
    """The contact rows (costs.facet.contact_rows, no kernel), their normal rows replaced by the
    smooth ones (:func:`_smooth_normal_rows`), then the kernel of ``params``."""
    plain = params.copy()
    plain[5] = 0.0
    contact_rows(T, data, plain, e, J)
    _smooth_normal_rows(T, data, smooth, place, params[0], params[1], e, J)
    if params[5] != 0.0:
        robust_rows(e, J, data.shape[0], params[4] != 0.0, int(params[5]), params[2], True)


@njit(cache=True)
def _smooth_normal_rows(T, data, smooth, place, inv_sn, inv_sx, e, J):
    """Overwrite the 3n normal rows of e and J with each contact's face rows
    r_n = W (n(p) + Rᵀ ñ), n = m/|m|, m = n_a + M (p - a), p = Rᵀ(x̃ - t) (smooth: from
    :func:`smooth_data`): ∂/∂ω = W (Dn [p]× + [Rᵀñ]×), ∂/∂v = -W Dn, Dn = (I - n nᵀ) M / |m|;
    without ``place``, Dn = 0 in the Jacobian. Where a crease edge of the facet costs less
    (:func:`_crease_rows`), its rows instead."""
    R, t = np.ascontiguousarray(T[:3, :3]), T[:3, 3].copy()
    edge_e, edge_J = np.empty(3), np.empty((3, 6))
    for i in range(data.shape[0]):
        rows = slice(3 * i, 3 * i + 3)
        if smooth[i, 15] == 0.0:
            e[rows] = 0.0
            J[rows] = 0.0
            continue
        M = smooth[i, 0:9].copy().reshape((3, 3))
        W = smooth[i, 16:25].copy().reshape((3, 3))
        p = np.array(object_point(R, t, data[i, 13:16]))
        w = -np.array(object_normal(R, data[i, 16:19]))  # Rᵀ ñ
        m = smooth[i, 12:15] + M @ (p - smooth[i, 9:12])
        size = np.sqrt(m @ m)
        nu = m / size
        e[rows] = W @ (nu + w)
        Dn = (np.eye(3) - np.outer(nu, nu)) @ M / size if place else np.zeros((3, 3))
        J[rows, :3] = W @ (Dn @ hat3(p) + hat3(w))  # Dn, the hats: fresh, contiguous
        J[rows, 3:] = -(W @ Dn)
        best = e[rows] @ e[rows]
        for k in range(3):
            edge = smooth[i, 25 + 12 * k:37 + 12 * k]
            if np.isnan(edge[0]):
                continue
            cost = _crease_rows(p, -w, data[i, 0:3], edge, place, inv_sn, inv_sx, edge_e, edge_J)
            if cost < best:
                best = cost
                e[rows] = edge_e
                J[rows] = edge_J


@njit(cache=True)
def _crease_rows(p, nu, n_f, edge, place, inv_sn, inv_sx, out, J):
    """The rows of a contact on a crease edge (edge: a, e, u, n_g of ObjectModel.crease_edges)
    whose measured outward normal ν (object frame) lies in the edge's arc of normals from n_f
    to n_g: its normal's residual to the arc's nearest direction ν* = Pν/|Pν| (P = I - e eᵀ),
    in the orthonormal axes e, ν* (ν - ν* = (ν·e) e + (|Pν| - 1) ν*), over σ_n, and the contact's
    distance across the edge in f's plane, u·(p - a), over σ_x (zero Jacobian without
    ``place``), written to out (3,) and J (3, 6). ∂ν/∂ω = [ν]×, ∂p/∂ω = [p]×, ∂p/∂v = -I.
    -> the rows' squared norm, or inf where ν lies outside the arc."""
    along, size, star, inside = _arc_nearest(nu, n_f, edge)
    if not inside:
        return np.inf
    a, ax, u = edge[0:3], edge[3:6], edge[6:9]
    out[0] = along * inv_sn
    out[1] = (size - 1.0) * inv_sn
    out[2] = (u @ (p - a)) * inv_sx
    hat_nu = hat3(nu)
    J[0, :3] = (ax @ hat_nu) * inv_sn
    J[1, :3] = (np.array(star) @ hat_nu) * inv_sn
    J[0:2, 3:] = 0.0
    if place:
        J[2, :3] = (u @ hat3(p)) * inv_sx
        J[2, 3:] = -u * inv_sx
    else:
        J[2] = 0.0
    return out @ out


@njit(cache=True)
def _arc_nearest(nu, n_f, edge):
    """The direction ν* = Pν/|Pν| (P = I - e eᵀ) of a crease edge's arc of normals from n_f
    to n_g (edge: a, e, u, n_g of ObjectModel.crease_edges) nearest to the unit ν (object
    frame): (ν·e, |Pν|, ν* (3-tuple), whether ν* lies inside the arc, not beyond its ends)."""
    ax, n_g = _t(edge[3:6]), _t(edge[9:12])
    along = _dot(_t(nu), ax)
    proj = _axpy(-along, ax, _t(nu))
    size = np.sqrt(_dot(proj, proj))
    if size < 1e-12:
        return along, size, proj, False
    star = (proj[0] / size, proj[1] / size, proj[2] / size)
    inside = _dot(_cross(_t(n_f), star), ax) > 0.0 and _dot(_cross(star, n_g), ax) > 0.0
    return along, size, star, inside


def touch_chi2(T, data, params, smooth=None):
    """χ² = Σ_i 2ρ(s_i) of H tracks' touches, each at its own pose, from one compiled pass: the
    kernel's rows of the facet model (costs.facet.contact_rows, ``smooth`` None) or of the
    smooth model (:func:`smooth_rows`) squared and summed (each robust row block has norm
    g(s) = √(2ρ(s))). T : (H, 4, 4); data : (H, n, 20); params : costs.facet.kernel_params with the
    kernel; smooth : (H, n, SMOOTH_COLUMNS) or None. -> (H,)"""
    T = np.ascontiguousarray(T, dtype=np.float64)
    if smooth is None:
        return _stacked_chi2(T, data, params, np.zeros(data.shape[:2] + (SMOOTH_COLUMNS,)), False)
    return _stacked_chi2(T, data, params, smooth, True)


@njit(cache=True)
def _stacked_chi2(T, data, params, smooth, smooth_on):
    m = data.shape[1] * (6 if params[4] != 0.0 else 4)  # factor_dim
    e, J = np.empty(m), np.empty((m, 6))
    out = np.empty(T.shape[0])
    for h in range(T.shape[0]):
        if smooth_on:
            smooth_rows(T[h], data[h], params, smooth[h], True, e, J)
        else:
            contact_rows(T[h], data[h], params, e, J[:0])
        out[h] = e @ e
    return out


@njit(cache=True)
def arc_misfits(nu, n_f, edges, weight):
    """weight · |ν - ν*|² to the arc of each of a facet's three edges (edges (3, 12) of
    ObjectModel.crease_edges; :func:`_arc_nearest`), inf where the edge is no crease or ν*
    would lie beyond the arc's ends. -> 3-tuple"""
    return (_arc_misfit(nu, n_f, edges[0], weight), _arc_misfit(nu, n_f, edges[1], weight),
            _arc_misfit(nu, n_f, edges[2], weight))


@njit(cache=True)
def _arc_misfit(nu, n_f, edge, weight):
    if np.isnan(edge[0]):
        return np.inf
    along, size, _, inside = _arc_nearest(nu, n_f, edge)
    return weight * (along * along + (size - 1.0) ** 2) if inside else np.inf


NO_ARCS = (np.inf, np.inf, np.inf)
