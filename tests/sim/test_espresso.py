"""The espresso experiment's quick run, and `build-model` on a point cloud.

The quick experiment (20k -> 1,000 facets, 6 grasps) takes about 25 s on two busy
cores; the cloud tests use a small banana scan (about 1,400 points).
"""

import csv
import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

o3d = pytest.importorskip("open3d")

from contactpose.cli import main  # noqa: E402
from contactpose.model.object_model import ObjectModel  # noqa: E402
from contactpose.scan.reconstruct import is_cloud_file, ply_face_count, surface_agreement  # noqa: E402
from contactpose.sim import objects  # noqa: E402
from contactpose.sim.range_scanner import scan  # noqa: E402

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "espresso.py"


def _experiment():
    spec = importlib.util.spec_from_file_location("espresso_experiment", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def banana_cloud():
    """(points, normals) of a simulated scan of banana512: about 1,400 points."""
    return scan(objects.load("banana512"), np.random.default_rng(0), resolution=48)


def _write_ply_cloud(path, points, normals):
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    assert o3d.io.write_point_cloud(str(path), pcd)
    return path


# ------------------------------------------------------------------ experiment


def test_espresso_quick_run_writes_outputs_with_finite_errors(tmp_path):
    experiment = _experiment()
    assert experiment.main(["--quick", "--out", str(tmp_path)]) == 0
    for name in ("espresso1000.ply", "espresso_true.ply", "grasps.csv", "summary.json", "config.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert (tmp_path / "espresso.png").stat().st_size > 5000
    reduced = trimesh.load(tmp_path / "espresso1000.ply", process=False)
    assert abs(len(reduced.faces) - 1000) <= 50
    with open(tmp_path / "grasps.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 6
    posed = [r for r in rows if r["status"] != "no_hypothesis"]
    assert posed, "no grasp found a hypothesis"
    for r in posed:
        assert math.isfinite(float(r["rot_err_deg"])) and math.isfinite(float(r["trans_err_mm"]))
        assert float(r["model_gap_max_mm"]) <= 2.0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["grasps"] == 6 and 0.0 <= summary["success_rate"] <= 1.0
    assert math.isfinite(summary["rot_err_deg"]["median"]) and math.isfinite(summary["trans_err_mm"]["max"])
    assert summary["model_error"] == pytest.approx(summary["scan_report"]["distance_p95"])
    # the figure is redrawn from the CSV alone
    (tmp_path / "espresso.png").unlink()
    assert experiment.main(["--plot-only", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "espresso.png").exists()


def test_exterior_mask_drops_surfaces_inside_other_parts():
    from contactpose.sim.espresso import SIZE, espresso_parts

    parts = espresso_parts()
    scale = SIZE / trimesh.util.concatenate(list(parts.values())).extents.max()
    (x0, y0, _), (x1, y1, z1) = parts["head"].bounds * scale
    _, _, column_top = parts["column"].bounds[1] * scale
    centre = [(x0 + x1) / 2, (y0 + y1) / 2]
    points = np.array([[*centre, z1],            # the head's top face: outside
                       [*centre, column_top],    # the column's top face, inside the head
                       [*centre, 0.1]])          # deep inside the column
    up = np.tile([0.0, 0.0, 1.0], (3, 1))
    assert _experiment().exterior_mask(points, up).tolist() == [True, False, False]


# ------------------------------------------------------------- cloud detection


def test_is_cloud_file_by_suffix_and_ply_faces(tmp_path, banana_cloud):
    points, normals = banana_cloud
    cloud_ply = _write_ply_cloud(tmp_path / "cloud.ply", points, normals)
    mesh_ply = tmp_path / "mesh.ply"
    objects.load("banana").export(mesh_ply)
    np.save(tmp_path / "cloud.npy", points)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    assert o3d.io.write_point_cloud(str(tmp_path / "cloud.pcd"), pcd)
    assert is_cloud_file(cloud_ply) and ply_face_count(cloud_ply) == 0
    assert not is_cloud_file(mesh_ply) and ply_face_count(mesh_ply) == 53
    assert is_cloud_file(tmp_path / "cloud.npy") and is_cloud_file(tmp_path / "cloud.pcd")
    assert not is_cloud_file(tmp_path / "missing.ply") and not is_cloud_file("banana")
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"not a ply file")
    assert ply_face_count(garbage) is None and not is_cloud_file(garbage)  # the mesh loader reports it
    ascii_cloud = tmp_path / "ascii.ply"
    assert o3d.io.write_point_cloud(str(ascii_cloud), pcd, write_ascii=True)
    assert is_cloud_file(ascii_cloud)


def test_build_model_from_a_cloud_scans_first(tmp_path, capsys, banana_cloud):
    cloud = _write_ply_cloud(tmp_path / "banana_scan.ply", *banana_cloud)
    out, mesh_out = tmp_path / "m.npz", tmp_path / "rec.ply"
    assert main(["build-model", str(cloud), "-o", str(out), "--scan-faces", "200", "--save-mesh", str(mesh_out)]) == 0
    text = capsys.readouterr().out
    assert "cloud -> mesh distance" in text and "facets: 200 (" in text and "build time" in text
    model = ObjectModel.load(out)
    rec = trimesh.load(mesh_out, process=False)
    assert model.num_facets == len(rec.faces) == 200
    assert np.allclose(model.vertices, rec.vertices, atol=1e-6)


def test_build_model_from_npy_cloud_default_output_name(tmp_path, capsys, monkeypatch, banana_cloud):
    np.save(tmp_path / "scan.npy", np.hstack(banana_cloud))
    monkeypatch.chdir(tmp_path)
    assert main(["build-model", "scan.npy", "--scan-faces", "150", "--scan-method", "poisson"]) == 0
    assert ObjectModel.load(tmp_path / "scan.npz").num_facets == 150


def test_build_model_bad_cloud_and_scan_options_on_a_mesh(tmp_path, capsys):
    np.save(tmp_path / "one.npy", np.zeros((1, 3)))
    assert main(["build-model", str(tmp_path / "one.npy"), "-o", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err
    assert "1 point" in err and err.count("\n") == 1
    assert not (tmp_path / "x.npz").exists()
    assert main(["build-model", "banana", "-o", str(tmp_path / "b.npz"), "--scan-faces", "100"]) == 0
    assert "not a point cloud file; ignoring --scan-faces" in capsys.readouterr().err
    assert ObjectModel.load(tmp_path / "b.npz").num_facets == 53


# ------------------------------------------------------------ surface agreement


def test_surface_agreement_matches_trimesh_closest_point():
    """Reference twin: trimesh.proximity.closest_point gives the same gaps and facets."""
    sphere = objects.load("sphere")
    rng = np.random.default_rng(4)
    points = rng.normal(size=(300, 3))
    points *= rng.uniform(0.03, 0.07, (300, 1)) / np.linalg.norm(points, axis=1, keepdims=True)
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    gap, angle, facet = surface_agreement(points, normals, sphere)
    _, ref_gap, ref_facet = trimesh.proximity.closest_point(sphere, points)
    assert np.allclose(gap, ref_gap, atol=1e-6)
    want = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", sphere.face_normals[ref_facet], normals), -1, 1)))
    same = facet == ref_facet  # ties on edges may pick either neighbour
    assert same.mean() > 0.9 and np.allclose(angle[same], want[same], atol=1e-3)
    assert angle.max() < 15.0  # a 320-facet sphere: facet normals within ~10 deg of radial
