"""Oriented surface samples (model.samples): against dense points on the surface (inside facets,
on edges, at vertices), each point has a sample within the covering radius whose cone holds the
normals of every facet that touches it; samples are spaced by the surface, not the facets; a
thin wall's two sides keep their cones apart."""

import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from contactpose.errors import ContactPoseError
from contactpose.geometry.kernels import point_triangle_distance
from contactpose.geometry.sampling import uniform_in_triangles
from contactpose.model.object_model import ObjectModel
from contactpose.model.samples import SurfaceSamples
from contactpose.sim import objects


def _model(mesh):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObjectModel.from_mesh(mesh, max_span=1e-9, patch_tol_deg=None, facet_pairs=True)


MESHES = {
    "rock": lambda: objects.load("rock"),
    "carton": lambda: objects.load("carton"),  # sharp edges and corners
    "banana": lambda: objects.load("banana"),  # 53 coarse facets
    "thin_ring": lambda: trimesh.creation.annulus(0.030, 0.032, 0.04, sections=32),  # a 2 mm wall
    "ycb_banana": lambda: objects.load("ycb:011_banana"),
}


def _probe_points(model, rng, count=1500):
    """Points inside facets, on edges (between two corners) and at every corner. -> (P, 3)"""
    valid = np.flatnonzero(model.planes.valid)
    tri = model.triangles[valid]
    inside = uniform_in_triangles(tri[rng.integers(len(tri), size=count)], rng)
    t = rng.random((count, 1))
    pick = tri[rng.integers(len(tri), size=count)]
    on_edges = (1 - t) * pick[:, 0] + t * pick[:, 1]
    corners = np.unique(tri.reshape(-1, 3), axis=0)
    corners = corners[rng.permutation(len(corners))[:count]]
    return np.concatenate([inside, on_edges, corners])


def _touching(model, points):
    """For each point, the valid facets it lies on (within 1e-12 of the diameter). -> [array]"""
    tree, valid, radius = model.centroid_tree
    out = []
    for p, near in zip(points, tree.query_ball_point(points, radius * 1.001)):
        near = valid[np.asarray(near, dtype=np.int64)]
        d = point_triangle_distance(np.broadcast_to(p, (len(near), 3)), model.triangles[near])
        out.append(near[d <= 1e-12 * model.diameter])
    return out


@pytest.mark.parametrize("name", list(MESHES))
def test_every_surface_point_has_a_sample_whose_cone_holds_its_normals(name):
    model = _model(MESHES[name]())
    samples = SurfaceSamples.of(model, 0.03 * model.diameter)
    points = _probe_points(model, np.random.default_rng(0))
    touching = _touching(model, points)
    tree = cKDTree(samples.points)
    normals = model.planes.normals
    for p, facets, near in zip(points, touching, tree.query_ball_point(points, samples.covering)):
        assert len(facets) and near, (name, p)
        near = np.asarray(near)
        angles = np.arccos(np.clip(samples.normals[near] @ normals[facets].T, -1.0, 1.0))  # (samples, facets)
        assert (angles <= samples.cones[near, None] + 1e-9).all(axis=1).any(), (name, p, facets)
    assert samples.covering <= 1.25 * samples.spacing


def test_samples_follow_the_surface_not_the_facets():
    """The rock and the rock with every facet cut in 16 (the same surface): about as many samples."""
    rock = objects.load("rock")
    fine = trimesh.Trimesh(*trimesh.remesh.subdivide(*trimesh.remesh.subdivide(rock.vertices, rock.faces)),
                           process=False)
    coarse_model, fine_model = _model(rock), _model(fine)
    assert fine_model.num_facets == 16 * coarse_model.num_facets
    spacing = 0.03 * coarse_model.diameter
    a, b = len(SurfaceSamples.of(coarse_model, spacing)), len(SurfaceSamples.of(fine_model, spacing))
    assert abs(a - b) <= 0.15 * a, (a, b)


def test_samples_are_spaced_and_a_thin_wall_keeps_its_sides_apart():
    """On the box no two samples are closer than the spacing; on a ring with a 2 mm wall, the only
    closer pairs face each other across the wall, and the cones stay narrow (by distance alone
    each would hold the other side's normals: 180°)."""
    box = _model(objects.load("box"))
    samples = SurfaceSamples.of(box, 0.03 * box.diameter)
    d, _ = cKDTree(samples.points).query(samples.points, k=2)
    assert d[:, 1].min() >= samples.spacing * (1 - 1e-12)
    ring = _model(MESHES["thin_ring"]())
    samples = SurfaceSamples.of(ring, 0.03 * ring.diameter)
    assert samples.covering > 0.002  # the wall lies within the covering radius
    pairs = cKDTree(samples.points).query_pairs(samples.spacing * (1 - 1e-12), output_type="ndarray")
    assert len(pairs) and (np.einsum("ij,ij->i", samples.normals[pairs[:, 0]], samples.normals[pairs[:, 1]]) < 0).all()
    assert np.median(samples.cones) < np.radians(30)


@pytest.mark.parametrize("spacing", [0.0, -1.0, float("nan"), "wide"])
def test_a_bad_spacing_is_named(spacing):
    model = _model(objects.load("rock"))
    with pytest.raises(ContactPoseError, match="spacing must be a positive length in the mesh's units, got"):
        SurfaceSamples.of(model, spacing)
