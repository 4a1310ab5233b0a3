"""Rounded-fingertip sweeps against references that share no code with the module.

References: trimesh's exact point-triangle distances and ray casts, dense surface
samples (area-uniform points, all vertices, points on every edge) with a closed-form
ray-ball entry time per sample, and convex polytopes whose face, edge and vertex
touches are known in closed form.
"""

import numpy as np
import pytest
import trimesh
from scipy.optimize import nnls

from contactpose.errors import ContactPoseError
from contactpose.sim import fingertip
from contactpose.sim.fingertip import FingertipContacts, approach, sweep_spheres

EXACT = 1e-9  # relative to the diameter


def diameter(vertices):
    return float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))


def jittered_icosphere(seed=0, jitter=0.02):
    """A fine (1280-facet), slightly non-convex closed mesh."""
    ico = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(seed)
    v = ico.vertices * (1.0 + jitter * rng.uniform(-1.0, 1.0, (len(ico.vertices), 1)))
    return trimesh.Trimesh(v, ico.faces, process=False)


def random_hull(seed=1, n=40):
    """A convex polytope: the hull of points near the unit sphere (no coplanar faces)."""
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p *= rng.uniform(0.8, 1.2, (n, 1)) / np.linalg.norm(p, axis=1, keepdims=True)
    return trimesh.convex.convex_hull(p)


MESHES = {
    "cube": lambda: trimesh.creation.box(extents=(1.0, 2.0, 3.0)),
    "icosahedron": trimesh.creation.icosahedron,
    "hull": random_hull,
}


def unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def reference_distance(mesh, points):
    """Exact distances (m,) of points to the mesh, brute force over all triangles (trimesh)."""
    m, f = len(points), len(mesh.faces)
    closest = trimesh.triangles.closest_point(np.tile(mesh.triangles, (m, 1, 1)), np.repeat(points, f, axis=0))
    return np.linalg.norm(closest - np.repeat(points, f, axis=0), axis=1).reshape(m, f).min(axis=1)


def dense_samples(mesh, seed=7, n=10_000, per_edge=8):
    """Area-uniform surface samples plus all vertices and points along every edge."""
    points, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    t = np.linspace(0.0, 1.0, per_edge + 2)[1:-1, None, None]
    e = mesh.edges_unique
    along = mesh.vertices[e[:, 0]] + t * (mesh.vertices[e[:, 1]] - mesh.vertices[e[:, 0]])
    return np.vstack([points, mesh.vertices, along.reshape(-1, 3)])


def first_sample_touch(starts, dirs, r, samples):
    """Travel (n,) at which a ball of radius r from starts along dirs first contains a sample."""
    out = np.full(len(starts), np.inf)
    for i, (c, u) in enumerate(zip(starts, dirs)):
        w = c - samples
        b = w @ u
        disc = b * b - (np.einsum("ij,ij->i", w, w) - r * r)
        ok = disc >= 0
        out[i] = np.min(-b[ok] - np.sqrt(disc[ok]), initial=np.inf)
    return out


def check_against_reference(mesh, contacts, samples):
    """The touch is at distance r, on the surface, and nothing was touched earlier."""
    d, r = diameter(mesh.vertices), contacts.radius
    hit = contacts.hit
    c, p = contacts.centres[hit], contacts.points[hit]
    assert np.allclose(c, contacts.starts[hit] + contacts.travel[hit, None] * contacts.directions[hit], atol=EXACT * d)
    assert np.all(np.abs(np.linalg.norm(p - c, axis=1) - r) <= EXACT * d)
    assert np.all(np.abs(reference_distance(mesh, c) - r) <= EXACT * d)
    assert np.all(reference_distance(mesh, p) <= EXACT * d)
    tri = mesh.triangles[contacts.facets[hit]]
    assert np.allclose(trimesh.triangles.closest_point(tri, p), p, atol=EXACT * d, rtol=0)
    gaps = np.linalg.norm(c[:, None] - samples[None], axis=2).min(axis=1)
    assert np.all(gaps >= r - EXACT * d)
    for frac in (0.5, 0.9, 0.99, 0.999):  # exact distance along the path before the touch
        before = contacts.starts[hit] + frac * contacts.travel[hit, None] * contacts.directions[hit]
        assert np.all(reference_distance(mesh, before) >= r - EXACT * d)
    if r > 0:
        first = first_sample_touch(contacts.starts[hit], contacts.directions[hit], r, samples)
        assert np.all(first >= contacts.travel[hit] - EXACT * d)
        assert np.allclose(contacts.normals[hit], (c - p) / r, atol=EXACT, rtol=0)
    else:
        locations, rays, _ = mesh.ray.intersects_location(contacts.starts[hit], contacts.directions[hit])
        travel = np.full(hit.sum(), np.inf)
        np.minimum.at(travel, rays, np.linalg.norm(locations - contacts.starts[hit][rays], axis=1))
        assert np.allclose(travel, contacts.travel[hit], atol=1e-7 * d, rtol=0)


@pytest.fixture(scope="module")
def fine_mesh():
    mesh = jittered_icosphere()
    return mesh, dense_samples(mesh)


@pytest.mark.parametrize("radius_rel", [0.0, 0.01, 0.02, 0.05])
@pytest.mark.parametrize("mode", ["cone", "closing"])
def test_random_batch_matches_dense_reference(fine_mesh, radius_rel, mode):
    mesh, samples = fine_mesh
    r = radius_rel * diameter(mesh.vertices)
    contacts = approach(mesh.vertices, mesh.faces, np.random.default_rng(11), 40, r, cone_deg=40.0, mode=mode)
    assert isinstance(contacts, FingertipContacts) and len(contacts) == 40
    assert contacts.hit.all()
    assert np.allclose(np.linalg.norm(contacts.normals, axis=1), 1.0, atol=1e-12)
    check_against_reference(mesh, contacts, samples)


def test_given_sweeps_match_dense_reference(fine_mesh):
    """Arbitrary starts and directions (many grazing or missing) on the fine mesh."""
    mesh, samples = fine_mesh
    rng = np.random.default_rng(5)
    d = diameter(mesh.vertices)
    starts = unit(rng.normal(size=(60, 3))) * 1.5 * d
    dirs = unit(rng.uniform(-0.6, 0.6, (60, 3)) * d - starts)
    contacts = sweep_spheres(mesh.vertices, mesh.faces, starts, dirs, 0.03 * d)
    assert 0 < contacts.hit.sum() < 60
    check_against_reference(mesh, contacts, samples)
    inner = reference_distance(mesh, np.zeros((1, 3)))[0]  # the ball of this radius is inside
    closest_approach = np.linalg.norm(np.cross(starts, dirs), axis=1)  # of each ray to the origin
    assert np.all(closest_approach[~contacts.hit] > inner + 0.03 * d)


def feature_cases(mesh, r):
    """Starts, directions, expected points, normals and kinds touching every face
    centroid, convex edge midpoint and vertex of a convex mesh head-on."""
    d = diameter(mesh.vertices)
    n_f = mesh.face_normals
    convex = mesh.face_adjacency_angles > 1e-6
    edges = mesh.face_adjacency_edges[convex]
    edge_normal = unit(n_f[mesh.face_adjacency[convex, 0]] + n_f[mesh.face_adjacency[convex, 1]])
    vertex_normal = unit(np.array([n_f[[f for f in fs if f >= 0]].sum(axis=0) for fs in mesh.vertex_faces]))
    targets = np.vstack([mesh.triangles_center, mesh.vertices[edges].mean(axis=1), mesh.vertices])
    normals = np.vstack([n_f, edge_normal, vertex_normal])
    kinds = ["face"] * len(n_f) + ["edge"] * len(edges) + ["vertex"] * len(mesh.vertices)
    return targets + (d + r) * normals, -normals, targets, normals, np.array(kinds)


@pytest.mark.parametrize("name", sorted(MESHES))
@pytest.mark.parametrize("radius_rel", [0.0, 0.03])
def test_touches_face_edge_vertex_exactly(name, radius_rel):
    mesh = MESHES[name]()
    d = diameter(mesh.vertices)
    r = radius_rel * d
    starts, dirs, targets, normals, kinds = feature_cases(mesh, r)
    contacts = sweep_spheres(mesh.vertices, mesh.faces, starts, dirs, r)
    assert contacts.hit.all()
    assert np.array_equal(contacts.features, kinds)
    assert np.allclose(contacts.points, targets, atol=EXACT * d, rtol=0)
    assert np.allclose(contacts.travel, d, atol=EXACT * d, rtol=0)
    if r > 0:
        assert np.allclose(contacts.normals, normals, atol=EXACT, rtol=0)
    else:  # a point finger reports the normal of its facet
        assert np.allclose(contacts.normals, mesh.face_normals[contacts.facets], atol=EXACT, rtol=0)


def normal_cone_residual(mesh, facet, point, normal, kind):
    """How far (unit normal) lies outside the normal cone of the touched feature, whose
    kind is checked against trimesh's barycentric coordinates of the point."""
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[[facet]], point[None])[0]
    corners = mesh.faces[facet][bary > 1e-9]
    assert len(corners) == {"face": 3, "edge": 2, "vertex": 1}[kind]
    if kind == "face":
        return np.linalg.norm(normal - mesh.face_normals[facet])
    if kind == "edge":
        faces = [f for f in mesh.vertex_faces[corners[0]] if f >= 0 and corners[1] in mesh.faces[f]]
        edge = unit(np.diff(mesh.vertices[corners], axis=0)[0])
        cone = mesh.face_normals[faces]
        residual = abs(normal @ edge)
    else:
        cone = mesh.face_normals[[f for f in mesh.vertex_faces[corners[0]] if f >= 0]]
        residual = 0.0
    return residual + nnls(cone.T, normal)[1]


@pytest.mark.parametrize("mesh_factory", [random_hull, jittered_icosphere], ids=["hull", "icosphere"])
def test_contact_normal_in_feature_normal_cone(mesh_factory):
    mesh = mesh_factory()
    r = 0.05 * diameter(mesh.vertices)
    contacts = approach(mesh.vertices, mesh.faces, np.random.default_rng(3), 300, r, cone_deg=60.0)
    assert contacts.hit.all()
    if mesh_factory is random_hull:
        assert set(contacts.features) == {"face", "edge", "vertex"}
    for i in range(len(contacts)):
        args = (contacts.facets[i], contacts.points[i], contacts.normals[i], contacts.features[i])
        assert normal_cone_residual(mesh, *args) <= 1e-9, (i, args)


@pytest.mark.parametrize("mesh_factory", [random_hull, lambda: trimesh.creation.icosphere(subdivisions=3)],
                         ids=["hull", "icosphere"])
def test_point_finger_without_cone_reproduces_facet_points(mesh_factory):
    mesh = mesh_factory()
    d = diameter(mesh.vertices)
    contacts = approach(mesh.vertices, mesh.faces, np.random.default_rng(2), 200, 0.0, cone_deg=0.0)
    assert contacts.hit.all()
    assert np.allclose(contacts.points, contacts.targets, atol=EXACT * d, rtol=0)
    assert np.array_equal(contacts.facets, contacts.target_facets)
    assert np.allclose(contacts.normals, mesh.face_normals[contacts.target_facets], atol=EXACT, rtol=0)
    assert np.all(contacts.features == "face")
    given = approach(mesh.vertices, mesh.faces, np.random.default_rng(9), None, 0.0, cone_deg=0.0,
                     surface_points=contacts.targets, facets=contacts.target_facets)
    assert np.allclose(given.points, contacts.targets, atol=EXACT * d, rtol=0)


def test_grazing_approach_is_exact():
    """Directions nearly parallel to a face: the touch comes after a long, slow slide."""
    mesh = trimesh.creation.box(extents=(4.0, 4.0, 1.0))
    r, height, slopes = 0.1, 0.5 + 0.1 + 0.01, np.array([1e-1, 1e-2, 3e-3])
    dirs = unit(np.column_stack([np.ones(3), np.zeros(3), -slopes]))
    starts = np.tile([-1.9, 0.3, height], (3, 1))
    contacts = sweep_spheres(mesh.vertices, mesh.faces, starts, dirs, r)
    expected = 0.01 / np.sin(np.arctan(slopes))
    ok = expected < 3.8
    assert np.array_equal(contacts.hit, ok)
    assert np.allclose(contacts.travel[ok], expected[ok], atol=EXACT * diameter(mesh.vertices), rtol=0)
    assert np.all(contacts.features[ok] == "face")
    assert np.allclose(contacts.normals[ok], [0.0, 0.0, 1.0], atol=EXACT)


def test_miss_is_reported():
    mesh = trimesh.creation.box()
    starts = np.array([[3.0, 0.0, 0.0], [3.0, 0.1, 0.3], [3.0, 0.55, 0.0], [3.0, 0.0, 0.0], [3.0, 0.61, 0.0]])
    dirs = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    contacts = sweep_spheres(mesh.vertices, mesh.faces, starts, dirs, 0.1)
    assert contacts.hit.tolist() == [False, True, True, False, False]  # the last passes 0.11 from an edge
    assert np.allclose(contacts.travel[1:3], [2.4, 2.5 - np.sqrt(0.0075)], atol=1e-12, rtol=0)
    assert contacts.features[1:3].tolist() == ["face", "edge"]
    assert np.allclose(contacts.normals[2], [np.sqrt(0.0075) / 0.1, 0.5, 0.0], atol=1e-12)
    miss = ~contacts.hit
    assert np.isnan(contacts.points[miss]).all() and np.isnan(contacts.centres[miss]).all()
    assert (contacts.facets[miss] == -1).all() and (contacts.features[miss] == "none").all()
    short = sweep_spheres(mesh.vertices, mesh.faces, starts[1:2], dirs[1:2], 0.1, max_travel=2.0)
    assert not short.hit[0]
    near = [[0.6, 0.1, 0.2], [0.6, 0.1, 0.2], [0.7, 0.0, 0.3]]  # touching at the start, or close
    away = sweep_spheres(mesh.vertices, mesh.faces, near, [[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0]], 0.1)
    assert away.hit.tolist() == [False, True, False] and away.travel[1] == 0.0


def test_float32_overshoot_is_caught_and_redone(fine_mesh, monkeypatch, caplog):
    """Open3D distances that overstate by three safety margins: exact results anyway."""
    mesh, _ = fine_mesh
    r = 0.02 * diameter(mesh.vertices)
    expected = approach(mesh.vertices, mesh.faces, np.random.default_rng(6), 30, r)
    true_distance = fingertip._Mesh.o3d_distance
    excess = 3 * fingertip.ADVANCE_MARGIN * (diameter(mesh.vertices) + r)
    monkeypatch.setattr(fingertip._Mesh, "o3d_distance", lambda self, p: true_distance(self, p) + excess)
    got = approach(mesh.vertices, mesh.faces, np.random.default_rng(6), 30, r)
    assert "overshot" in caplog.text
    assert np.allclose(got.centres, expected.centres, atol=1e-12, rtol=0)
    assert np.array_equal(got.features, expected.features)


def test_degenerate_faces_are_ignored(fine_mesh):
    mesh, _ = fine_mesh
    f = mesh.faces
    extra = np.array([[f[0, 0], f[0, 0], f[0, 1]], [f[5, 0], f[5, 1], f[5, 1]]])
    faces = np.vstack([f, extra])
    r = 0.02 * diameter(mesh.vertices)
    clean = approach(mesh.vertices, f, np.random.default_rng(4), 50, r)
    dirty = approach(mesh.vertices, faces, np.random.default_rng(4), 50, r)
    assert np.allclose(clean.points, dirty.points, atol=1e-12) and np.allclose(clean.normals, dirty.normals)
    assert np.all(dirty.facets < len(f))


def test_same_seed_same_contacts(fine_mesh):
    mesh, _ = fine_mesh
    a, b = (approach(mesh.vertices, mesh.faces, np.random.default_rng(8), 20, 0.05) for _ in range(2))
    assert np.array_equal(a.points, b.points) and np.array_equal(a.features, b.features)


BOX = trimesh.creation.box()
GOOD = dict(vertices=BOX.vertices, faces=BOX.faces, starts=[[2.0, 0, 0]], directions=[[-1.0, 0, 0]], radius=0.1)


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(radius=-0.1), "radius"),
        (dict(radius=np.nan), "radius"),
        (dict(starts=[[2.0, 0.0]]), "starts"),
        (dict(starts=[[np.inf, 0, 0]]), "starts[0]"),
        (dict(directions=[[0.0, 0, 0]]), "directions[0]"),
        (dict(directions=[[-1.0, 0, 0], [1.0, 0, 0]]), "directions"),
        (dict(vertices=BOX.vertices[:, :2]), "vertices"),
        (dict(faces=BOX.faces + 100), "faces"),
        (dict(faces=BOX.faces.astype(float)), "faces"),
        (dict(max_travel=0.0), "max_travel"),
        (dict(starts=[[0.55, 0, 0]]), "starts[0]"),
        (dict(starts=[[0.1, 0, 0]]), "starts[0]"),
    ],
)
def test_sweep_rejects_bad_input(change, message):
    with pytest.raises(ContactPoseError, match=message.replace("[", r"\[").replace("]", r"\]")):
        sweep_spheres(**{**GOOD, **change})


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(cone_deg=90.0), "cone_deg"),
        (dict(cone_deg=-1.0), "cone_deg"),
        (dict(mode="open"), "mode"),
        (dict(rng=0), "rng"),
        (dict(n=-1), "n"),
        (dict(radius=-1.0), "radius"),
        (dict(surface_points=np.zeros((3, 3)), n=2), "n"),
        (dict(standoff=0.0), "standoff"),
    ],
)
def test_approach_rejects_bad_input(change, message):
    kwargs = {**dict(rng=np.random.default_rng(0), n=3, radius=0.1), **change}
    with pytest.raises(ContactPoseError, match=message):
        approach(BOX.vertices, BOX.faces, **kwargs)


@pytest.mark.parametrize("radius_rel", [0.0, 0.02, 0.05])
def test_swept_free_points_lie_outside_the_object_along_each_path(radius_rel):
    """The free space the fingers swept (the peers' free points): every point outside the
    closed mesh by trimesh's signed distance; the centres on each finger's path from its start,
    a spacing apart, up to its touch (a ray: one spacing short of it)."""
    mesh = jittered_icosphere(seed=3)
    D = diameter(mesh.vertices)
    touch = approach(mesh.vertices, mesh.faces, np.random.default_rng(2), 4, radius_rel * D)
    spacing = 0.02 * D
    points = fingertip.swept_free_points(touch, spacing)
    assert trimesh.proximity.signed_distance(mesh, points).max() < 0  # positive inside
    per_finger = [np.floor((t - (spacing if radius_rel == 0 else 0)) / spacing) + 2 for t in touch.travel]
    centres = points[:int(np.sum(per_finger))]
    assert len(points) == len(centres) * (1 if radius_rel == 0 else 7)
    first = 0
    for k, count in enumerate(per_finger):
        along = (centres[first:first + int(count)] - touch.starts[k]) @ touch.directions[k]
        off = centres[first:first + int(count)] - touch.starts[k] - along[:, None] * touch.directions[k]
        assert np.allclose(off, 0, atol=1e-12) and along.min() == 0
        assert along.max() == pytest.approx(touch.travel[k] - (spacing if radius_rel == 0 else 0), abs=1e-12)
        first += int(count)
