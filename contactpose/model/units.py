"""Search units for contacts on sharp edges and vertices: each valid facet, each convex edge
between facets that are not coplanar, each vertex whose facets are not all coplanar
(research/edge_contacts.md).

A rounded fingertip touching a facet-table model touches a face, an edge or a vertex. On a face
its normal is the facet's; on a convex edge it lies on the arc between the two facets' normals;
at a vertex, in the cone of its facets' normals. The facet table compares a contact's normal
with facet normals only, so one edge contact on a coarse mesh can leave no admissible tuple.
Here each unit is a small piece of the surface with the normals a contact on it can have:

* its geometry, as a triangle: the facet's own, an edge's segment (a, b, b) or a vertex's point;
* an axis and a half-angle β that hold every such normal: the facet's normal and 0; the bisector
  of the edge's two normals and half their angle; the normalised sum of the vertex's facet
  normals and the largest angle from it to one of them (π when past a right angle, where a cap
  of the sphere stops being convex); π for an edge or vertex on the border of an open mesh;
* a representative facet whose plane holds the unit (the edge's or vertex's first facet), on
  which a hypothesis is posed and reported.

:func:`unit_features` gives every unit pair the characteristics of the facet table, each
holding every contact pair on the two units: the exact Δmin and Δmax of the two triangles, the
normal angle widened to [α − β_u − β_v, α + β_u + β_v], and direction intervals from the unit's
axis, widened by 2 sin(β / 2) Δmax (a normal within β of the axis changes the height of a point
at most Δmax away by at most that).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactpose.geometry.kernels import triangle_pair_bounds
from contactpose.model.features import PairFeatures, round_down32, round_up32
from contactpose.model.memory import check_fits
from contactpose.model.table import STORED_BYTES_PER_PAIR

#: Facet normals closer than this (radians) count as coplanar: their edge or vertex is no unit.
COPLANAR_ANGLE = 1e-9
#: Bytes per unit pair while the features are computed (float64 work arrays beside the stored ones).
BUILD_BYTES_PER_PAIR = STORED_BYTES_PER_PAIR + 96
#: Seconds per unit pair to build their features and table (1.4 µs measured on rock1k's
#: 3.7 M pairs on a 2-core machine; rounded up).
BUILD_SECONDS_PER_PAIR = 2e-6
#: Unit kinds.
FACE, EDGE, VERTEX = 0, 1, 2

__all__ = ["EDGE", "FACE", "VERTEX", "SearchUnits", "unit_features", "unit_table_cost"]


@dataclass(frozen=True)
class SearchUnits:
    """triangles (U, 3, 3): each unit's geometry (object frame); normals (U, 3): its unit axis;
    cones (U,): β in radians; facets (U,) int: its representative facet; kinds (U,) int:
    FACE, EDGE or VERTEX. The first units are the valid facets, in facet order."""

    triangles: np.ndarray
    normals: np.ndarray
    cones: np.ndarray
    facets: np.ndarray
    kinds: np.ndarray

    @classmethod
    def of(cls, model):
        """The units of ``model`` (an ObjectModel): its valid facets, sharp convex edges and
        vertices (model.topology)."""
        valid = np.flatnonzero(model.planes.valid)
        normals = model.planes.normals
        parts = [(model.triangles[valid], normals[valid], np.zeros(len(valid)), valid, FACE),
                 _edges(model.topology, normals, model.planes.valid),
                 _vertices(model.topology, normals, model.planes.valid)]
        return cls(*(np.concatenate([p[i] for p in parts]) for i in range(4)),
                   np.concatenate([np.full(len(p[3]), p[4]) for p in parts]))

    def __len__(self):
        return len(self.facets)


def _edges(topology, normals, valid):
    """Convex edges between valid facets whose normals differ, and the border edges of an open
    mesh (a fingertip may touch those from any side: cone π): (triangles, axes, cones, facets, EDGE)."""
    fv, nbr = topology.fv, topology.edge_nbr
    f, slot = np.nonzero(topology.edge_convex & (nbr > np.arange(len(fv))[:, None]))
    g = nbr[f, slot]
    turn = _angle(normals[f], normals[g])
    keep = turn > COPLANAR_ANGLE
    f, slot, g, turn = f[keep], slot[keep], g[keep], turn[keep]
    fb, sb = _border(topology, valid)
    f, slot = np.concatenate([f, fb]), np.concatenate([slot, sb])
    axes = np.concatenate([_unit(normals[f[:len(g)]] + normals[g]), normals[fb]])
    cones = np.concatenate([turn / 2.0, np.full(len(fb), np.pi)])
    a, b = topology.points[fv[f, slot]], topology.points[fv[f, (slot + 1) % 3]]
    return np.stack([a, b, b], axis=1), axes, cones, f, EDGE


def _border(topology, valid):
    """(facets, slots) of the edges of valid facets that have no neighbour (an open mesh's border)."""
    f, slot = np.nonzero((topology.edge_nbr < 0) & valid[:, None])
    return f, slot


def _vertices(topology, normals, valid):
    """Vertices whose valid facets are not all coplanar, and those on an open mesh's border
    (cone π): (triangles, axes, cones, facets, VERTEX)."""
    count = np.diff(topology.vf_ptr)
    owner = np.repeat(np.arange(len(count)), count)
    sums = np.zeros((len(count), 3))
    np.add.at(sums, owner, normals[topology.vf])
    has = (count > 0) & (np.linalg.norm(sums, axis=1) > 0)
    axes = np.zeros_like(sums)
    axes[has] = _unit(sums[has])
    spread = np.zeros(len(count))
    np.maximum.at(spread, owner, _angle(axes[owner], normals[topology.vf]))
    fb, sb = _border(topology, valid)
    border = np.zeros(len(count), dtype=bool)
    border[topology.fv[fb, sb]] = border[topology.fv[fb, (sb + 1) % 3]] = True
    keep = np.flatnonzero(has & ((spread > COPLANAR_ANGLE) | border))
    cones = np.where((spread[keep] < np.pi / 2) & ~border[keep], spread[keep], np.pi)
    first = topology.vf[topology.vf_ptr[keep]]
    return np.repeat(topology.points[keep][:, None], 3, axis=1), axes[keep], cones, first, VERTEX


def unit_table_cost(n):
    """(bytes, seconds) that building the pair features of n search units takes, estimated
    (BUILD_BYTES_PER_PAIR and BUILD_SECONDS_PER_PAIR per unordered pair)."""
    pairs = n * (n + 1) // 2
    return BUILD_BYTES_PER_PAIR * pairs, BUILD_SECONDS_PER_PAIR * pairs


def unit_features(units, progress=None):
    """PairFeatures of every unordered unit pair {u, v}, u <= v (see the module's notes); k and
    l index ``units``. ResourceError when they would not fit in memory."""
    n = len(units)
    check_fits(unit_table_cost(n)[0], f"pair features of {n:,} search units (facets, edges, vertices)",
               "use a model of surface regions for a mesh this fine")
    k, l = np.triu_indices(n)
    dmin, dmin_vertex, dmax = triangle_pair_bounds(units.triangles, k, l)
    alpha = _angle(units.normals[k], units.normals[l])
    spread = units.cones[k] + units.cones[l]
    return PairFeatures(k.astype(np.int32), l.astype(np.int32), round_up32(dmax), round_down32(dmin_vertex),
                        round_down32(dmin), round_down32(np.maximum(alpha - spread, 0.0)),
                        _heights(units, k, l, dmax), _heights(units, l, k, dmax),
                        round_up32(np.minimum(alpha + spread, np.pi)))


def _heights(units, u, v, dmax):
    """Direction intervals (P, 2) float32 of the pairs (u, v): the heights n_uᵀ(q − p) of unit v's
    corners q over unit u's first corner p along u's axis (the whole unit lies at one height:
    a facet in its plane, an edge across its bisector), widened by 2 sin(β_u / 2) Δmax."""
    tri, axes = units.triangles, units.normals
    h = np.einsum("pj,pij->pi", axes[u], tri[v] - tri[u][:, :1])
    by = 2.0 * np.sin(np.minimum(units.cones[u], np.pi) / 2.0) * dmax
    return np.stack([round_down32(h.min(axis=1) - by), round_up32(h.max(axis=1) + by)], axis=1)


def _angle(a, b):
    """Angles (radians) between the rows of unit vectors a and b (p, 3)."""
    return np.arccos(np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0))


def _unit(v):
    return v / np.linalg.norm(v, axis=1, keepdims=True)
