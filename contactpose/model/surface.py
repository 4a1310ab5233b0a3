"""The surface's topology: which facets meet at each edge and vertex of the vertex-merged mesh,
and which edges and vertices are convex. The surface contact model (costs.surface) walks it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SurfaceTopology:
    """Which facets meet at each edge and vertex of a model's vertex-merged mesh.

    fv : (m, 3) merged vertex of each facet corner; points : (V, 3) merged positions;
    edge_nbr : (m, 3) the facet across edge j = (fv[:, j], fv[:, j+1]) (-1: none);
    edge_convex : (m, 3) bool; vf_ptr (V + 1,), vf : CSR valid facets at each vertex;
    vertex_convex : (V,) bool, every edge at the vertex convex.
    """

    fv: np.ndarray
    points: np.ndarray
    edge_nbr: np.ndarray
    edge_convex: np.ndarray
    vf_ptr: np.ndarray
    vf: np.ndarray
    vertex_convex: np.ndarray

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
        vertex_convex = np.ones(nv, dtype=bool)
        vertex_convex[edges[~convex].ravel()] = False
        faces = np.flatnonzero(valid)
        corner_v = fv[faces].ravel()
        order = np.argsort(corner_v, kind="stable")
        vf_ptr = np.zeros(nv + 1, dtype=np.int64)
        np.cumsum(np.bincount(corner_v, minlength=nv), out=vf_ptr[1:])
        return cls(fv, np.asarray(merged.vertices, dtype=np.float64), edge_nbr, edge_convex, vf_ptr,
                   np.repeat(faces, 3)[order], vertex_convex)

