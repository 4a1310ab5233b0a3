"""Tests for the built-in procedural objects (contactpose.sim.objects)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from contactpose.errors import ContactPoseError
from contactpose.sim import objects

CLOSED = ["banana512", "carton", "rock", "rock1k", "box", "cylinder", "sphere", "twin_rock", "tri_rock"]

FACET_COUNTS = {
    "banana": (53, 53),
    "banana512": (512, 512),
    "carton": (200, 300),
    "rock": (250, 400),
    "rock1k": (980, 1100),
    "box": (48, 48),
    "cylinder": (96, 96),
    "sphere": (320, 320),
    "twin_rock": (320, 320),
    "tri_rock": (320, 320),
}

# Bounding-box extents (m), sorted descending, with an absolute tolerance.
EXTENTS = {
    "carton": ([0.20, 0.07, 0.07], 1e-9),
    "box": ([0.10, 0.06, 0.04], 1e-9),
    "cylinder": ([0.08, 0.06, 0.06], 1e-9),
    "sphere": ([0.10, 0.10, 0.10], 1e-9),
}


@pytest.fixture(scope="module")
def meshes():
    return {name: objects.load(name) for name in objects.names(ycb_objects=False)}


def _merged(mesh):
    m2 = mesh.copy()
    m2.merge_vertices()
    return m2


def _sample_surface(mesh, n, seed):
    """(n, 3) points spread over the surface, area-weighted, deterministic."""
    rng = np.random.default_rng(seed)
    face = rng.choice(len(mesh.faces), size=n, p=mesh.area_faces / mesh.area)
    r1, r2 = rng.random(n), rng.random(n)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    a, b, c = np.moveaxis(mesh.triangles[face], 1, 0)
    return a + r1[:, None] * (b - a) + r2[:, None] * (c - a)


def _two_way_distance(mesh_a, mesh_b, n=2000, dense=200000):
    """Hausdorff-like distance (m): the largest distance from n samples of
    either mesh to a dense sample of the other."""
    pa, pb = _sample_surface(mesh_a, n, 1), _sample_surface(mesh_b, n, 2)
    da, db = _sample_surface(mesh_a, dense, 3), _sample_surface(mesh_b, dense, 4)
    return max(cKDTree(db).query(pa)[0].max(), cKDTree(da).query(pb)[0].max())


#: Built from the espresso generator with Open3D decimation (slow: tested in test_scan.py's slow set).
GENERATED = {"espresso6767", "espresso83846"}


def test_names_are_all_listed():
    assert set(objects.names(ycb_objects=False)) == set(FACET_COUNTS) | GENERATED


@pytest.mark.slow
def test_espresso6767_facet_count_and_size():
    mesh = objects.load("espresso6767")
    assert abs(len(mesh.faces) - 6767) <= 0.01 * 6767
    assert abs(mesh.extents.max() - 0.35) < 0.005


@pytest.mark.parametrize("name", sorted(FACET_COUNTS))
def test_facet_count(meshes, name):
    low, high = FACET_COUNTS[name]
    assert low <= len(meshes[name].faces) <= high


@pytest.mark.parametrize("name", sorted(FACET_COUNTS))
def test_deterministic(meshes, name):
    again = objects.load(name)
    assert np.array_equal(again.vertices, meshes[name].vertices)
    assert np.array_equal(again.faces, meshes[name].faces)


@pytest.mark.parametrize("name", sorted(FACET_COUNTS))
def test_no_degenerate_facets_or_unused_vertices(meshes, name):
    mesh = meshes[name]
    assert mesh.area_faces.min() > 1e-12
    assert np.array_equal(np.unique(mesh.faces), np.arange(len(mesh.vertices)))


@pytest.mark.parametrize("name", CLOSED)
def test_closed_and_outward(meshes, name):
    m2 = _merged(meshes[name])
    assert len(m2.vertices) == len(meshes[name].vertices)  # nothing left to merge
    assert m2.is_watertight
    assert m2.is_winding_consistent
    assert m2.volume > 0


@pytest.mark.parametrize("name", sorted(EXTENTS))
def test_extents(meshes, name):
    expected, tol = EXTENTS[name]
    assert np.allclose(np.sort(meshes[name].extents)[::-1], expected, atol=tol)


@pytest.mark.parametrize("name, size", [("rock", 0.12), ("rock1k", 0.15), ("twin_rock", 0.12),
                                             ("tri_rock", 0.12)])
def test_rock_size_and_irregularity(meshes, name, size):
    extents = meshes[name].extents
    assert extents.max() == pytest.approx(size)
    assert extents.min() < 0.85 * size  # not a sphere


@pytest.mark.parametrize("name", ["banana", "banana512"])
def test_banana_size(meshes, name):
    length, width, thickness = meshes[name].extents
    assert 0.16 <= length <= 0.20       # 0.19 m along the curve, shorter as chord
    assert 0.035 <= width <= 0.06       # thickness plus the bend's bulge
    assert 0.025 <= thickness <= 0.04   # about 0.035 m at the middle


def test_banana512_is_curved_and_tapered(meshes):
    v = meshes["banana512"].vertices
    middle, ends = np.abs(v[:, 0]) < 0.01, np.abs(v[:, 0]) > 0.08
    assert v[middle, 1].mean() - v[ends, 1].mean() > 0.015   # bent toward +y
    assert 0.03 <= np.ptp(v[middle, 2]) <= 0.04              # ~0.035 m thick
    assert np.ptp(v[ends, 2]) < 0.5 * np.ptp(v[middle, 2])  # tapers off


def test_banana53_is_open_only_at_one_facet(meshes):
    m2 = _merged(meshes["banana"])
    assert m2.is_winding_consistent
    assert not m2.is_watertight
    edges, counts = np.unique(np.sort(m2.edges, axis=1), axis=0, return_counts=True)
    assert sorted(set(counts)) == [1, 2]
    assert np.count_nonzero(counts == 1) == 3  # the cut-off stem facet's rim


def test_banana53_faces_outward(meshes):
    reduced, full = meshes["banana"], meshes["banana512"]
    _, nearest = cKDTree(full.triangles_center).query(reduced.triangles_center)
    dots = np.einsum("ij,ij->i", reduced.face_normals, full.face_normals[nearest])
    assert dots.min() > 0.3


def test_banana53_close_to_banana512(meshes):
    assert _two_way_distance(meshes["banana"], meshes["banana512"]) < 0.008


def test_shipped_banana53_matches_regeneration(meshes):
    regenerated = objects.make_banana53()
    assert len(regenerated.faces) == 53
    assert _two_way_distance(regenerated, meshes["banana"]) < 0.001


@pytest.mark.parametrize("bad", ["bananna", "", "BOX"])
def test_unknown_name_raises(bad):
    with pytest.raises(ContactPoseError) as info:
        objects.load(bad)
    message = str(info.value)
    assert repr(bad) in message
    assert all(name in message for name in objects.names(ycb_objects=False))


def test_non_string_name_raises():
    with pytest.raises(ContactPoseError, match="42"):
        objects.load(42)


def _turn_gap(mesh):
    """Function of R (3, 3): mean distance (m) of 4000 surface samples turned by R to a dense sample."""
    points = _sample_surface(mesh, 4000, 5)
    tree = cKDTree(_sample_surface(mesh, 200000, 6))
    return lambda R: np.mean(tree.query(points @ R.T)[0])


def test_twin_rock_has_exactly_one_half_turn_symmetry(meshes):
    """A half turn about z maps the surface onto itself; the half turns about x and y move it
    by 5 % of its size on average (mean distance of surface samples to a dense sample)."""
    mesh = meshes["twin_rock"]
    gap = _turn_gap(mesh)
    half_z = np.diag([-1.0, -1.0, 1.0])
    assert np.abs(np.sort(mesh.vertices @ half_z.T, axis=0) - np.sort(mesh.vertices, axis=0)).max() < 1e-12
    assert gap(half_z) < 1.1 * gap(np.eye(3))  # the sampling floor
    for R in (np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0])):
        assert gap(R) > 0.04 * mesh.extents.max()


def _turn_z(angle):
    """(3, 3) rotation by ``angle`` (rad) about z."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_tri_rock_has_exactly_one_three_fold_symmetry(meshes):
    """A third of a turn about z maps the mesh onto itself, vertex onto vertex and facet onto
    facet with its winding; a half turn about z, x or y moves the surface by over 2 % of its
    size on average, and a 10° turn about z by over 1 % (the symmetry is discrete)."""
    mesh = meshes["tri_rock"]
    third = _turn_z(2 * np.pi / 3)
    dist, image = cKDTree(mesh.vertices).query(mesh.vertices @ third.T)
    assert dist.max() < 1e-12
    assert np.array_equal(np.sort(image), np.arange(len(mesh.vertices)))  # a permutation
    cyclic = lambda faces: {tuple(np.roll(f, -np.argmin(f))) for f in faces}  # noqa: E731
    assert cyclic(image[mesh.faces]) == cyclic(mesh.faces)
    gap = _turn_gap(mesh)
    assert gap(third) < 1.1 * gap(np.eye(3))  # the sampling floor
    for R in (_turn_z(np.pi), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0])):
        assert gap(R) > 0.02 * mesh.extents.max()
    assert gap(_turn_z(np.radians(10))) > 0.01 * mesh.extents.max()
