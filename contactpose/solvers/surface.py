"""Poses on the real surface: the contact model of model.surface, minimised over the pose.

A hypothesis is posed on its facets' planes. On a curved region, or with a contact on an
edge or vertex, a contact belongs to a neighbouring facet, or to an edge whose normal cone
holds its normal, and the plane pose is biased. Here each contact lands on the feature of
least whitened cost near its facet (model.surface.land), and the pose minimises

    χ²_S(ξ) = Σ_i |p_i(ξ) − q_i|²/σ_x² + |ν_i(ξ) − ν*_i|²/σ_n²,

with p_i, ν_i the contact point and outward normal in the object frame under the pose moved
by the right perturbation ξ = (ω, v) (rotation first, as scoring.infacet moves poses), q_i the
closest point of its feature and ν*_i the nearest direction of that feature's normal cone,
both found again at every evaluation (scipy.optimize.least_squares, Levenberg–Marquardt).
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np
from scipy.optimize import least_squares

from contactpose.geometry.kernels import point_triangle_distance
from contactpose.geometry.se3 import hat, retract
from contactpose.model.surface import land

#: Residual evaluations of one stage of a surface fit.
MAX_EVALUATIONS = 200
#: Relative step and cost change at which a stage stops.
XTOL = 1e-12
#: The stages run again from where they stopped, up to RESTARTS times in all, while χ²_S
#: still falls by more than RESTART_TOL (relative).
RESTARTS = 3
RESTART_TOL = 1e-10
#: needs_surface: the least cost χ²_S must be below the facets' by this much (relative).
GATE_TOL = 1e-9
#: The fit runs in stages with σ_x widened by these factors: with a wide σ_x an edge or vertex
#: whose cone holds the contact's normal wins over the face the contact sits on, so the fit
#: is drawn to it instead of settling on the face (research/surface.md).
CONTINUATION = (4.0, 1.0)


def object_frame(contacts, R, t):
    """The contacts under pose (R, t) in the object frame: points p = Rᵀ(x − t) and outward
    normals ν = −Rᵀñ, (n, 3) each."""
    return (contacts.points - t) @ R, -(contacts.finger_normals @ R)


def landing(model, contacts, R, t, facets, tolerance, widen=1.0):
    """Where the contacts of one pose land (model.surface.land -> Landing), walking from
    ``facets`` ((n,) int, -1: an unassigned finger, left out); widen : σ_x times this."""
    p, nu = object_frame(contacts, R, t)
    return land(model.topology, model.triangles, model.planes.normals, model.planes.valid, p, nu, facets,
                widen * tolerance.position_noise, tolerance.normal_noise)


class _Problem:
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
            p, nu = object_frame(self.contacts, R[0], t[0])
            got = landing(self.model, self.contacts, R[0], t[0], self.start, self.tolerance, self.widen)
            self._at = (xi.copy(), p[self.used], nu[self.used], got)
        return self._at[1:]

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
    """Whitened residuals of χ²_S at the pose (R, t), (6 n',): see :class:`_Problem`."""
    return _Problem(model, contacts, R, t, np.asarray(facets), tolerance, widen).residuals(np.zeros(6))


def surface_fit(model, contacts, R, t, facets, tolerance):
    """The pose of least χ²_S from (R, t), the contacts walking from ``facets`` (n,).

    Returns (R, t, facets, cone, gap, chi2): the landing facets (n,), cone directions ν*
    (n, 3) and distances |p − q| (n,) at the pose, and χ²_S there.
    """
    start = np.asarray(facets, dtype=np.int64).copy()
    chi2 = np.inf
    for _ in range(RESTARTS):  # a stage may stall where a contact changes feature: run them again
        for widen in CONTINUATION:
            R, t = _stage(model, contacts, R, t, start, tolerance, widen)
            start = landing(model, contacts, R, t, start, tolerance, widen).facet  # walk on from there
        last, chi2 = chi2, np.sum(surface_residuals(model, contacts, R, t, start, tolerance) ** 2)
        if last - chi2 <= RESTART_TOL * chi2:
            break
    got = landing(model, contacts, R, t, start, tolerance)
    gap = np.linalg.norm(object_frame(contacts, R, t)[0] - got.q, axis=1)
    return R, t, got.facet, got.cone, gap, float(np.nansum(got.cost))


def _stage(model, contacts, R, t, start, tolerance, widen):
    """One least-squares stage of the surface fit with σ_x times ``widen``. -> (R, t)"""
    problem = _Problem(model, contacts, R, t, start, tolerance, widen)
    fit = least_squares(problem.residuals, np.zeros(6), jac=problem.jacobian, method="lm", x_scale="jac",
                        xtol=XTOL, ftol=XTOL, max_nfev=MAX_EVALUATIONS)
    R, t = retract(R[None], t[None], fit.x[None])
    return R[0], t[0]


def needs_surface(model, contacts, R, t, facets, tolerance):
    """Whether the contact model fits this pose better than the facets do, with σ_x widened
    as the fit's first stage widens it: some contact costs less on another facet, an edge or a
    vertex (by more than GATE_TOL, relative, so that ties stay with the facets)."""
    widen = CONTINUATION[0]
    cost = landing(model, contacts, R, t, facets, tolerance, widen).cost
    p, nu = object_frame(contacts, R, t)
    used = facets >= 0
    f = facets[used]
    d = point_triangle_distance(p[used], model.triangles[f])
    own = (d / (widen * tolerance.position_noise)) ** 2 + np.sum((nu[used] - model.planes.normals[f]) ** 2,
                                                                   axis=1) / tolerance.normal_noise**2
    return bool(np.sum(own) - np.sum(cost[used]) > GATE_TOL * (1.0 + np.sum(own)))


def surface_factor(model, contacts, facets, tolerance, key):
    """χ²_S of some contacts as a gtsam.CustomFactor on the Pose3 ``key``: the whitened
    residuals and Jacobian of :class:`_Problem` at the pose (rotation first, as Pose3's
    tangent), each contact landing afresh at every evaluation, walking on from where it landed
    the last time (first from ``facets`` (n,) int, -1: left out)."""
    start = np.asarray(facets, dtype=np.int64).copy()
    m = 6 * int(np.sum(start >= 0))
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(m), [key],
                              partial(_surface_error, model, contacts, start, tolerance, key))


def _surface_error(model, contacts, start, tolerance, key, this, values, H):
    T = values.atPose3(key).matrix()
    problem = _Problem(model, contacts, T[:3, :3], T[:3, 3], start.copy(), tolerance, 1.0)
    zero = np.zeros(6)
    e = problem.residuals(zero)
    if H is not None:
        H[0] = problem.jacobian(zero)
    start[:] = np.where(start >= 0, problem._at[3].facet, -1)
    return e
