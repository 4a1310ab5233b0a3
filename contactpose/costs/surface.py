"""The surface model of a contact: where on the closed mesh a contact (point, normal) may lie.

A contact (p, ν) in the object frame (ν the outward surface normal it measures) lies on a
*feature* of the surface with ν in that feature's normal cone (research/surface.md):

* a face interior: the face normal;
* a convex edge: the great-circle arc between its two faces' normals (a rounded fingertip
  rolling over the edge);
* a vertex: the directions ν with ν · (u − v) <= 0 for every neighbour u (no edge at it
  rises above the fingertip's tangent plane; model.surface.normal_cone_rays). At a convex
  vertex, the convex cone its faces' normals span; at one with concave edges, a smaller
  cone; at a saddle, none;
* a concave edge: only its faces' normals, which the faces already give.

The whitened cost of a contact on a feature is c = d(p, feature)²/σ_x² + |ν − ν*|²/σ_n², where
ν* is the direction of the cone nearest to ν (|ν − ν*| = 2 sin(θ/2) for the angle θ to the
cone, the norm of the residual r_n of costs.facet). :func:`land` finds the feature of least
cost near a starting facet, by walking over the facets that share a vertex
(model.surface.SurfaceTopology), and the pose's cost is

    χ²_S(ξ) = Σ_i |p_i(ξ) − q_i|²/σ_x² + |ν_i(ξ) − ν*_i|²/σ_n²,

with p_i, ν_i the contact point and outward normal in the object frame under the pose moved
by ξ (geometry.se3.retract), q_i the closest point of its feature and ν*_i the nearest
direction of that feature's normal cone (:class:`SurfaceResiduals`, its rows and Jacobian;
solvers.surface minimises it, the tracks take it as a factor, the sampler as a likelihood).
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numba
import numpy as np

from contactpose.costs.frame import object_frame, object_normal, object_point
from contactpose.costs.robust import robust_rho
from contactpose.geometry.kernels import (
    _closest_on_segment,
    _cross,
    _d2,
    _dot,
    _sub,
    _t,
    _triangle_feature,
    _unit,
    point_triangle_distance,
)
from contactpose.geometry.se3 import hat, hat3, retract

#: Steps of the walk from facet to facet (each to a facet sharing a vertex).
MAX_WALK = 16
#: Feature kinds reported by :func:`land`.
FACE, EDGE, VERTEX = 0, 1, 2
#: A vertex with more cone rays than this gets only the arcs between them, not the inside of
#: its cone (the inside test visits every triple of rays).
MAX_CONE_FACES = 24


@dataclass
class Landing:
    """Where k contacts land (:func:`land`), and how their residuals move with them.

    cost (k,) whitened cost; facet (k,) the facet a contact lands on (for an edge or vertex,
    its face whose normal is nearest ν*); kind (k,) FACE / EDGE / VERTEX; q (k, 3) closest
    point of the feature, cone (k, 3) ν*. For the Jacobian of p − q and ν − ν*:
    pcode (k,) 0 q fixed (a corner), 1 q slides along the line pdir, 2 in the plane of normal
    pdir; ncode (k,) 0 ν* fixed, 1 ν* slides on the arc from arc[:, 0] to arc[:, 1], 2 ν* = ν
    (inside a vertex's cone).
    """

    cost: np.ndarray
    facet: np.ndarray
    kind: np.ndarray
    q: np.ndarray
    cone: np.ndarray
    pcode: np.ndarray
    pdir: np.ndarray
    ncode: np.ndarray
    arc: np.ndarray


def land(topology, triangles, normals, valid, points, nu, start, sigma_position, sigma_normal):
    """The feature of least whitened cost for each contact, walking from ``start``.

    triangles : (m, 3, 3), normals : (m, 3), valid : (m,) bool of the model; points, nu :
    (k, 3) contacts and their outward unit normals in the object frame; start : (k,) facets
    to walk from (-1: left out, NaN rows). -> Landing
    """
    k = len(start)
    out = Landing(np.full(k, np.nan), np.asarray(start, dtype=np.int64).copy(), np.zeros(k, dtype=np.int64),
                  np.full((k, 3), np.nan), np.full((k, 3), np.nan), np.zeros(k, dtype=np.int64),
                  np.zeros((k, 3)), np.zeros(k, dtype=np.int64), np.zeros((k, 2, 3)))
    _land(*topology.arrays, np.ascontiguousarray(triangles, dtype=np.float64),
          np.ascontiguousarray(normals, dtype=np.float64), np.asarray(valid, dtype=np.bool_),
          np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(nu, dtype=np.float64),
          1.0 / sigma_position**2, 1.0 / sigma_normal**2,
          out.cost, out.facet, out.kind, out.q, out.cone, out.pcode, out.pdir, out.ncode, out.arc)
    return out


@numba.njit(cache=True)
def _land(fv, vpos, edge_nbr, edge_convex, vf_ptr, vf, cone_ptr, cone_rays, cone_bound, tri, normals, valid, points,
          nu, wx, wn, cost, facet, kind, q, cone, pcode, pdir, ncode, arc):
    for i in range(len(facet)):
        if facet[i] < 0:
            continue
        p, n = _t(points[i]), _t(nu[i])
        cur = facet[i]
        for _ in range(MAX_WALK):
            best = _best_near(cur, p, n, fv, vpos, edge_nbr, edge_convex, vf_ptr, vf, cone_ptr, cone_rays,
                              cone_bound, tri, normals, valid, wx, wn)
            if best[1] == cur:
                break
            cur = best[1]
        cost[i], facet[i], kind[i], pcode[i], ncode[i] = best[0], best[1], best[2], best[5], best[7]
        for a in range(3):
            q[i, a], cone[i, a], pdir[i, a] = best[3][a], best[4][a], best[6][a]
            arc[i, 0, a], arc[i, 1, a] = best[8][a], best[9][a]


@numba.njit(cache=True)
def _best_near(cur, p, n, fv, vpos, edge_nbr, edge_convex, vf_ptr, vf, cone_ptr, cone_rays, cone_bound, tri, normals,
               valid, wx, wn):
    """Least-cost feature among the faces, edges and vertices of the facets sharing a vertex
    with ``cur``. -> (cost, facet, kind, closest point, ν*, pcode, pdir, ncode, arc ends)"""
    zero = (0.0, 0.0, 0.0)
    best = (np.inf, cur, FACE, p, n, 0, zero, 0, zero, zero)
    for c in range(3):
        u = fv[cur, c]
        for e in range(vf_ptr[u], vf_ptr[u + 1]):
            best = _facet_features(best, p, n, vf[e], fv, vpos, edge_nbr, edge_convex, vf_ptr, vf, cone_ptr,
                                   cone_rays, cone_bound, tri, normals, wx, wn)
    return best


@numba.njit(cache=True)
def _facet_features(best, p, n, g, fv, vpos, edge_nbr, edge_convex, vf_ptr, vf, cone_ptr, cone_rays, cone_bound, tri,
                    normals, wx, wn):
    """``best`` (as :func:`_best_near` returns it) or, where cheaper, one of facet g's own
    features: its face, its convex edges, its vertices with a normal cone."""
    zero = (0.0, 0.0, 0.0)
    x, code, direction = _triangle_feature(p, _t(tri[g, 0]), _t(tri[g, 1]), _t(tri[g, 2]))
    d2 = wx * _d2(p, x)
    if d2 < best[0]:
        ng = _t(normals[g])
        total = d2 + wn * _d2(n, ng)
        if total < best[0]:
            best = (total, g, FACE, x, ng, code, direction, 0, zero, zero)
    for j in range(3):
        h = edge_nbr[g, j]
        if h < 0 or not edge_convex[g, j]:
            continue
        a, b = _t(vpos[fv[g, j]]), _t(vpos[fv[g, (j + 1) % 3]])
        x, code, direction = _segment_feature(p, a, b)
        d2 = wx * _d2(p, x)
        if d2 < best[0]:
            ng, nh = _t(normals[g]), _t(normals[h])
            s, inner = _arc_nearest(n, ng, nh)
            total = d2 + wn * _d2(n, s)
            if total < best[0]:
                best = (total, g if _dot(s, ng) >= _dot(s, nh) else h, EDGE, x, s, code, direction,
                        1 if inner else 0, ng, nh)
    for j in range(3):
        w = fv[g, j]
        if cone_ptr[w + 1] == cone_ptr[w]:
            continue
        x = _t(vpos[w])
        d2 = wx * _d2(p, x)
        if d2 + wn * _beyond_cone2(n, cone_bound[w]) < best[0]:
            s, near, ncode, ea, eb = _cone_nearest(n, cone_rays[cone_ptr[w]:cone_ptr[w + 1]],
                                                   vf[vf_ptr[w]:vf_ptr[w + 1]], normals)
            total = d2 + wn * _d2(n, s)
            if total < best[0]:
                best = (total, near, VERTEX, x, s, 0, zero, ncode, ea, eb)
    return best


@numba.njit(cache=True)
def facet_surface_cost(p, n, f, fv, vpos, edge_nbr, edge_convex, cone_ptr, cone_rays, cone_bound, vf_ptr, vf, tri,
                       normals, w):
    """The least cost, in length² (d² + w |ν − ν*|², w = σ_x²/σ_n²), of a contact (p, ν
    outward, 3-tuples) on facet f's own features (:func:`_facet_features` with σ_x = 1): the
    surface model's cost of one facet."""
    zero = (0.0, 0.0, 0.0)
    start = (np.inf, f, FACE, p, n, 0, zero, 0, zero, zero)
    return _facet_features(start, p, n, f, fv, vpos, edge_nbr, edge_convex, vf_ptr, vf, cone_ptr, cone_rays,
                           cone_bound, tri, normals, 1.0, w)[0]


@numba.njit(cache=True)
def _beyond_cone2(n, bound):
    """A lower bound on |n − ν*|² over a vertex's cone, from its axis and half-angle
    (model.surface.cone_bounds): the chord of the angle by which n lies beyond the half-angle."""
    c = n[0] * bound[0] + n[1] * bound[1] + n[2] * bound[2]
    beyond = np.arccos(max(-1.0, min(1.0, c))) - bound[3]
    return 0.0 if beyond <= 0.0 else 2.0 - 2.0 * np.cos(beyond)


@numba.njit(cache=True)
def _segment_feature(p, a, b):
    """Closest point to p on segment ab: (point, 1, unit direction) inside it, (end, 0, 0) at an end."""
    x = _closest_on_segment(p, a, b)
    d = _sub(b, a)
    s = _dot(_sub(x, a), d)
    if 0.0 < s < _dot(d, d):
        return x, 1, _unit(d)
    return x, 0, (0.0, 0.0, 0.0)


@numba.njit(cache=True)
def _arc_nearest(n, a, b):
    """Direction of the minor great-circle arc from a to b (unit 3-tuples) nearest to n, and
    whether it lies inside the arc (not at an end)."""
    w = _cross(a, b)
    ww = _dot(w, w)
    if ww < 1e-24:
        return (a if _dot(n, a) >= _dot(n, b) else b), False
    s = _dot(n, w) / ww
    m = (n[0] - s * w[0], n[1] - s * w[1], n[2] - s * w[2])  # n projected on the arc's plane
    if _dot(m, m) > 1e-24:
        m = _unit(m)
        if _dot(_cross(a, m), w) > 0.0 and _dot(_cross(m, b), w) > 0.0:
            return m, True
    return (a if _dot(n, a) >= _dot(n, b) else b), False


@numba.njit(cache=True)
def _cone_nearest(n, rays, faces, normals):
    """Direction of the convex cone spanned by ``rays`` (k, 3) nearest to n, the face (of
    ``faces``, indices into ``normals``) whose normal is nearest to it, and how it moves with n
    (ncode of :class:`Landing`, the arc's ends). Inside the cone when some three of the rays
    span n with non-negative weights; else on the arc between some two of them, or at one."""
    k = len(rays)
    zero = (0.0, 0.0, 0.0)
    if k <= MAX_CONE_FACES:
        for a in range(k):
            na = _t(rays[a])
            for b in range(a + 1, k):
                nb = _t(rays[b])
                ab = _cross(na, nb)
                for c in range(b + 1, k):
                    nc = _t(rays[c])
                    det = _dot(ab, nc)
                    if abs(det) < 1e-12:
                        continue
                    la = _dot(_cross(nb, nc), n) / det
                    lb = _dot(_cross(nc, na), n) / det
                    lc = _dot(ab, n) / det
                    if la >= 0.0 and lb >= 0.0 and lc >= 0.0:
                        return n, _nearest_face(n, faces, normals), 2, zero, zero
    best, bd, code, ea, eb = _t(rays[0]), np.inf, 0, zero, zero
    for a in range(k):
        na = _t(rays[a])
        for b in range(a + 1, k):
            nb = _t(rays[b])
            s, inner = _arc_nearest(n, na, nb)
            d = _d2(n, s)
            if d < bd:
                best, bd, code, ea, eb = s, d, 1 if inner else 0, na, nb
        d = _d2(n, na)
        if d < bd:
            best, bd, code = na, d, 0
    return best, _nearest_face(best, faces, normals), code, ea, eb


@numba.njit(cache=True)
def _nearest_face(s, faces, normals):
    best, bd = faces[0], -np.inf
    for f in faces:
        d = _dot(s, _t(normals[f]))
        if d > bd:
            best, bd = f, d
    return best


def landing(model, contacts, R, t, facets, tolerance, widen=1.0):
    """Where the contacts of one pose (R (3, 3), t (3,)) land (:func:`land` -> Landing), walking
    from ``facets`` ((n,) int, -1: an unassigned finger, left out); widen : σ_x times this."""
    p, nu = object_frame(R, t, contacts.points, contacts.finger_normals)
    return land(model.topology, model.triangles, model.planes.normals, model.planes.valid, p, nu, facets,
                widen * tolerance.position_noise, tolerance.normal_noise)


class SurfaceResiduals:
    """χ²_S of one hypothesis as a function of the right perturbation ξ of the pose (R, t):
    whitened residuals (6 n',) for the n' assigned fingers, position parts (p − q)/σ_x then
    normal parts (ν − ν*)/σ_n, and their Jacobian (6 n', 6), the features held where they are
    (q sliding on its face, edge or at its corner, ν* on its arc; research/surface.md)."""

    def __init__(self, model, contacts, R, t, start, tolerance, widen):
        self.model, self.contacts, self.R, self.t, self.tolerance = model, contacts, R, t, tolerance
        self.start, self.used = start, start >= 0
        self.sx, self.sn = widen * tolerance.position_noise, tolerance.normal_noise
        self.widen = widen
        self._at = None

    def _landing(self, xi):
        if self._at is None or not np.array_equal(self._at[0], xi):
            R, t = retract(self.R[None], self.t[None], xi[None])
            p, nu = object_frame(R[0], t[0], self.contacts.points, self.contacts.finger_normals)
            got = landing(self.model, self.contacts, R[0], t[0], self.start, self.tolerance, self.widen)
            self._at = (xi.copy(), p[self.used], nu[self.used], got)
        return self._at[1:]

    @property
    def landed(self):
        """The Landing of the last evaluation."""
        return self._at[3]

    def residuals(self, xi):
        p, nu, got = self._landing(xi)
        u = self.used
        return np.concatenate([((p - got.q[u]) / self.sx).ravel(), ((nu - got.cone[u]) / self.sn).ravel()])

    def jacobian(self, xi):
        p, nu, got = self._landing(xi)
        u = self.used
        Jr = gtsam.Rot3.ExpmapDerivative(xi[:3])
        k = len(p)
        dp = np.zeros((k, 3, 6))  # p = Exp(ω)ᵀ p₀ − v, ν = Exp(ω)ᵀ ν₀
        dp[:, :, :3] = hat(p + xi[3:]) @ Jr
        dp[:, :, 3:] = -np.eye(3)
        dnu = hat(nu) @ Jr
        Jp = _position_projector(got.pcode[u], got.pdir[u]) @ dp / self.sx
        Jn = np.zeros((k, 3, 6))
        Jn[:, :, :3] = _normal_projector(nu, got.cone[u], got.ncode[u], got.arc[u]) @ dnu / self.sn
        return np.concatenate([Jp.reshape(-1, 6), Jn.reshape(-1, 6)])


def _position_projector(code, direction):
    """∂(p − q)/∂p with q the closest point of a fixed feature: I at a corner, I − eeᵀ on a
    line of direction e, nnᵀ in a plane of normal n. -> (k, 3, 3)"""
    outer = np.einsum("ki,kj->kij", direction, direction)
    eye = np.broadcast_to(np.eye(3), outer.shape)
    return np.where((code == 1)[:, None, None], eye - outer, np.where((code == 2)[:, None, None], outer, eye))


def _normal_projector(nu, cone, code, arc):
    """∂(ν − ν*)/∂ν: I for a fixed ν*, 0 inside a vertex's cone (ν* = ν), and on an arc of
    plane normal w, where ν* = m/|m| with m = (I − wwᵀ)ν: I − (I − ν*ν*ᵀ)(I − wwᵀ)/|m|. -> (k, 3, 3)"""
    eye = np.broadcast_to(np.eye(3), (len(nu), 3, 3))
    out = np.where((code == 2)[:, None, None], 0.0, eye)
    on_arc = np.flatnonzero(code == 1)
    if len(on_arc):
        w = np.cross(arc[on_arc, 0], arc[on_arc, 1])
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        plane = np.eye(3) - np.einsum("ki,kj->kij", w, w)
        m = np.einsum("kij,kj->ki", plane, nu[on_arc])
        s = cone[on_arc]
        tangent = np.eye(3) - np.einsum("ki,kj->kij", s, s)
        out[on_arc] = np.eye(3) - tangent @ plane / np.linalg.norm(m, axis=1)[:, None, None]
    return out


def surface_residuals(model, contacts, R, t, facets, tolerance, widen=1.0):
    """Whitened residuals of χ²_S at the pose (R, t), (6 n',): see :class:`SurfaceResiduals`."""
    return SurfaceResiduals(model, contacts, R, t, np.asarray(facets), tolerance, widen).residuals(np.zeros(6))


def face_costs(model, contacts, R, t, facets, tolerance, widen=1.0):
    """Each assigned contact's whitened cost on its own facet, face normal and triangle,
    d(p, V_f)²/(widen σ_x)² + |ν − n_f|²/σ_n²: the surface model held to the hypothesis's
    facets. facets : (n,) int, -1 left out -> (n',)"""
    p, nu = object_frame(R, t, contacts.points, contacts.finger_normals)
    used = facets >= 0
    f = facets[used]
    d = point_triangle_distance(p[used], model.triangles[f])
    return (d / (widen * tolerance.position_noise)) ** 2 + np.sum((nu[used] - model.planes.normals[f]) ** 2,
                                                                    axis=1) / tolerance.normal_noise**2


def robust_cost(model, contacts, poses, facets, tolerance, robust):
    """Σ_i ρ(√c_i) of the surface model at poses (W, 4, 4), c_i each contact's whitened landing
    cost walking from ``facets`` (n,), ρ the kernel named ``robust`` (costs.robust): the
    negative log-likelihood the sampler's surface posterior takes. -> (W,)"""
    p, nu = object_frame(poses[:, :3, :3], poses[:, :3, 3], contacts.points, contacts.finger_normals)
    start = np.tile(facets, len(poses))
    cost = land(model.topology, model.triangles, model.planes.normals, model.planes.valid, p.reshape(-1, 3),
                nu.reshape(-1, 3), start, tolerance.position_noise, tolerance.normal_noise).cost
    return robust_rho(np.sqrt(cost), robust).reshape(len(poses), -1).sum(axis=1)


@numba.njit(cache=True)
def surface_rows(R, t, points, finger_normals, facets, topology, tri, normals, valid, sigma_position, sigma_normal,
                 e, J):
    """χ²_S's whitened rows at the pose (R (3, 3), t (3,)) and their Jacobian in the right
    perturbation ξ = (ω, v) at ξ = 0, compiled: :class:`SurfaceResiduals` without its Python
    side. Each assigned contact (facets (n,) int, -1: left out) lands walking from its facet,
    which ``facets`` then holds; rows (p − q)/σ_x of the used contacts first, then (ν − ν*)/σ_n,
    written to e (6 n',) and J (6 n', 6). topology : model.surface.SurfaceTopology.arrays.
    -> χ²_S (the sum of the landing costs)"""
    n = len(facets)
    p, nu = np.empty((n, 3)), np.empty((n, 3))
    for i in range(n):
        p[i] = np.array(object_point(R, t, points[i]))
        nu[i] = np.array(object_normal(R, finger_normals[i]))
    cost, kind, q, cone = np.zeros(n), np.zeros(n, np.int64), np.zeros((n, 3)), np.zeros((n, 3))
    pcode, pdir, ncode, arc = np.zeros(n, np.int64), np.zeros((n, 3)), np.zeros(n, np.int64), np.zeros((n, 2, 3))
    _land(topology[0], topology[1], topology[2], topology[3], topology[4], topology[5], topology[6], topology[7],
          topology[8], tri, normals, valid, p, nu,
          1.0 / sigma_position**2, 1.0 / sigma_normal**2, cost, facets, kind, q, cone, pcode, pdir, ncode, arc)
    used = 0
    for i in range(n):
        used += facets[i] >= 0
    row, total = 0, 0.0
    for i in range(n):
        if facets[i] < 0:
            continue
        total += cost[i]
        Pp = _position_rows(pcode[i], pdir[i])
        Pn = _normal_rows(nu[i], cone[i], ncode[i], arc[i])
        dp = np.zeros((3, 6))
        dp[:, :3] = hat3(p[i])  # p = Exp(ω)ᵀ p₀ − v, ν = Exp(ω)ᵀ ν₀: [p]×, -I and [ν]×, 0 at ξ = 0
        dp[0, 3], dp[1, 4], dp[2, 5] = -1.0, -1.0, -1.0
        Jp = Pp @ dp / sigma_position
        Jn = (Pn @ hat3(nu[i])) / sigma_normal
        for a in range(3):
            e[3 * row + a] = (p[i, a] - q[i, a]) / sigma_position
            e[3 * (used + row) + a] = (nu[i, a] - cone[i, a]) / sigma_normal
            for c in range(6):
                J[3 * row + a, c] = Jp[a, c]
                J[3 * (used + row) + a, c] = Jn[a, c] if c < 3 else 0.0
        row += 1
    return total


@numba.njit(cache=True)
def _position_rows(code, direction):
    """:func:`_position_projector` of one contact, compiled. -> (3, 3)"""
    outer = np.outer(direction, direction)
    if code == 1:
        return np.eye(3) - outer
    if code == 2:
        return outer
    return np.eye(3)


@numba.njit(cache=True)
def _normal_rows(nu, cone, code, arc):
    """:func:`_normal_projector` of one contact, compiled. -> (3, 3)"""
    if code == 2:
        return np.zeros((3, 3))
    if code != 1:
        return np.eye(3)
    w = np.cross(arc[0], arc[1])
    w = w / np.sqrt(w @ w)
    plane = np.eye(3) - np.outer(w, w)
    m = plane @ nu
    tangent = np.eye(3) - np.outer(cone, cone)
    return np.eye(3) - tangent @ plane / np.sqrt(m @ m)
