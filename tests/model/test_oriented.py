"""The offline half of the search by hypothesize and verify (model.oriented): the samples'
spreads and radii hold for points the measurement never saw, the field names the sample
nearest each voxel centre (brute force), and the pair features are those of the points
(direct computation)."""

import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from contactpose.geometry.sampling import uniform_in_triangles
from contactpose.model.object_model import ObjectModel
from contactpose.model.oriented import SIDE_NEIGHBOURS, OrientedSamples
from contactpose.sim import objects


def _model(mesh):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ObjectModel.from_mesh(mesh, max_span=1e-9, patch_tol_deg=None, facet_pairs=True)


MESHES = {
    "carton": lambda: objects.load("carton"),  # sharp edges and corners
    "banana512": lambda: objects.load("banana512"),
    "ycb_banana": lambda: objects.load("ycb:011_banana"),
}


@pytest.fixture(scope="module", params=list(MESHES))
def oriented(request):
    model = _model(MESHES[request.param]())
    return request.param, model, OrientedSamples.of(model)


def _probes(model, rng, count=3000):
    """Random points inside random valid facets (area-blind: small facets too) and their facets."""
    valid = np.flatnonzero(model.planes.valid)
    facets = valid[rng.integers(len(valid), size=count)]
    return uniform_in_triangles(model.triangles[facets], rng), facets


def test_spreads_and_radii_hold_for_unseen_surface_points(oriented):
    """Each random surface point's nearest sample on its own side lies within that sample's
    radius, and its facet's normal within that sample's spread: measured on a grid six times
    finer than the spacing, so a point of a sliver of a Voronoi cell the grid missed may
    exceed it; 99.5 % must hold, and none by more than 10°."""
    name, model, o = oriented
    points, facets = _probes(model, np.random.default_rng(1))
    normals = model.planes.normals[facets]
    _, near = cKDTree(o.points).query(points, k=SIDE_NEIGHBOURS)
    same = np.einsum("pkj,pj->pk", o.normals[near], normals) > 0
    assert same.any(axis=1).all(), name
    s = near[np.arange(len(points)), np.argmax(same, axis=1)]
    gap = np.linalg.norm(points - o.points[s], axis=1)
    angle = np.arccos(np.clip(np.einsum("pj,pj->p", normals, o.normals[s]), -1.0, 1.0))
    assert np.mean(gap <= o.radii[s] + 1e-12) >= 0.995, name
    held = angle <= o.spreads[s] + 1e-9
    assert np.mean(held) >= 0.995, name
    assert np.all(angle <= o.spreads[s] + np.radians(10.0)), name


def test_field_names_the_sample_nearest_each_voxel_centre(oriented):
    name, model, o = oriented
    rng = np.random.default_rng(2)
    shape = np.array(o.nearest.shape)
    idx = rng.integers(0, shape, size=(2000, 3))
    centres = o.origin + o.cell * idx
    d_field = np.linalg.norm(centres - o.points[o.nearest_samples(centres)], axis=1)
    d_brute = np.min(np.linalg.norm(centres[:, None] - o.points[None], axis=2), axis=1)
    np.testing.assert_allclose(d_field, d_brute, rtol=0, atol=1e-12)
    outside = o.origin - 2 * o.cell
    assert o.nearest_samples(outside[None])[0] == -1


def test_field_reaches_every_surface_point(oriented):
    """A surface point's field sample lies within ``reach`` of it (covering radius plus a
    voxel's diagonal)."""
    name, model, o = oriented
    points, _ = _probes(model, np.random.default_rng(3))
    gap = np.linalg.norm(points - o.points[o.nearest_samples(points)], axis=1)
    assert np.all(gap <= o.reach), name


def test_pair_features_are_the_points_features(oriented):
    name, model, o = oriented
    f = o.pairs
    n = len(o)
    assert len(f.distance) == n * (n - 1) // 2
    assert np.all(f.first < f.second)
    # every pair once, in the bin of its distance
    assert len(np.unique(f.first.astype(np.int64) * n + f.second)) == len(f.first)
    bins = np.repeat(np.arange(len(f.offsets) - 1), np.diff(f.offsets))
    exact = np.linalg.norm(o.points[f.second] - o.points[f.first], axis=1)
    np.testing.assert_array_equal(bins, np.floor(exact / f.bin).astype(np.int64))
    rng = np.random.default_rng(4)
    rows = rng.integers(len(f.distance), size=500)
    a, b = f.first[rows], f.second[rows]
    d = o.points[b] - o.points[a]
    dist = np.linalg.norm(d, axis=1)
    u = d / dist[:, None]
    np.testing.assert_allclose(f.distance[rows], dist, rtol=1e-6)
    for got, x, y in ((f.angle_first, o.normals[a], u), (f.angle_second, o.normals[b], u),
                      (f.angle_normals, o.normals[a], o.normals[b])):
        np.testing.assert_allclose(got[rows], np.arccos(np.clip(np.einsum("ij,ij->i", x, y), -1, 1)), atol=1e-5)
    lo, hi = np.quantile(f.distance, [0.3, 0.4])
    sl = f.within(lo, hi)
    assert np.all((f.distance[sl] >= lo - f.bin) & (f.distance[sl] <= hi + f.bin))
    inside = (f.distance >= lo) & (f.distance <= hi)
    assert inside[sl].sum() == inside.sum()


def test_thin_wall_sides_name_each_other():
    """On a 2 mm wall, every sample's other side is a sample facing away, across the wall."""
    model = _model(trimesh.creation.annulus(0.030, 0.032, 0.04, sections=32))
    o = OrientedSamples.of(model, spacing=0.003)
    side = o.other_side
    curved = np.abs(o.normals[:, 2]) < 0.5  # the ring's inner and outer walls, not its rims
    assert np.all(side[curved] >= 0)
    s = side[curved]
    assert np.all(np.einsum("ij,ij->i", o.normals[curved], o.normals[s]) < 0)
    assert np.all(np.linalg.norm(o.points[curved] - o.points[s], axis=1) <= o.covering + 0.002 + 1e-9)
