"""What a build will need before it starts: planes before the diameter, near-pair count
estimates, candidate listing in blocks, and the span a refusal suggests."""

import numpy as np
import pytest
import trimesh

from contactpose.model.features import SAMPLE_ROWS, NearPairs
from contactpose.model.object_model import ObjectModel, early_planes, facet_planes, mesh_diameter
from contactpose.model.patches import PatchLayout, patch_spheres
from contactpose.model.plan import PairPlan, _round_down
from contactpose.sim import objects


def _facet_spheres(mesh):
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
    return tri, np.arange(len(tri))


@pytest.mark.parametrize("name", ["banana", "rock1k", "carton", "espresso6767"])
def test_early_planes_equal_the_planes_of_the_diameter(name):
    mesh = objects.load(name)
    v, f = np.asarray(mesh.vertices, float), np.asarray(mesh.faces)
    planes, diameter = early_planes(v[f], v)
    reference = facet_planes(v[f], mesh_diameter(v))
    assert diameter is None  # nothing near degenerate: the hull waits until after the guard
    for a, b in zip(vars(planes).values(), vars(reference).values()):
        assert np.array_equal(a, b)


def test_early_planes_compute_the_diameter_when_a_facet_depends_on_it():
    """A sliver whose altitude lies between the thresholds of D = diagonal/100 and D = diagonal."""
    mesh = objects.load("banana")
    v = np.vstack([mesh.vertices, [[0, 0, 0], [0.01, 0, 0], [0.005, 1e-10, 0]]])
    f = np.vstack([mesh.faces, [[len(v) - 3, len(v) - 2, len(v) - 1]]])
    planes, diameter = early_planes(v[f], v)
    assert diameter == mesh_diameter(v)
    assert np.array_equal(planes.valid, facet_planes(v[f], diameter).valid)


def test_patch_spheres_equal_the_layout_spheres():
    model = ObjectModel.from_mesh(objects.load("banana512"))
    layout = PatchLayout.of(model.triangles, model.patches)
    centres, radii = patch_spheres(model.triangles, model.patches)
    assert np.array_equal(centres, layout.centre) and np.array_equal(radii, layout.radius)


def test_count_estimate_is_close_to_the_listed_pairs():
    tri, ids = _facet_spheres(trimesh.creation.icosphere(subdivisions=4))  # 5,120 facets: a sample
    near = NearPairs.of_facets(tri, ids, 0.3)
    assert len(ids) > SAMPLE_ROWS
    listed = len(near.all_rows()[0])
    assert abs(near.count_estimate() - listed) <= 0.05 * listed
    assert near.count_estimate() <= near.count_bound()


def test_all_rows_lists_in_blocks_what_rows_lists_at_once():
    tri, ids = _facet_spheres(objects.load("rock1k"))
    near = NearPairs.of_facets(tri, ids, 0.03)
    k, l = near.all_rows(chunk_pairs=500)  # many blocks
    k0, l0 = near.rows(0, len(ids))
    assert k.dtype == np.int32 and np.array_equal(k, k0) and np.array_equal(l, l0)


def test_suggested_span_fits_the_limit():
    model = ObjectModel.from_mesh(objects.load("banana512"), patch_tol_deg=None)
    plan = PairPlan(model.triangles, model.planes.valid, None, False, lambda count: True)
    full = plan.need(None)
    for fraction in (0.5, 0.2, 0.1):
        span = plan.suggest_span(fraction * full)
        assert span is not None and plan.need(span) <= fraction * full, fraction
    # every facet pairs with itself and its neighbours: below about 7.5 % no span fits
    assert plan.suggest_span(0.05 * full) is None and plan.suggest_span(0.0) is None


@pytest.mark.parametrize("x, want", [(0.0312, 0.031), (123.7, 120.0), (0.5, 0.5), (9.99, 9.9), (0.000456, 0.00045)])
def test_round_down_to_two_digits(x, want):
    assert _round_down(x) == want
