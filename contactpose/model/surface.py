"""The surface's topology: which facets meet at each edge and vertex of the vertex-merged mesh,
which edges are convex, and each vertex's normal cone. The surface contact model
(costs.surface) walks it."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

#: A unit direction ν is in a vertex's normal cone when no edge at the vertex, as a unit
#: direction, rises above the plane of normal ν by more than this.
POLAR_TOL = 1e-9


@dataclass
class SurfaceTopology:
    """Which facets meet at each edge and vertex of a model's vertex-merged mesh.

    fv : (m, 3) merged vertex of each facet corner; points : (V, 3) merged positions;
    edge_nbr : (m, 3) the facet across edge j = (fv[:, j], fv[:, j+1]) (-1: none);
    edge_convex : (m, 3) bool; vf_ptr (V + 1,), vf : CSR valid facets at each vertex;
    cone_ptr (V + 1,), cone_rays (K, 3) : CSR unit rays spanning each vertex's normal cone
    (:func:`normal_cone_rays`; none where a ball cannot touch the vertex alone); cone_bound
    (V, 4) : a unit axis and a half-angle (radians) that hold each vertex's cone; spread (m,) :
    the largest angle (radians) from each facet's normal to a normal its own features admit
    (:func:`facet_spread`).
    """

    fv: np.ndarray
    points: np.ndarray
    edge_nbr: np.ndarray
    edge_convex: np.ndarray
    vf_ptr: np.ndarray
    vf: np.ndarray
    cone_ptr: np.ndarray
    cone_rays: np.ndarray
    cone_bound: np.ndarray
    spread: np.ndarray

    @classmethod
    def of(cls, merged, valid):
        """merged : trimesh.Trimesh with coincident vertices merged (the model's face order);
        valid : (m,) bool, the facets with a plane."""
        fv = np.asarray(merged.faces, dtype=np.int64)
        m, nv = len(fv), len(merged.vertices)
        adjacency = np.asarray(merged.face_adjacency, dtype=np.int64).reshape(-1, 2)
        edges = np.sort(np.asarray(merged.face_adjacency_edges, dtype=np.int64).reshape(-1, 2), axis=1)
        convex = np.asarray(merged.face_adjacency_convex, dtype=bool).reshape(-1)
        keep = valid[adjacency].all(axis=1)
        adjacency, edges, convex = adjacency[keep], edges[keep], convex[keep]
        edge_nbr, edge_convex = -np.ones((m, 3), dtype=np.int64), np.zeros((m, 3), dtype=bool)
        corners = np.sort(np.stack([fv, np.roll(fv, -1, axis=1)], axis=2), axis=2)  # (m, 3, 2) edge j
        for side in (0, 1):
            f, g = adjacency[:, side], adjacency[:, 1 - side]
            slot = np.argmax((corners[f] == edges[:, None, :]).all(axis=2), axis=1)
            free = edge_nbr[f, slot] < 0  # a non-manifold edge keeps its first neighbour
            edge_nbr[f[free], slot[free]], edge_convex[f[free], slot[free]] = g[free], convex[free]
        faces = np.flatnonzero(valid)
        corner_v = fv[faces].ravel()
        order = np.argsort(corner_v, kind="stable")
        vf_ptr = np.zeros(nv + 1, dtype=np.int64)
        np.cumsum(np.bincount(corner_v, minlength=nv), out=vf_ptr[1:])
        points = np.asarray(merged.vertices, dtype=np.float64)
        vf = np.repeat(faces, 3)[order]
        normals = np.asarray(merged.face_normals, dtype=np.float64)
        cone_ptr, cone_rays = normal_cone_rays(points, fv[faces], vf_ptr, vf, normals)
        spread = facet_spread(fv, edge_nbr, edge_convex, cone_ptr, cone_rays, normals, valid)
        return cls(fv, points, edge_nbr, edge_convex, vf_ptr, vf, cone_ptr, cone_rays, cone_bounds(cone_ptr, cone_rays),
                   spread)

    @property
    def arrays(self):
        """The arrays the compiled contact model takes (costs.surface.surface_rows), in order."""
        return (self.fv, self.points, self.edge_nbr, self.edge_convex, self.vf_ptr, self.vf, self.cone_ptr,
                self.cone_rays, self.cone_bound)


def cone_bounds(cone_ptr, rays):
    """Per vertex, a unit axis (the normalised sum of its cone's rays) and the largest angle
    from it to a ray: under a right angle, every direction of the (convex) cone lies within
    that angle of the axis (the cap is convex and holds the rays), so a normal θ from the axis
    is at least θ − half from the cone; π past it. -> (V, 4), axis then half; (0, 0, 0, 0) for
    a vertex without a cone."""
    nv = len(cone_ptr) - 1
    owner = np.repeat(np.arange(nv), np.diff(cone_ptr))
    axis = np.zeros((nv, 3))
    np.add.at(axis, owner, rays)
    norm = np.linalg.norm(axis, axis=1, keepdims=True)
    axis = np.divide(axis, norm, out=np.zeros_like(axis), where=norm > 1e-12)
    half = np.zeros(nv)
    np.maximum.at(half, owner, np.arccos(np.clip(np.sum(axis[owner] * rays, axis=1), -1.0, 1.0)))
    half[half >= np.pi / 2] = np.pi  # a cap past a right angle is not convex: no bound
    return np.column_stack([axis, half])


def normal_cone_rays(points, faces, vf_ptr, vf, face_normals):
    """Each vertex's normal cone: the outward directions ν that a ball of any radius touching
    the vertex alone can have, ν · (u − v) <= 0 for every neighbour u of v (no edge at v rises
    above the ball's tangent plane; the polar of the cone of its edges), on the side of its
    facets' normals. At a convex vertex these are the directions its facets' normals span; at
    a vertex with concave edges, fewer, and none at a saddle. -> (cone_ptr (V + 1,), rays
    (K, 3)): CSR unit rays (the cone's extreme rays) spanning it.

    points : (V, 3); faces : (m', 3) the valid facets' merged vertices; vf_ptr, vf : CSR valid
    facets at each vertex (indices into face_normals (m, 3))."""
    nv = len(points)
    ends = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    ends = np.unique(np.concatenate([ends, ends[:, ::-1]]), axis=0)  # (v, u), sorted by v
    nb_ptr = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(np.bincount(ends[:, 0], minlength=nv), out=nb_ptr[1:])
    edges = points[ends[:, 1]] - points[ends[:, 0]]
    edges /= np.maximum(np.linalg.norm(edges, axis=1, keepdims=True), 1e-300)
    owner = np.repeat(np.arange(nv), np.diff(vf_ptr))
    outward = np.zeros((nv, 3))
    np.add.at(outward, owner, face_normals[vf])
    counts, rays = _polar_rays(edges, nb_ptr, outward, POLAR_TOL)
    cone_ptr = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(counts, out=cone_ptr[1:])
    return cone_ptr, rays[:cone_ptr[-1]]


@numba.njit(cache=True)
def facet_spread(fv, edge_nbr, edge_convex, cone_ptr, cone_rays, normals, valid):
    """The largest angle (radians) from each valid facet's normal to a normal one of its own
    features admits: its convex edges' arcs reach the neighbour's normal, its vertices' cones
    their rays (cones are convex, so under a right angle their rays bound them; π past it). A
    contact whose normal is θ from the facet's is at least θ − spread from every feature of it
    (a lower bound that lets the surface association skip the facet). -> (m,), 0 for an
    invalid facet"""
    out = np.zeros(len(fv))
    for f in range(len(fv)):
        if not valid[f]:
            continue
        widest = 1.0
        for j in range(3):
            h = edge_nbr[f, j]
            if h >= 0 and edge_convex[f, j]:
                widest = min(widest, normals[f] @ normals[h])
            u = fv[f, j]
            for r in range(cone_ptr[u], cone_ptr[u + 1]):
                widest = min(widest, normals[f] @ cone_rays[r])
        out[f] = np.arccos(max(-1.0, min(1.0, widest))) if widest > 0.0 else np.pi  # a cap past a right angle: no bound
    return out


@numba.njit(cache=True)
def _polar_rays(edges, nb_ptr, outward, tol):
    """The extreme rays of {ν : ν · e <= tol for the unit edges e at each vertex, ν · outward > 0}:
    of the cross products of every two edges, both signs, those that hold every constraint,
    each once. -> (counts (V,), rays (>= K, 3) in vertex order)"""
    nv = len(nb_ptr) - 1
    cap = 0
    for v in range(nv):
        k = nb_ptr[v + 1] - nb_ptr[v]
        cap += k * (k - 1)
    rays, counts, used = np.empty((cap, 3)), np.zeros(nv, dtype=np.int64), 0
    for v in range(nv):
        lo, hi = nb_ptr[v], nb_ptr[v + 1]
        start = used
        for a in range(lo, hi):
            for b in range(a + 1, hi):
                c = np.cross(edges[a], edges[b])
                norm = np.sqrt(c @ c)
                if norm < 1e-12:
                    continue
                c /= norm
                if c @ outward[v] < 0.0:
                    c = -c
                if c @ outward[v] <= 0.0:
                    continue
                feasible = True
                for e in range(lo, hi):
                    if edges[e] @ c > tol:
                        feasible = False
                        break
                if not feasible:
                    continue
                for r in range(start, used):
                    if rays[r] @ c > 1.0 - 1e-12:
                        feasible = False
                        break
                if feasible:
                    rays[used] = c
                    used += 1
        counts[v] = used - start
    return counts, rays

