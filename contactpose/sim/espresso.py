"""A procedural espresso-machine-like object, standing in for the paper's scanned coffee maker.

The paper's second experiment scanned a real espresso machine into 83,846
facets. :func:`espresso_machine` builds a deterministic look-alike from
primitives: a plinth with a drip tray, a back column, an overhanging head with
the group, a portafilter (basket, handle, two spouts), a water tank at the back
and a steam wand. The parts overlap but are not unioned, so the mesh is not
watertight; every part is closed and wound outward. Units are metres, z is up,
the front faces -y; the machine's largest extent is ``SIZE`` = 0.35 m.
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh
from trimesh.creation import box, capsule, cylinder
from trimesh.remesh import subdivide_to_size

from contactpose.errors import ContactPoseError

log = logging.getLogger(__name__)

__all__ = ["espresso_machine", "espresso_parts", "SIZE"]

#: Largest extent of the machine, metres.
SIZE = 0.35


def espresso_parts() -> dict[str, trimesh.Trimesh]:
    """The machine's parts, each a closed outward-wound coarse mesh, by name (design units, about 0.4 m)."""
    parts = {
        "plinth": _box((-0.12, -0.12, 0.0), (0.12, 0.14, 0.035)),
        "drip_tray": _box((-0.095, -0.175, 0.005), (0.095, -0.02, 0.045)),
        "grate": _box((-0.085, -0.165, 0.045), (0.085, -0.03, 0.05)),
        "column": _box((-0.12, 0.0, 0.035), (0.12, 0.14, 0.27)),
        "head": _box((-0.12, -0.11, 0.25), (0.12, 0.14, 0.33)),
        "group": _cylinder(0.038, (0.0, -0.06, 0.225), (0.0, -0.06, 0.25)),
        "basket": _cylinder(0.034, (0.0, -0.06, 0.19), (0.0, -0.06, 0.225)),
        "spout_left": _cylinder(0.006, (-0.012, -0.06, 0.165), (-0.012, -0.06, 0.19)),
        "spout_right": _cylinder(0.006, (0.012, -0.06, 0.165), (0.012, -0.06, 0.19)),
        # handle: from the basket rim forward and slightly down
        "handle": _capsule(0.012, (0.0, -0.09, 0.205), (0.0, -0.2, 0.19)),
        "tank": _cylinder(0.055, (0.0, 0.18, 0.035), (0.0, 0.18, 0.3)),
        "tank_lid": _cylinder(0.06, (0.0, 0.18, 0.3), (0.0, 0.18, 0.315)),
        "steam_wand": _capsule(0.005, (0.1, -0.1, 0.25), (0.12, -0.14, 0.12)),
        "knob": _cylinder(0.015, (0.07, -0.11, 0.29), (0.07, -0.125, 0.29)),
    }
    return parts


def espresso_machine(target_faces: int = 80_000) -> trimesh.Trimesh:
    """A deterministic coffee-machine-like mesh with about ``target_faces`` facets.

    The coarse parts are concatenated and their edges split until the facet
    count is within 3 % of the target (bisection on the longest allowed edge).

    Parameters
    ----------
    target_faces : int
      Wanted facet count; at least the coarse count (about 1,500).

    Returns
    -------
    mesh : trimesh.Trimesh
      Outward wound (every part is closed with positive volume); not watertight
      as a whole because the parts overlap.
    """
    coarse = trimesh.util.concatenate(list(espresso_parts().values()))
    # scale so the largest extent is SIZE
    coarse.apply_scale(SIZE / coarse.extents.max())
    if target_faces < len(coarse.faces):
        raise ContactPoseError(f"target_faces is {target_faces}; the coarse machine already has "
                               f"{len(coarse.faces)} facets, ask for at least that many")
    vertices, faces = coarse.vertices, coarse.faces
    # edge length of an equilateral tiling with target_faces facets, as a first guess
    edge = np.sqrt(4.0 * coarse.area / (np.sqrt(3.0) * target_faces))
    lo, hi = 0.3 * edge, 4.0 * edge
    best = None
    for _ in range(24):
        edge = np.sqrt(lo * hi)
        v, f = subdivide_to_size(vertices, faces, max_edge=edge, max_iter=12)
        if best is None or abs(len(f) - target_faces) < abs(len(best[1]) - target_faces):
            best = (v, f)
        if abs(len(f) - target_faces) <= 0.03 * target_faces:
            break
        # more facets than wanted: allow longer edges
        lo, hi = (edge, hi) if len(f) > target_faces else (lo, edge)
    mesh = trimesh.Trimesh(*best, process=True)
    log.debug("espresso_machine: %d facets (target %d)", len(mesh.faces), target_faces)
    return mesh


def _box(lo, hi) -> trimesh.Trimesh:
    """Axis-aligned box from its min and max corners."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    return box(extents=hi - lo, transform=trimesh.transformations.translation_matrix(0.5 * (lo + hi)))


def _axis_transform(a, b) -> tuple[np.ndarray, float]:
    """(4, 4) transform taking the z axis, centred at the origin, onto segment a-b; and its length."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    axis = b - a
    length = float(np.linalg.norm(axis))
    T = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], axis / length)
    T[:3, 3] = 0.5 * (a + b)
    return T, length


def _cylinder(radius: float, a, b) -> trimesh.Trimesh:
    """Closed cylinder between the centres of its two caps."""
    T, length = _axis_transform(a, b)
    return cylinder(radius=radius, height=length, sections=48, transform=T)


def _capsule(radius: float, a, b) -> trimesh.Trimesh:
    """Capsule whose spherical ends are centred on a and b."""
    T, length = _axis_transform(a, b)
    # trimesh's capsule is centred on the origin along z
    return capsule(height=length, radius=radius, count=[24, 12], transform=T)
