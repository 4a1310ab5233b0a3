"""The online half of the search by hypothesize and verify (research/verify_search.md): no
region tuples and no join. Every contact pair is matched against the sample pairs
(model.oriented) whose features agree within the samples' measured spreads and radii and
the noise; each match is a pose in closed
form (two oriented points fix it); every pose is checked against the field, moved by a few
Gauss–Newton steps onto the samples' tangent planes, checked again, and the poses that pass
are grouped by a hash of the pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numba import njit

from contactpose.geometry.se3 import _exp_into

#: Gauss–Newton steps that move a candidate onto the samples' tangent planes.
REFINE_STEPS = 3
#: The steps' trust region: a prior of this turn (radians) on each step, and of the covering
#: radius plus the pair distance gate on its shift.
STEP_TURN = np.radians(5.0)
#: After the first step a candidate is checked again, its turn taken as off by at most the
#: pair's lean and this much of the roll (radians).
FIRST_STEP_TURN = np.radians(15.0)
#: A candidate survives when each contact lies within its gate of its nearest sample after the
#: steps: distance reach + VERIFY_SIGMA σ_x, normal the sample's spread + VERIFY_SIGMA σ_n.
VERIFY_SIGMA = 3.0
#: Matches checked at a time (the grain of the deadline's checks and of the output buffers).
MATCH_CHUNK = 65_536
#: The pose hash's cells: rotation (radians) and translation (fraction of the diameter).
CLUSTER_ROT = np.radians(5.0)
CLUSTER_TRANS_FRAC = 0.05


@dataclass
class Candidates:
    """K verified poses: R (K, 3, 3), t (K, 3) T_world_object; cost (K,) the sum of squared
    whitened residuals to the nearest samples' tangent planes and normals; samples (K, n) int:
    each contact's nearest sample."""

    R: np.ndarray
    t: np.ndarray
    cost: np.ndarray
    samples: np.ndarray

    def take(self, idx):
        return Candidates(self.R[idx], self.t[idx], self.cost[idx], self.samples[idx])

    def __len__(self):
        return len(self.cost)


def pair_matches(oriented, p, nu, tolerance):
    """The sample pairs that may hold the contacts (p (2, 3), outward normals nu (2, 3)):
    (a (M,), b (M,)) sample indices, a for the first contact and b for the second, both
    orders of each stored pair."""
    feats = oriented.pairs
    d_vec = p[1] - p[0]
    d = float(np.linalg.norm(d_vec))
    u = d_vec / d
    th0, th1, th01 = (float(np.arccos(np.clip(x @ y, -1.0, 1.0))) for x, y in ((nu[0], u), (nu[1], u), (nu[0], nu[1])))
    widest = 2.0 * float(oriented.radii.max()) + tolerance.distance
    sl = feats.within(d - widest, d + widest)
    a, b = np.empty(2 * (sl.stop - sl.start), np.int64), np.empty(2 * (sl.stop - sl.start), np.int64)
    k = _matching(feats.first[sl], feats.second[sl], feats.distance[sl], feats.angle_first[sl], feats.angle_second[sl],
                  feats.angle_normals[sl], oriented.radii, oriented.spreads, d, th0, th1, th01, tolerance.distance,
                  VERIFY_SIGMA * tolerance.normal_noise, a, b)
    return a[:k], b[:k]


@njit(cache=True)
def _matching(first, second, distance, angle_first, angle_second, angle_normals, radii, spreads, d, th0, th1, th01, tol_d,
              g, out_a, out_b):
    """Write the stored pairs whose distance lies within the samples' radii and tol_d of d and
    whose angles lie within their spreads, g and the lean of d; each in the order (first,
    second) where it matches contacts (0, 1) so, then (second, first) where reversed. -> their
    count"""
    k = 0
    for c in range(first.shape[0]):
        fa, fb = first[c], second[c]
        slack_d = radii[fa] + radii[fb] + tol_d
        if abs(distance[c] - d) > slack_d:
            continue
        sa, sb = spreads[fa], spreads[fb]
        if abs(angle_normals[c] - th01) > sa + sb + 2.0 * g:
            continue
        lean = np.arcsin(min(1.0, slack_d / d))
        if abs(angle_first[c] - th0) <= sa + g + lean and abs(angle_second[c] - th1) <= sb + g + lean:
            out_a[k], out_b[k] = fa, fb
            k += 1
        if abs((np.pi - angle_second[c]) - th0) <= sb + g + lean and abs((np.pi - angle_first[c]) - th1) <= sa + g + lean:
            out_a[k], out_b[k] = fb, fa
            k += 1
    return k


@njit(cache=True, inline="always")
def _frame_into(u0, u1, u2, F):
    """F (3, 3): a rotation whose first column is the unit (u0, u1, u2), the second a fixed
    perpendicular (u × the axis u is least along)."""
    a0, a1, a2 = abs(u0), abs(u1), abs(u2)
    if a0 <= a1 and a0 <= a2:
        e0, e1, e2 = 0.0, u2, -u1
    elif a1 <= a2:
        e0, e1, e2 = -u2, 0.0, u0
    else:
        e0, e1, e2 = u1, -u0, 0.0
    s = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    e0, e1, e2 = e0 / s, e1 / s, e2 / s
    F[0, 0], F[1, 0], F[2, 0] = u0, u1, u2
    F[0, 1], F[1, 1], F[2, 1] = e0, e1, e2
    F[0, 2], F[1, 2], F[2, 2] = u1 * e2 - u2 * e1, u2 * e0 - u0 * e2, u0 * e1 - u1 * e0


@njit(cache=True, inline="always")
def _roll_terms(m0, m1, m2, n0, n1, n2, Fs, Fc):
    """The two normals' parts across the line, in each frame: (cos part, sin part, leverage)."""
    s1 = m0 * Fs[0, 1] + m1 * Fs[1, 1] + m2 * Fs[2, 1]
    s2 = m0 * Fs[0, 2] + m1 * Fs[1, 2] + m2 * Fs[2, 2]
    c1 = n0 * Fc[0, 1] + n1 * Fc[1, 1] + n2 * Fc[2, 1]
    c2 = n0 * Fc[0, 2] + n1 * Fc[1, 2] + n2 * Fc[2, 2]
    return s1 * c1 + s2 * c2, s1 * c2 - s2 * c1, np.sqrt((s1 * s1 + s2 * s2) * (c1 * c1 + c2 * c2))


@njit(cache=True, inline="always")
def _pair_pose(Q, M, a, b, p, nu, i, j, Fs, Fc, R, t):
    """R (3, 3), t (3,) := the pose that puts samples a, b (points Q, normals M) on contacts
    i, j (points p, outward normals nu), the line exactly, turned about it so that the normals
    meet in least squares. Fs, Fc: scratch. -> the turn's leverage w (the normals' lengths
    across the line, summed)"""
    u0, u1, u2 = Q[b, 0] - Q[a, 0], Q[b, 1] - Q[a, 1], Q[b, 2] - Q[a, 2]
    h = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    _frame_into(u0 / h, u1 / h, u2 / h, Fs)
    u0, u1, u2 = p[j, 0] - p[i, 0], p[j, 1] - p[i, 1], p[j, 2] - p[i, 2]
    h = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    _frame_into(u0 / h, u1 / h, u2 / h, Fc)
    re, im, w = _roll_terms(M[a, 0], M[a, 1], M[a, 2], nu[i, 0], nu[i, 1], nu[i, 2], Fs, Fc)
    re2, im2, w2 = _roll_terms(M[b, 0], M[b, 1], M[b, 2], nu[j, 0], nu[j, 1], nu[j, 2], Fs, Fc)
    re, im, w = re + re2, im + im2, w + w2
    h = np.sqrt(re * re + im * im)
    c, s = (re / h, im / h) if h > 0 else (1.0, 0.0)
    for r in range(3):  # R = Fc turn Fsᵀ, turn about the first axis by (c, s)
        g0, g1, g2 = Fc[r, 0], c * Fc[r, 1] + s * Fc[r, 2], -s * Fc[r, 1] + c * Fc[r, 2]
        for k in range(3):
            R[r, k] = g0 * Fs[k, 0] + g1 * Fs[k, 1] + g2 * Fs[k, 2]
    for r in range(3):
        t[r] = 0.5 * (p[i, r] + p[j, r]) - 0.5 * (R[r, 0] * (Q[a, 0] + Q[b, 0]) + R[r, 1] * (Q[a, 1] + Q[b, 1])
                                                + R[r, 2] * (Q[a, 2] + Q[b, 2]))
    return w


@njit(cache=True, inline="always")
def _to_object(R, t, p, x):
    """x := Rᵀ (p − t)."""
    d0, d1, d2 = p[0] - t[0], p[1] - t[1], p[2] - t[2]
    for r in range(3):
        x[r] = R[0, r] * d0 + R[1, r] * d1 + R[2, r] * d2


@njit(cache=True, inline="always")
def _turn_back(R, n, v):
    """v := Rᵀ n."""
    for r in range(3):
        v[r] = R[0, r] * n[0] + R[1, r] * n[1] + R[2, r] * n[2]


@njit(cache=True, inline="always")
def _nearest(x, origin, cell, nearest):
    """The field's sample for the object-frame point x, -1 outside it."""
    i0 = int(np.floor((x[0] - origin[0]) / cell + 0.5))
    i1 = int(np.floor((x[1] - origin[1]) / cell + 0.5))
    i2 = int(np.floor((x[2] - origin[2]) / cell + 0.5))
    if 0 <= i0 < nearest.shape[0] and 0 <= i1 < nearest.shape[1] and 0 <= i2 < nearest.shape[2]:
        return nearest[i0, i1, i2]
    return -1


@njit(cache=True)
def _gn_step(R, t, p, nu, Q, M, S, other, origin, cell, nearest, sx, sn, reach, x, v, H, g, J, T):
    """One Gauss–Newton step of the pose (R, t, in place) onto the contacts' nearest samples'
    tangent planes (σ sx) and normals (σ sn), a right perturbation (geometry.se3.retract: an
    object-frame point moves by x × ω − v, a normal by ν × ω). x, v, H, g, J, T: scratch.
    False when a contact left the field."""
    H[:, :] = 0.0
    g[:] = 0.0
    for k in range(p.shape[0]):
        _to_object(R, t, p[k], x)
        _turn_back(R, nu[k], v)
        s = _nearest(x, origin, cell, nearest)
        if s < 0:
            return False
        if v[0] * M[s, 0] + v[1] * M[s, 1] + v[2] * M[s, 2] < 0.0 and other[s] >= 0:
            s = other[s]  # a thin wall: the contact is on its other side
        m, q = M[s], Q[s]
        d0, d1, d2 = x[0] - q[0], x[1] - q[1], x[2] - q[2]
        # the tangent plane of a sample is off by its spread times the way along it, and the
        # sample's normal by its spread: both join the noise
        wx = 1.0 / np.sqrt(sx * sx + (S[s] * S[s]) * (d0 * d0 + d1 * d1 + d2 * d2))
        wn = 1.0 / np.sqrt(sn * sn + S[s] * S[s])
        J[0], J[1], J[2] = (m[1] * x[2] - m[2] * x[1]) * wx, (m[2] * x[0] - m[0] * x[2]) * wx, \
            (m[0] * x[1] - m[1] * x[0]) * wx
        J[3], J[4], J[5] = -m[0] * wx, -m[1] * wx, -m[2] * wx
        e = (m[0] * d0 + m[1] * d1 + m[2] * d2) * wx
        for a in range(6):
            g[a] += J[a] * e
            for b in range(6):
                H[a, b] += J[a] * J[b]
        # ν × ω = [ν]× ω: rows of [ν]×
        for r in range(3):
            if r == 0:
                J[0], J[1], J[2] = 0.0, -v[2] * wn, v[1] * wn
            elif r == 1:
                J[0], J[1], J[2] = v[2] * wn, 0.0, -v[0] * wn
            else:
                J[0], J[1], J[2] = -v[1] * wn, v[0] * wn, 0.0
            e = (v[r] - m[r]) * wn
            for a in range(3):
                g[a] += J[a] * e
                for b in range(3):
                    H[a, b] += J[a] * J[b]
    for a in range(6):  # a trust region: steps of about STEP_TURN and the shift ``reach``
        H[a, a] += 1.0 / (STEP_TURN * STEP_TURN) if a < 3 else 1.0 / (reach * reach)
    _cholesky_solve(H, g)
    xi = g
    xi *= -1.0
    _exp_into(xi[0], xi[1], xi[2], 0.0, 0.0, 0.0, T)
    for r in range(3):
        g0, g1, g2 = R[r, 0], R[r, 1], R[r, 2]
        for k in range(3):
            R[r, k] = g0 * T[0, k] + g1 * T[1, k] + g2 * T[2, k]
    for r in range(3):
        t[r] += R[r, 0] * xi[3] + R[r, 1] * xi[4] + R[r, 2] * xi[5]
    return True


@njit(cache=True)
def _cholesky_solve(H, g):
    """g := H⁻¹ g for a symmetric positive definite H (6, 6), overwritten by its factor."""
    n = H.shape[0]
    for c in range(n):
        s = H[c, c]
        for k in range(c):
            s -= H[c, k] * H[c, k]
        H[c, c] = np.sqrt(max(s, 1e-300))
        for r in range(c + 1, n):
            s = H[r, c]
            for k in range(c):
                s -= H[r, k] * H[c, k]
            H[r, c] = s / H[c, c]
    for r in range(n):
        s = g[r]
        for k in range(r):
            s -= H[r, k] * g[k]
        g[r] = s / H[r, r]
    for r in range(n - 1, -1, -1):
        s = g[r]
        for k in range(r + 1, n):
            s -= H[k, r] * g[k]
        g[r] = s / H[r, r]


@njit(cache=True, inline="always")
def _check(R, t, p, nu, Q, M, S, other, origin, cell, nearest, gate_x, gate_n, lever, slack, sx, sn, found, x, v,
           order):
    """The cost Σ (plane offset / sx)² + (normal excess / sn)² of the pose over the contacts,
    inf unless every contact lies within gate_x + lever[k] slack of its nearest sample and its
    normal within that sample's spread + gate_n + slack; found[k] := that sample. The contacts
    are checked in ``order``, the first to fail ending it. x, v: scratch."""
    cost = 0.0
    for k in order:
        _to_object(R, t, p[k], x)
        s = _nearest(x, origin, cell, nearest)
        if s < 0:
            return np.inf
        q, m = Q[s], M[s]
        d0, d1, d2 = x[0] - q[0], x[1] - q[1], x[2] - q[2]
        if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > gate_x + lever[k] * slack:
            return np.inf
        _turn_back(R, nu[k], v)
        cosine = v[0] * m[0] + v[1] * m[1] + v[2] * m[2]
        if cosine < 0.0 and other[s] >= 0:  # a thin wall: the contact is on its other side
            s = other[s]
            q, m = Q[s], M[s]
            d0, d1, d2 = x[0] - q[0], x[1] - q[1], x[2] - q[2]
            cosine = v[0] * m[0] + v[1] * m[1] + v[2] * m[2]
        excess = np.arccos(min(1.0, max(-1.0, cosine))) - S[s]
        if excess > gate_n + slack:
            return np.inf
        found[k] = s
        off = (m[0] * d0 + m[1] * d1 + m[2] * d2) / sx
        cost += off * off + (max(excess, 0.0) / sn) ** 2
    return cost


@njit(cache=True)
def _levers(p, i, j):
    """(lever (n,): each contact's distance from the middle of contacts i and j, order (n,):
    the others, least lever first, then i and j, which fit by construction)."""
    n = p.shape[0]
    lever = np.empty(n)
    for k in range(n):
        d0, d1, d2 = p[k, 0] - 0.5 * (p[i, 0] + p[j, 0]), p[k, 1] - 0.5 * (p[i, 1] + p[j, 1]), \
            p[k, 2] - 0.5 * (p[i, 2] + p[j, 2])
        lever[k] = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    order = np.argsort(lever)
    return lever, np.concatenate((order[(order != i) & (order != j)], np.array([i, j])))


@njit(cache=True)
def _loose_poses(a, b, Q, M, S, other, p, nu, i, j, origin, cell, nearest, gate_x, gate_n, lean, shift, sx, sn,
                 out_R, out_t, out_roll, out_cost):
    """Pose each match (a[c], b[c]) of the contact pair (i, j) and check it loosely: each
    contact within ``shift`` more, and what the pair's turn may be off by (lean, and the roll
    the normals leave) times its lever. The poses that pass, the roll each may be off by and
    their cost are written from the start of the out_ arrays. -> their count"""
    lever, order = _levers(p, i, j)
    found = np.empty(p.shape[0], dtype=np.int64)
    R, t = np.empty((3, 3)), np.empty(3)
    Fs, Fc, x, v = np.empty((3, 3)), np.empty((3, 3)), np.empty(3), np.empty(3)
    count = 0
    for c in range(a.shape[0]):
        w = _pair_pose(Q, M, a[c], b[c], p, nu, i, j, Fs, Fc, R, t)
        roll = min(np.pi, (S[a[c]] + S[b[c]] + 2.0 * gate_n) / max(w, 0.2))
        cost = _check(R, t, p, nu, Q, M, S, other, origin, cell, nearest, gate_x + shift, gate_n, lever, lean + roll,
                      sx, sn, found, x, v, order)
        if np.isinf(cost):
            continue
        out_R[count], out_t[count], out_roll[count], out_cost[count] = R, t, roll, cost
        count += 1
    return count


@njit(cache=True)
def _refined(R_in, t_in, roll, Q, M, S, other, p, nu, i, j, origin, cell, nearest, gate_x, gate_n, lean, shift, sx, sn,
             steps, out_R, out_t, out_cost, out_s):
    """Move each loose pose (R_in, t_in) of the contact pair (i, j) by ``steps`` Gauss–Newton
    steps, checked again after the first (its turn off by at most lean and min(roll,
    FIRST_STEP_TURN) times the lever), and check it tightly; the survivors are written from the
    start of the out_ arrays. -> their count"""
    n = p.shape[0]
    lever, order = _levers(p, i, j)
    zero = np.zeros(n)
    found = np.empty(n, dtype=np.int64)
    R, t = np.empty((3, 3)), np.empty(3)
    x, v = np.empty(3), np.empty(3)
    H, g, J, T = np.empty((6, 6)), np.empty(6), np.empty(6), np.empty((3, 4))
    count = 0
    for c in range(R_in.shape[0]):
        R[:, :], t[:] = R_in[c], t_in[c]
        moved = True
        for step in range(steps):
            moved = _gn_step(R, t, p, nu, Q, M, S, other, origin, cell, nearest, sx, sn, shift, x, v, H, g, J, T)
            if not moved:
                break
            if step == 0 and np.isinf(_check(R, t, p, nu, Q, M, S, other, origin, cell, nearest, gate_x + shift,
                                             gate_n, lever, lean + min(roll[c], FIRST_STEP_TURN), sx, sn, found, x,
                                             v, order)):
                moved = False
                break
        if not moved:
            continue
        cost = _check(R, t, p, nu, Q, M, S, other, origin, cell, nearest, gate_x, gate_n, zero, 0.0, sx, sn, found, x,
                      v, order)
        if np.isinf(cost):
            continue
        out_R[count], out_t[count], out_cost[count], out_s[count] = R, t, cost, found
        count += 1
    return count


def _cell_keys(R, t, diameter):
    """(K,) int64: each pose's cell of the pose hash (R (K, 3, 3), t (K, 3)): the entries of
    R's first two columns in steps of CLUSTER_ROT (a turn by θ moves them by up to θ) and the
    translation in steps of CLUSTER_TRANS_FRAC of the diameter, packed into one number."""
    if not len(R):
        return np.zeros(0, dtype=np.int64)
    cells = np.concatenate([np.floor(R[:, :, :2].reshape(len(R), 6) / CLUSTER_ROT),
                            np.floor(t / (CLUSTER_TRANS_FRAC * diameter))], axis=1).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    if np.prod(span.astype(float)) < 2.0 ** 62:
        return np.ravel_multi_index(tuple(cells.T), span)
    return np.unique(cells, axis=0, return_inverse=True)[1].ravel()


def _least_per_cell(key, cost):
    """(L,) int: the index of the least cost in each cell (key (K,)), ordered by cost."""
    order = np.argsort(cost, kind="stable")
    _, first = np.unique(key[order], return_index=True)
    best = order[first]
    return best[np.argsort(cost[best], kind="stable")]


def clustered(candidates, diameter):
    """One candidate per cell of the pose hash (rotation in CLUSTER_ROT cells,
    translation in CLUSTER_TRANS_FRAC of the diameter), the least cost of each, ordered by
    cost."""
    if not len(candidates):
        return candidates
    return candidates.take(_least_per_cell(_cell_keys(candidates.R, candidates.t, diameter), candidates.cost))


def posed_pairs(points):
    """The contact pairs (i, j), i < j, of the points (n, 3), longest first: the candidates of
    one pair of right contacts hold the truth (every contact is checked), and a longer pair
    poses them with a longer lever."""
    pairs = list(combinations(range(len(points)), 2))
    length = [np.linalg.norm(points[j] - points[i]) for i, j in pairs]
    return [pairs[k] for k in np.argsort(length, kind="stable")[::-1]]


def candidate_poses(oriented, contacts, tolerance, diameter, deadline=None):
    """Every verified, clustered candidate of the contacts (Contacts) on the oriented model
    (model.oriented.OrientedSamples), from the matches of the first contact pair of
    :func:`posed_pairs` whose matches yield one (a pair whose own contacts are off yields
    none, and the next is tried). Each match is posed and checked loosely; of the loose poses
    in one cell of the pose hash only the least-cost one is refined and checked tightly (its
    neighbours in the cell would walk to the same place). Work goes MATCH_CHUNK at a time until
    the deadline (a progress.Deadline) passes (then ``deadline.hit``). -> Candidates, ordered
    by cost"""
    p = np.ascontiguousarray(contacts.points)
    nu = np.ascontiguousarray(contacts.object_normals)
    model = (oriented.points, oriented.normals, oriented.spreads, oriented.other_side)
    field = (oriented.origin, oriented.cell, oriented.nearest)
    found = Candidates(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, contacts.n), np.int64))
    for i, j in posed_pairs(p):
        a, b = pair_matches(oriented, p[[i, j]], nu[[i, j]], tolerance)
        lean = float(np.arcsin(min(1.0, (2.0 * oriented.covering + tolerance.distance) / np.linalg.norm(p[j] - p[i]))))
        gates = (oriented.reach + VERIFY_SIGMA * tolerance.position_noise, VERIFY_SIGMA * tolerance.normal_noise, lean,
                 oriented.covering + tolerance.distance, tolerance.position_noise, tolerance.normal_noise)
        R, t, roll, cost = _chunked(_loose_poses, (a, b), (*model, p, nu, i, j, *field, *gates),
                                    [(3, 3), (3,), (), ()], [np.float64] * 4, deadline)
        keep = _least_per_cell(_cell_keys(R, t, diameter), cost)
        found = Candidates(*_chunked(_refined, (R[keep], t[keep], roll[keep]),
                                     (*model, p, nu, i, j, *field, *gates, REFINE_STEPS),
                                     [(3, 3), (3,), (), (contacts.n,)], [np.float64] * 3 + [np.int64], deadline))
        if len(found) or (deadline is not None and deadline.passed):
            return clustered(found, diameter)
    return found


def _chunked(kernel, rows, args, shapes, dtypes, deadline):
    """kernel(*(x[lo:lo + MATCH_CHUNK] for x in rows), *args, *out) over the rows MATCH_CHUNK at
    a time until they are done or the deadline passes, each call writing at most one result
    per row into out (arrays of MATCH_CHUNK × shapes, dtypes) and returning their count.
    -> the results, one array per out array"""
    out = [np.empty((MATCH_CHUNK, *shape), dtype) for shape, dtype in zip(shapes, dtypes)]
    parts = []
    for lo in range(0, len(rows[0]), MATCH_CHUNK):
        if deadline is not None and deadline.passed:
            break
        k = kernel(*(x[lo:lo + MATCH_CHUNK] for x in rows), *args, *out)
        parts.append([x[:k].copy() for x in out])
    if not parts:
        return [x[:0].copy() for x in out]
    return [np.concatenate(col) for col in zip(*parts)]
