"""Rounded fingertips: a sphere of radius r sweeps toward a mesh and stops at first touch.

A finger is a ball of radius ``r >= 0`` (``r = 0`` is a point finger). It moves from a
start along a unit direction and stops the moment it touches the object's surface, a
closed, outward-wound triangle mesh (vertices (V, 3) float, faces (F, 3) int). The
contact point is where the ball touches; it may lie on a face, an edge or a vertex,
and it need not be the surface point the finger was aimed at.

Conventions: lengths are in mesh units, the object frame is the mesh's frame, arrays
of points and directions are float64 (n, 3), every random function takes
``rng: numpy.random.Generator``. The *diameter* is the bounding-box diagonal; relative
tolerances are multiples of it.

The sweep (:func:`sweep_spheres`) has two stages, both vectorised over the fingers:

1. **Conservative advancement** with Open3D's ``RaycastingScene`` (float32): the ball
   of radius d(c) around the centre c is free of the object, so the centre may move by
   d(c) - r without touching. Each step is shortened by ``ADVANCE_MARGIN`` · diameter,
   which bounds Open3D's float32 distance error about a hundredfold, so no step ever
   penetrates. It stops when the gap is within two margins, after
   ``MAX_ADVANCE_STEPS`` steps (grazing approaches converge slowly), or when the
   finger has passed the object.
2. **Exact finish** in float64: the set of centres within r of a triangle is the union
   of two caps (the triangle shifted by ±r along its normal), three cylinders around
   its edges and three balls around its vertices. The first entry of the centre's ray
   into that set is solved in closed form for every triangle near the ray (found with
   k-d trees over triangle centroids) over a look-ahead interval, which grows until a
   touch is found or the finger runs past ``max_travel`` (a miss, ``hit=False``).

The contact is then the exact closest point of the final centre on the mesh; its
triangle and its barycentric coordinates give the touched feature. Triangles whose
altitude is below ``DEGENERATE_ALTITUDE`` · diameter have no usable plane: only their
edges and vertices count (they lie within that altitude of their edges), and they get
no normal and no sampling weight.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from contactpose.errors import ContactPoseError
from contactpose.geometry.raycast import Raycaster
from contactpose.geometry.sampling import tangent_basis, uniform_in_triangles

log = logging.getLogger(__name__)

FACE, EDGE, VERTEX, MISS = "face", "edge", "vertex", "none"
MODES = ("cone", "closing")
#: Cap on the Open3D advancement steps per finger before the exact finish takes over.
MAX_ADVANCE_STEPS = 200
#: Safety margin of an Open3D (float32) advancement step, as a fraction of the diameter.
ADVANCE_MARGIN = 1e-5
#: Triangles with a smaller altitude (fraction of the diameter) count as degenerate.
DEGENERATE_ALTITUDE = 1e-10
#: A barycentric coordinate at or below this is zero when naming the touched feature.
FEATURE_TOL = 1e-9
#: Caps reach this far (barycentric) past their triangle, so that a ray through an edge
#: or a vertex cannot slip between two triangles by rounding (r = 0 relies on it).
CAP_SLACK = 1e-12
#: Default standoff of :func:`approach`, in diameters (plus the radius).
STANDOFF_DIAMETERS = 1.05
#: Fingers per batch of the exact stages (bounds the memory of finger-triangle pairs).
_CHUNK = 2048
_EDGES = ((0, 1), (1, 2), (2, 0))


@dataclass
class FingertipContacts:
    """Where n spherical fingertips of radius r touched the object (object frame).

    radius : r; points : (n, 3) contact points on the surface; normals : (n, 3) unit, from the
    contact toward the ball centre (the outward object normal; the finger's normal is
    the opposite; for r = 0 the normal of the contact's facet); centres : (n, 3) ball
    centres at contact; facets : (n,) int, the triangle the contact lies on (the
    closest one); features : (n,) str, "face" | "edge" | "vertex"; hit : (n,) bool;
    travel : (n,) distance the centre moved; starts, directions : (n, 3) start centres
    and unit directions (centres = starts + travel · directions).
    A finger that missed keeps its row with hit False, NaN points, normals, centres
    and travel, facet -1 and feature "none".
    targets : (n, 3) and target_facets : (n,) are the aimed-at surface points and
    their triangles (set by :func:`approach`, else None).
    """

    radius: float
    points: np.ndarray
    normals: np.ndarray
    centres: np.ndarray
    facets: np.ndarray
    features: np.ndarray
    hit: np.ndarray
    travel: np.ndarray
    starts: np.ndarray
    directions: np.ndarray
    targets: np.ndarray | None = None
    target_facets: np.ndarray | None = None

    def __len__(self):
        return len(self.hit)


# ----------------------------------------------------------------------------- input


def _points_array(value, name, n=None):
    """Finite (n, 3) float64 array, else ContactPoseError naming ``name``."""
    arr = np.array(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and len(arr) != n):
        want = "(n, 3)" if n is None else f"({n}, 3)"
        raise ContactPoseError(f"{name} must have shape {want}, got {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise ContactPoseError(f"{name}[{np.flatnonzero(bad)[0]}] is not finite; expected finite coordinates")
    return arr


def _unit_directions(value, n):
    """(n, 3) unit vectors from non-zero finite directions."""
    d = _points_array(value, "directions", n)
    length = np.linalg.norm(d, axis=1)
    bad = ~(length > 0)
    if bad.any():
        i = np.flatnonzero(bad)[0]
        raise ContactPoseError(f"directions[{i}] is the zero vector; expected a non-zero direction")
    return d / length[:, None]


def _positive(value, name, *, allow_zero=False, allow_inf=False):
    """A float > 0 (or >= 0), finite unless allow_inf."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ContactPoseError(f"{name} must be a number, got {value!r}") from None
    ok = (x >= 0 if allow_zero else x > 0) and (np.isfinite(x) or (allow_inf and x == np.inf))
    if not ok:
        want = (">= 0" if allow_zero else "> 0") + ("" if allow_inf else " and finite")
        raise ContactPoseError(f"{name} must be {want}, got {value!r}")
    return x


def _mesh_arrays(vertices, faces):
    """Validated vertices (V, 3) float64 and faces (F, 3) int64."""
    v = _points_array(vertices, "vertices")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ContactPoseError(f"faces must have shape (F, 3) with F >= 1, got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ContactPoseError(f"faces must be integer vertex indices, got dtype {f.dtype}")
    if f.min() < 0 or f.max() >= len(v):
        raise ContactPoseError(f"faces index vertices 0..{len(v) - 1}, got indices {f.min()}..{f.max()}")
    return v, f.astype(np.int64)


# ------------------------------------------------------------------------ geometry


def _barycentric(q, tri, cross):
    """Barycentric coordinates of points q (P, 3) in triangles tri (P, 3, 3) with
    unnormalised normals cross (P, 3) (non-zero). -> (P, 3)"""
    a = tri[:, 0]
    den = np.einsum("ij,ij->i", cross, cross)
    beta = np.einsum("ij,ij->i", np.cross(q - a, tri[:, 2] - a), cross) / den
    gamma = np.einsum("ij,ij->i", np.cross(tri[:, 1] - a, q - a), cross) / den
    return np.stack([1.0 - beta - gamma, beta, gamma], axis=1)


def _closest_on_triangles(p, tri, cross, normals, planar):
    """Exact closest points of p (P, 3) on triangles tri (P, 3, 3), pairwise.

    cross, normals : (P, 3) raw and unit normals; planar : (P,) bool, False for
    degenerate triangles (only their edges count).
    Returns points (P, 3), barycentrics (P, 3), distances (P,).
    """
    P = len(p)
    best_q = np.empty((P, 3))
    best_b = np.zeros((P, 3))
    best_d2 = np.full(P, np.inf)
    for i, j in _EDGES:
        a, e = tri[:, i], tri[:, j] - tri[:, i]
        length2 = np.einsum("ij,ij->i", e, e)
        t = np.einsum("ij,ij->i", p - a, e) / np.where(length2 > 0, length2, 1.0)
        t = np.clip(t, 0.0, 1.0)
        q = a + t[:, None] * e
        d2 = np.einsum("ij,ij->i", p - q, p - q)
        better = d2 < best_d2
        best_q[better], best_d2[better] = q[better], d2[better]
        bary = np.zeros((better.sum(), 3))
        bary[:, i], bary[:, j] = 1.0 - t[better], t[better]
        best_b[better] = bary
    if planar.any():
        idx = np.flatnonzero(planar)
        h = np.einsum("ij,ij->i", p[idx] - tri[idx, 0], normals[idx])
        q = p[idx] - h[:, None] * normals[idx]
        bary = _barycentric(q, tri[idx], cross[idx])
        inside = (bary >= 0).all(axis=1)
        idx, q, bary, h = idx[inside], q[inside], bary[inside], h[inside]
        best_q[idx], best_b[idx], best_d2[idx] = q, bary, h * h
    return best_q, best_b, np.sqrt(best_d2)


def _ball_entry(w, u, r, slack):
    """First σ >= 0 with |w + σ u| = r for a ray entering the ball (inf if none).

    w : (P, 3) centre minus ball centre; u : (P, 3) unit."""
    b = np.einsum("ij,ij->i", w, u)
    c = np.einsum("ij,ij->i", w, w) - r * r
    disc = b * b - c
    ok = (b < 0) & (disc >= 0) & (np.sqrt(np.maximum(c + r * r, 0.0)) >= r - slack)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.maximum(c, 0.0) / (np.sqrt(np.maximum(disc, 0.0)) - b)
    return np.where(ok, sigma, np.inf)


def _cylinder_entry(w, u, e, r, slack):
    """First σ >= 0 at which the ray w + σ u (relative to the edge start) comes within r
    of the edge segment e through its side (inf if none). w, u, e : (P, 3)."""
    length2 = np.einsum("ij,ij->i", e, e)
    safe = np.where(length2 > 0, length2, 1.0)
    w_perp = w - (np.einsum("ij,ij->i", w, e) / safe)[:, None] * e
    u_perp = u - (np.einsum("ij,ij->i", u, e) / safe)[:, None] * e
    a = np.einsum("ij,ij->i", u_perp, u_perp)
    b = np.einsum("ij,ij->i", w_perp, u_perp)
    w2 = np.einsum("ij,ij->i", w_perp, w_perp)
    c = w2 - r * r
    disc = b * b - a * c
    ok = (length2 > 0) & (a > 1e-30) & (b < 0) & (disc >= 0) & (np.sqrt(w2) >= r - slack)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.maximum(c, 0.0) / (np.sqrt(np.maximum(disc, 0.0)) - b)
        t = np.einsum("ij,ij->i", w + np.where(ok, sigma, 0.0)[:, None] * u, e) / safe
    ok &= (t >= 0.0) & (t <= 1.0)
    return np.where(ok, sigma, np.inf)


def _cap_entry(c, u, tri, cross, normals, planar, r, slack):
    """First σ >= 0 at which c + σ u reaches distance r of the triangle's plane with its
    foot inside the triangle, from the side c is on (inf if none). -> (P,)"""
    sigma = np.full(len(c), np.inf)
    idx = np.flatnonzero(planar)
    if len(idx) == 0:
        return sigma
    n = normals[idx]
    h = np.einsum("ij,ij->i", c[idx] - tri[idx, 0], n)
    side = np.where(h >= 0, 1.0, -1.0)
    rate = side * np.einsum("ij,ij->i", u[idx], n)
    ok = (rate < 0) & (side * h >= r - slack)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.maximum(side * h - r, 0.0) / -rate
    s = np.where(ok, s, 0.0)
    foot = c[idx] + s[:, None] * u[idx] - (side * r)[:, None] * n
    inside = (_barycentric(foot, tri[idx], cross[idx]) >= -CAP_SLACK).all(axis=1)
    sigma[idx] = np.where(ok & inside, s, np.inf)
    return sigma


class _Mesh:
    """Float64 triangles with normals, centroid k-d trees by size class, and Open3D."""

    def __init__(self, vertices, faces):
        self.vertices, self.faces = _mesh_arrays(vertices, faces)
        self.tri = self.vertices[self.faces]
        lo, hi = self.vertices.min(axis=0), self.vertices.max(axis=0)
        self.centre = 0.5 * (lo + hi)
        self.diameter = float(np.linalg.norm(hi - lo))
        if not self.diameter > 0:
            raise ContactPoseError("vertices must span a non-zero extent; all vertices coincide")
        self.bound = float(np.max(np.linalg.norm(self.vertices - self.centre, axis=1)))
        self.cross = np.cross(self.tri[:, 1] - self.tri[:, 0], self.tri[:, 2] - self.tri[:, 0])
        double_area = np.linalg.norm(self.cross, axis=1)
        longest = np.max(np.linalg.norm(self.tri - np.roll(self.tri, 1, axis=1), axis=2), axis=1)
        self.planar = double_area > DEGENERATE_ALTITUDE * self.diameter * longest
        self.areas = np.where(self.planar, 0.5 * double_area, 0.0)
        if not self.planar.any():
            raise ContactPoseError("mesh has no non-degenerate face; expected triangles of non-zero area")
        self.normals = np.zeros_like(self.cross)
        self.normals[self.planar] = self.cross[self.planar] / double_area[self.planar, None]
        edges = np.sort(self.faces[self.planar][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        self.closed = bool(np.all(np.unique(edges, axis=0, return_counts=True)[1] == 2))
        self._build_trees()
        self._scene = None

    def _build_trees(self):
        """k-d trees over triangle centroids, one per power-of-two class of triangle size."""
        centroids = self.tri.mean(axis=1)
        size = np.max(np.linalg.norm(self.tri - centroids[:, None], axis=2), axis=1)
        top = max(size.max(), 1e-300)
        level = np.clip(np.ceil(np.log2(np.maximum(size, top * 2.0**-30) / top)), -30, 0).astype(int)
        self.trees = []
        for k in np.unique(level):
            ids = np.flatnonzero(level == k)
            self.trees.append((cKDTree(centroids[ids]), ids, top * 2.0**k * (1 + 1e-12)))

    def candidates(self, points, radius):
        """Pairs (point index, triangle id) with triangles that may lie within radius
        (scalar or (m,)) of points (m, 3); a superset, never missing one."""
        radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(points),))
        qi, ti = [], []
        for tree, ids, size in self.trees:
            lists = tree.query_ball_point(points, radius + size, return_sorted=False)
            counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(points))
            if counts.sum():
                qi.append(np.repeat(np.arange(len(points)), counts))
                ti.append(ids[np.concatenate([np.asarray(x, dtype=np.int64) for x in lists])])
        if not qi:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        return np.concatenate(qi), np.concatenate(ti)

    def scene(self):
        """The mesh's Raycaster (Open3D, float32), centred on the bounding-box centre."""
        if self._scene is None:
            self._scene = Raycaster(self.vertices, self.faces, centred=True)
        return self._scene

    def o3d_distance(self, points):
        """Float32 distances of points (m, 3) to the surface, as float64 (m,)."""
        return self.scene().distance(points)

    def o3d_inside(self, points):
        """(m,) bool: points inside the mesh (majority of three ray parities); all
        False for a mesh that is not closed, where inside has no meaning."""
        if not self.closed or len(points) == 0:
            return np.zeros(len(points), dtype=bool)
        return self.scene().inside(points)

    def closest(self, points, radius):
        """Exact closest points on the mesh among triangles within radius of points (m, 3).

        Returns points (m, 3), triangle ids (m,), barycentrics (m, 3), distances (m,)
        (inf and id -1 where no triangle lies within radius). Degenerate triangles lose
        ties to non-degenerate ones.
        """
        m = len(points)
        out_q, out_b = np.full((m, 3), np.nan), np.full((m, 3), np.nan)
        out_t, out_d = np.full(m, -1, dtype=np.int64), np.full(m, np.inf)
        qi, ti = self.candidates(points, radius)
        if len(qi) == 0:
            return out_q, out_t, out_b, out_d
        q, b, d = _closest_on_triangles(points[qi], self.tri[ti], self.cross[ti], self.normals[ti], self.planar[ti])
        key = d + np.where(self.planar[ti], 0.0, 1e-13 * self.diameter)
        order = np.lexsort((key, qi))
        first = order[np.r_[True, qi[order][1:] != qi[order][:-1]]]
        sel = qi[first]
        out_q[sel], out_t[sel], out_b[sel], out_d[sel] = q[first], ti[first], b[first], d[first]
        return out_q, out_t, out_b, out_d

    def first_entry(self, c, u, r, reach, slack, check_overlap=False):
        """Exact first touch of balls (radius r) moving from c (m, 3) along u (m, 3)
        within travel reach (m,). Returns σ (m,) (inf: no touch within reach) and
        (m,) bool: the ball already overlaps the mesh by more than slack (computed
        only with check_overlap)."""
        qi, ti = self.candidates(c, r + reach)
        sigma = np.full(len(c), np.inf)
        overlap = np.zeros(len(c), dtype=bool)
        if len(qi) == 0:
            return sigma, overlap
        cq, uq, tri = c[qi], u[qi], self.tri[ti]
        if check_overlap:
            _, _, dist = _closest_on_triangles(cq, tri, self.cross[ti], self.normals[ti], self.planar[ti])
            np.logical_or.at(overlap, qi, dist < r - slack)
        pair = _cap_entry(cq, uq, tri, self.cross[ti], self.normals[ti], self.planar[ti], r, slack)
        for i, j in _EDGES:
            pair = np.minimum(pair, _cylinder_entry(cq - tri[:, i], uq, tri[:, j] - tri[:, i], r, slack))
            pair = np.minimum(pair, _ball_entry(cq - tri[:, i], uq, r, slack))
        np.minimum.at(sigma, qi, pair)
        return np.where(sigma <= reach, sigma, np.inf), overlap


# --------------------------------------------------------------------------- sweep


def _ray_ball_span(mesh, starts, dirs, radius):
    """Travel interval (s_in, s_out) (n,) of centres within the ball of radius
    bound + r around the mesh centre (s_in > s_out: the ray passes it by)."""
    reach = mesh.bound + radius + 1e-9 * mesh.diameter
    w = starts - mesh.centre
    b = np.einsum("ij,ij->i", w, dirs)
    disc = b * b - (np.einsum("ij,ij->i", w, w) - reach * reach)
    root = np.sqrt(np.maximum(disc, 0.0))
    s_in, s_out = np.maximum(-b - root, 0.0), np.where(disc >= 0, -b + root, -np.inf)
    return s_in, s_out


def _advance(mesh, starts, dirs, radius, s, s_end):
    """Open3D conservative advancement: moves s (n,) in place and returns the
    estimated remaining gap (n,) (inf for fingers that passed s_end)."""
    margin = ADVANCE_MARGIN * (mesh.diameter + radius)
    gap = np.full(len(s), np.inf)
    active = np.flatnonzero(s <= s_end)
    for _ in range(MAX_ADVANCE_STEPS):
        if len(active) == 0:
            break
        d = mesh.o3d_distance(starts[active] + s[active, None] * dirs[active])
        step = d - radius - margin
        gap[active] = d - radius + margin
        move = step > margin
        s[active[move]] += step[move]
        passed = s[active] > s_end[active]
        gap[active[passed]] = np.inf
        active = active[move & ~passed]
    return gap


def _finish(mesh, starts, dirs, radius, s, s_end, gap, slack):
    """Exact sweep from s (n,) to first touch or s_end. Returns s (n,) with NaN for
    misses and (n,) bool of fingers that overlapped the mesh where the sweep began
    (left where they were)."""
    s = s.copy()
    hit = np.zeros(len(s), dtype=bool)
    overlap = np.zeros(len(s), dtype=bool)
    reach = np.clip(2.0 * gap, 1e-4 * mesh.diameter, 0.25 * mesh.diameter)
    active = np.flatnonzero(s <= s_end)
    first = True
    while len(active):
        step = np.minimum(reach[active], s_end[active] - s[active])
        centres = starts[active] + s[active, None] * dirs[active]
        sigma, over = mesh.first_entry(centres, dirs[active], radius, step, slack, check_overlap=first)
        if first:
            overlap[active], first = over, False
        touched = np.isfinite(sigma) & ~over
        s[active[touched]] += sigma[touched]
        hit[active[touched]] = True
        ahead = ~touched & ~over & (step < s_end[active] - s[active])
        s[active[ahead]] += step[ahead]
        reach[active] = np.minimum(4.0 * reach[active], 0.25 * mesh.diameter)
        active = active[ahead]
    return np.where(hit | overlap, s, np.nan), overlap


def _check_starts(mesh, starts, radius, slack):
    """ContactPoseError for a start inside the object or closer than r to its surface."""
    near = mesh.o3d_distance(starts)
    margin = ADVANCE_MARGIN * (mesh.diameter + radius)
    check = np.flatnonzero(near < radius + 2 * margin)
    _, _, _, dist = mesh.closest(starts[check], near[check] + margin)
    close = check[dist < radius - slack]
    if len(close):
        i, dist = close[0], dist[dist < radius - slack]
        raise ContactPoseError(
            f"starts[{i}] is {dist[0]:.6g} from the surface, closer than the radius {radius:.6g}; "
            "expected the finger to start clear of the object"
        )
    inside = np.flatnonzero(mesh.o3d_inside(starts) & (near > ADVANCE_MARGIN * mesh.diameter))
    if len(inside):
        raise ContactPoseError(f"starts[{inside[0]}] lies inside the object; expected a start outside it")


def _contacts(mesh, starts, dirs, radius, s):
    """FingertipContacts from travel s (n,) (NaN: miss)."""
    n = len(s)
    hit = np.isfinite(s)
    points, normals = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    centres, facets = np.full((n, 3), np.nan), np.full(n, -1, dtype=np.int64)
    features = np.full(n, MISS, dtype="<U6")
    idx = np.flatnonzero(hit)
    if len(idx):
        c = starts[idx] + s[idx, None] * dirs[idx]
        q, t, bary, dist = mesh.closest(c, radius + 1e-6 * mesh.diameter)
        if not np.all(np.abs(dist - radius) <= 1e-9 * max(mesh.diameter, radius)):
            log.warning("fingertip contact off the sphere by %.3g", np.max(np.abs(dist - radius)))
        normal = mesh.normals[t]
        if radius > DEGENERATE_ALTITUDE * mesh.diameter:
            normal = (c - q) / dist[:, None]
        zeros = (bary <= FEATURE_TOL).sum(axis=1)
        centres[idx], points[idx], normals[idx], facets[idx] = c, q, normal, t
        features[idx] = np.array([FACE, EDGE, VERTEX, VERTEX])[zeros]
    travel = np.where(hit, s, np.nan)
    return FingertipContacts(radius, points, normals, centres, facets, features, hit, travel, starts, dirs)


def _finish_checked(mesh, starts, dirs, radius, s, s_in, s_end, gap, suspect, slack):
    """_finish, redone exactly from s_in for fingers that the float32 advancement may
    have taken into the object (suspect (n,) bool, or overlapping where it stopped)."""
    done, overlap = _finish(mesh, starts, dirs, radius, s, s_end, gap, slack)
    redo = np.flatnonzero(overlap | suspect)
    if len(redo):
        log.warning("%d fingertip(s) overshot in float32 advancement; redone exactly", len(redo))
        wide = np.full(len(redo), 0.25 * mesh.diameter)
        done[redo], _ = _finish(mesh, starts[redo], dirs[redo], radius, s_in[redo], s_end[redo], wide, slack)
    return done


def _sweep(mesh, starts, dirs, radius, max_travel, tol):
    """sweep_spheres on a prepared mesh (inputs validated)."""
    slack = tol * mesh.diameter
    if len(starts) == 0:
        return _contacts(mesh, starts, dirs, radius, np.zeros(0))
    _check_starts(mesh, starts, radius, slack)
    s_in, s_out = _ray_ball_span(mesh, starts, dirs, radius)
    s_end = np.minimum(s_out, max_travel)
    s = s_in.copy()
    gap = _advance(mesh, starts, dirs, radius, s, s_end)
    moved = np.flatnonzero((s > s_in) & (s <= s_end))
    suspect = np.zeros(len(s), dtype=bool)
    suspect[moved] = mesh.o3d_inside(starts[moved] + s[moved, None] * dirs[moved])
    out = np.full(len(s), np.nan)
    for lo in range(0, len(s), _CHUNK):
        sl = slice(lo, lo + _CHUNK)
        args = (s[sl], s_in[sl], s_end[sl], gap[sl], suspect[sl])
        out[sl] = _finish_checked(mesh, starts[sl], dirs[sl], radius, *args, slack)
    return _contacts(mesh, starts, dirs, radius, out)


def sweep_spheres(vertices, faces, starts, directions, radius, *, max_travel=None, tol=1e-12):
    """Move balls of radius r from starts along directions until they first touch the mesh.

    vertices : (V, 3) float; faces : (F, 3) int, closed and outward-wound;
    starts : (n, 3) ball centres, outside the object and at least r from it;
    directions : (n, 3) non-zero (normalised here); radius : r >= 0;
    max_travel : longest centre travel (default: until the ball has passed the object);
    tol : touching tolerance as a fraction of the diameter (a start within tol of
    touching counts as touching).
    Returns FingertipContacts of n rows; fingers that touch nothing have hit False.
    """
    mesh = _Mesh(vertices, faces)
    starts = _points_array(starts, "starts")
    dirs = _unit_directions(directions, len(starts))
    radius = _positive(radius, "radius", allow_zero=True)
    max_travel = np.inf if max_travel is None else _positive(max_travel, "max_travel", allow_inf=True)
    tol = _positive(tol, "tol")
    return _sweep(mesh, starts, dirs, radius, max_travel, tol)


# ------------------------------------------------------------------------ approach


def _sample_surface(mesh, n, rng):
    """n area-uniform surface points (n, 3) and their triangles (n,)."""
    facets = rng.choice(len(mesh.areas), size=n, p=mesh.areas / mesh.areas.sum())
    return uniform_in_triangles(mesh.tri[facets], rng), facets


def _cone_directions(axes, half_angle, rng):
    """Unit directions (n, 3) uniform in cones of half_angle (radians) about unit axes (n, 3)."""
    n = len(axes)
    cos_t = 1.0 - rng.random(n) * (1.0 - np.cos(half_angle))
    sin_t = np.sqrt(np.maximum(1.0 - cos_t**2, 0.0))
    phi = rng.uniform(0.0, 2 * np.pi, n)
    e1, e2 = tangent_basis(axes).transpose(1, 0, 2)
    d = cos_t[:, None] * axes + sin_t[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _targets(mesh, n, rng, surface_points, facets):
    """Aimed-at points (n, 3) and their planar triangles (n,): sampled or given."""
    if surface_points is None:
        if n is None or isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ContactPoseError(f"n must be an integer >= 0, got {n!r}")
        return _sample_surface(mesh, int(n), rng)
    points = _points_array(surface_points, "surface_points")
    if n is not None and n != len(points):
        raise ContactPoseError(f"n must equal len(surface_points) = {len(points)}, got {n!r}")
    if facets is None:
        _, facets, _, _ = mesh.closest(points, mesh.o3d_distance(points) + ADVANCE_MARGIN * mesh.diameter)
    facets = np.asarray(facets)
    if facets.shape != (len(points),) or not np.issubdtype(facets.dtype, np.integer):
        raise ContactPoseError(f"facets must be ({len(points)},) int, got {facets.shape} {facets.dtype}")
    bad = (facets < 0) | (facets >= len(mesh.faces))
    bad[~bad] = ~mesh.planar[facets[~bad]]
    if bad.any():
        raise ContactPoseError(f"facets[{np.flatnonzero(bad)[0]}] is not a non-degenerate face index")
    return points, facets.astype(np.int64)


def approach(vertices, faces, rng, n, radius, *, cone_deg=30.0, mode="cone", standoff=None,
             surface_points=None, facets=None, max_travel=None):
    """n fingertips of radius r aimed at surface points, each stopping at its first touch.

    vertices : (V, 3) float; faces : (F, 3) int, closed and outward-wound;
    rng : numpy.random.Generator; n : number of fingers (may be None when
    surface_points is given); radius : r >= 0.
    Targets: n area-uniform surface points, or surface_points (n, 3) on the facets
    (n,) int (default: the closest triangle). Directions: mode "cone", uniform in a cone
    of half-angle cone_deg (in [0, 90)) about the target's inward facet normal; mode
    "closing", from the target toward the area-weighted surface centroid (the inward
    normal if they coincide). The ball starts standoff (default 1.05 diameters + r)
    back from the target along the direction, outside the object, and sweeps as in
    :func:`sweep_spheres`; the touch may come before the target (first contact).
    Returns FingertipContacts with targets and target_facets set.
    """
    if not isinstance(rng, np.random.Generator):
        raise ContactPoseError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if mode not in MODES:
        raise ContactPoseError(f"mode must be one of {MODES}, got {mode!r}")
    try:
        cone = float(cone_deg)
    except (TypeError, ValueError):
        raise ContactPoseError(f"cone_deg must be a number in [0, 90), got {cone_deg!r}") from None
    if not 0.0 <= cone < 90.0:
        raise ContactPoseError(f"cone_deg must be in [0, 90), got {cone_deg!r}")
    mesh = _Mesh(vertices, faces)
    radius = _positive(radius, "radius", allow_zero=True)
    max_travel = np.inf if max_travel is None else _positive(max_travel, "max_travel", allow_inf=True)
    standoff = STANDOFF_DIAMETERS * mesh.diameter + radius if standoff is None else _positive(standoff, "standoff")
    points, target_facets = _targets(mesh, n, rng, surface_points, facets)
    inward = -mesh.normals[target_facets]
    if mode == "cone":
        dirs = _cone_directions(inward, np.radians(cone), rng)
    else:
        centroid = (mesh.areas[:, None] * mesh.tri.mean(axis=1)).sum(axis=0) / mesh.areas.sum()
        to_centre = centroid - points
        length = np.linalg.norm(to_centre, axis=1, keepdims=True)
        dirs = np.where(length > 1e-9 * mesh.diameter, to_centre / np.where(length > 0, length, 1.0), inward)
    out = _sweep(mesh, points - standoff * dirs, dirs, radius, max_travel, 1e-12)
    out.targets, out.target_facets = points, target_facets
    return out


def swept_free_points(touch, spacing, inner=0.8):
    """Points the fingertips swept through before they touched (object frame): the ball
    centres along each hit finger's path from its start to its touch, ``spacing`` apart, and
    for r > 0 the points inner·r from each centre along ±x, ±y and ±z, inside the ball, which
    the first touch keeps outside the object. A fingertip of radius 0 (a ray) stops one
    spacing short of its touch, which lies on the surface.

    touch : FingertipContacts (from :func:`approach` or :func:`sweep_spheres`); spacing > 0
    (length units); inner in [0, 1). -> (M, 3) float64
    """
    spacing = _positive(spacing, "spacing")
    if not 0.0 <= inner < 1.0:
        raise ContactPoseError(f"inner must be in [0, 1), got {inner!r}")
    hit = np.flatnonzero(touch.hit)
    end = touch.travel[hit] - (spacing if touch.radius == 0 else 0.0)
    steps = [np.append(np.arange(0.0, e, spacing), e) if e >= 0 else np.zeros(0) for e in end]
    centres = np.concatenate([touch.starts[k] + s[:, None] * touch.directions[k] for k, s in zip(hit, steps)]
                             + [np.zeros((0, 3))])
    if touch.radius == 0 or len(centres) == 0:
        return centres
    offsets = inner * touch.radius * np.concatenate([np.eye(3), -np.eye(3)])
    return np.concatenate([centres, (centres[:, None, :] + offsets[None]).reshape(-1, 3)])
