"""Oriented samples of an object's surface, each with the normal cone of the surface near it:
the model that a search on the surface matches contacts against (research/surface_search.md;
the search itself has not landed).

Sample a is a point q_a on a valid facet, that facet's normal n_a, and a half-angle β_a. What
holds, whatever the tessellation (tests/model/test_samples.py checks it against dense points):

* **covering**: every point of every valid facet lies within ``covering`` of some sample;
* **cones**: every point x of a valid facet has a sample a within ``covering`` whose *patch*
  holds x's facet; a's patch is the valid facets within ``covering`` of q_a that connect to a's
  own facet through such facets (sharing a vertex), and β_a is the largest angle from n_a to the
  normal of a facet in it (π past a right angle, where the cap of the sphere stops being
  convex: up to a right angle the normalised convex combinations of normals in the cap stay
  in it, so a box's edge keeps a 90° cone). A contact at x, on a face, an edge or a vertex, has its normal in the convex hull of
  the normals of the facets that touch x; those touch x's facet, lie within ``covering`` of q_a
  and so are in a's patch: the normal lies within β_a of n_a. Connected patches keep a thin
  wall's other side out of the cone (the YCB mug: median β 180° by distance alone, both walls
  within the covering radius). This holds on a conforming mesh (facets meet at shared
  vertices, no T-junctions);
* **spacing**: no two samples are closer than ``spacing``, so their number follows the
  surface's area over spacing², not its facet count (two sides of a thin wall are sampled
  apart).

How: each valid facet is cut into a barycentric grid whose cells hold every point of the facet
within δ ≤ spacing / GRID_DIVISOR of a grid point (a point of a triangle lies within the
triangle's circumradius, and within its longest edge, of a corner); the grid points are thinned
greedily: a point is kept unless a kept point within ``spacing`` has its facet in its patch, so
every grid point lies within ``spacing`` of a sample whose patch holds its facet, and
covering = spacing + δ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from contactpose.errors import check_length
from contactpose.geometry.kernels import point_triangle_distance
from contactpose.model.memory import check_fits

#: The grid's cells are at most spacing / GRID_DIVISOR across (from a point to its nearest
#: grid corner): the covering radius is then at most (1 + 1 / GRID_DIVISOR) spacing.
GRID_DIVISOR = 4
#: Default spacing as a fraction of the object's diameter (the prototypes' 3 %), or the pair
#: distance gate when that is wider (spacing_for).
SPACING_FRAC = 0.03
#: Facet normals this far past a right angle (in cosine) still count as at one (a box's edges).
RIGHT_ANGLE_SLACK = 1e-12
#: Bytes per grid point while the samples are drawn (points, facet, thinning flags, the tree).
GRID_BYTES_PER_POINT = 120


@dataclass(frozen=True)
class SurfaceSamples:
    """points (N, 3) and normals (N, 3): the samples and their facets' unit normals, object
    frame; cones (N,): β_a in radians; facets (N,) int: the facet each lies on; spacing and
    covering: lengths in the mesh's units (see the module's notes)."""

    points: np.ndarray
    normals: np.ndarray
    cones: np.ndarray
    facets: np.ndarray
    spacing: float
    covering: float

    @classmethod
    def of(cls, model, spacing):
        """The samples of ``model``'s valid facets at ``spacing`` (a positive length)."""
        spacing = check_length(spacing, "spacing")
        valid = np.flatnonzero(model.planes.valid)
        grid, owner, cell = _grid_points(model.triangles[valid], spacing / GRID_DIVISOR)
        covering = spacing + cell
        kept, cones = _thinned(model, grid, valid[owner], spacing, covering)
        facets = valid[owner[kept]]
        return cls(grid[kept], model.planes.normals[facets], cones, facets, spacing, covering)

    def __len__(self):
        return len(self.points)


def spacing_for(model, tolerance):
    """The default spacing: SPACING_FRAC of the diameter, or the pair distance gate
    (tolerance.distance: the stated noise and model error) when that is wider."""
    return max(SPACING_FRAC * model.diameter, tolerance.distance)


def _grid_points(triangles, step):
    """Barycentric grid points of each triangle (T, 3, 3), each point of a triangle within
    ``step`` of one of its grid points. -> (points (G, 3), owner (G,) index into triangles,
    the largest distance bound δ <= step)"""
    edges = np.linalg.norm(triangles - np.roll(triangles, 1, axis=1), axis=2)
    reach = np.minimum(_circumradius(edges), edges.max(axis=1))  # nearest-corner distance bound
    cuts = np.maximum(1, np.ceil(reach / step)).astype(np.int64)
    count = int(np.sum((cuts + 1) * (cuts + 2) // 2))
    check_fits(GRID_BYTES_PER_POINT * count, f"sampling the surface at spacing {GRID_DIVISOR * step:.3g}",
               "use a larger spacing")
    points, owner = [], []
    for n in np.unique(cuts):
        rows = np.flatnonzero(cuts == n)
        i, j = np.triu_indices(n + 1)
        bary = np.stack([n - j, j - i, i], axis=1) / n  # every (k, l, m) >= 0 with k + l + m = n, once
        points.append(np.einsum("gk,tkd->tgd", bary, triangles[rows]).reshape(-1, 3))
        owner.append(np.repeat(rows, len(bary)))
    return np.concatenate(points), np.concatenate(owner), float(np.max(reach / cuts))


def _circumradius(edges):
    """Circumradius of triangles with side lengths ``edges`` (T, 3) (inf for a degenerate one)."""
    a, b, c = edges.T
    area4 = np.sqrt(np.maximum((a + b + c) * (-a + b + c) * (a - b + c) * (a + b - c), 0.0))
    with np.errstate(divide="ignore"):
        return np.where(area4 > 0, a * b * c / np.where(area4 > 0, area4, 1.0), np.inf)


def _thinned(model, grid, owner, spacing, covering):
    """Greedy thinning of the grid points (G, 3) on facets ``owner`` (G,): each point, in order,
    is kept unless blocked, and a kept point blocks the points within ``spacing`` on the
    facets of its patch. -> (kept (N,) indices, β (N,) radians)"""
    points_tree = cKDTree(grid)
    facet_tree, valid, radius = model.centroid_tree
    graph = _vertex_graph(model)
    normals, triangles = model.planes.normals, model.triangles
    blocked = np.zeros(len(grid), dtype=bool)
    in_patch = np.zeros(len(normals), dtype=bool)
    kept, cones = [], []
    for i in range(len(grid)):
        if blocked[i]:
            continue
        patch = _patch(graph, grid[i], owner[i], facet_tree, valid, radius, triangles, covering)
        least = float(np.min(normals[patch] @ normals[owner[i]]))
        in_patch[patch] = True
        near = np.asarray(points_tree.query_ball_point(grid[i], spacing), dtype=np.int64)
        blocked[near[in_patch[owner[near]]]] = True
        in_patch[patch] = False
        kept.append(i)
        cones.append(np.arccos(np.clip(least, 0.0, 1.0)) if least > -RIGHT_ANGLE_SLACK else np.pi)
    return np.array(kept, dtype=np.int64), np.array(cones)


def _patch(graph, point, facet, facet_tree, valid, radius, triangles, covering):
    """The valid facets within ``covering`` of ``point`` connected to ``facet`` through such
    facets (graph: facets sharing a vertex). -> (k,) facet indices, ``facet`` among them"""
    near = valid[np.asarray(facet_tree.query_ball_point(point, covering + radius), dtype=np.int64)]
    near = near[point_triangle_distance(np.broadcast_to(point, (len(near), 3)), triangles[near]) <= covering]
    near = np.union1d(near, [facet])
    _, labels = connected_components(graph[near][:, near], directed=False)
    return near[labels == labels[np.searchsorted(near, facet)]]


def _vertex_graph(model):
    """(m, m) sparse: facets that share a vertex of the vertex-merged mesh (model.topology)."""
    fv = model.topology.fv
    m = len(fv)
    incidence = csr_matrix((np.ones(3 * m), (np.repeat(np.arange(m), 3), fv.ravel())),
                           shape=(m, int(fv.max()) + 1))
    return (incidence @ incidence.T).tocsr()
