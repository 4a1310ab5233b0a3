"""A rounded fingertip on a crease of a model of surface regions (stages.with_widened_normals),
against a known answer: on a fine mesh of flat panels meeting at creases of 5-16°, a
noise-free contact on a crease has the normal halfway between its two panels', farther than
the normal gate from either where the crease's half-angle exceeds the gate. Where the search at the stated noise then fits nothing within
noise, the search with the angle gates widened lists the true pose first, exactly (χ² 0: the
contact model lets an edge contact take any normal on its arc)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from contactpose import Contacts, ObjectModel, localize, stages
from contactpose.contacts import Tolerance
from contactpose.model.symmetry import symmetry
from contactpose.progress import Deadline
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.stages import NORMAL_WIDEN, NORMALS_NOTE

NOISE_FRAC = 0.0025


@pytest.fixture(scope="module")
def panels():
    """An ellipsoid of 320 flat panels (a geodesic sphere scaled 5 : 4 : 3), each cut into 16
    coplanar facets, searched over regions without a facet table, as a fine scan is; and the
    panel mesh itself."""
    coarse = trimesh.creation.icosphere(subdivisions=2)
    coarse.apply_scale([0.05, 0.04, 0.03])
    fine = coarse.subdivide().subdivide()
    model = ObjectModel.from_mesh(fine, patch_tol_deg=5.0, facet_pairs=False)
    assert model.has_regions and model.table is None
    return model, coarse


def crease_grasps(coarse, diameter, count, rng):
    """Contacts (object frame) with one on a crease sharper than the stated pair gate (its
    normal the bisector of its panels') and three at panel interiors, all 30 % of the
    diameter apart or more: [(points (4, 3), normals (4, 3), half the crease's angle, degrees)]."""
    gate_deg = np.degrees(Tolerance.from_noise(NOISE_FRAC * diameter, 1.0).angle)
    half = np.degrees(coarse.face_adjacency_angles) / 2
    sharp = np.flatnonzero(half > gate_deg)
    out = []
    for e in rng.permutation(sharp)[:count]:
        a, b = coarse.face_adjacency[e]
        ends = coarse.vertices[coarse.face_adjacency_edges[e]]
        s = rng.uniform(0.3, 0.7)
        normal = coarse.face_normals[a] + coarse.face_normals[b]
        points, normals = [(1 - s) * ends[0] + s * ends[1]], [normal / np.linalg.norm(normal)]
        while len(points) < 4:
            f = rng.integers(len(coarse.faces))
            p = rng.dirichlet([4, 4, 4]) @ coarse.triangles[f]
            if min(np.linalg.norm(p - q) for q in points) > 0.3 * diameter:
                points.append(p)
                normals.append(coarse.face_normals[f])
        out.append((np.array(points), np.array(normals), half[e]))
    return out


def test_normals_widened_widens_the_angle_gate_only():
    tol = Tolerance.from_noise(0.001, 1.0)
    wide = tol.normals_widened(2.0)
    assert wide.angle == pytest.approx(2 * tol.angle) and wide.distance == tol.distance
    assert (wide.position_noise, wide.normal_noise) == (tol.position_noise, tol.normal_noise)
    assert wide.direction(0.1) == pytest.approx(tol.distance + (0.1 + tol.distance) * 2 * tol.angle)
    assert tol.normals_widened(1e3).angle == pytest.approx(np.pi)


def test_a_crease_contact_is_found_by_the_widened_search(panels):
    model, coarse = panels
    D = model.diameter
    group = symmetry(model)
    options = dict(position_noise=NOISE_FRAC * D, diagnose=False)
    rng = np.random.default_rng(29)
    lost = 0
    for points, normals, half in crease_grasps(coarse, D, 12, rng):
        pose = simulate.random_pose(rng, max_translation=0.5 * D)
        R, t = pose[:3, :3], pose[:3, 3]
        contacts = Contacts(points @ R.T + t, object_normals=normals @ R.T)
        stated = localize(model, contacts, **options)
        tips = localize(model, contacts, finger_radius=0.02 * D, **options)
        if stated.status != "poor_fit":
            assert NORMALS_NOTE not in (tips.hint or "")  # something fits: no second search
            continue
        lost += 1
        assert half <= NORMAL_WIDEN * np.degrees(Tolerance.from_noise(NOISE_FRAC * D, 1.0).angle)
        rotation, translation = group.errors(tips.best.pose, pose)
        assert tips.status == "ok" and NORMALS_NOTE in tips.hint
        assert rotation < 1e-3 and translation < 1e-6 * D and tips.best.chi2 < 1e-6
        assert group.errors(stated.best.pose, pose)[0] > 5.0  # what the stated gates gave instead
        stages_seconds = sum(v for k, v in tips.timing.items() if k != "total")
        assert stages_seconds <= tips.timing["total"]  # the second search's seconds counted once
    assert lost >= 1  # the stated gates lose the truth on some of these grasps


def test_a_region_model_with_a_facet_table_widens_its_normals_instead_of_searching_edges():
    """The search over edges and vertices builds a unit table of about twice the facets (GiBs
    on a fine mesh, mid-search): a model searched over regions takes the widened normal gates
    instead, a facet model the edges."""
    mesh = objects.load("rock1k")
    regions, facets = ObjectModel.from_mesh(mesh, patch_tol_deg=5.0), ObjectModel.from_mesh(mesh)
    assert regions.has_regions and regions.table is not None and not facets.has_regions
    grasp = simulate.grasp(facets, np.random.default_rng(3), n=4)
    tolerance = Tolerance.from_noise(NOISE_FRAC * facets.diameter, 1.0)
    nothing = stages.search(facets, grasp.contacts, tolerance)[0].take(np.arange(0))
    assert stages._edges_may_help(facets, grasp.contacts, tolerance, nothing, Deadline(), 0.01)
    assert not stages._edges_may_help(regions, grasp.contacts, tolerance, nothing, Deadline(), 0.01)
