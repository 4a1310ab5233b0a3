"""Members of a patch for a contact, checked by brute force over every member."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from contactpose.contacts import Contacts, Tolerance
from contactpose.costs.association import fitting_members, nearest_members
from contactpose.geometry.kernels import point_triangle_distance
from contactpose.model.object_model import ObjectModel
from contactpose.model.patches import GROUP_FACETS
from contactpose.sim import objects


@pytest.fixture(scope="module")
def curved():
    """The 512-facet banana in regions of 10°: patches of several curved members."""
    model = ObjectModel.from_mesh(objects.load("banana512"), patch_tol_deg=10.0, facet_pairs=False)
    assert np.diff(model.patches.indptr).max() > 5
    return model


def test_fitting_members_minimise_the_whitened_cost(curved):
    """Each contact takes the member with the least d²/σ_x² + |n_f - n|²/σ_n², by brute force;
    with a normal weight of zero it is the nearest member."""
    m, rng = curved, np.random.default_rng(3)
    tol = Tolerance.from_noise(0.002, 2.0)
    big = np.flatnonzero(np.diff(m.patches.indptr) > 3)
    tuples = rng.choice(big, size=(20, 4))
    R = np.repeat(np.eye(3)[None], 20, axis=0)
    t = np.zeros((20, 3))
    points = rng.normal(0.0, 0.05, (4, 3))
    finger = rng.normal(size=(4, 3))
    finger /= np.linalg.norm(finger, axis=1, keepdims=True)
    contacts = Contacts(points, finger_normals=finger)
    got = fitting_members(m, contacts, tuples, R, t, tol)
    for h in range(20):
        for i in range(4):
            members = m.patches.of(tuples[h, i])
            d = point_triangle_distance(np.repeat(points[i][None], len(members), axis=0), m.triangles[members])
            cost = d**2 / tol.position_noise**2 + np.sum((m.planes.normals[members] + finger[i]) ** 2, axis=1) \
                / tol.normal_noise**2
            assert cost[list(members).index(got[h, i])] == pytest.approx(cost.min(), rel=1e-9, abs=1e-12)
    plain = nearest_members(m.member_groups, m.triangles, tuples, np.broadcast_to(points, (20, 4, 3)).copy())
    for h in range(20):
        for i in range(4):
            members = m.patches.of(tuples[h, i])
            d = point_triangle_distance(np.repeat(points[i][None], len(members), axis=0), m.triangles[members])
            assert d[list(members).index(plain[h, i])] == pytest.approx(d.min(), abs=1e-15)
    pruned = nearest_members(m.member_groups, m.triangles, tuples, np.broadcast_to(points, (20, 4, 3)).copy(),
                             spheres=(m.centroids, m.facet_radii))
    assert np.array_equal(pruned, plain)  # the bounding spheres only skip members that cannot win


@pytest.fixture(scope="module")
def fine_box():
    """A box whose faces are patches of 128 facets each: regions of many runs."""
    mesh = trimesh.creation.box(extents=(0.10, 0.06, 0.04))
    for _ in range(3):
        mesh = mesh.subdivide()
    model = ObjectModel.from_mesh(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False))
    assert np.diff(model.patches.indptr).min() > 2 * GROUP_FACETS
    return model


def test_member_runs_hold_their_members(fine_box):
    """Each region's members, in runs: a permutation of the patch's members, and each run's
    sphere holds every vertex of its facets."""
    m, g = fine_box, fine_box.member_groups
    for r in range(m.patches.count):
        assert sorted(g.members[g.indptr[r]:g.indptr[r + 1]]) == sorted(m.patches.of(r))
        assert g.grp_mem[g.grp_ptr[r]] == g.indptr[r] and g.grp_mem[g.grp_ptr[r + 1]] == g.indptr[r + 1]
    for k in range(len(g.radius)):
        facets = g.members[g.grp_mem[k]:g.grp_mem[k + 1]]
        assert len(facets) <= GROUP_FACETS
        assert np.linalg.norm(m.triangles[facets] - g.centre[k], axis=2).max() <= g.radius[k] + 1e-15
        assert g.spread[k] == m.facet_radii[facets].max()


def test_member_runs_skip_only_members_that_cannot_win(fine_box):
    """On regions of many runs, the nearest member and the member of least whitened cost
    equal brute force over every member, for points near and far from the region."""
    m, rng = fine_box, np.random.default_rng(8)
    tol = Tolerance.from_noise(0.001, 2.0)
    tuples = rng.integers(0, m.patches.count, size=(60, 4))
    points = rng.uniform(-0.07, 0.07, (60, 4, 3))
    finger = rng.normal(size=(4, 3))
    finger /= np.linalg.norm(finger, axis=1, keepdims=True)
    normals = np.broadcast_to(-finger, (60, 4, 3)).copy()
    weight = (tol.position_noise / tol.normal_noise) ** 2
    plain = nearest_members(m.member_groups, m.triangles, tuples, points)
    whitened = nearest_members(m.member_groups, m.triangles, tuples, points, normals=(m.planes.normals, normals, weight),
                               spheres=(m.centroids, m.facet_radii))
    for h in range(60):
        for i in range(4):
            members = m.patches.of(tuples[h, i])
            d2 = point_triangle_distance(np.repeat(points[h, i][None], len(members), axis=0), m.triangles[members]) ** 2
            cost = d2 + weight * np.sum((m.planes.normals[members] - normals[h, i]) ** 2, axis=1)
            assert d2[list(members).index(plain[h, i])] == pytest.approx(d2.min(), rel=1e-12, abs=1e-18)
            assert cost[list(members).index(whitened[h, i])] == pytest.approx(cost.min(), rel=1e-12, abs=1e-18)
