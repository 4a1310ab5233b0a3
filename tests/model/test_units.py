"""Search units for contacts on sharp edges and vertices (model.units), against dense samples of
the units and against the fingertip simulator's contacts."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from contactpose import Contacts, ObjectModel, Tolerance, localize
from contactpose.geometry.kernels import point_triangle_distance
from contactpose.model.object_model import merged_mesh
from contactpose.model.symmetry import symmetry
from contactpose.model.units import EDGE, FACE, VERTEX, unit_features
from contactpose.search.grow import grow_tree
from contactpose.sim import fingertip, objects

MESHES = ["box", "rock", "banana", "carton", "banana512"]


def _model(name):
    return ObjectModel.from_mesh(objects.load(name))


def _points_on(units, u, steps=24):
    """Points of unit u on a barycentric grid of ``steps`` (its corners and edges included)."""
    i, j = np.triu_indices(steps + 1)
    a, b = (j - i) / steps, i / steps
    t = units.triangles[u]
    return t[0] + a[:, None] * (t[1] - t[0]) + b[:, None] * (t[2] - t[0])


def _normals_in(units, u, rng, n):
    """n unit normals within unit u's cone of its axis (the cone's rim included)."""
    axis, cone = units.normals[u], min(units.cones[u], np.pi)
    tilt = cone * np.sqrt(rng.random(n))
    tilt[:2] = cone
    side = rng.normal(size=(n, 3))
    side -= np.outer(side @ axis, axis)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    return np.cos(tilt)[:, None] * axis + np.sin(tilt)[:, None] * side


@pytest.mark.parametrize("name", ["box", "rock", "banana"])
def test_unit_pair_features_hold_dense_samples_of_both_units(name):
    """Every pair of points on two units, with any normals in their cones, has its distance in
    [Δmin, Δmax] (Δmin within a grid step of the dense minimum), its normal angle in [α, α_hi] and
    each height n_uᵀ(q − p) in the pair's direction interval."""
    model = _model(name)
    units = model.units
    f = unit_features(units)
    rng = np.random.default_rng(0)
    rows = rng.choice(len(f.k), size=300, replace=False)
    assert set(units.kinds[f.k[rows]]) | set(units.kinds[f.l[rows]]) == {FACE, EDGE, VERTEX}
    for e in rows:
        u, v = int(f.k[e]), int(f.l[e])
        p, q = _points_on(units, u), _points_on(units, v)
        span = np.linalg.norm(q[:, None] - p[None], axis=2)
        assert f.dmin_exact[e] <= span.min() + 1e-7 and span.max() <= f.dmax[e] + 1e-7
        assert span.min() - f.dmin_exact[e] <= 0.05 * np.max(np.linalg.norm(np.diff(units.triangles[[u, v]], axis=1),
                                                                            axis=2)) + 1e-6
        p, q = p[rng.integers(len(p), size=400)], q[rng.integers(len(q), size=400)]
        m_u, m_v = _normals_in(units, u, rng, 400), _normals_in(units, v, rng, 400)
        angle = np.arccos(np.clip(np.einsum("ij,ij->i", m_u, m_v), -1, 1))
        assert np.all((f.alpha[e] - 1e-6 <= angle) & (angle <= f.alpha_hi[e] + 1e-6))
        for m, a, b, interval in ((m_u, p, q, f.h_kl[e]), (m_v, q, p, f.h_lk[e])):
            h = np.einsum("ij,ij->i", m, b - a)
            assert np.all((interval[0] - 1e-7 <= h) & (h <= interval[1] + 1e-7)), (name, u, v)


def _touches(model, rng, n, radius):
    mesh = merged_mesh(model.vertices, model.faces)
    got = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, n, radius)
    return got, got.hit


@pytest.mark.parametrize("name", MESHES)
def test_every_simulated_fingertip_contact_lies_on_a_unit_with_its_normal_in_the_cone(name):
    """Rounded fingertips of 5 % of the diameter on faces, edges and vertices: each contact is on
    some unit (within 1e-9 of the diameter) whose cone holds its normal (to 1e-6 rad, arccos near 1); edge and vertex contacts
    on a coarse mesh need the edge and vertex units (the facets alone miss some)."""
    model = _model(name)
    units = model.units
    rng = np.random.default_rng(1)
    got, hit = _touches(model, rng, 400, 0.05 * model.diameter)
    missed_by_facets = 0
    for x, m, kind in zip(got.points[hit], got.normals[hit], got.features[hit]):
        on = point_triangle_distance(np.broadcast_to(x, (len(units), 3)), units.triangles) <= 1e-9 * model.diameter
        inside = np.arccos(np.clip(units.normals @ m, -1, 1)) <= units.cones + 1e-6
        assert np.any(on & inside), (name, kind)
        missed_by_facets += not np.any(on & inside & (units.kinds == FACE))
    if name in ("box", "carton", "banana512"):
        assert missed_by_facets > 0


@pytest.mark.parametrize("name", ["box", "rock", "banana512"])
def test_search_over_units_keeps_the_true_facets_of_contacts_within_their_gates(name):
    """Brute force: random poses, 4 fingertips of 5 %, each contact moved and its normal tilted
    by up to the per-contact bounds the pair gates allow; some tuple of the search over facets,
    sharp edges and vertices has, for every contact, the representative facet of a unit that
    holds it (point on the unit, normal in its cone)."""
    model = _model(name)
    units = model.units
    tol = Tolerance.from_noise(0.002 * model.diameter, 1.0)
    dx, dn = tol.per_contact_bounds()
    rng = np.random.default_rng(2)
    edges_seen = 0
    for _ in range(12):
        got, hit = _touches(model, rng, 4, 0.05 * model.diameter)
        if not hit.all():
            continue
        edges_seen += sum(str(k) != fingertip.FACE for k in got.features)
        R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        t = rng.normal(size=3) * model.diameter
        shift = rng.normal(size=(4, 3))
        shift *= 0.999 * dx * rng.random((4, 1)) / np.linalg.norm(shift, axis=1, keepdims=True)
        tilt = Rotation.from_rotvec(_tangent(got.normals, rng) * 0.999 * dn * rng.random((4, 1)))
        contacts = Contacts((got.points + shift) @ R.T + t, finger_normals=-(tilt.apply(got.normals) @ R.T))
        allowed = []
        for x, m in zip(got.points, got.normals):
            on = point_triangle_distance(np.broadcast_to(x, (len(units), 3)), units.triangles) <= 1e-9
            inside = np.arccos(np.clip(units.normals @ m, -1, 1)) <= units.cones + 1e-6
            allowed.append(np.unique(units.facets[on & inside]))
        tuples = grow_tree(model, contacts, tol, edges=True)[0].tuples
        held = np.ones(len(tuples), dtype=bool)
        for i, facets in enumerate(allowed):
            held &= np.isin(tuples[:, i], facets)
        assert held.any(), name
    assert edges_seen > 0


def _tangent(normals, rng):
    """A random unit vector perpendicular to each normal (n, 3)."""
    side = rng.normal(size=normals.shape)
    side -= np.einsum("ij,ij->i", side, normals)[:, None] * normals
    return side / np.linalg.norm(side, axis=1, keepdims=True)


def test_an_edge_grasp_the_facets_cannot_match_is_found_by_the_edges_search():
    """Fingertips of 10 % on the box touching its edges: no facet tuple fits, so localize searches
    the facets, edges and vertices, fits the best on the surface, and the best pose is the true
    one modulo the box's symmetry, with a hint that says what ran."""
    model = _model("box")
    rng = np.random.default_rng(5)
    group = symmetry(model)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.4, -0.3, 0.8]).as_matrix()
    pose[:3, 3] = [0.02, 0.01, -0.03]
    while True:
        got, hit = _touches(model, rng, 4, 0.1 * model.diameter)
        if hit.all() and sum(str(k) != fingertip.FACE for k in got.features) >= 2:
            break
    R, t = pose[:3, :3], pose[:3, 3]
    contacts = Contacts(got.points @ R.T + t, finger_normals=-(got.normals @ R.T))
    sx = 0.002 * model.diameter
    r = localize(model, contacts, position_noise=sx, diagnose=False)
    rot, trans = group.errors(r.best.pose, pose)
    assert rot < 0.5 and trans < 0.01 * model.diameter
    assert "sharp edges" in r.hint and r.status in ("ok", "ambiguous", "underdetermined")


def test_free_directions_are_those_the_closed_form_reports():
    """closed_form.free_directions on the facet normals of random hypotheses gives the closed
    form's own masks and rows; zero rows (contacts that hold no normal) change nothing."""
    from contactpose.solvers.closed_form import fit_poses, free_directions

    model = _model("box")
    rng = np.random.default_rng(6)
    facets = rng.integers(0, model.num_facets, size=(200, 3))
    normals = model.planes.normals[facets]
    points = rng.normal(size=(3, 3)) * 0.01
    finger = -rng.normal(size=(3, 3))
    finger /= np.linalg.norm(finger, axis=1, keepdims=True)
    fit = fit_poses(normals, model.planes.offsets[facets], points, finger, angle_tol=np.radians(1.0),
                    centroids=model.centroids[facets])
    rows, mask, axis, turn = free_directions(fit.R, np.concatenate([normals, np.zeros((200, 1, 3))], axis=1),
                                             np.radians(1.0))
    assert np.array_equal(mask, fit.free_translation_mask) and np.array_equal(turn, fit.free_rotation_mask)
    assert mask.any() and not mask.all()
    assert np.allclose(np.abs(np.einsum("hij,hij->hi", rows, fit.free_translation)), 1.0)


def test_an_edge_grasp_whose_normals_leave_a_direction_free_is_underdetermined():
    """Five fingertips on the box's top and on edges along its x axis: every contact normal is
    perpendicular to x, so the contacts slide along it. The edges' search poses them on the
    surface, and the answer says the pose is a family, free along the box's x axis."""
    model = _model("box")
    rng = np.random.default_rng(5)
    mesh = merged_mesh(model.vertices, model.faces)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.4, -0.3, 0.8]).as_matrix()
    while True:
        got = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 5, 0.05 * model.diameter)
        if got.hit.all() and sum(str(k) != fingertip.FACE for k in got.features) >= 2:
            break
    assert np.allclose(got.normals[:, 0], 0.0, atol=1e-9)  # the geometry this test is about
    R, t = pose[:3, :3], pose[:3, 3]
    noisy = got.points @ R.T + t + rng.normal(0, 0.0025 * model.diameter, (5, 3))
    r = localize(model, Contacts(noisy, finger_normals=-(got.normals @ R.T)),
                 position_noise=0.0025 * model.diameter, diagnose=False, finger_radius=0.05 * model.diameter)
    assert "sharp edges" in r.hint and r.status == "underdetermined"
    best = r.best
    free = best.free_translation
    assert len(free) == 1
    assert abs(free[0] @ (best.pose[:3, :3] @ [1.0, 0.0, 0.0])) > np.cos(np.radians(1.0))
