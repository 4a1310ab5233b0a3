"""The surface contact model against independent references: dense sampling of arcs, the
projection on a convex cone by non-negative least squares, a vertex's normal cone by the
Moreau decomposition against its edges' cone, brute force over every feature of a mesh, and
the fingertip simulator's own contacts."""

import numpy as np
import pytest
import trimesh
from scipy.optimize import nnls
from scipy.spatial.transform import Rotation

from contactpose import Contacts, ObjectModel
from contactpose.contacts import Tolerance
from contactpose.costs import surface
from contactpose.costs.association import nearest_fit_facets
from contactpose.costs.surface import SurfaceResiduals, landing
from contactpose.geometry.se3 import retract
from contactpose.model.object_model import merged_mesh
from contactpose.scoring.rank import hypothesis_arrays
from contactpose.sim import fingertip, objects
from contactpose.solvers import surface as solvers_surface
from contactpose.solvers.closed_form import fit_poses
from contactpose.solvers.surface import surface_fit


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _cone_reference(n, generators):
    """Nearest direction of the convex cone spanned by ``generators`` (k, 3) to n: the
    Euclidean projection of n on the cone (nnls), normalised."""
    weights, _ = nnls(generators.T, n)
    y = generators.T @ weights
    if np.linalg.norm(y) < 1e-12:  # n makes an obtuse angle with the whole cone
        return generators[np.argmax(generators @ n)]
    return y / np.linalg.norm(y)


def test_arc_nearest_matches_dense_sampling():
    rng = np.random.default_rng(0)
    for _ in range(200):
        a = _unit(rng.normal(size=3))
        b = _unit(a + rng.uniform(0.05, 1.5) * _unit(rng.normal(size=3)))
        n = _unit(a + rng.normal(scale=0.8, size=3))
        s = np.array(surface._arc_nearest(tuple(n), tuple(a), tuple(b))[0])
        omega = np.arccos(np.clip(a @ b, -1, 1))
        u = np.linspace(0.0, 1.0, 20001)[:, None]
        arc = (np.sin((1 - u) * omega) * a + np.sin(u * omega) * b) / np.sin(omega)
        dense = np.min(np.linalg.norm(arc - n, axis=1))
        assert abs(np.linalg.norm(s) - 1) < 1e-12
        assert np.linalg.norm(n - s) <= dense + 1e-12
        assert np.linalg.norm(n - s) >= dense - 1e-6


def test_cone_nearest_matches_nonnegative_least_squares():
    rng = np.random.default_rng(1)
    for trial in range(300):
        k = rng.integers(2, 8)
        axis = _unit(rng.normal(size=3))
        gens = _unit(axis + rng.uniform(0.05, 0.6) * rng.normal(size=(k, 3)))
        n = _unit(axis + rng.normal(scale=0.5, size=3))
        faces = np.arange(k)
        s, near, _, _, _ = surface._cone_nearest(tuple(n), gens, faces, gens)
        ref = _cone_reference(n, gens)
        assert np.linalg.norm(n - np.array(s)) == pytest.approx(np.linalg.norm(n - ref), abs=1e-9), trial
        assert near == np.argmax(gens @ np.array(s))


def _features(mesh, valid):
    """Every feature of a vertex-merged mesh: faces, convex edges (with their two faces),
    vertices (with the unit directions of their edges), as the contact model defines them."""
    adjacency, edges = mesh.face_adjacency, mesh.face_adjacency_edges
    convex = mesh.face_adjacency_convex
    vertices = []
    for v in range(len(mesh.vertices)):
        faces = np.flatnonzero((mesh.faces == v).any(axis=1) & valid)
        if len(faces):
            others = np.setdiff1d(mesh.faces[faces].ravel(), [v])
            vertices.append((v, _unit(mesh.vertices[others] - mesh.vertices[v])))
    return np.flatnonzero(valid), [(e, pair) for e, pair, c in zip(edges, adjacency, convex) if c], vertices


def _polar_reference(n, edges):
    """Nearest direction to n of a vertex's normal cone {ν : ν · e <= 0 for its edges e}, by
    the Moreau decomposition n = P_K(n) + P_K°(n), K the cone of the edges (nnls), K° the
    normal cone; None where P_K°(n) = 0 (n at least 90° from the whole cone, or no cone)."""
    weights, _ = nnls(edges.T, n)
    y = n - edges.T @ weights
    return None if np.linalg.norm(y) < 1e-9 else y / np.linalg.norm(y)


def _brute_cost(mesh, valid, p, n, sx, sn, features=None):
    """Least whitened cost over every feature of the mesh (dense arcs, nnls cones);
    features : _features(mesh, valid), when already listed."""
    tri = mesh.triangles
    normals = mesh.face_normals
    faces, edges, vertices = features or _features(mesh, valid)
    closest = trimesh.triangles.closest_point(tri[faces], np.repeat(p[None], len(faces), axis=0))
    d2 = np.sum((closest - p) ** 2, axis=1) / sx**2 + np.sum((normals[faces] - n) ** 2, axis=1) / sn**2
    best = d2.min()
    for (u, w), (f, g) in edges:
        a, b = mesh.vertices[u], mesh.vertices[w]
        s = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        x = a + s * (b - a)
        if np.sum((x - p) ** 2) / sx**2 >= best:  # the normal's part only adds
            continue
        cone = _cone_reference(n, normals[[f, g]])
        best = min(best, np.sum((x - p) ** 2) / sx**2 + np.sum((cone - n) ** 2) / sn**2)
    for v, directions in vertices:
        if np.sum((mesh.vertices[v] - p) ** 2) / sx**2 >= best:
            continue
        cone = _polar_reference(n, directions)
        if cone is not None:
            best = min(best, np.sum((mesh.vertices[v] - p) ** 2) / sx**2 + np.sum((cone - n) ** 2) / sn**2)
    return best


def _bumpy(seed=0, subdivisions=2, bump=0.06):
    """An icosphere with random radial bumps: a closed mesh with many non-convex vertices."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    radius = 1.0 + bump * np.random.default_rng(seed).uniform(-1, 1, len(sphere.vertices))
    return trimesh.Trimesh(sphere.vertices * radius[:, None], sphere.faces, process=False)


def test_vertex_cones_are_the_polar_cones_of_their_edges():
    """Each vertex's cone rays span exactly {ν : ν · e <= 0 for its edges e}: random
    directions are in the span of its rays (nnls residual 0) iff they hold every edge
    constraint, at convex and non-convex vertices alike; a saddle has no rays."""
    model = ObjectModel.from_mesh(_bumpy())
    mesh = merged_mesh(model.vertices, model.faces)
    top = model.topology
    _, _, vertices = _features(mesh, model.planes.valid)
    rng = np.random.default_rng(3)
    concave = mesh.face_adjacency_edges[~mesh.face_adjacency_convex].ravel()
    kinds = set()
    for v, directions in vertices:
        rays = top.cone_rays[top.cone_ptr[v]:top.cone_ptr[v + 1]]
        kinds.add((v in concave, len(rays) > 0))
        outward = _unit(mesh.vertex_normals[v])
        probes = _unit(np.concatenate([outward + rng.normal(scale=0.4, size=(60, 3)), rays + 1e-3 * rng.normal(size=rays.shape)]))
        for nu in probes:
            inside = np.all(directions @ nu <= 1e-9)
            spanned = len(rays) > 0 and nnls(rays.T, nu)[1] < 1e-9
            assert inside == spanned or abs(np.max(directions @ nu)) < 1e-7, (v, nu)
    assert {(False, True), (True, True), (True, False)} <= kinds, kinds  # convex, concave-edged, saddle


@pytest.mark.parametrize("name", ["bumpy", "rock"])
def test_surface_association_lands_on_the_least_cost_feature_of_the_whole_mesh(name):
    """nearest_fit_facets(surface=True) under a pose: the contact, landing from the facet it
    returns, costs what the brute force over every feature of the mesh finds (dense arcs,
    nnls cones), for fingertip contacts with noise at a perturbed pose. On the rough bumpy
    sphere the facet of least plane cost (surface=False) lands elsewhere for some contacts."""
    mesh = _bumpy(seed=2, subdivisions=3, bump=0.1) if name == "bumpy" else objects.load(name)
    model = ObjectModel.from_mesh(mesh, max_span=1e-9, patch_tol_deg=None)  # no search: no pair is tabled
    mesh = merged_mesh(model.vertices, model.faces)
    rng = np.random.default_rng(6)
    D = model.diameter
    tol = Tolerance.from_noise(0.008 * D, 1.0)  # facets a few σ_x wide, their normals far apart: rough
    got = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 80, 0.1 * D)
    hit = got.hit
    p = got.points[hit] + rng.normal(scale=tol.position_noise, size=(hit.sum(), 3))
    n = _unit(got.normals[hit] + rng.normal(scale=tol.normal_noise, size=(hit.sum(), 3)))
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.01, -0.02, 0.015]).as_matrix()
    pose[:3, 3] = 0.005 * D
    contacts = Contacts(p @ pose[:3, :3].T + pose[:3, 3], finger_normals=-(n @ pose[:3, :3].T))
    facets = nearest_fit_facets(model, contacts, pose, tol, surface=True)
    landed = landing(model, contacts, pose[:3, :3], pose[:3, 3], facets, tol)
    q, nu = (contacts.points - pose[:3, 3]) @ pose[:3, :3], -(contacts.finger_normals @ pose[:3, :3])
    for i in range(len(p)):
        assert landed.cost[i] == pytest.approx(_brute_cost(mesh, model.planes.valid, q[i], nu[i], tol.position_noise,
                                                           tol.normal_noise), rel=1e-6, abs=1e-9), i
    by_planes = landing(model, contacts, pose[:3, :3], pose[:3, 3], nearest_fit_facets(model, contacts, pose, tol), tol)
    assert np.all(by_planes.cost >= landed.cost - 1e-9)
    if name == "bumpy":
        assert np.any(by_planes.cost > landed.cost + 1.0)


def test_surface_fit_ends_where_each_contact_sits_on_its_least_cost_feature_of_the_whole_mesh():
    """On a rough mesh (a bumpy sphere of 5,120 facets, σ_x a fraction of a facet) the fit's
    walk can stop with a contact on a feature behind a ridge of cost from its best. From
    starts 4° and 2 % D off, the surface fit (which gathers the contacts' facets again over
    the whole mesh) ends at a pose where χ²_S equals the brute-force least cost over every
    feature in 5 grasps of 6 or more, the walk alone in fewer, and it never fits worse."""
    model = ObjectModel.from_mesh(_bumpy(seed=2, subdivisions=4, bump=0.06), max_span=1e-9, patch_tol_deg=None)
    mesh = merged_mesh(model.vertices, model.faces)  # no search here: a pair table that holds no pair
    features = _features(mesh, model.planes.valid)
    D = model.diameter
    tol = Tolerance.from_noise(0.008 * D, 1.0)
    rng = np.random.default_rng(8)
    at_least = {"walk": 0, "gathered": 0}
    for _ in range(6):
        got = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 4, 0.1 * D)
        while not got.hit.all():
            got = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 4, 0.1 * D)
        p = got.points + rng.normal(scale=tol.position_noise, size=(4, 3))
        n = _unit(got.normals + rng.normal(scale=tol.normal_noise, size=(4, 3)))
        contacts = Contacts(p, finger_normals=-n)
        R0 = Rotation.from_rotvec(_unit(rng.normal(size=3)) * np.radians(4.0)).as_matrix()
        t0 = 0.02 * D * _unit(rng.normal(size=3))
        start = np.eye(4)
        start[:3, :3], start[:3, 3] = R0, t0
        facets = nearest_fit_facets(model, contacts, start, tol)
        chi2 = {}
        for kind, fit in (("walk", solvers_surface._walked_fit), ("gathered", surface_fit)):
            R, t, _, _, _, chi2[kind] = fit(model, contacts, R0, t0, facets, tol)
            q, nu = (p - t) @ R, n @ R
            least = sum(_brute_cost(mesh, model.planes.valid, q[i], nu[i], tol.position_noise, tol.normal_noise,
                                    features) for i in range(4))
            assert least <= chi2[kind] * (1 + 1e-9) + 1e-9
            at_least[kind] += bool(chi2[kind] <= least * (1 + 1e-6) + 1e-9)
        assert chi2["gathered"] <= chi2["walk"] + 1e-9
    assert at_least["gathered"] >= 5 and at_least["walk"] < at_least["gathered"], at_least


def test_fingertip_contacts_at_non_convex_vertices_cost_nothing():
    """A ball touching a vertex that has concave edges has its normal in the vertex's
    (smaller) cone: the simulator's noise-free contacts on the bumpy sphere cost 0."""
    model = ObjectModel.from_mesh(_bumpy(seed=1))
    mesh = merged_mesh(model.vertices, model.faces)
    concave = set(mesh.face_adjacency_edges[~mesh.face_adjacency_convex].ravel().tolist())
    rng = np.random.default_rng(5)
    got = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 300, 1.0)
    hit = got.hit
    tol = Tolerance.from_noise(0.002 * model.diameter, 1.0)
    landed = surface.land(model.topology, model.triangles, model.planes.normals, model.planes.valid,
                          got.points[hit], got.normals[hit], got.facets[hit], tol.position_noise, tol.normal_noise)
    at = np.argmin(np.linalg.norm(got.points[hit][:, None] - mesh.vertices[None], axis=2), axis=1)
    on_concave_vertex = (got.features[hit] == "vertex") & np.isin(at, list(concave))
    assert on_concave_vertex.sum() >= 10
    assert np.all(landed.cost < 1e-12)


@pytest.mark.parametrize("name", ["box", "rock"])
def test_landing_finds_the_least_cost_feature_of_the_whole_mesh(name):
    model = ObjectModel.from_mesh(objects.load(name))
    mesh = merged_mesh(model.vertices, model.faces)
    valid = model.planes.valid
    rng = np.random.default_rng(2)
    D = model.diameter
    sx, sn = 0.01 * D, np.radians(3.0)
    got = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 40, 0.05 * D)
    hit = got.hit
    p = got.points[hit] + rng.normal(scale=0.3 * sx, size=(hit.sum(), 3))
    n = _unit(got.normals[hit] + rng.normal(scale=0.3 * sn, size=(hit.sum(), 3)))
    got = surface.land(model.topology, model.triangles, model.planes.normals, valid, p, n, got.facets[hit], sx, sn)
    cost, kind, q, cone = got.cost, got.kind, got.q, got.cone
    assert {surface.EDGE, surface.VERTEX} & set(kind.tolist()), "the sample should touch edges or vertices"
    for i in range(len(p)):
        ref = _brute_cost(mesh, valid, p[i], n[i], sx, sn)
        assert cost[i] == pytest.approx(ref, rel=1e-6, abs=1e-9), i
        # the reported feature is what the cost says: its point and cone direction
        assert np.sum((p[i] - q[i]) ** 2) / sx**2 + np.sum((n[i] - cone[i]) ** 2) / sn**2 == pytest.approx(cost[i])


def test_topology_neighbours_share_their_edge():
    model = ObjectModel.from_mesh(objects.load("rock"))
    top = model.topology
    f, j = np.nonzero(top.edge_nbr >= 0)
    g = top.edge_nbr[f, j]
    a, b = top.fv[f, j], top.fv[f, (j + 1) % 3]
    assert np.all((top.fv[g] == a[:, None]).any(axis=1) & (top.fv[g] == b[:, None]).any(axis=1))
    assert np.all(f != g)


def _edge_grasp(model, rng, radius, pose):
    """Noise-free fingertip contacts (world frame) of a grasp that touches edges or vertices."""
    mesh = merged_mesh(model.vertices, model.faces)
    while True:
        got = fingertip.approach(np.asarray(mesh.vertices), np.asarray(mesh.faces), rng, 4, radius)
        if got.hit.all() and any(str(k) != fingertip.FACE for k in got.features):
            break
    R, t = pose[:3, :3], pose[:3, 3]
    return Contacts(got.points @ R.T + t, finger_normals=-(got.normals @ R.T)), got


def test_simulated_edge_contacts_fit_the_contact_model_exactly_and_the_fit_returns_to_them():
    """At the true pose a rounded fingertip's contacts cost nothing under the contact model
    (they lie on features with normals in the cones), while the facet model charges the
    edge contacts; from a perturbed pose the surface fit comes back to the truth."""
    model = ObjectModel.from_mesh(objects.load("box"))
    rng = np.random.default_rng(4)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    pose[:3, 3] = [0.01, -0.02, 0.03]
    contacts, got = _edge_grasp(model, rng, 0.1 * model.diameter, pose)
    tol = Tolerance.from_noise(0.001 * model.diameter, 1.0)
    R, t = pose[:3, :3], pose[:3, 3]
    assert np.all(landing(model, contacts, R, t, got.facets, tol).cost < 1e-12)
    facets = got.facets[None]
    fit = fit_poses(model.planes.normals[facets], model.planes.offsets[facets], contacts.points,
                    contacts.finger_normals, angle_tol=tol.normal_noise, centroids=model.centroids[facets])
    fit.R, fit.t = R[None], t[None]
    facet_chi2 = hypothesis_arrays(model, contacts, facets, fit, tol, order=False).chi2[0]
    assert facet_chi2 > 100.0
    R1 = R @ Rotation.from_rotvec([0.02, -0.01, 0.015]).as_matrix()
    t1 = t + 0.01 * model.diameter * np.array([1.0, -0.5, 0.3])
    R2, t2, _, _, _, chi2 = surface_fit(model, contacts, R1, t1, got.facets, tol)
    assert chi2 < 1e-6
    assert np.degrees(Rotation.from_matrix(R2.T @ R).magnitude()) < 0.01
    assert np.linalg.norm(t2 - t) < 1e-4 * model.diameter


def test_localize_reports_the_contact_model_fit_of_an_edge_grasp():
    """Noise-free fingertip contacts on the rock's edges: the best hypothesis is the true
    pose, its χ² is the contact model's cost at its pose (recomputed here by landing), its
    facets are where the contacts land; the facet model alone leaves a pose 1.3° off."""
    from contactpose import localize

    model = ObjectModel.from_mesh(objects.load("rock1k"))
    rng = np.random.default_rng(7)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([-0.4, 0.1, 0.7]).as_matrix()
    contacts, got = _edge_grasp(model, rng, 0.1 * model.diameter, pose)
    sx = 0.002 * model.diameter
    plain = localize(model, contacts, position_noise=sx, surface=False)
    r = localize(model, contacts, position_noise=sx, surface=True)
    best = r.best
    err = np.degrees(Rotation.from_matrix(best.pose[:3, :3].T @ pose[:3, :3]).magnitude())
    assert r.status == "ok" and err < 1e-6
    at = landing(model, contacts, best.pose[:3, :3], best.pose[:3, 3], np.asarray(best.facets), r.tolerance)
    cost, landed = at.cost, at.facet
    assert r.hypotheses.arrays.chi2[0] == pytest.approx(cost.sum(), rel=1e-9)
    assert np.array_equal(landed, best.facets)
    assert r.hypotheses.arrays.chi2[0] < 1e-12 < 1.0 < plain.hypotheses.arrays.chi2[0]


def _noisy_edge_grasp(model, rng, tol):
    """A random rotation, an edge grasp under it with half-σ position noise and slightly tilted
    normals. -> (pose (4, 4), Contacts, fingertip.approach's answer)"""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    contacts, got = _edge_grasp(model, rng, 0.1 * model.diameter, pose)
    noisy = Contacts(contacts.points + rng.normal(scale=0.5 * tol.position_noise, size=(4, 3)),
                     finger_normals=_unit(contacts.finger_normals + rng.normal(scale=0.02, size=(4, 3))))
    return pose, noisy, got


@pytest.mark.parametrize("name", ["rock1k", "box"])
def test_surface_jacobian_matches_finite_differences(name):
    """The Jacobian of χ²_S's residuals, features held, against central differences at
    perturbations ξ where no contact changes feature (faces, edges, arcs, vertex cones)."""
    model = ObjectModel.from_mesh(objects.load(name))
    rng = np.random.default_rng(8)
    tol = Tolerance.from_noise(0.002 * model.diameter, 2.0)
    checked = set()
    for trial in range(40):
        pose, noisy, got = _noisy_edge_grasp(model, rng, tol)
        problem = SurfaceResiduals(model, noisy, pose[:3, :3], pose[:3, 3], got.facets, tol, 1.0)
        xi = rng.normal(scale=1e-3, size=6) * np.r_[1, 1, 1, [model.diameter] * 3]
        R, t = retract(pose[None, :3, :3], pose[None, :3, 3], xi[None])
        at = landing(model, noisy, R[0], t[0], got.facets, tol)
        J = problem.jacobian(xi)
        h = 1e-7 * np.r_[1, 1, 1, [model.diameter] * 3]
        numeric = np.empty_like(J)
        same = True
        for c in range(6):
            e = np.zeros(6)
            e[c] = h[c]
            for sign in (1, -1):
                moved_at = SurfaceResiduals(model, noisy, pose[:3, :3], pose[:3, 3], got.facets, tol, 1.0)
                moved_at.residuals(xi + sign * e)
                same &= np.array_equal(moved_at.landed.kind, at.kind) and np.array_equal(
                    moved_at.landed.ncode, at.ncode) and np.array_equal(moved_at.landed.pcode, at.pcode)
            numeric[:, c] = (problem.residuals(xi + e) - problem.residuals(xi - e)) / (2 * h[c])
        if not same:
            continue
        assert np.allclose(J, numeric, rtol=1e-5, atol=1e-5 * np.abs(J).max()), trial
        checked |= {(int(k), int(c)) for k, c in zip(at.kind, at.ncode)}
    assert {(surface.FACE, 0), (surface.EDGE, 1), (surface.VERTEX, 2)} <= checked, checked


@pytest.mark.parametrize("name", ["rock1k", "box"])
def test_compiled_surface_rows_equal_the_residuals_and_jacobian_at_the_pose(name):
    """surface_rows, the compiled rows the fit steps with, against SurfaceResiduals (numpy, its
    Jacobian checked by central differences above) at ξ = 0: the same residuals, the same
    Jacobian and the same landing, at faces, edges and vertices; χ²_S is the rows' square sum."""
    model = ObjectModel.from_mesh(objects.load(name))
    rng = np.random.default_rng(9)
    tol = Tolerance.from_noise(0.002 * model.diameter, 2.0)
    topo = model.topology
    arrays = topo.arrays
    kinds = set()
    for _ in range(12):
        pose, noisy, got = _noisy_edge_grasp(model, rng, tol)
        reference = SurfaceResiduals(model, noisy, pose[:3, :3], pose[:3, 3], got.facets, tol, 1.0)
        e, J = np.empty(24), np.empty((24, 6))
        facets = np.asarray(got.facets, dtype=np.int64).copy()
        chi2 = surface.surface_rows(pose[:3, :3].copy(), pose[:3, 3].copy(), noisy.points, noisy.finger_normals, facets,
                                    arrays, model.triangles, model.planes.normals, model.planes.valid,
                                    tol.position_noise, tol.normal_noise, e, J)
        np.testing.assert_allclose(e, reference.residuals(np.zeros(6)), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(J, reference.jacobian(np.zeros(6)), rtol=1e-9, atol=1e-9 * np.abs(J).max())
        assert np.array_equal(facets, reference.landed.facet)
        assert chi2 == pytest.approx(e @ e, rel=1e-12)
        kinds |= set(reference.landed.kind.tolist())
    assert {surface.FACE, surface.EDGE} <= kinds, kinds


def test_has_regions_only_when_patches_grown_above_the_coplanar_tolerance_are_searched():
    sphere = objects.load("sphere")
    assert ObjectModel.from_mesh(sphere, patch_tol_deg=25.0).has_regions      # 46 regions of 320 facets
    assert not ObjectModel.from_mesh(sphere, patch_tol_deg=0.5).has_regions   # coplanar patches only
    assert not ObjectModel.from_mesh(objects.load("carton")).has_regions     # patches of flat faces


def test_surface_auto_fits_on_the_surface_on_a_model_of_regions_only():
    """localize's default surface="auto": an edge grasp on a model of surface regions is posed
    on the surface contact model (the answer of surface=True, a lower χ² than the facets'),
    on a facet table as by the facets (surface=False); any other value is one clear error."""
    from contactpose import localize
    from contactpose.errors import ContactPoseError

    rng = np.random.default_rng(3)
    regions = ObjectModel.from_mesh(objects.load("rock1k"), patch_tol_deg=10.0)
    facets = ObjectModel.from_mesh(objects.load("rock1k"))
    assert regions.has_regions and not facets.has_regions
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.2, -0.6, 0.3]).as_matrix()
    contacts, _ = _edge_grasp(regions, rng, 0.05 * regions.diameter, pose)
    sx = 0.002 * regions.diameter
    for model, same in ((regions, True), (facets, False)):
        auto = localize(model, contacts, position_noise=sx, diagnose=False)
        fixed = localize(model, contacts, position_noise=sx, diagnose=False, surface=same)
        other = localize(model, contacts, position_noise=sx, diagnose=False, surface=not same)
        assert np.array_equal(auto.hypotheses.arrays.poses, fixed.hypotheses.arrays.poses)
        assert np.array_equal(auto.hypotheses.arrays.chi2, fixed.hypotheses.arrays.chi2)
        on, off = (auto, other) if same else (other, auto)
        assert on.hypotheses.arrays.chi2[0] < off.hypotheses.arrays.chi2[0]
    with pytest.raises(ContactPoseError, match="surface must be True, False or 'auto', got 'yes'"):
        localize(facets, contacts, surface="yes")


def test_surface_factor_jacobian_is_the_pose3_tangent_derivative():
    """The GTSAM factor of χ²_S: its error is the residual of SurfaceResiduals at the pose, and its
    Jacobian matches central differences through Pose3.retract (rotation first), wherever no
    contact changes feature within the step."""
    import gtsam

    from contactpose.solvers.surface import surface_factor

    model = ObjectModel.from_mesh(objects.load("rock1k"))
    rng = np.random.default_rng(11)
    tol = Tolerance.from_noise(0.002 * model.diameter, 2.0)
    compared = 0
    for trial in range(30):
        pose, noisy, got = _noisy_edge_grasp(model, rng, tol)
        factor = surface_factor(model, noisy, got.facets, tol, 0)
        values = gtsam.Values()
        values.insert(0, gtsam.Pose3(pose))
        e = factor.unwhitenedError(values)
        problem = SurfaceResiduals(model, noisy, pose[:3, :3], pose[:3, 3], got.facets, tol, 1.0)
        assert np.allclose(e, problem.residuals(np.zeros(6)), rtol=0, atol=1e-12)
        A, b = factor.linearize(values).jacobian()
        h = 1e-7 * np.r_[1, 1, 1, [model.diameter] * 3]
        numeric, same = np.empty_like(A), True
        for c in range(6):
            step = np.zeros(6)
            step[c] = h[c]
            errors = []
            for sign in (1, -1):
                moved_values = gtsam.Values()
                moved_values.insert(0, gtsam.Pose3(pose).retract(sign * step))
                probe = SurfaceResiduals(model, noisy, *(lambda T: (T[:3, :3], T[:3, 3]))(moved_values.atPose3(0).matrix()),
                                 got.facets, tol, 1.0)
                probe.residuals(np.zeros(6))
                same &= np.array_equal(probe.landed.kind, problem.landed.kind)
                errors.append(surface_factor(model, noisy, got.facets, tol, 0).unwhitenedError(moved_values))
            numeric[:, c] = (errors[0] - errors[1]) / (2 * h[c])
        if not same:
            continue
        assert np.allclose(A, numeric, rtol=1e-5, atol=1e-5 * np.abs(A).max()), trial
        assert np.allclose(b, -e, atol=1e-12)
        compared += 1
    assert compared >= 20


@pytest.mark.parametrize("seed", [5, 6])
def test_near_copies_of_the_best_are_fitted_on_the_surface_when_it_does_not_fit(seed):
    """stages._refit_near_copies against brute force: every assignment within NEAR_COPY_REACH
    near-copy radii of the first pose fitted on the surface from its own facet pose
    (solvers.surface.surface_fit); the first hypothesis comes back with the least χ² among those
    fits when that beats its own, and as it was otherwise."""
    from contactpose import localize, stages
    from contactpose.geometry.metrics import rms_displacement
    from contactpose.scoring.classes import distinct_radius

    rng = np.random.default_rng(seed)
    model = ObjectModel.from_mesh(objects.load("rock1k"), patch_tol_deg=10.0)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    contacts, _ = _edge_grasp(model, rng, 0.05 * model.diameter, pose)
    sx = 0.002 * model.diameter
    tol = Tolerance.from_noise(sx, 1.0)
    every = localize(model, contacts, position_noise=sx, diagnose=False, distinct=False).hypotheses.arrays
    first = every.take([0])
    got = stages._refit_near_copies(model, contacts, first, every, tol)
    reach = stages.NEAR_COPY_REACH * distinct_radius(model, sx)
    near = np.flatnonzero(rms_displacement(every.poses, first.poses[0], *model.class_moments) <= reach)
    near = near[~every.fit.underdetermined[near]][:stages.NEAR_COPY_REFITS]
    brute = min(surface_fit(model, contacts, every.fit.R[k], every.fit.t[k], every.facets[k], tol)[5] for k in near)
    assert len(near) > 1
    if brute < first.chi2[0] - 1e-9:
        assert got.chi2[0] == pytest.approx(brute, rel=1e-9) and len(got.cost) <= 2  # 1: it landed on first's facets
    else:
        assert np.array_equal(got.poses, first.poses)
