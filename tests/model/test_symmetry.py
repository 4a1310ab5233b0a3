"""The rotation group of known solids (model.symmetry), against references that do not use it:
the groups written out by hand (a box's half turns, a prism's turns and flips, a cube's signed
permutations), dense area-uniform samples measured to the mesh by trimesh, and the group
axioms (products and inverses stay in the group)."""

import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from contactpose.model.object_model import ObjectModel
from contactpose.model.symmetry import (
    FINE_FRAC,
    SYMMETRY_ADDS_FRAC,
    SurfaceDistance,
    find_symmetry,
    symmetries,
    symmetry,
)
from contactpose.sim import objects


def prism(n, radius=0.04, height=0.03):
    """A regular n-sided prism about z, extruded from a fan of its polygon."""
    angle = 2 * np.pi * np.arange(n) / n
    polygon = np.r_[[[0.0, 0.0]], radius * np.c_[np.cos(angle), np.sin(angle)]]
    fan = np.array([[0, 1 + i, 1 + (i + 1) % n] for i in range(n)])
    return trimesh.creation.extrude_triangulation(polygon, fan, height)


def about(axis, degrees):
    return Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis, float)).as_matrix()


def turns(axis, n):
    """The n turns about ``axis`` by multiples of 360°/n."""
    return [about(axis, 360.0 * k / n) for k in range(n)]


def dihedral(axis, across, n):
    """The 2n rotations of an n-sided prism: turns about ``axis``, and each followed by a half
    turn about ``across``."""
    return turns(axis, n) + [R @ about(across, 180) for R in turns(axis, n)]


def cube_group():
    """The 24 signed permutation matrices of determinant +1."""
    import itertools

    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            M = np.zeros((3, 3))
            M[range(3), perm] = signs
            if np.linalg.det(M) > 0:
                out.append(M)
    return out


# name -> (mesh, the group's rotations written out (None: continuous), continuous axis or None, words)
SOLIDS = {
    "torus24": (lambda: trimesh.creation.torus(0.05, 0.015, major_sections=24, minor_sections=12),
                dihedral([0, 0, 1], [1, 0, 0], 24), None, "24-fold about axis (0.00, 0.00, 1.00)"),
    "annulus24": (lambda: trimesh.creation.annulus(0.03, 0.05, 0.02, sections=24),
                  dihedral([0, 0, 1], [1, 0, 0], 24), None, "24-fold about axis (0.00, 0.00, 1.00)"),
    "cylinder": (lambda: trimesh.creation.cylinder(0.03, 0.08), None, [0, 0, 1],
                 "rotation about axis (0.00, 0.00, 1.00) and half turns across it"),
    "box": (lambda: trimesh.creation.box([0.10, 0.06, 0.04]), dihedral([0, 0, 1], [1, 0, 0], 2), None,
            "4 rotations (those of a box): half turns about axes"),
    "square_box": (lambda: trimesh.creation.box([0.10, 0.06, 0.06]), dihedral([1, 0, 0], [0, 1, 0], 4), None,
                   "8 rotations (those of a 4-sided prism): 4-fold about axis (1.00, 0.00, 0.00)"),
    "cube": (lambda: trimesh.creation.box([0.05, 0.05, 0.05]), cube_group(), None, "24 rotations (those of a cube)"),
    "prism5": (lambda: prism(5), dihedral([0, 0, 1], [1, 0, 0], 5), None,
               "10 rotations (those of a 5-sided prism): 5-fold about axis (0.00, 0.00, 1.00)"),
    "rock1k": (lambda: objects.load("rock1k"), [np.eye(3)], None, "no symmetry"),
    "rock": (lambda: objects.load("rock"), [np.eye(3)], None, "no symmetry"),
}


@pytest.fixture(scope="module")
def solids():
    """name -> (mesh, model, its Symmetry)."""
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, (make, *_) in SOLIDS.items():
            mesh = make()
            model = ObjectModel.from_mesh(mesh)
            out[name] = (mesh, model, symmetry(model))
    return out


def _farthest(mesh, transforms, count=2000):
    """The largest distance (over dense area-uniform samples, trimesh's own closest points) of
    the surface moved by each (4, 4) transform to the unmoved surface. -> (K,)"""
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=7)
    moved = np.concatenate([points @ T[:3, :3].T + T[:3, 3] for T in transforms])
    _, dist, _ = trimesh.proximity.closest_point(mesh, moved)
    return dist.reshape(len(transforms), count).max(axis=1)


def _same_rotations(found, expected, tol=1e-9):
    """Whether two lists of (3, 3) rotations hold the same set."""
    if len(found) != len(expected):
        return False
    return all(min(np.linalg.norm(R - Q) for Q in found) < tol for R in expected)


@pytest.mark.parametrize("name", [n for n, s in SOLIDS.items() if s[1] is not None])
def test_finite_groups_are_those_written_out(solids, name):
    _, expected, _, words = SOLIDS[name]
    _, _, group = solids[name]
    assert len(group.axes) == 0
    assert np.array_equal(group.rotations[0], np.eye(4))
    assert _same_rotations(list(group.rotations[:, :3, :3]), expected, tol=1e-6)
    assert words in group.describe()


@pytest.mark.parametrize("name", ["torus24", "annulus24", "box", "square_box", "cube", "prism5", "cylinder"])
def test_every_element_maps_the_surface_onto_itself(solids, name):
    """Each symmetry found moves none of 2,000 dense surface samples off the surface (trimesh's
    closest points); each is a rotation about the surface centroid, which it fixes."""
    mesh, model, group = solids[name]
    assert _farthest(mesh, group.rotations).max() < 1e-9 * model.diameter
    c = group.centre
    assert np.allclose(group.rotations[:, :3, :3] @ c + group.rotations[:, :3, 3], c, atol=1e-12)
    assert np.allclose(np.linalg.det(group.rotations[:, :3, :3]), 1.0)


@pytest.mark.parametrize("name", ["torus24", "box", "square_box", "cube", "prism5"])
def test_groups_are_closed(solids, name):
    """The product of two elements and the inverse of each are in the group (Frobenius 1e-9)."""
    R = solids[name][2].rotations[:, :3, :3]
    near = lambda M: np.linalg.norm(R - M, axis=(1, 2)).min() < 1e-9  # noqa: E731
    assert all(near(A @ B) for A in R for B in R)
    assert all(near(A.T) for A in R)
    assert len({tuple(np.round(A, 6).ravel()) for A in R}) == len(R)  # no element twice


def test_torus_is_discrete_and_cylinder_continuous(solids):
    """The half step between two of the torus's 15° turns moves its rim by more than FINE_FRAC
    of the diameter (so no continuous axis); any turn about the 32-section cylinder's axis, and
    its half turn across, stays within it (dense samples, trimesh's distances)."""
    mesh, model, group = solids["torus24"]
    half_step = np.eye(4)
    half_step[:3, :3] = about([0, 0, 1], 7.5)
    assert _farthest(mesh, [half_step])[0] > FINE_FRAC * model.diameter
    mesh, model, group = solids["cylinder"]
    axis = group.axes[0]
    assert abs(abs(axis @ [0, 0, 1]) - 1) < 1e-9 and len(group.rotations) == 2
    c = group.centre
    moves = []
    for degrees in (3.0, 37.0, 101.0):
        T = np.eye(4)
        T[:3, :3] = about(axis, degrees)
        T[:3, 3] = c - T[:3, :3] @ c
        moves.append(T)
    assert _farthest(mesh, moves + [group.rotations[1]]).max() < FINE_FRAC * model.diameter


def test_asymmetric_rocks_have_no_symmetry(solids):
    """The rocks: the identity alone, and no status hint; every principal half turn moves
    their surface by more than the near regime's ADD-S limit (dense samples)."""
    for name in ("rock", "rock1k"):
        mesh, model, group = solids[name]
        assert group.trivial and symmetries(model) == [] and group.describe() == "no symmetry"
        points, _ = trimesh.sample.sample_surface(mesh, 2000, seed=3)
        c = mesh.center_mass
        _, axes = np.linalg.eigh(np.cov((points - c).T))
        for axis in axes.T:
            Q = about(axis, 180)
            _, dist, _ = trimesh.proximity.closest_point(mesh, (points - c) @ Q.T + c)
            assert dist.mean() > SYMMETRY_ADDS_FRAC * model.diameter


def test_rocks_with_built_in_symmetry():
    """twin_rock (a half turn about z) and tri_rock (a third of a turn), as sim.objects builds them."""
    for name, n in (("twin_rock", 2), ("tri_rock", 3)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            group = find_symmetry(ObjectModel.from_mesh(objects.load(name)))
        assert _same_rotations(list(group.rotations[:, :3, :3]), turns([0, 0, 1], n), tol=1e-6)
        assert group.describe() == f"{n}-fold about axis (0.00, 0.00, 1.00)"


def test_symmetries_lists_the_group_for_the_status_hint(solids):
    _, model, group = solids["torus24"]
    assert symmetries(model) == [group] and symmetry(model) is group  # found once per model


def test_errors_modulo_the_group_vanish_on_its_twins(solids):
    """A pose and each of its twins T G are 0° and 0 apart modulo the group."""
    _, _, group = solids["prism5"]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    T[:3, 3] = [0.1, 0.02, -0.03]
    rot, trans = group.errors(T @ group.rotations, T)
    assert np.abs(rot).max() < 1e-6 and np.abs(trans).max() < 1e-12


def test_surface_distance_matches_open3d(solids):
    """SurfaceDistance (brute force on a small mesh, nearest facets on a larger one) against
    Open3D's distance (float32: 1e-7 of the object's size), on points within 2 cm of each surface."""
    from contactpose.geometry.raycast import Raycaster

    rng = np.random.default_rng(0)
    for name in ("box", "rock1k", "torus24"):
        mesh, model, _ = solids[name]
        points = mesh.sample(500, seed=1) + rng.normal(0.0, 0.01, (500, 3))
        want = Raycaster(mesh.vertices, mesh.faces).distance(points)
        assert np.allclose(SurfaceDistance(model)(points), want, rtol=0.0, atol=1e-7 * model.diameter), name
