"""Tests for the scan pipeline (contactpose.scan.reconstruct), the simulated scanner and the espresso object.

Small clouds only (a few thousand points): the whole file runs in well under a
minute on two cores. The espresso-scale run is marked slow.
"""

import argparse
import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.distance import pdist

o3d = pytest.importorskip("open3d")

from contactpose.cli import scan as cli_scan  # noqa: E402
from contactpose.cli.scan import options_from_args  # noqa: E402
from contactpose.errors import ContactPoseError, ScanError  # noqa: E402
from contactpose.scan import reconstruct as scanmod  # noqa: E402
from contactpose.scan.reconstruct import (  # noqa: E402
    STEPS,
    ScanOptions,
    check_cloud,
    cloud_to_mesh_distance,
    crop_mask,
    load_cloud,
    orient_outward,
    scan_to_mesh,
    write_mesh,
)
from contactpose.sim.espresso import SIZE, espresso_machine, espresso_parts  # noqa: E402
from contactpose.sim.range_scanner import scan, viewpoints  # noqa: E402

#: Acceptance: 95th-percentile distance to the true surface, fraction of the diameter.
P95_MAX = 0.01
#: Acceptance: facet count within this fraction of the target.
FACES_REL = 0.05
#: Simulated-scan rays per image side: about 6,000-11,000 points per object.
RES = 64


def _banana() -> trimesh.Trimesh:
    """The project's 512-facet banana, or a curved capsule-ended tube standing in for it."""
    try:
        from contactpose.sim import objects
        return objects.load("banana512")
    except (ImportError, ContactPoseError, AttributeError):
        pass
    # a tube along a circular arc, radius tapering to the ends, closed by fans
    u = np.linspace(0.0, 1.0, 40)
    angle = (u - 0.5) * 1.2
    centre = np.column_stack([0.15 * np.sin(angle), np.zeros_like(u), 0.15 * (1 - np.cos(angle))])
    radius = 0.004 + 0.016 * np.sin(np.pi * u) ** 0.5
    phi = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    tangent = np.gradient(centre, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    side = np.array([0.0, 1.0, 0.0])
    normal = np.cross(tangent, side)
    ring = (centre[:, None] + radius[:, None, None] * (np.cos(phi)[None, :, None] * side
                                                      + np.sin(phi)[None, :, None] * normal[:, None]))
    vertices = np.vstack([ring.reshape(-1, 3), centre[[0, -1]]])
    n, m = len(u), len(phi)
    faces = []
    for i in range(n - 1):
        for j in range(m):
            a, b = i * m + j, i * m + (j + 1) % m
            faces += [[a, b, a + m], [b, b + m, a + m]]
    for j in range(m):
        faces += [[n * m, (j + 1) % m, j], [n * m + 1, (n - 1) * m + j, (n - 1) * m + (j + 1) % m]]
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


SHAPES = {
    "sphere": lambda: trimesh.creation.icosphere(subdivisions=4, radius=0.05),
    "box": lambda: trimesh.creation.box(extents=(0.10, 0.06, 0.04)),
    "banana": _banana,
}


def _diameter(mesh) -> float:
    """Largest distance between two vertices: the diameter of a polyhedron."""
    return float(pdist(mesh.vertices).max())


@pytest.fixture(scope="module")
def sphere_run():
    """One reconstructed noisy sphere scan, shared by the report tests."""
    truth = SHAPES["sphere"]()
    points, normals = scan(truth, np.random.default_rng(1), resolution=RES)
    result = scan_to_mesh((points, normals), ScanOptions(faces=800))
    return truth, points, result


# ---------------------------------------------------------------- acceptance


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_known_shape_reconstruction(name):
    """0.5 % range noise: p95 distance to the true surface <= 1 % of the diameter, facets within 5 %."""
    truth = SHAPES[name]()
    diameter = _diameter(truth)
    points, normals = scan(truth, np.random.default_rng(0), range_noise=0.005, resolution=RES)
    target = 1000
    result = scan_to_mesh((points, normals), ScanOptions(faces=target))
    mesh = result.mesh

    assert abs(len(mesh.faces) - target) <= FACES_REL * target
    # reconstructed surface -> true surface
    samples = trimesh.sample.sample_surface(mesh, 20_000, seed=0)[0]
    to_truth, _ = cloud_to_mesh_distance(samples, truth)
    assert np.percentile(to_truth, 95) <= P95_MAX * diameter
    # seen true surface -> reconstruction (catches holes): noise-free hits of the same rays
    clean, _ = scan(truth, np.random.default_rng(0), range_noise=0.0, resolution=RES)
    to_mesh, _ = cloud_to_mesh_distance(clean, mesh)
    assert np.percentile(to_mesh, 95) <= P95_MAX * diameter
    # outward: positive volume when closed, else normals agree with the scan's
    if mesh.is_watertight:
        assert mesh.volume > 0
    assert result.report.n_faces == len(mesh.faces)


def test_distance_matches_trimesh_reference():
    """Open3D ray-scene distance agrees with trimesh's exact closest point (reference twin)."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    query = np.random.default_rng(3).uniform(-2, 2, (300, 3))
    fast, n = cloud_to_mesh_distance(query, mesh)
    _, slow, _ = trimesh.proximity.closest_point(mesh, query)
    assert n == 300
    np.testing.assert_allclose(fast, slow, atol=1e-5)


def test_distance_subsamples_to_max_points():
    mesh = trimesh.creation.box()
    dist, n = cloud_to_mesh_distance(np.zeros((1000, 3)), mesh, max_points=100)
    assert n == 100 and len(dist) == 100
    np.testing.assert_allclose(dist, 0.5, atol=1e-6)


# ---------------------------------------------------------------- bad clouds


def _planar_cloud(n=500):
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 1, n), rng.uniform(0, 1, n), np.zeros(n)])
    return pts + rng.normal(0, 1e-5, pts.shape)


@pytest.mark.parametrize("cloud, words", [
    (np.zeros((0, 3)), ["0 points", "at least 50"]),
    (np.full((200, 3), np.nan), ["200 NaN or infinite", "0 points", "at least 50"]),
    (np.array([[0.1, 0.2, 0.3]]), ["1 point;", "at least 50"]),
    (np.vstack([np.full((300, 3), np.inf), np.random.default_rng(0).normal(size=(10, 3))]),
     ["10 points", "at least 50"]),
    (_planar_cloud(), ["planar", "ratio of at least 0.01"]),
    (np.outer(np.linspace(0, 1, 100), [1.0, 2.0, 3.0]), ["linear"]),
    (np.ones((100, 3)), ["coincide"]),
    (np.zeros((10, 4)), ["shape (10, 4)", "(n, 3)"]),
], ids=["empty", "all-nan", "single", "few-finite", "planar", "linear", "coincident", "bad-shape"])
def test_bad_cloud_raises_clear_error(cloud, words):
    with pytest.raises(ScanError) as info:
        scan_to_mesh(cloud)
    for w in words:
        assert w in str(info.value)


def test_bad_cloud_writes_no_file(tmp_path):
    cloud = tmp_path / "empty.npy"
    np.save(cloud, np.zeros((0, 3)))
    out = tmp_path / "out.ply"
    args = _parse(["scan", str(cloud), "-o", str(out)])
    with pytest.raises(ScanError, match="0 points"):
        args.func(args)
    assert not out.exists()


def test_empty_reconstruction_raises(monkeypatch):
    monkeypatch.setattr(scanmod, "reconstruct", lambda *a, **k: o3d.geometry.TriangleMesh())
    points, normals = scan(trimesh.creation.icosphere(2), np.random.default_rng(0), resolution=32)
    with pytest.raises(ScanError, match="left 0 facets"):
        scan_to_mesh((points, normals))


def test_write_mesh_refuses_empty(tmp_path):
    with pytest.raises(ScanError, match="empty mesh"):
        write_mesh(trimesh.Trimesh(), tmp_path / "x.ply")
    assert not (tmp_path / "x.ply").exists()


@pytest.mark.parametrize("options, words", [
    (ScanOptions(method="marching"), ["method", "poisson"]),
    (ScanOptions(faces=2), ["faces is 2"]),
    (ScanOptions(crop=(0, 0, 0, -1, 1, 1)), ["crop box", "xmin < xmax"]),
    (ScanOptions(crop=(1, 2, 3)), ["crop has shape (3,)"]),
    (ScanOptions(crop=(5, 5, 5, 6, 6, 6)), ["after cropping", "0 points"]),
])
def test_bad_options_raise(sphere_run, options, words):
    _, points, _ = sphere_run
    with pytest.raises(ScanError) as info:
        scan_to_mesh(points, options)
    for w in words:
        assert w in str(info.value)


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(ScanError, match="does not exist"):
        load_cloud(tmp_path / "nope.ply")
    (tmp_path / "cloud.txt").write_text("1 2 3\n")
    with pytest.raises(ScanError, match="suffix '.txt'"):
        load_cloud(tmp_path / "cloud.txt")


def test_check_cloud_accepts_a_solid():
    check_cloud(np.random.default_rng(0).normal(size=(100, 3)))


# ---------------------------------------------------------------- loading


def test_npy_loading_3_and_6_columns(tmp_path):
    pts = np.random.default_rng(0).normal(size=(100, 3))
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    np.save(tmp_path / "p3.npy", pts)
    np.save(tmp_path / "p6.npy", np.hstack([pts, nrm]))
    p, n = load_cloud(tmp_path / "p3.npy")
    assert n is None and np.array_equal(p, pts)
    p, n = load_cloud(str(tmp_path / "p6.npy"))
    assert np.array_equal(p, pts) and np.array_equal(n, nrm)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz"])
def test_open3d_formats_round_trip(tmp_path, suffix):
    pts = np.random.default_rng(0).normal(size=(100, 3))
    path = tmp_path / ("cloud" + suffix)
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    p, _ = load_cloud(path)
    np.testing.assert_allclose(p, pts, atol=1e-5)


def test_npy_without_normals_is_meshed_outward(tmp_path):
    """(n, 3) file: normals estimated and oriented by tangent-plane propagation; the mesh is outward."""
    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    points, _ = scan(truth, np.random.default_rng(0), resolution=48)
    np.save(tmp_path / "sphere.npy", points)
    result = scan_to_mesh(tmp_path / "sphere.npy", ScanOptions(faces=300))
    assert result.mesh.volume > 0
    assert result.report.n_input == len(points)
    assert abs(result.mesh.volume / truth.volume - 1) < 0.05


def test_nan_rows_are_dropped(sphere_run):
    truth, points, _ = sphere_run
    points = points[::2]
    noisy = np.vstack([points, np.full((50, 3), np.nan)])
    result = scan_to_mesh(noisy, ScanOptions(faces=300))
    assert result.report.n_input == len(points) + 50
    assert result.report.n_finite == len(points)


# ---------------------------------------------------------------- crop, orientation


def test_crop_keeps_the_object_and_drops_the_table():
    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    points, normals = scan(truth, np.random.default_rng(0), resolution=48)
    rng = np.random.default_rng(1)
    # a table slab under the object, outside the crop box
    table = np.column_stack([rng.uniform(-0.2, 0.2, 3000), rng.uniform(-0.2, 0.2, 3000),
                             rng.uniform(-0.09, -0.08, 3000)])
    cloud = np.vstack([points, table])
    box = (-0.07, -0.07, -0.07, 0.07, 0.07, 0.07)
    result = scan_to_mesh(cloud, ScanOptions(crop=box, faces=400))
    assert result.report.n_cropped == len(points)
    assert np.all(result.mesh.bounds[0] > -0.07) and np.all(result.mesh.bounds[1] < 0.07)


def test_crop_mask_union_and_oriented_box():
    pts = np.array([[0.0, 0, 0], [2.0, 0, 0], [5.0, 0, 0]])
    two = crop_mask(pts, [(-1, -1, -1, 1, 1, 1), (1.5, -1, -1, 2.5, 1, 1)])
    assert two.tolist() == [True, True, False]
    obb = o3d.geometry.OrientedBoundingBox(np.array([5.0, 0, 0]), np.eye(3), np.ones(3))
    assert crop_mask(pts, obb).tolist() == [False, False, True]


def test_orient_outward_flips_inverted_closed_mesh():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.invert()
    fixed, flipped = orient_outward(mesh, mesh.vertices, mesh.vertex_normals)
    assert flipped and fixed.volume > 0


def test_orient_outward_open_mesh_uses_cloud_normals():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    upper = sphere.submesh([sphere.triangles_center[:, 2] > 0], append=True)
    outward = upper.vertex_normals.copy()
    upper.invert()
    fixed, flipped = orient_outward(upper, upper.vertices, outward)
    assert flipped
    assert np.einsum("ij,ij->", fixed.vertex_normals, outward) > 0


# ---------------------------------------------------------------- report, CLI


def test_report_fields(sphere_run):
    _, points, result = sphere_run
    rep = result.report
    assert rep.n_input == rep.n_finite == rep.n_cropped == len(points)
    assert rep.n_input >= rep.n_filtered >= rep.n_downsampled > 0
    assert rep.n_faces == len(result.mesh.faces) and rep.n_vertices == len(result.mesh.vertices)
    assert rep.n_faces_reconstructed >= rep.n_faces
    assert rep.watertight == result.mesh.is_watertight
    assert 0 <= rep.distance_mean <= rep.distance_p95 <= rep.distance_max
    assert rep.distance_p95_pct == pytest.approx(100 * rep.distance_p95 / rep.diameter)
    assert rep.distance_points == len(points)
    assert set(rep.timings) == set(STEPS) and rep.seconds > 0
    for key in ("voxel", "spacing", "depth", "normal_radius", "outlier_radius"):
        assert rep.parameters[key] > 0
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["n_faces"] == rep.n_faces and "seconds" in d
    text = rep.format()
    assert f"{rep.n_faces} facets" in text and "p95" in text and "%" in text


def test_progress_is_silent_off_terminal(sphere_run, capsys):
    _, points, _ = sphere_run
    scan_to_mesh(points[::2], ScanOptions(faces=200, normals="estimate"))
    assert capsys.readouterr().err == ""


def _parse(argv):
    parser = argparse.ArgumentParser(prog="contactpose")
    sub = parser.add_subparsers(dest="command")
    cli_scan.register(sub)
    return parser.parse_args(argv)


def test_cli_scan_writes_mesh_and_prints_report(tmp_path, capsys):
    truth = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    points, normals = scan(truth, np.random.default_rng(0), resolution=48)
    np.save(tmp_path / "cloud.npy", np.hstack([points, normals]))
    out, js = tmp_path / "mesh.ply", tmp_path / "report.json"
    args = _parse(["scan", str(tmp_path / "cloud.npy"), "-o", str(out), "--faces", "300",
                   "--method", "poisson", "--crop", "-1", "-1", "-1", "1", "1", "1",
                   "--report-json", str(js)])
    assert args.func is cli_scan.run
    assert cli_scan.run(args) == 0
    mesh = trimesh.load(out)
    assert abs(len(mesh.faces) - 300) <= 15
    assert "facets" in capsys.readouterr().out
    assert json.loads(js.read_text())["n_faces"] == len(mesh.faces)


def test_add_scan_options_prefix_and_defaults():
    parser = argparse.ArgumentParser()
    cli_scan.add_scan_options(parser, prefix="scan-")
    args = parser.parse_args(["--scan-faces", "50", "--scan-voxel", "0.01", "--scan-method", "bpa",
                              "--scan-crop", "0", "0", "0", "1", "1", "1",
                              "--scan-crop", "2", "0", "0", "3", "1", "1"])
    opt = options_from_args(args)
    assert (opt.faces, opt.voxel, opt.method) == (50, 0.01, "bpa")
    assert np.asarray(opt.crop).shape == (2, 6)
    assert options_from_args(parser.parse_args([])) == ScanOptions()


def test_ball_pivoting_method(sphere_run):
    truth, points, _ = sphere_run
    result = scan_to_mesh(points, ScanOptions(method="bpa"))
    assert len(result.mesh.faces) > 100
    assert len(result.report.parameters["bpa_radii"]) == 3


# ---------------------------------------------------------------- simulated scanner


def test_scanner_noise_is_relative_to_range():
    """range_noise=0.005: the range error has std 0.5 % of the range (tolerance band)."""
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    eye = np.array([[0.0, -0.3, 0.0]])
    clean, _ = scan(mesh, np.random.default_rng(0), eyes=eye, range_noise=0.0, resolution=96)
    noisy, _ = scan(mesh, np.random.default_rng(0), eyes=eye, range_noise=0.005, resolution=96)
    rng_clean = np.linalg.norm(clean - eye, axis=1)
    rel = (np.linalg.norm(noisy - eye, axis=1) - rng_clean) / rng_clean
    assert len(rel) > 1000
    assert abs(rel.mean()) < 0.0005
    assert 0.0045 < rel.std() < 0.0055


def test_scanner_normals_face_the_sensor_and_are_deterministic():
    mesh = trimesh.creation.box(extents=(0.1, 0.06, 0.04))
    eyes = viewpoints(mesh, 6)
    p1, n1 = scan(mesh, np.random.default_rng(5), eyes=eyes, resolution=32)
    p2, n2 = scan(mesh, np.random.default_rng(5), eyes=eyes, resolution=32)
    assert np.array_equal(p1, p2) and np.array_equal(n1, n2)
    np.testing.assert_allclose(np.linalg.norm(n1, axis=1), 1.0, atol=1e-5)
    # a box's outward normals point away from its centre; sensor-facing ones too
    assert np.all(np.einsum("ij,ij->i", n1, p1) > 0)


def test_scanner_outliers_and_bad_input():
    mesh = trimesh.creation.icosphere(subdivisions=2)
    p, _ = scan(mesh, np.random.default_rng(0), resolution=24)
    q, _ = scan(mesh, np.random.default_rng(0), resolution=24, outlier_fraction=0.1)
    assert len(q) - len(p) == round(0.1 / 0.9 * len(p))
    with pytest.raises(ContactPoseError, match="numpy.random.Generator"):
        scan(mesh, 0)
    with pytest.raises(ContactPoseError, match="range_noise"):
        scan(mesh, np.random.default_rng(0), range_noise=-1)


# ---------------------------------------------------------------- espresso object


def test_espresso_parts_are_closed_and_outward():
    for name, part in espresso_parts().items():
        assert part.is_watertight, name
        assert part.volume > 0, name


def test_espresso_machine_size_count_and_determinism():
    a = espresso_machine(80_000)
    b = espresso_machine(80_000)
    assert abs(len(a.faces) - 80_000) <= 0.03 * 80_000
    assert a.extents.max() == pytest.approx(SIZE)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert a.is_winding_consistent and a.volume > 0
    with pytest.raises(ContactPoseError, match="target_faces"):
        espresso_machine(10)


@pytest.mark.slow
def test_espresso_scale_pipeline():
    """About 80k-facet object -> scan -> reconstruct -> 6,767 facets in at most 60 s."""
    truth = espresso_machine(80_000)
    points, normals = scan(truth, np.random.default_rng(0), n_views=12, resolution=160)
    result = scan_to_mesh((points, normals), ScanOptions(faces=6767))
    assert abs(result.report.n_faces - 6767) <= FACES_REL * 6767
    assert result.report.seconds <= 60
    samples = trimesh.sample.sample_surface(result.mesh, 50_000, seed=0)[0]
    d, _ = cloud_to_mesh_distance(samples, truth)
    assert np.percentile(d, 95) <= P95_MAX * np.linalg.norm(truth.extents)
