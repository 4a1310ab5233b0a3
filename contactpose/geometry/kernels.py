"""Exact distances between points, segments and triangles, as numba kernels.

What it handles:

* point–triangle squared distance and closest point (Voronoi-region method;
  zero-area and sliver facets fall back to their three edges);
* segment–segment squared distance, parallel and zero-length segments included;
* segment–triangle crossing test (non-coplanar configurations);
* the exact triangle–triangle minimum distance, 0 when the facets touch or
  intersect (paper erratum 4: the vertex-only minimum of §3.1 is wrong);
* ``triangle_pair_bounds``: the distance characteristics of facet pairs for
  the pair table — exact minimum, the paper's vertex-only minimum (kept to
  reproduce the paper) and the maximum, which is exact by convexity.

The scalar helpers (``point_triangle_dist2``, ``closest_point_triangle``,
``segment_segment_dist2``, ``segment_triangle_intersect``,
``triangle_triangle_dist2``) take (3,) float64 arrays and are meant to be
called from other numba code. The vectorised functions validate their inputs
and raise :class:`~contactpose.errors.ContactPoseError`.
"""

import numba
import numpy as np
from numba import njit

from contactpose.errors import ContactPoseError

# numba's own workqueue layer: Open3D brings its own OpenMP runtime, and two OpenMP
# runtimes in one process can crash; probing an old TBB first also prints a warning.
numba.config.THREADING_LAYER_PRIORITY = ["workqueue", "omp", "tbb"]

__all__ = [
    "SLIVER_REL",
    "point_triangle_dist2",
    "closest_point_triangle",
    "segment_segment_dist2",
    "segment_triangle_intersect",
    "triangle_triangle_dist2",
    "point_triangle_distance",
    "closest_points_on_triangles",
    "triangle_pair_bounds",
    "triangle_pair_vertex_bounds",
]

#: A triangle whose smallest altitude is at most ``SLIVER_REL`` times its
#: longest edge L is treated as its three edges. The fallback errs by at most
#: that altitude h; the face-plane projection it replaces errs by about
#: eps * L**2 / h (rounding of the normal). Both are ~1e-8 L at h = 1e-8 L,
#: which is sqrt(eps) and balances the two.
SLIVER_REL = 1e-8


# ---------------------------------------------------------------- 3-tuples ---

@njit(cache=True)
def _t(x):
    """(3,) array (or tuple) -> float64 3-tuple."""
    return (float(x[0]), float(x[1]), float(x[2]))


@njit(cache=True)
def _sub(u, v):
    return (u[0] - v[0], u[1] - v[1], u[2] - v[2])


@njit(cache=True)
def _add(u, v):
    return (u[0] + v[0], u[1] + v[1], u[2] + v[2])


@njit(cache=True)
def _axpy(s, u, v):
    """v + s * u."""
    return (v[0] + s * u[0], v[1] + s * u[1], v[2] + s * u[2])


@njit(cache=True)
def _dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


@njit(cache=True)
def _cross(u, v):
    return (u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0])


@njit(cache=True)
def _rt_apply(R, x):
    """Rᵀ x for a (3, 3) array R and a 3-tuple x."""
    return (R[0, 0] * x[0] + R[1, 0] * x[1] + R[2, 0] * x[2],
            R[0, 1] * x[0] + R[1, 1] * x[1] + R[2, 1] * x[2],
            R[0, 2] * x[0] + R[1, 2] * x[1] + R[2, 2] * x[2])


@njit(cache=True)
def _r_apply(R, x):
    """R x for a (3, 3) array R and a 3-tuple x."""
    return (R[0, 0] * x[0] + R[0, 1] * x[1] + R[0, 2] * x[2],
            R[1, 0] * x[0] + R[1, 1] * x[1] + R[1, 2] * x[2],
            R[2, 0] * x[0] + R[2, 1] * x[1] + R[2, 2] * x[2])


@njit(cache=True)
def _d2(u, v):
    """Squared distance between two points."""
    w = _sub(u, v)
    return _dot(w, w)


# ------------------------------------------------------- point to segment ---

@njit(cache=True)
def _closest_on_segment(x, p, q):
    """Closest point to x on the closed segment pq (pq may have zero length)."""
    d = _sub(q, p)
    dd = _dot(d, d)
    if dd == 0.0:
        return p
    s = _dot(_sub(x, p), d) / dd
    s = min(max(s, 0.0), 1.0)
    return _axpy(s, d, p)


@njit(cache=True)
def _point_segment_d2(x, p, q):
    return _d2(x, _closest_on_segment(x, p, q))


# ------------------------------------------------------ point to triangle ---

@njit(cache=True)
def _is_sliver(ab, ac, bc, n):
    """True when the smallest altitude is <= SLIVER_REL * longest edge."""
    l2 = max(_dot(ab, ab), _dot(ac, ac), _dot(bc, bc))
    return _dot(n, n) <= (SLIVER_REL * l2) ** 2


@njit(cache=True)
def _closest_on_edges(p, a, b, c):
    """Closest point to p on the boundary of triangle abc."""
    best = _closest_on_segment(p, a, b)
    for u, v in ((b, c), (c, a)):
        x = _closest_on_segment(p, u, v)
        if _d2(p, x) < _d2(p, best):
            best = x
    return best


@njit(cache=True)
def _closest_on_triangle(p, a, b, c):
    """Closest point to p on the closed triangle abc (3-tuples)."""
    return _triangle_feature(p, a, b, c)[0]


@njit(cache=True)
def _triangle_feature(p, a, b, c):
    """Closest point to p on the closed triangle abc, and where it lies: (point, code, dir)
    with code 0 a vertex, 1 an edge of direction dir (unit), 2 the inside, of normal dir
    (unit). Sliver triangles answer by their edges, code 0."""
    ab = _sub(b, a)
    ac = _sub(c, a)
    n = _cross(ab, ac)
    none = (0.0, 0.0, 0.0)
    if _is_sliver(ab, ac, _sub(c, b), n):
        return _closest_on_edges(p, a, b, c), 0, none
    ap = _sub(p, a)
    bp = _sub(p, b)
    cp = _sub(p, c)
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    # Voronoi regions of the vertices, then of the edges (disjoint, so any order)
    if d1 <= 0.0 and d2 <= 0.0:
        return a, 0, none
    if d3 >= 0.0 and d4 <= d3:
        return b, 0, none
    if d6 >= 0.0 and d5 <= d6:
        return c, 0, none
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return _axpy(d1 / (d1 - d3), ab, a), 1, _unit(ab)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return _axpy(d2 / (d2 - d6), ac, a), 1, _unit(ac)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 >= d3 and d5 >= d6:
        e43 = d4 - d3
        bc = _sub(c, b)
        return _axpy(e43 / (e43 + (d5 - d6)), bc, b), 1, _unit(bc)
    # Face region: project onto the plane (better conditioned for thin
    # facets than recombining the barycentric weights).
    return _axpy(-_dot(n, ap) / _dot(n, n), n, p), 2, _unit(n)


@njit(cache=True)
def _unit(v):
    """v / |v| (v non-zero)."""
    s = np.sqrt(_dot(v, v))
    return (v[0] / s, v[1] / s, v[2] / s)


@njit(cache=True)
def _point_triangle_d2(p, a, b, c):
    return _d2(p, _closest_on_triangle(p, a, b, c))


@njit(cache=True)
def point_triangle_dist2(p, a, b, c):
    """Squared distance from point p to the closed triangle abc.

    p, a, b, c : (3,) float. Zero-area and sliver triangles (see
    ``SLIVER_REL``) are handled as their three edges.
    """
    return _point_triangle_d2(_t(p), _t(a), _t(b), _t(c))


@njit(cache=True)
def segment_d2(x, p, q):
    """Squared distance from the point x to the closed segment pq, each (3,)."""
    return _point_segment_d2(_t(x), _t(p), _t(q))


@njit(cache=True)
def closest_point_triangle(p, a, b, c):
    """Closest point to p on the closed triangle abc.

    p, a, b, c : (3,) float. Returns a new (3,) float64 array.
    """
    x = _closest_on_triangle(_t(p), _t(a), _t(b), _t(c))
    out = np.empty(3)
    out[0], out[1], out[2] = x
    return out


# ----------------------------------------------------- segment to segment ---

@njit(cache=True)
def _segment_segment_d2(p1, q1, p2, q2):
    """Squared distance between closed segments p1q1 and p2q2.

    The minimum of the convex quadratic over [0, 1]^2 is either its interior
    stationary point or on the boundary, i.e. an endpoint-to-segment
    distance; taking the minimum of all five candidates is exact for
    parallel and zero-length segments without special tolerances.
    """
    best = min(_point_segment_d2(p1, p2, q2), _point_segment_d2(q1, p2, q2),
               _point_segment_d2(p2, p1, q1), _point_segment_d2(q2, p1, q1))
    d1 = _sub(q1, p1)
    d2 = _sub(q2, p2)
    r = _sub(p1, p2)
    a = _dot(d1, d1)
    b = _dot(d1, d2)
    e = _dot(d2, d2)
    denom = a * e - b * b
    if denom > 0.0:
        c = _dot(d1, r)
        f = _dot(d2, r)
        s = (b * f - c * e) / denom
        t = (a * f - b * c) / denom
        if 0.0 < s < 1.0 and 0.0 < t < 1.0:
            best = min(best, _d2(_axpy(s, d1, p1), _axpy(t, d2, p2)))
    return best


@njit(cache=True)
def segment_segment_dist2(p1, q1, p2, q2):
    """Squared distance between the closed segments p1q1 and p2q2.

    p1, q1, p2, q2 : (3,) float. Robust for parallel and zero-length segments.
    """
    return _segment_segment_d2(_t(p1), _t(q1), _t(p2), _t(q2))


# ---------------------------------------------------- segment vs triangle ---

@njit(cache=True)
def _crosses(p, q, sp, sq, a, b, c):
    """Segment pq meets triangle abc, given the signed plane offsets sp, sq.

    Coplanar segments (sp == sq == 0) report False.
    """
    if (sp > 0.0 and sq > 0.0) or (sp < 0.0 and sq < 0.0):
        return False
    if sp == 0.0 and sq == 0.0:
        return False
    e = _sub(q, p)
    pa = _sub(a, p)
    pb = _sub(b, p)
    pc = _sub(c, p)
    v1 = _dot(e, _cross(pa, pb))
    v2 = _dot(e, _cross(pb, pc))
    v3 = _dot(e, _cross(pc, pa))
    return ((v1 >= 0.0 and v2 >= 0.0 and v3 >= 0.0)
            or (v1 <= 0.0 and v2 <= 0.0 and v3 <= 0.0))


@njit(cache=True)
def _segment_triangle_hit(p, q, a, b, c):
    n = _cross(_sub(b, a), _sub(c, a))
    return _crosses(p, q, _dot(n, _sub(p, a)), _dot(n, _sub(q, a)), a, b, c)


@njit(cache=True)
def segment_triangle_intersect(p, q, a, b, c):
    """Does the closed segment pq touch or cross the closed triangle abc?

    p, q, a, b, c : (3,) float. Decided by signs of the plane offsets of p, q
    and of the three triple products of pq with the triangle's corners.
    A segment lying in the triangle's plane (and any segment against a
    zero-area triangle) reports False: the triangle-triangle distance catches
    coplanar overlap through its vertex-triangle and edge-edge terms instead.
    """
    return _segment_triangle_hit(_t(p), _t(q), _t(a), _t(b), _t(c))


# --------------------------------------------------- triangle to triangle ---

@njit(cache=True)
def _edges_cross(u0, u1, u2, v0, v1, v2):
    """Does an edge of triangle u cross triangle v (non-coplanar)? Never when v is a segment or a
    point (v1 = v2, or all three equal: model.units), which has no interior to cross."""
    n = _cross(_sub(v1, v0), _sub(v2, v0))
    if _dot(n, n) == 0.0:
        return False
    s0 = _dot(n, _sub(u0, v0))
    s1 = _dot(n, _sub(u1, v0))
    s2 = _dot(n, _sub(u2, v0))
    if (s0 > 0.0 and s1 > 0.0 and s2 > 0.0) or (s0 < 0.0 and s1 < 0.0 and s2 < 0.0):
        return False
    return (_crosses(u0, u1, s0, s1, v0, v1, v2)
            or _crosses(u1, u2, s1, s2, v0, v1, v2)
            or _crosses(u2, u0, s2, s0, v0, v1, v2))


@njit(cache=True)
def _separated_d2(a0, a1, a2, b0, b1, b2):
    """Min of the 6 vertex-triangle and 9 edge-edge squared distances."""
    d = min(_point_triangle_d2(a0, b0, b1, b2), _point_triangle_d2(a1, b0, b1, b2),
            _point_triangle_d2(a2, b0, b1, b2), _point_triangle_d2(b0, a0, a1, a2),
            _point_triangle_d2(b1, a0, a1, a2), _point_triangle_d2(b2, a0, a1, a2))
    for p, q in ((a0, a1), (a1, a2), (a2, a0)):
        for r, s in ((b0, b1), (b1, b2), (b2, b0)):
            d = min(d, _segment_segment_d2(p, q, r, s))
    return d


@njit(cache=True)
def _triangle_triangle_d2(a0, a1, a2, b0, b1, b2):
    if _edges_cross(a0, a1, a2, b0, b1, b2) or _edges_cross(b0, b1, b2, a0, a1, a2):
        return 0.0
    return _separated_d2(a0, a1, a2, b0, b1, b2)


@njit(cache=True)
def triangle_triangle_dist2(a0, a1, a2, b0, b1, b2):
    """Exact squared minimum distance between two closed triangles.

    a0, a1, a2, b0, b1, b2 : (3,) float. 0 when the triangles touch or
    intersect (an edge of one crosses the other, or coplanar overlap, which
    shows up as a zero vertex-triangle or edge-edge distance); otherwise the
    minimum of the 6 vertex-triangle and 9 edge-edge squared distances.
    """
    return _triangle_triangle_d2(_t(a0), _t(a1), _t(a2), _t(b0), _t(b1), _t(b2))


# ------------------------------------------------------ vectorised kernels ---

@njit(cache=True)
def _point_triangle_rows(points, triangles, out_d, out_x, want_x):
    for i in range(points.shape[0]):
        t = triangles[i]
        p = _t(points[i])
        x = _closest_on_triangle(p, _t(t[0]), _t(t[1]), _t(t[2]))
        out_d[i] = np.sqrt(_d2(p, x))
        if want_x:
            out_x[i, 0], out_x[i, 1], out_x[i, 2] = x


@njit(cache=True)
def _vertex_minmax(tri, k, l):
    """Min and max of the 9 vertex-vertex squared distances of facets k, l."""
    lo = np.inf
    hi = 0.0
    for i in range(3):
        for j in range(3):
            d = _d2(_t(tri[k, i]), _t(tri[l, j]))
            lo = min(lo, d)
            hi = max(hi, d)
    return lo, hi


@njit(cache=True)
def _vertex_row(tri, ks, ls, i, dmin_v, dmax):
    lo, hi = _vertex_minmax(tri, ks[i], ls[i])
    dmin_v[i] = np.sqrt(lo)
    dmax[i] = np.sqrt(hi)


@njit(cache=True)
def _bounds_row(tri, ks, ls, i, dmin, dmin_v, dmax):
    _vertex_row(tri, ks, ls, i, dmin_v, dmax)
    if dmin_v[i] == 0.0:  # a shared vertex: the facets touch
        dmin[i] = 0.0
        return
    a = tri[ks[i]]
    b = tri[ls[i]]
    dmin[i] = np.sqrt(_triangle_triangle_d2(_t(a[0]), _t(a[1]), _t(a[2]), _t(b[0]), _t(b[1]), _t(b[2])))


# prange halves the wall time of both pair kernels on 2 idle cores (measured:
# vertex-only 2.5e7 -> 6e7 pairs/s, exact 1.5e6 -> 3e6 pairs/s); with the
# other core busy it matches the serial loop. Small batches take the serial twin:
# waking the thread pool costs more than it saves.

@njit(cache=True, parallel=True)
def _pair_vertex_kernel(tri, ks, ls, dmin_v, dmax):
    for i in numba.prange(ks.shape[0]):
        _vertex_row(tri, ks, ls, i, dmin_v, dmax)


@njit(cache=True)
def _pair_vertex_serial(tri, ks, ls, dmin_v, dmax):
    for i in range(ks.shape[0]):
        _vertex_row(tri, ks, ls, i, dmin_v, dmax)


@njit(cache=True, parallel=True)
def _pair_bounds_kernel(tri, ks, ls, dmin, dmin_v, dmax):
    for i in numba.prange(ks.shape[0]):
        _bounds_row(tri, ks, ls, i, dmin, dmin_v, dmax)


@njit(cache=True)
def _pair_bounds_serial(tri, ks, ls, dmin, dmin_v, dmax):
    for i in range(ks.shape[0]):
        _bounds_row(tri, ks, ls, i, dmin, dmin_v, dmax)


# ------------------------------------------------------ input validation ---

def _as_float(name, x, trailing):
    """float64 array with shape (n,) + trailing, finite."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.ndim != 1 + len(trailing) or x.shape[1:] != trailing:
        want = "(n, " + ", ".join(map(str, trailing)) + ")"
        raise ContactPoseError(f"{name} has shape {x.shape}, expected {want}")
    if not np.isfinite(x).all():
        raise ContactPoseError(f"{name} contains NaN or infinite values")
    return x


def _as_index(name, x, m):
    """int64 (p,) array of indices in [0, m)."""
    x = np.asarray(x)
    if x.ndim != 1:
        raise ContactPoseError(f"{name} has shape {x.shape}, expected (p,)")
    if x.dtype.kind not in "iu":
        raise ContactPoseError(f"{name} has dtype {x.dtype}, expected integers")
    if x.size and (x.min() < 0 or x.max() >= m):
        raise ContactPoseError(
            f"{name} has values in [{x.min()}, {x.max()}], expected indices in [0, {m})")
    return np.ascontiguousarray(x, dtype=np.int64)


def _rows(points, triangles):
    points = _as_float("points", points, (3,))
    triangles = _as_float("triangles", triangles, (3, 3))
    if len(points) != len(triangles):
        raise ContactPoseError(
            f"points has {len(points)} rows and triangles {len(triangles)}, expected equal")
    return points, triangles


def _pairs(triangles, k, l):
    triangles = _as_float("triangles", triangles, (3, 3))
    k = _as_index("k", k, len(triangles))
    l = _as_index("l", l, len(triangles))
    if len(k) != len(l):
        raise ContactPoseError(f"k has {len(k)} entries and l {len(l)}, expected equal")
    return triangles, k, l


# ------------------------------------------------------ public vectorised ---

def point_triangle_distance(points, triangles):
    """Distance from each point to the triangle in the same row.

    points : (n, 3) float
    triangles : (n, 3, 3) float
    Returns (n,) float64.
    """
    points, triangles = _rows(points, triangles)
    d = np.empty(len(points))
    _point_triangle_rows(points, triangles, d, np.empty((0, 3)), False)
    return d


def closest_points_on_triangles(points, triangles):
    """Closest point on the triangle in the same row to each point.

    points : (n, 3) float
    triangles : (n, 3, 3) float
    Returns (n, 3) float64.
    """
    points, triangles = _rows(points, triangles)
    x = np.empty((len(points), 3))
    _point_triangle_rows(points, triangles, np.empty(len(points)), x, True)
    return x


#: Batches smaller than this run serially: waking the thread pool costs more than it
#: saves, and on 2 cores it contends with numpy's BLAS threads.
PARALLEL_MIN_PAIRS = 50_000


def triangle_pair_vertex_bounds(triangles, k, l):
    """The paper's vertex-only distance bounds of facet pairs (k[i], l[i]).

    triangles : (m, 3, 3) float
    k, l : (p,) int, indices into triangles
    Returns (dmin_vertex (p,), dmax (p,)): min and max of the 9
    vertex-vertex distances. dmax is exact (by convexity); dmin_vertex is
    only an upper bound of the true minimum (paper erratum 4).
    """
    triangles, k, l = _pairs(triangles, k, l)
    dmin_v = np.empty(len(k))
    dmax = np.empty(len(k))
    kernel = _pair_vertex_kernel if len(k) >= PARALLEL_MIN_PAIRS else _pair_vertex_serial
    kernel(triangles, k, l, dmin_v, dmax)
    return dmin_v, dmax


def triangle_pair_bounds(triangles, k, l):
    """Distance bounds of facet pairs (k[i], l[i]).

    triangles : (m, 3, 3) float
    k, l : (p,) int, indices into triangles
    Returns (dmin_exact (p,), dmin_vertex (p,), dmax (p,)): the exact
    triangle-triangle minimum distance (0 for touching or intersecting
    facets), the paper's minimum over the 9 vertex-vertex distances, and the
    maximum over them (exact by convexity).
    """
    triangles, k, l = _pairs(triangles, k, l)
    dmin = np.empty(len(k))
    dmin_v = np.empty(len(k))
    dmax = np.empty(len(k))
    kernel = _pair_bounds_kernel if len(k) >= PARALLEL_MIN_PAIRS else _pair_bounds_serial
    kernel(triangles, k, l, dmin, dmin_v, dmax)
    return dmin, dmin_v, dmax
