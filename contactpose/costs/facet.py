"""The facet model of a contact: its facet's plane, and its facet's triangle.

For contact i (world point x̃_i, finger normal ñ_i) assigned to facet k (unit outward normal
n_k, offset d_k, triangle V_k) under the pose ``T_world_object = (R, t)``, with
p_i = Rᵀ (x̃_i - t) the contact in the object frame (costs.frame):

* normal residual (eq. 7, first term):     r_n = R n_k + ñ_i             (3,)
  Its norm is 2 sin(θ/2) for the angle θ between -ñ_i and R n_k.
* origin-invariant offset (research/errata.md): r_o = n_kᵀ p_i + d_k
  The signed distance of the contact from facet k's plane, in length units.
* lateral residual (the triangle):         r_l = sqrt(dist(p_i, V_k)² - r_o²)
  How far the contact lies outside its facet *triangle*, in the plane; as rows, the
  in-plane vector w from the triangle to the contact (|w| = r_l, :func:`lateral_rows`).

Whitened by the sensor noise (σ_n per normal axis, σ_x per position axis) they make the
default method's χ² = Σ_i |r_n|²/σ_n² + (r_o² + r_l²)/σ_x² (:func:`whitened_cost`): the
plane model without r_l, the triangle model with it.

Jacobians, in GTSAM's tangent order and convention (geometry.se3): rotation first, right
perturbation ξ = (ω, v), R' = R (I + [ω]×), t' = t + R v to first order, so that
dp/dξ = [[p]×, -I] and

* ``∂r_n/∂ξ = [-R [n_k]×, 0]``,
* ``∂r_o/∂ξ = [(n_k × p)ᵀ, -n_kᵀ]``,
* ``∂w/∂ξ = P [[p]×, -I]`` with P = u uᵀ beside an edge (u = w/|w|) and I - n_k n_kᵀ beside
  a corner; the rows are zero when the contact lies over its triangle (w = 0, flat). The
  vector w, not its norm r_l, so that Gauss-Newton's model of r_l² keeps all its curvature
  in p (research/tracking.md, "iSAM2 against batch LM").

Three forms of the one model:

* the residuals of many hypotheses at once (:func:`contact_residuals`, one compiled pass,
  for ranking thousands; the per-term functions are its readable reference, a test holds
  them equal);
* the packed rows of one hypothesis with their Jacobian (:func:`contact_rows`): ``[r_n / σ_n
  (3n: x, y, z of contact 0, then 1, ...), r_o / σ_x (n), w / σ_x (2n, point_to_facet only)]``,
  the per-contact robust kernel applied to each contact's block (:func:`robust_rows`,
  costs.robust), the rows the factor graph, the tracks and the sampler share;
* the plane's Gauss–Newton quantities (:func:`plane_jacobian`, :func:`normal_gradient`),
  which the in-facet bound (solvers.polish) assembles.

The peers score a pose with a variant that measures the normal's misfit as an angle and lets
each contact take the best of several candidate facets (:func:`angle_chi2`).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit

from contactpose.costs.frame import object_point
from contactpose.costs.robust import KERNEL_CODE, kernel_width, robust_scale
from contactpose.geometry.kernels import (  # 3-tuple kernels
    _point_triangle_d2,
    _t,
    closest_point_triangle,
    point_triangle_distance,
)

#: A lateral residual below this fraction of σ_x counts as 0 (rounding of the face projection).
LATERAL_ZERO_REL = 1e-9
#: Columns of :func:`pack_contacts`'s per-contact rows.
PACKED_COLUMNS = 20


# ------------------------------------------------------------ one contact ---

@njit(cache=True)
def plane_residual(R, t, normal, offset, point, finger_normal):
    """One contact on one facet plane: (p, r_n, r_o), p and r_n 3-tuples. R (3, 3), t (3,);
    normal (3,) n_k, offset d_k; point x̃ (3,), finger_normal ñ (3,)."""
    p = object_point(R, t, point)
    n0, n1, n2 = float(normal[0]), float(normal[1]), float(normal[2])
    return p, normal_residual(R, (n0, n1, n2), finger_normal), n0 * p[0] + n1 * p[1] + n2 * p[2] + offset


@njit(cache=True)
def normal_residual(R, normal, finger_normal):
    """r_n = R n_k + ñ (3-tuple) of one contact: R (3, 3), normal a 3-tuple, finger_normal (3,)."""
    n0, n1, n2 = normal
    return (R[0, 0] * n0 + R[0, 1] * n1 + R[0, 2] * n2 + float(finger_normal[0]),
            R[1, 0] * n0 + R[1, 1] * n1 + R[1, 2] * n2 + float(finger_normal[1]),
            R[2, 0] * n0 + R[2, 1] * n1 + R[2, 2] * n2 + float(finger_normal[2]))


@njit(cache=True)
def plane_jacobian(J, row_n, row_o, R, normal, p, inv_sn, inv_sx):
    """Write the whitened Jacobian rows of r_n (three, from ``row_n``: -R [n_k]×, 0) and of r_o
    (``row_o``: (n_k × p)ᵀ, -n_kᵀ) into J (m, 6)."""
    nk = normal
    for a in range(3):
        # row a of -R [n_k]×
        J[row_n + a, 0] = -(R[a, 1] * nk[2] - R[a, 2] * nk[1]) * inv_sn
        J[row_n + a, 1] = -(R[a, 2] * nk[0] - R[a, 0] * nk[2]) * inv_sn
        J[row_n + a, 2] = -(R[a, 0] * nk[1] - R[a, 1] * nk[0]) * inv_sn
        J[row_n + a, 3] = 0.0
        J[row_n + a, 4] = 0.0
        J[row_n + a, 5] = 0.0
    p0, p1, p2 = p
    J[row_o, 0] = (nk[1] * p2 - nk[2] * p1) * inv_sx
    J[row_o, 1] = (nk[2] * p0 - nk[0] * p2) * inv_sx
    J[row_o, 2] = (nk[0] * p1 - nk[1] * p0) * inv_sx
    J[row_o, 3] = -nk[0] * inv_sx
    J[row_o, 4] = -nk[1] * inv_sx
    J[row_o, 5] = -nk[2] * inv_sx


@njit(cache=True)
def plane_terms(R, t, normal, offset, point, finger_normal):
    """One contact on one facet plane with its Gauss–Newton quantities: (p, r_n, r_o, J_nᵀ r_n,
    n_k × p), 3-tuples but r_o: the offset row is j_o = (n_k × p, -n_k) and J_nᵀ J_n = I - n_k n_kᵀ
    (:func:`plane_residual`, :func:`normal_gradient`)."""
    p, r_n, r_o = plane_residual(R, t, normal, offset, point, finger_normal)
    n0, n1, n2 = float(normal[0]), float(normal[1]), float(normal[2])
    return p, r_n, r_o, normal_gradient(R, (n0, n1, n2), r_n), (n1 * p[2] - n2 * p[1], n2 * p[0] - n0 * p[2],
                                                                 n0 * p[1] - n1 * p[0])


@njit(cache=True)
def normal_gradient(R, normal, r_n):
    """J_nᵀ r_n = n_k × Rᵀ r_n (3-tuple), the rotation gradient of ½|r_n|²; its Gauss–Newton
    matrix is J_nᵀ J_n = I - n_k n_kᵀ. normal : 3-tuple n_k; r_n : 3-tuple."""
    n0, n1, n2 = normal
    r0 = R[0, 0] * r_n[0] + R[1, 0] * r_n[1] + R[2, 0] * r_n[2]  # Rᵀ r_n
    r1 = R[0, 1] * r_n[0] + R[1, 1] * r_n[1] + R[2, 1] * r_n[2]
    r2 = R[0, 2] * r_n[0] + R[1, 2] * r_n[1] + R[2, 2] * r_n[2]
    return (n1 * r2 - n2 * r1, n2 * r0 - n0 * r2, n0 * r1 - n1 * r0)


@njit(cache=True)
def in_plane(d, normal):
    """The part of the 3-tuple d in the plane of unit ``normal`` (3-tuple): d - (d·n) n, the
    lateral vector when d runs from the triangle's closest point to the contact."""
    s = -(d[0] * normal[0] + d[1] * normal[1] + d[2] * normal[2])
    return (d[0] + s * normal[0], d[1] + s * normal[1], d[2] + s * normal[2])


# -------------------------------------------------------- many hypotheses ---

def contact_residuals(R, t, obj_normals, obj_offsets, triangles, points, finger_normals):
    """r_n, r_o and r_l of every contact under every hypothesis, in one compiled pass.

    R : (H, 3, 3), t : (H, 3); obj_normals : (H, n, 3), obj_offsets : (H, n), triangles :
    (H, n, 3, 3) of the hypothesised facets; points, finger_normals : (n, 3)
    ->  r_n (H, n, 3), r_o (H, n), r_l (H, n)
    """
    h, n = np.shape(obj_offsets)
    r_n, r_o, r_l = np.empty((h, n, 3)), np.empty((h, n)), np.empty((h, n))
    _residuals(*(np.ascontiguousarray(a, dtype=np.float64) for a in
                 (R, t, obj_normals, obj_offsets, triangles, points, finger_normals)), r_n, r_o, r_l)
    return r_n, r_o, r_l


@numba.njit(cache=True)
def _residuals(R, t, normals, offsets, triangles, points, finger_normals, r_n, r_o, r_l):
    for h in range(R.shape[0]):
        for i in range(points.shape[0]):
            p, rn, r_o[h, i] = plane_residual(R[h], t[h], normals[h, i], offsets[h, i], points[i], finger_normals[i])
            r_n[h, i, 0], r_n[h, i, 1], r_n[h, i, 2] = rn
            tri = triangles[h, i]
            dist2 = _point_triangle_d2(p, _t(tri[0]), _t(tri[1]), _t(tri[2]))
            r_l[h, i] = np.sqrt(max(dist2 - r_o[h, i] ** 2, 0.0))


def normal_residuals(R, obj_normals, finger_normals):
    """r_n = R n_k + ñ_i.

    R : (H, 3, 3), obj_normals : (H, n, 3), finger_normals : (n, 3)  ->  (H, n, 3)
    """
    return np.einsum("hij,hnj->hni", R, obj_normals) + finger_normals[None]


def offset_residuals(p_obj, obj_normals, obj_offsets):
    """r_o = n_kᵀ p_i + d_k, the signed point-to-plane distance (origin-invariant).

    p_obj : (H, n, 3) contacts in the object frame, obj_normals : (H, n, 3),
    obj_offsets : (H, n)  ->  (H, n)
    """
    return np.einsum("hni,hni->hn", obj_normals, p_obj) + obj_offsets


def lateral_residuals(p_obj, triangles, r_offset):
    """r_l = sqrt(max(dist(p, triangle)² - r_o², 0)): distance outside the triangle, in-plane.

    p_obj : (H, n, 3), triangles : (H, n, 3, 3), r_offset : (H, n)  ->  (H, n)
    """
    h, n = r_offset.shape
    dist = point_triangle_distance(p_obj.reshape(-1, 3), triangles.reshape(-1, 3, 3))
    return np.sqrt(np.maximum(dist.reshape(h, n) ** 2 - r_offset**2, 0.0))


def whitened_cost(r_normal, r_offset, r_lateral, sigma_normal, sigma_position):
    """χ² of the default method: Σ_i |r_n|²/σ_n² + (r_o² + r_l²)/σ_x².

    r_normal : (H, n, 3), r_offset, r_lateral : (H, n)  ->  (H,)
    sigma_normal in radians, sigma_position in length units (per-axis standard deviations).
    """
    normal = np.einsum("hni,hni->h", r_normal, r_normal) / sigma_normal**2
    position = (np.sum(r_offset**2, axis=1) + np.sum(r_lateral**2, axis=1)) / sigma_position**2
    return normal + position


def contact_chi2(model, contacts, facets, poses, tolerance, point_to_facet=True):
    """Whitened χ² of :func:`contact_residuals` over the assigned contacts, the lateral term
    only with ``point_to_facet``. facets : (H, n) int, -1 unassigned; poses : (H, 4, 4) -> (H,)"""
    ok, safe = facets >= 0, np.maximum(facets, 0)
    r_n, r_o, r_l = contact_residuals(poses[:, :3, :3], poses[:, :3, 3], model.planes.normals[safe],
                                      model.planes.offsets[safe], model.triangles[safe], contacts.points,
                                      contacts.finger_normals)
    return whitened_cost(r_n * ok[..., None], r_o * ok, r_l * (ok & point_to_facet), tolerance.normal_noise,
                         tolerance.position_noise)


# ---------------------------------------------------- rows of one hypothesis ---

def pack_contacts(model, contacts, facets):
    """Per-contact factor data: normal (3), offset, triangle (9), point (3), finger normal (3),
    assigned (1.0, or 0.0 for facet -1: an unassigned finger, whose rows are 0).

    model : ObjectModel; contacts : Contacts; facets : (..., n) int  ->  (..., n, 20) float64
    """
    facets = np.asarray(facets)
    safe = np.maximum(facets, 0)
    data = np.empty(facets.shape + (PACKED_COLUMNS,))
    data[..., 0:3] = model.planes.normals[safe]
    data[..., 3] = model.planes.offsets[safe]
    data[..., 4:13] = model.triangles[safe].reshape(facets.shape + (9,))
    data[..., 13:16] = contacts.points
    data[..., 16:19] = contacts.finger_normals
    data[..., 19] = facets >= 0
    return data


def kernel_params(tolerance, robust="none", point_to_facet=True):
    """(6,) float64 factor settings: 1/σ_n, 1/σ_x, kernel width k, the r_l zero, point-to-facet
    (0/1), kernel code (0 none, 1 Huber, 2 Cauchy)."""
    k = kernel_width(robust)
    return np.array([1.0 / tolerance.normal_noise, 1.0 / tolerance.position_noise, k,
                     LATERAL_ZERO_REL * tolerance.position_noise, float(bool(point_to_facet)),
                     float(KERNEL_CODE[robust])])


def factor_dim(n, point_to_facet):
    """Rows of the batched contact factor of n contacts."""
    return n * (6 if point_to_facet else 4)


def lateral_norms(e, n):
    """r_l / σ_x of each contact (its two lateral rows' norm) from the error e (6n,) of a
    factor with point-to-facet rows and no robust kernel. -> (n,)"""
    return np.hypot(e[4 * n::2], e[4 * n + 1::2])


def factor_rows(T, data, params, jacobian=True):
    """The batched contact factor's error and Jacobian at a pose (solvers.factor_graph puts
    them in a gtsam.CustomFactor).

    T : (4, 4); data : (n, 20) from :func:`pack_contacts`; params : from :func:`kernel_params`.
    Returns e (m,) and J (m, 6) (None when not ``jacobian``), m = :func:`factor_dim`.
    """
    m = factor_dim(len(data), params[4] != 0.0)
    e = np.empty(m)
    J = np.empty((m if jacobian else 0, 6))
    contact_rows(np.ascontiguousarray(T, dtype=np.float64), data, params, e, J)
    return e, (J if jacobian else None)


@njit(cache=True)
def contact_rows(M, data, params, e, J):
    """Whitened (robust) contact residuals and their Jacobian w.r.t. the Pose3.

    M : (4, 4) pose; data : (n, 20) packed contacts; params : from :func:`kernel_params`;
    e : (m,) out; J : (m, 6) out, written unless it has 0 rows. Rows: 3n normal
    (contact-major), n offset, then 2n lateral (:func:`lateral_rows`, contact-major) when
    point-to-facet is on. The rows of an
    unassigned contact (data[i, 19] == 0) are 0.
    """
    n = data.shape[0]
    inv_sn, inv_sx, k, tiny = params[0], params[1], params[2], params[3]
    lateral = params[4] != 0.0
    kernel = int(params[5])
    want_j = J.shape[0] > 0
    R = M[:3, :3]
    t = M[:3, 3]
    for i in range(n):
        if data[i, 19] == 0.0:  # unassigned finger: no residual
            _zero_rows(e, J, (3 * i, 3 * i + 1, 3 * i + 2, 3 * n + i, 4 * n + 2 * i, 4 * n + 2 * i + 1), lateral, want_j)
            continue
        nk = data[i, 0:3]
        p, r_n, r_o = plane_residual(R, t, nk, data[i, 3], data[i, 13:16], data[i, 16:19])
        row = 3 * n + i
        for a in range(3):
            e[3 * i + a] = r_n[a] * inv_sn
        e[row] = r_o * inv_sx
        if want_j:
            plane_jacobian(J, 3 * i, row, R, nk, p, inv_sn, inv_sx)
        if lateral:
            lateral_rows(e, J, 4 * n + 2 * i, nk, p, data[i], inv_sx, tiny, want_j)
    if kernel != 0:
        robust_rows(e, J, n, lateral, kernel, k, want_j)


@njit(cache=True)
def lateral_rows(e, J, row, nk, p, datum, inv_sx, tiny, want_j):
    """The two lateral rows of one contact, from ``row`` on: w = the in-plane part of
    p - closest(p, V_k), in the facet's in-plane basis (e_1 along its first edge, e_2 = n_k × e_1),
    so that |w| = r_l. w is 0 over the triangle and affine in p on each side of it, so that
    Gauss-Newton's model of r_l² is exact there: ∂w/∂ξ = P [[p]×, -I] with P = I - n_k n_kᵀ
    beside a corner (w = p - corner, in-plane) and P = u uᵀ beside an edge (u = w/|w|).
    The scalar r_l of the same cost bends around each corner (its Hessian holds (I - u uᵀ)/r_l),
    which Gauss-Newton leaves out; that stalled iSAM2's trust region on fine meshes."""
    p0, p1, p2 = p
    c = closest_point_triangle(np.array((p0, p1, p2)), datum[4:7], datum[7:10], datum[10:13])
    w0, w1, w2 = p0 - c[0], p1 - c[1], p2 - c[2]
    w0, w1, w2 = in_plane((w0, w1, w2), nk)
    rl = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    f0, f1, f2 = datum[7] - datum[4], datum[8] - datum[5], datum[9] - datum[6]  # e_1: the first edge
    size = np.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
    f0, f1, f2 = f0 / size, f1 / size, f2 / size
    g0, g1, g2 = nk[1] * f2 - nk[2] * f1, nk[2] * f0 - nk[0] * f2, nk[0] * f1 - nk[1] * f0  # e_2 = n_k × e_1
    outside = rl > tiny
    corner = False
    for s in range(3):  # c is a corner itself (a vertex region), else a point of an edge
        corner = corner or (c[0] == datum[4 + 3 * s] and c[1] == datum[5 + 3 * s] and c[2] == datum[6 + 3 * s])
    for j in range(2):
        x, y, z = (f0, f1, f2) if j == 0 else (g0, g1, g2)
        along = x * w0 + y * w1 + z * w2
        e[row + j] = along * inv_sx if outside else 0.0
        if not want_j:
            continue
        if outside and not corner:  # v = (e_j·u) u
            x, y, z = along / (rl * rl) * w0, along / (rl * rl) * w1, along / (rl * rl) * w2
        if not outside:
            x = y = z = 0.0
        # the row e_jᵀ P [[p]×, -I] = [(v × p)ᵀ, -vᵀ], v = e_j beside a corner, (e_j·u) u beside an edge
        J[row + j, 0] = (y * p2 - z * p1) * inv_sx
        J[row + j, 1] = (z * p0 - x * p2) * inv_sx
        J[row + j, 2] = (x * p1 - y * p0) * inv_sx
        J[row + j, 3] = -x * inv_sx
        J[row + j, 4] = -y * inv_sx
        J[row + j, 5] = -z * inv_sx


@njit(cache=True)
def robust_rows(e, J, n, lateral, kernel, k, want_j):
    """The per-contact robust kernel on the contact factor's rows, in place:
    ẽ = f e, ∂ẽ = f ∂e + (g' - f) û ûᵀ ∂e (costs.robust.robust_scale)."""
    rows = np.empty(6, np.int64)
    nrow = 6 if lateral else 4
    for i in range(n):
        rows[0], rows[1], rows[2], rows[3] = 3 * i, 3 * i + 1, 3 * i + 2, 3 * n + i
        rows[4], rows[5] = 4 * n + 2 * i, 4 * n + 2 * i + 1
        s2 = 0.0
        for a in range(nrow):
            s2 += e[rows[a]] ** 2
        s = np.sqrt(s2)
        if s == 0.0:
            continue
        fs, gp = robust_scale(s, kernel, k)
        if want_j and (fs != 1.0 or gp != 1.0):
            for c6 in range(6):
                proj = 0.0
                for a in range(nrow):
                    proj += e[rows[a]] * J[rows[a], c6]
                proj /= s2  # (ûᵀ ∂e) / s
                for a in range(nrow):
                    J[rows[a], c6] = fs * J[rows[a], c6] + (gp - fs) * e[rows[a]] * proj
        for a in range(nrow):
            e[rows[a]] *= fs


@njit(cache=True)
def _zero_rows(e, J, rows, lateral, want_j):
    """Zero the residual rows (and Jacobian rows) of one contact; the lateral rows only if present."""
    for a in range(6 if lateral else 4):
        e[rows[a]] = 0.0
        if want_j:
            for c6 in range(6):
                J[rows[a], c6] = 0.0


# ------------------------------------------------------------------ peers ---

def angle_chi2(p, nu, candidates, triangles, normals, sigma_position, sigma_normal):
    """The peers' whitened χ² of contacts: for each, the least over its candidate facets of
    d²/σ_x² + θ²/σ_n², d its distance to the facet's triangle and θ the angle between its
    outward normal and the facet's.
    p, nu : (N, 3) object-frame points and outward normals; candidates : (N, D) int facets;
    triangles : (m, 3, 3), normals : (m, 3); σ_n in radians. -> (N,)"""
    D = candidates.shape[1]
    d = point_triangle_distance(np.repeat(p, D, axis=0), triangles[candidates.ravel()]).reshape(-1, D)
    cos = np.einsum("ij,ikj->ik", nu, normals[candidates])
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    return ((d / sigma_position) ** 2 + (angle / sigma_normal) ** 2).min(axis=1)
