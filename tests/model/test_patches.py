"""Members of a patch for a contact, checked by brute force over every member."""

from __future__ import annotations

import numpy as np
import pytest

from contactpose.contacts import Contacts, Tolerance
from contactpose.geometry.kernels import point_triangle_distance
from contactpose.model.object_model import ObjectModel
from contactpose.model.patches import nearest_members
from contactpose.scoring.rank import fitting_members
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
    plain = nearest_members(m.patches, m.triangles, tuples, np.broadcast_to(points, (20, 4, 3)).copy())
    for h in range(20):
        for i in range(4):
            members = m.patches.of(tuples[h, i])
            d = point_triangle_distance(np.repeat(points[i][None], len(members), axis=0), m.triangles[members])
            assert d[list(members).index(plain[h, i])] == pytest.approx(d.min(), abs=1e-15)
    pruned = nearest_members(m.patches, m.triangles, tuples, np.broadcast_to(points, (20, 4, 3)).copy(),
                             spheres=(m.centroids, m.facet_radii))
    assert np.array_equal(pruned, plain)  # the bounding spheres only skip members that cannot win
