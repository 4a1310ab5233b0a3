"""Poses on the real surface: the surface contact model (costs.surface) minimised over the pose.

A hypothesis is posed on its facets' planes. On a curved region, or with a contact on an
edge or vertex, a contact belongs to a neighbouring facet, or to an edge whose normal cone
holds its normal, and the plane pose is biased. Here each contact lands on the feature of
least whitened cost near its facet (costs.surface.land), and the pose minimises χ²_S of
costs.surface, the features found again at every evaluation (a compiled Levenberg–Marquardt on
the rows of costs.surface.surface_rows), from a continuation in σ_x (:data:`CONTINUATION`);
then each contact's facet of least surface cost over the whole mesh is gathered at the fitted
pose and the fit runs on from there while χ²_S falls (:data:`REGATHERS`).
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np
from numba import njit
from scipy.spatial.transform import Rotation

from contactpose.costs.association import nearest_fit_facets
from contactpose.costs.frame import object_frame
from contactpose.costs.surface import SurfaceResiduals, face_costs, landing, surface_residuals, surface_rows
from contactpose.geometry.se3 import retract3
from contactpose.options import fit_threshold, outlier_penalty
from contactpose.solvers.closed_form import free_directions

#: Residual evaluations of one stage of a surface fit.
MAX_EVALUATIONS = 200
#: Relative step and cost change at which a stage stops.
XTOL = 1e-12
#: The stages run again from where they stopped, up to RESTARTS times in all, while χ²_S
#: still falls by more than RESTART_TOL (relative).
RESTARTS = 3
RESTART_TOL = 1e-10
#: localize(..., surface=True) fits this many of its best hypotheses on the surface.
SURFACE_REFINE = 8
#: localize fits its best MULTISTART_ROWS surface poses again from 12 starts around each: the
#: pose turned by ±MULTISTART_TURN_DEG about each object axis, and moved by
#: ±MULTISTART_SHIFT_FRAC of the diameter along each (multistart_poses). On a rough scan the
#: χ²_S of a pose a few degrees off lies behind a ridge from the truth's (research/surface.md,
#: "Starts around the best poses").
MULTISTART_ROWS = 2
MULTISTART_TURN_DEG = 5.0
MULTISTART_SHIFT_FRAC = 0.01
#: needs_surface: the least cost χ²_S must be below the facets' by this much (relative).
GATE_TOL = 1e-9
#: The fit runs in stages with σ_x widened by these factors: with a wide σ_x an edge or vertex
#: whose cone holds the contact's normal wins over the face the contact sits on, so the fit
#: is drawn to it instead of settling on the face (research/surface.md).
CONTINUATION = (4.0, 1.0)
#: surface_fit gathers the contacts' facets again over the whole mesh and fits on at most
#: this many times (on the YCB wrench and hammer, 90 grasps: strict +4 grasps, +20 % time).
REGATHERS = 3
#: ... when the gathered features cost less than the fit's by more than this (relative).
GATHER_TOL = 1e-9


def surface_fit(model, contacts, R, t, facets, tolerance):
    """The pose of least χ²_S from (R, t), the contacts walking from ``facets`` (n,; −1: left
    out), then gathered again: each contact's facet of least surface cost over the whole mesh
    at the fitted pose (costs.association.nearest_fit_facets with ``surface``); where a
    contact lands cheaper from there, the fit runs on from it, up to REGATHERS times while χ²_S falls. The
    walk finds a contact's least-cost feature near where it was; a rough scan has ridges of
    that cost between the two.

    Returns (R, t, facets, cone, gap, chi2): the landing facets (n,), cone directions ν*
    (n, 3) and distances |p − q| (n,) at the pose, and χ²_S there.
    """
    used = np.asarray(facets) >= 0
    got = _walked_fit(model, contacts, R, t, facets, tolerance)
    for _ in range(REGATHERS):
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = got[0], got[1]
        gathered = np.where(used, nearest_fit_facets(model, contacts, pose, tolerance, surface=True), -1)
        if np.nansum(landing(model, contacts, got[0], got[1], gathered, tolerance).cost) >= got[5] * (1 - GATHER_TOL):
            break  # each contact already sits on its least-cost feature (or one as good)
        again = _walked_fit(model, contacts, got[0], got[1], gathered, tolerance)
        if again[5] >= got[5]:
            break
        got = again
    return got


def _walked_fit(model, contacts, R, t, facets, tolerance):
    """:func:`surface_fit` without the gathering: the stages of CONTINUATION, the contacts
    walking on from where they landed, run again while χ²_S falls (RESTARTS)."""
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
    gap = np.linalg.norm(object_frame(R, t, contacts.points) - got.q, axis=1)
    return R, t, got.facet, got.cone, gap, float(np.nansum(got.cost))


def _stage(model, contacts, R, t, start, tolerance, widen):
    """One least-squares stage of the surface fit with σ_x times ``widen``: compiled
    Levenberg–Marquardt (:func:`_lm`) on χ²_S's rows (costs.surface.surface_rows). -> (R, t)"""
    arrays = model.topology.arrays
    return _lm(np.ascontiguousarray(R, dtype=np.float64), np.ascontiguousarray(t, dtype=np.float64),
               np.ascontiguousarray(contacts.points), np.ascontiguousarray(contacts.finger_normals),
               np.asarray(start, dtype=np.int64).copy(), arrays, np.ascontiguousarray(model.triangles),
               np.ascontiguousarray(model.planes.normals), np.asarray(model.planes.valid, dtype=np.bool_),
               widen * tolerance.position_noise, tolerance.normal_noise, MAX_EVALUATIONS, XTOL)


@njit(cache=True)
def _lm(R, t, points, finger_normals, facets, topology, tri, normals, valid, sx, sn, max_evaluations, tol):
    """Levenberg–Marquardt with diagonal (Marquardt) damping on χ²_S from (R, t), each step the
    retraction of geometry.se3 and the contacts landing again from where they last landed;
    stops when χ²_S falls by less than ``tol`` of itself, the step by less than ``tol`` of the
    pose, or after ``max_evaluations``. -> (R, t)"""
    m = 0
    for f in facets:
        m += 6 * (f >= 0)
    e, J, e_try, J_try = np.empty(m), np.empty((m, 6)), np.empty(m), np.empty((m, 6))
    cost = surface_rows(R, t, points, finger_normals, facets, topology, tri, normals, valid, sx, sn, e, J)
    lam, evaluations = 1e-3, 1
    while evaluations < max_evaluations and cost > 0.0:
        H, g = J.T @ J, J.T @ e
        A = H.copy()
        for a in range(6):
            A[a, a] += lam * max(H[a, a], 1e-30)
        step = -np.linalg.solve(A, g)
        R_try, t_try = retract3(R, t, step)
        landed = facets.copy()
        cost_try = surface_rows(R_try, t_try, points, finger_normals, landed, topology, tri, normals, valid, sx, sn,
                                e_try, J_try)
        evaluations += 1
        if cost_try < cost:
            small = cost - cost_try <= tol * cost or np.sqrt(step @ step) <= tol
            R, t, facets[:] = R_try, t_try, landed
            e, J, e_try, J_try, cost = e_try, J_try, e, J, cost_try
            lam = max(lam * 0.1, 1e-12)
            if small:
                break
        else:
            lam *= 10.0
            if lam > 1e12:
                break
    return R, t


def needs_surface(model, contacts, R, t, facets, tolerance):
    """Whether the contact model fits this pose better than the facets do, with σ_x widened
    as the fit's first stage widens it: some contact costs less on another facet, an edge or a
    vertex (by more than GATE_TOL, relative, so that ties stay with the facets)."""
    widen = CONTINUATION[0]
    cost = landing(model, contacts, R, t, facets, tolerance, widen).cost
    own = face_costs(model, contacts, R, t, facets, tolerance, widen)
    used = facets >= 0
    return bool(np.sum(own) - np.sum(cost[used]) > GATE_TOL * (1.0 + np.sum(own)))


def surface_factor(model, contacts, facets, tolerance, key):
    """χ²_S of some contacts as a gtsam.CustomFactor on the Pose3 ``key``: the whitened
    residuals and Jacobian of costs.surface.SurfaceResiduals at the pose (rotation first, as Pose3's
    tangent), each contact landing afresh at every evaluation, walking on from where it landed
    the last time (first from ``facets`` (n,) int, -1: left out)."""
    start = np.asarray(facets, dtype=np.int64).copy()
    m = 6 * int(np.sum(start >= 0))
    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(m), [key],
                              partial(_surface_error, model, contacts, start, tolerance, key))


def _surface_error(model, contacts, start, tolerance, key, this, values, H):
    T = values.atPose3(key).matrix()
    problem = SurfaceResiduals(model, contacts, T[:3, :3], T[:3, 3], start.copy(), tolerance, 1.0)
    zero = np.zeros(6)
    e = problem.residuals(zero)
    if H is not None:
        H[0] = problem.jacobian(zero)
    start[:] = np.where(start >= 0, problem.landed.facet, -1)
    return e


def surface_poses(model, contacts, arrays, tolerance, k=SURFACE_REFINE):
    """The best ``k`` determined hypotheses of the ranked arrays (HypothesisArrays) posed on
    the surface (:func:`surface_fit`), those where the contact model differs from their facets
    (:func:`needs_surface`) and the surface pose lowers χ² (outlier penalty included): their
    facets become those the contacts land on, and what the pose leaves free is what the
    normals of the features they land on leave free (closed_form.free_directions). -> (rows (K,) int, PoseFit of the surface poses,
    facets (K, n) int, (cone directions ν* (K, n, 3), distances |p − q| (K, n))), K >= 0"""
    rows = np.flatnonzero(~arrays.fit.underdetermined)[:k]
    starts = _surface_starts(model, contacts, arrays.fit.take(rows).poses(), arrays.facets[rows], tolerance)
    fits = []
    for r, start in zip(rows, starts):
        R, t, f = arrays.fit.R[r], arrays.fit.t[r], arrays.facets[r]
        if needs_surface(model, contacts, R, t, f, tolerance):
            fits.append((r, surface_fit(model, contacts, R, t, start, tolerance)))
    return _lowered(arrays, fits, tolerance)


def _surface_starts(model, contacts, poses, facets, tolerance):
    """The facets the surface fits walk from at poses (H, 4, 4): each assigned contact's facet
    of least surface cost over the whole mesh (costs.association.nearest_fit_facets with
    ``surface``), from which it lands on its least-cost feature; the hypothesis's own facet
    may lie behind a ridge of that cost. facets (H, n): −1, an unassigned finger, stays out."""
    if not len(poses):
        return facets
    return np.where(facets >= 0, nearest_fit_facets(model, contacts, poses, tolerance, surface=True), -1)


def multistart_poses(model, contacts, arrays, tolerance, k=MULTISTART_ROWS, rows=None, deadline=None):
    """The best ``k`` determined hypotheses of the ranked arrays (or the given ``rows`` (m,)
    int) fitted on the surface from each of :func:`multistart_starts` around their poses
    (:func:`multistart_ends`), row by row until ``deadline`` (a progress.Deadline) passes. Returns
    (lowered, basins), each as :func:`surface_poses` returns: ``lowered``, each row moved to
    its end of least χ²_S where that (outlier penalty included) is below its χ²; ``basins``,
    the other ends that fit within noise (fit_threshold), each a pose of its own for the
    placements' evidence (research/sure.md, "Basins beside the best")."""
    rows = np.flatnonzero(~arrays.fit.underdetermined)[:k] if rows is None else rows
    least, basins = [], []
    limit = fit_threshold(contacts.n)
    for r in rows:
        if deadline is not None and deadline.passed:
            break
        ends = multistart_ends(model, contacts, arrays.fit.R[r], arrays.fit.t[r], arrays.facets[r], tolerance)
        best = int(np.argmin([got[5] for got in ends]))
        least.append((r, ends[best]))
        penalty = outlier_penalty(arrays.facets[r:r + 1])[0]
        basins += [(r, got) for i, got in enumerate(ends) if i != best and got[5] + penalty <= limit]
    return _lowered(arrays, least, tolerance), _posed(arrays, basins, tolerance)


def multistart_starts(R, t, diameter):
    """The 12 starts around the pose (R (3, 3), t (3,)): turned by ±MULTISTART_TURN_DEG about
    each axis of the object frame (R Exp(±θ e_i), t) and moved by ±MULTISTART_SHIFT_FRAC of the
    diameter along each (R, t ± s R e_i). -> (12, 4, 4)"""
    steps = np.concatenate([np.eye(3), -np.eye(3)])
    starts = np.tile(np.eye(4), (12, 1, 1))
    starts[:6, :3, :3] = R @ Rotation.from_rotvec(np.radians(MULTISTART_TURN_DEG) * steps).as_matrix()
    starts[:6, :3, 3] = t
    starts[6:, :3, :3] = R
    starts[6:, :3, 3] = t + MULTISTART_SHIFT_FRAC * diameter * steps @ R.T
    return starts


def multistart_ends(model, contacts, R, t, facets, tolerance):
    """The :func:`surface_fit` from (R, t) walking from ``facets`` and from each of
    :func:`multistart_starts`, each contact walking from its facet of least surface cost
    there (:func:`_surface_starts`; an unassigned finger, facet −1, stays out): 13 results
    as :func:`surface_fit` returns them, the first from (R, t)."""
    starts = multistart_starts(R, t, model.diameter)
    nearest = _surface_starts(model, contacts, starts, np.broadcast_to(facets, (len(starts), len(facets))), tolerance)
    return [surface_fit(model, contacts, R, t, facets, tolerance)] + \
        [surface_fit(model, contacts, pose[:3, :3], pose[:3, 3], start, tolerance) for pose, start in zip(starts, nearest)]


def _lowered(arrays, fits, tolerance):
    """Of fits [(row, surface_fit result)], those whose χ²_S (outlier penalty included) is below
    the row's χ², as :func:`surface_poses` returns them (:func:`_posed`)."""
    return _posed(arrays, [(r, got) for r, got in fits
                           if got[5] + outlier_penalty(arrays.facets[r:r + 1])[0] < arrays.chi2[r]], tolerance)


def _posed(arrays, fits, tolerance):
    """Fits [(row, surface_fit result)] as :func:`surface_poses` returns them: (rows (K,) int,
    PoseFit of the surface poses (what each leaves free from the features it lands on),
    facets (K, n) int, (cone directions (K, n, 3), distances (K, n)) or None when K = 0)."""
    rows = np.array([r for r, _ in fits], dtype=np.int64)
    fit = arrays.fit.take(rows)
    if not fits:
        return rows, fit, arrays.facets[rows], None
    fit.R, fit.t = np.stack([got[0] for _, got in fits]), np.stack([got[1] for _, got in fits])
    facets = np.stack([np.where(arrays.facets[r] >= 0, got[2], -1) for r, got in fits])
    cones = np.stack([got[3] for _, got in fits])
    held = np.where((facets >= 0)[..., None], np.nan_to_num(cones), 0.0)
    (fit.free_translation, fit.free_translation_mask, fit.free_rotation,
     fit.free_rotation_mask) = free_directions(fit.R, held, tolerance.normal_noise)
    return rows, fit, facets, (cones, np.stack([got[4] for _, got in fits]))
