"""Scan preprocessing: from a point cloud to an outward-wound contact mesh.

Every step is Open3D and headless, one short function each:

    load -> crop -> outliers -> downsample -> normals -> reconstruct
         -> decimate -> clean -> orient -> distance report

Every parameter has a default scaled to the cloud: its *diameter* (the
bounding-box diagonal of the cloud after outlier removal) and its mean
nearest-neighbour *spacing*. Any of them can be set in :class:`ScanOptions`.
The defaults and the reasons for them are in ``research/scan.md``.

Public API: :func:`scan_to_mesh` (returns a :class:`ScanResult` with the mesh and
a :class:`ScanReport`), :class:`ScanOptions`, :func:`load_cloud`,
:func:`write_mesh`, :func:`surface_agreement` (a mesh against the true surface) and
:func:`is_cloud_file`. The command line (``contactpose scan``, the scan options of
``build-model``) is :mod:`contactpose.cli.scan`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Iterator, Sequence

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from contactpose import tol
from contactpose.deferred import deferred
from contactpose.errors import ScanError
from contactpose.geometry.raycast import Raycaster
from contactpose.model.memory import check_fits

log = logging.getLogger(__name__)

o3d = deferred("open3d")
trimesh = deferred("trimesh")


__all__ = [
    "ScanOptions", "ScanReport", "ScanResult", "scan_to_mesh", "load_cloud",
    "check_cloud", "write_mesh", "cloud_to_mesh_distance", "surface_agreement",
    "is_cloud_file", "ply_face_count",
]

#: File suffixes read by ``open3d.io.read_point_cloud``; ``.npy`` is read by numpy.
CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts")
#: Suffixes that are always clouds; a ``.ply`` is a cloud when it declares no faces.
CLOUD_ONLY_SUFFIXES = (".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts", ".npy")
#: Bytes read to find the end of a PLY header.
PLY_HEADER_MAX = 1 << 16
#: Reconstruction methods.
METHODS = ("poisson", "bpa")
#: Peak bytes per input point of the steps before reconstruction (Open3D copies of the cloud
#: through cropping, outlier removal and downsampling, and the distance report), and per
#: point that reaches the reconstruction, by method. Measured peak RSS over the import
#: baseline: 166-170 B/pt for 0.8-3.2 M points; Poisson on 200 k points 1.9 (depth 8) to
#: 4.3 kB/pt (depth 10), ball pivoting 2.0 kB/pt; rounded up.
CLOUD_BYTES_PER_POINT = 200
RECONSTRUCT_BYTES_PER_POINT = {"poisson": 5000, "bpa": 2500}
#: Ways to get normals: estimate and orient by given normals when present ("auto"),
#: use the given ones as they are ("given"), or ignore them ("estimate").
NORMAL_MODES = ("auto", "given", "estimate")
#: Pipeline steps, in order; each has a timing in the report.
STEPS = ("load", "crop", "outliers", "downsample", "normals", "reconstruct",
         "decimate", "clean", "orient", "distance")


@dataclass
class ScanOptions:
    """Parameters of :func:`scan_to_mesh`; ``None`` means "scaled to the cloud".

    Lengths are in the cloud's units. "diameter" is the bounding-box diagonal
    of the cloud after outlier removal, "spacing" its mean nearest-neighbour
    distance after downsampling.
    """

    #: Keep only points inside: ``(xmin, ymin, zmin, xmax, ymax, zmax)``, a
    #: ``(k, 6)`` list of such boxes (their union is kept), or Open3D
    #: ``AxisAlignedBoundingBox`` / ``OrientedBoundingBox`` objects (one or a list).
    crop: Any = None
    #: Fewest finite points a cloud may have, before and after each filter.
    min_points: int = 50
    #: A cloud whose smallest principal standard deviation is below this
    #: fraction of its largest is planar (or linear) and is refused.
    planar_ratio: float = 0.01
    #: Radius outlier removal: a point needs ``outlier_min_neighbors`` others
    #: within ``outlier_radius`` (default ``outlier_radius_spacings`` times the
    #: 90th percentile of the nearest-neighbour distance, so sparse but genuine
    #: regions pass); ``outlier_min_neighbors=0`` disables it.
    outlier_radius: float | None = None
    outlier_radius_spacings: float = 4.0
    outlier_min_neighbors: int = 5
    #: Statistical outlier removal (off by default: on scans of uneven density it
    #: removes the sparse but genuine regions, and the mesh gets holes there):
    #: neighbours looked at, and the cut in standard deviations; 0 disables it.
    outlier_neighbors: int = 20
    outlier_std: float = 0.0
    #: Voxel edge for downsampling; default ``diameter * voxel_rel``; 0 disables.
    voxel: float | None = None
    voxel_rel: float = 1.0 / 150.0
    #: One of NORMAL_MODES.
    normals: str = "auto"
    #: Normal estimation neighbourhood: radius (default ``3 * max(voxel, spacing)``)
    #: and the most neighbours used.
    normal_radius: float | None = None
    normal_max_nn: int = 30
    #: Neighbours for consistent tangent-plane orientation (no given normals).
    orient_k: int = 15
    #: Sensor position (3,) to orient normals towards, when known.
    camera_location: Sequence[float] | None = None
    #: One of METHODS.
    method: str = "poisson"
    #: Poisson octree depth; default: finest cell about ``max(voxel, spacing)`` (clamped to 5..10).
    depth: int | None = None
    #: Poisson's minimum samples per octree node: above 1.5 it averages more
    #: noise and runs faster.
    samples_per_node: float = 2.0
    #: Poisson trimming: drop vertices whose density is below this quantile *and*
    #: that lie farther than ``trim_distance`` from the cloud (default two cells,
    #: a cell being ``max(voxel, spacing)``), so only unsupported surface goes.
    density_quantile: float = 0.05
    trim_distance: float | None = None
    #: Ball-pivoting radii; default ``spacing * (1, 2, 4)``.
    bpa_radii: Sequence[float] | None = None
    #: Target facet count for quadric decimation; ``None`` keeps the reconstruction.
    faces: int | None = None
    #: Connected pieces with fewer than this fraction of the facets are dropped.
    min_component: float = 0.01
    #: At most this many input points are used for the distance report.
    report_max_points: int = 200_000


@dataclass
class ScanReport:
    """What :func:`scan_to_mesh` did, and how close the mesh is to the cloud.

    The distances are from the finite, cropped input points (before outlier
    removal) to the output mesh; the ``*_pct`` ones are in % of ``diameter``.
    """

    n_input: int
    n_finite: int
    n_cropped: int
    n_filtered: int
    n_downsampled: int
    n_faces_reconstructed: int
    n_faces: int
    n_vertices: int
    watertight: bool
    flipped: bool
    method: str
    diameter: float
    distance_points: int
    distance_mean: float
    distance_p95: float
    distance_max: float
    distance_mean_pct: float
    distance_p95_pct: float
    distance_max_pct: float
    parameters: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        """Total time of all steps."""
        return float(sum(self.timings.values()))

    def to_dict(self) -> dict:
        """Plain JSON-serialisable dict of every field plus ``seconds``."""
        out = dataclasses.asdict(self)
        out["seconds"] = self.seconds
        return out

    def format(self) -> str:
        """Human-readable multi-line summary, as printed by the CLI."""
        lines = [
            f"points: {self.n_input} read, {self.n_finite} finite, {self.n_cropped} after crop, "
            f"{self.n_filtered} after outlier removal, {self.n_downsampled} after downsampling",
            f"mesh ({self.method}): {self.n_faces_reconstructed} facets reconstructed, "
            f"{self.n_faces} facets and {self.n_vertices} vertices out, "
            f"{'watertight' if self.watertight else 'not watertight'}"
            f"{', orientation flipped to outward' if self.flipped else ''}",
            f"cloud -> mesh distance over {self.distance_points} points "
            f"(diameter {self.diameter:.4g}): mean {self.distance_mean:.3g} "
            f"({self.distance_mean_pct:.2f} %), p95 {self.distance_p95:.3g} "
            f"({self.distance_p95_pct:.2f} %), max {self.distance_max:.3g} "
            f"({self.distance_max_pct:.2f} %)",
            "parameters: " + ", ".join(f"{k}={_fmt(v)}" for k, v in self.parameters.items()),
            "timings: " + ", ".join(f"{k} {v:.2f}s" for k, v in self.timings.items())
            + f"; total {self.seconds:.2f}s",
        ]
        return "\n".join(lines)


@dataclass
class ScanResult:
    """The output of :func:`scan_to_mesh`."""

    #: Cleaned, outward-wound mesh.
    mesh: trimesh.Trimesh
    report: ScanReport


# --------------------------------------------------------------------------- API


def scan_to_mesh(cloud_or_path, options: ScanOptions | None = None, *, progress: bool | None = None) -> ScanResult:
    """Turn a point cloud into a cleaned, outward-wound triangle mesh.

    Parameters
    ----------
    cloud_or_path : path, (n, 3) or (n, 6) float, (points, normals), or open3d PointCloud
      The cloud; a path is read by :func:`load_cloud`.
    options : ScanOptions, optional
      Parameters; defaults scale with the cloud.
    progress : bool, optional
      Show a tqdm bar over the steps; default: only when stderr is a terminal.

    Returns
    -------
    result : ScanResult
      ``result.mesh`` (trimesh.Trimesh) and ``result.report`` (ScanReport).

    Raises
    ------
    ScanError
      The cloud is unreadable, too small, planar, or yields an empty mesh.
    """
    opt = options or ScanOptions()
    _check_options(opt)
    timings: dict[str, float] = {}
    params: dict[str, Any] = {}
    disable = (not sys.stderr.isatty()) if progress is None else not progress
    with tqdm(total=len(STEPS), desc="scan", unit="step", disable=disable, leave=False) as bar:
        step = _stepper(bar, timings)

        with step("load"):
            points, normals, n_input = _load_finite(cloud_or_path, opt)
            n_finite = len(points)
            _check_memory(n_finite, CLOUD_BYTES_PER_POINT, "cleaning", "crop the cloud (--crop) or thin it first")
        with step("crop"):
            if opt.crop is not None:
                points, normals = _take(points, normals, crop_mask(points, opt.crop))
                check_cloud(points, opt.min_points, opt.planar_ratio, what="cloud after cropping")
            n_cropped = len(points)
            measured = points
        with step("outliers"):
            pcd = remove_outliers(_to_pcd(points, normals), opt, params)
            filtered = np.asarray(pcd.points)
            check_cloud(filtered, opt.min_points, opt.planar_ratio, what="cloud after outlier removal")
            diameter = float(np.linalg.norm(filtered.max(axis=0) - filtered.min(axis=0)))
            n_filtered = len(filtered)
        with step("downsample"):
            voxel = diameter * opt.voxel_rel if opt.voxel is None else float(opt.voxel)
            if voxel > 0:
                pcd = pcd.voxel_down_sample(voxel)
            check_cloud(np.asarray(pcd.points), opt.min_points, opt.planar_ratio,
                        what=f"cloud after downsampling to voxel {voxel:.4g}")
            spacing = float(np.mean(pcd.compute_nearest_neighbor_distance()))
            params.update(diameter=diameter, voxel=voxel, spacing=spacing)
        with step("normals"):
            radius = opt.normal_radius or 3.0 * max(voxel, spacing)
            params["normal_radius"] = radius
            pcd = estimate_normals(pcd, radius, opt)
        with step("reconstruct"):
            _check_memory(len(pcd.points), RECONSTRUCT_BYTES_PER_POINT[opt.method], f"{opt.method} reconstruction of",
                          "downsample it more (a larger --voxel) or crop it (--crop)")
            mesh = reconstruct(pcd, opt, voxel, spacing, params)
            mesh = remove_small_components(mesh, opt.min_component)
            mesh = clean_mesh(mesh)
            _check_mesh(mesh, f"{opt.method} reconstruction")
            n_reconstructed = len(mesh.triangles)
        with step("decimate"):
            if opt.faces is not None and len(mesh.triangles) > opt.faces:
                mesh = mesh.simplify_quadric_decimation(int(opt.faces))
        with step("clean"):
            mesh = clean_mesh(mesh)
            _check_mesh(mesh, "cleaning")
            tm = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), process=True)
            tm = drop_degenerate(tm, diameter)
            _check_mesh(tm, "dropping degenerate facets")
        with step("orient"):
            tm, flipped = orient_outward(tm, np.asarray(pcd.points), np.asarray(pcd.normals))
        with step("distance"):
            dist, n_used = cloud_to_mesh_distance(measured, tm, opt.report_max_points)

    counts = dict(n_input=n_input, n_finite=n_finite, n_cropped=n_cropped, n_filtered=n_filtered,
                  n_downsampled=len(pcd.points), n_faces_reconstructed=n_reconstructed)
    report = _make_report(tm, dist, diameter, counts, flipped=flipped, method=opt.method,
                          distance_points=n_used, parameters=params, timings=timings)
    log.info("scan: %d facets, p95 distance %.3g %% of diameter, %.2f s",
             report.n_faces, report.distance_p95_pct, report.seconds)
    return ScanResult(mesh=tm, report=report)


def load_cloud(source) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a point cloud from a file or take it from memory.

    Parameters
    ----------
    source : path, (n, 3) or (n, 6) float, (points, normals) pair, or open3d PointCloud
      Files: PLY, PCD, XYZ (and XYZN, XYZRGB, PTS) via ``open3d.io``; NPY of
      (n, 3) points or (n, 6) points and normals via numpy.

    Returns
    -------
    points : (n, 3) float
      Possibly with non-finite rows; the caller drops them.
    normals : (n, 3) float or None
      The cloud's normals, when it has them.
    """
    if isinstance(source, o3d.geometry.PointCloud):
        points = np.asarray(source.points, dtype=np.float64)
        normals = np.asarray(source.normals, dtype=np.float64) if source.has_normals() else None
        return points.reshape(-1, 3), normals
    if isinstance(source, tuple) and len(source) == 2:
        points, normals = source
        points = _as_rows(points, 3, "cloud points")
        normals = None if normals is None else _as_rows(normals, 3, "cloud normals")
        if normals is not None and len(normals) != len(points):
            raise ScanError(f"cloud has {len(points)} points but {len(normals)} normals; "
                            "expected one normal per point")
        return points, normals
    if isinstance(source, (str, os.PathLike)):
        return _read_cloud_file(os.fspath(source))
    array = np.asanyarray(source, dtype=np.float64)
    return _split_columns(array, "cloud array")


def check_cloud(points: np.ndarray, min_points: int = 50, planar_ratio: float = 0.01, *, what: str = "cloud") -> None:
    """Raise ScanError unless ``points`` can be meshed as a 3-D surface.

    Parameters
    ----------
    points : (n, 3) float
      Finite points.
    min_points : int
      Fewest points accepted.
    planar_ratio : float
      Smallest accepted ratio of the smallest to the largest principal
      standard deviation (PCA); below it the cloud is flat or a line.
    what : str
      How to name the cloud in the message.
    """
    n = len(points)
    if n < min_points:
        noun = "point" if n == 1 else "points"
        raise ScanError(f"{what} has {n} {noun}; need at least {min_points} finite points "
                        "to reconstruct a surface")
    # principal standard deviations, largest first
    sd = np.linalg.svd(points - points.mean(axis=0), compute_uv=False) / math.sqrt(n)
    if sd[0] <= 0.0:
        raise ScanError(f"{what}: all {n} points coincide; need a 3-D cloud")
    ratio = sd[2] / sd[0]
    if ratio < planar_ratio:
        shape = "linear" if sd[1] / sd[0] < planar_ratio else "planar"
        raise ScanError(
            f"{what} is {shape}: its thinnest principal spread is {ratio:.2g} of its largest "
            f"(std {sd[2]:.3g} vs {sd[0]:.3g}); need a 3-D cloud with a ratio of at least "
            f"{planar_ratio:g} to reconstruct a closed surface")


def write_mesh(mesh: trimesh.Trimesh, path) -> None:
    """Write a non-empty mesh; the format follows the suffix (PLY, STL, OBJ, OFF, GLB)."""
    if mesh is None or len(mesh.faces) == 0:
        raise ScanError(f"refusing to write an empty mesh to {path}; expected at least one facet")
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ScanError(f"output folder {folder} does not exist; create it first")
    try:
        mesh.export(path)
    except ValueError as exc:  # unknown suffix
        raise ScanError(f"cannot write mesh to {path}: {exc}; use .ply, .stl, .obj or .off") from exc


def cloud_to_mesh_distance(points: np.ndarray, mesh: trimesh.Trimesh,
                           max_points: int = 200_000) -> tuple[np.ndarray, int]:
    """Unsigned distance from points to a mesh surface (Open3D ray-casting scene).

    Parameters
    ----------
    points : (n, 3) float
    mesh : trimesh.Trimesh
    max_points : int
      Use at most this many points, an even stride through the cloud.

    Returns
    -------
    distance : (m,) float
      m = min(n, max_points).
    m : int
    """
    stride = max(1, math.ceil(len(points) / max_points))
    query = np.ascontiguousarray(points[::stride], dtype=np.float32)
    dist = Raycaster.of_mesh(mesh).distance(query)
    return dist, len(query)


def surface_agreement(points: np.ndarray, normals: np.ndarray,
                      mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How well a mesh models an oriented surface: gap and normal error at each sample.

    For judging a reconstruction against the true object: sample the true
    surface, then compare each sample with the nearest point of the mesh.

    Parameters
    ----------
    points : (n, 3) float
      Samples of the true surface.
    normals : (n, 3) float
      Unit outward normals of the true surface at them.
    mesh : trimesh.Trimesh
      The model, outward wound.

    Returns
    -------
    distance : (n,) float
      Distance from each sample to the mesh.
    angle_deg : (n,) float
      Angle between each sample's normal and the normal of the nearest facet, degrees.
    facet : (n,) int
      The nearest facet.
    """
    points = _as_rows(points, 3, "surface points")
    normals = _as_rows(normals, 3, "surface normals")
    if len(normals) != len(points):
        raise ScanError(f"{len(points)} surface points but {len(normals)} normals; expected one normal per point")
    if mesh is None or len(mesh.faces) == 0:
        raise ScanError("mesh to compare is empty; expected at least one facet")
    closest, facet = Raycaster.of_mesh(mesh).closest_points(points)
    distance = np.linalg.norm(closest - points, axis=1)
    # angle between the true normal and the nearest facet's normal
    cos = np.einsum("ij,ij->i", np.asarray(mesh.face_normals)[facet], normals)
    return distance, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), facet


# ----------------------------------------------------------------------- steps


def crop_mask(points: np.ndarray, crop) -> np.ndarray:
    """Mask (n,) bool of points inside the crop box, or inside any of several.

    ``crop`` is ``(xmin, ymin, zmin, xmax, ymax, zmax)``, a (k, 6) array of such
    boxes, an Open3D axis-aligned or oriented bounding box, or a list of them.
    """
    boxes = _crop_boxes(crop)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    keep = np.zeros(len(points), dtype=bool)
    for box in boxes:
        keep[np.asarray(box.get_point_indices_within_bounding_box(pcd.points), dtype=np.int64)] = True
    return keep


def remove_outliers(pcd: o3d.geometry.PointCloud, opt: ScanOptions, params: dict) -> o3d.geometry.PointCloud:
    """Radius outlier removal (scaled to the spacing), then optional statistical removal."""
    if opt.outlier_min_neighbors > 0:
        radius = opt.outlier_radius or opt.outlier_radius_spacings * float(
            np.quantile(pcd.compute_nearest_neighbor_distance(), 0.9))
        params["outlier_radius"] = radius
        pcd, _ = pcd.remove_radius_outlier(int(opt.outlier_min_neighbors), float(radius))
    if opt.outlier_std > 0:
        pcd, _ = pcd.remove_statistical_outlier(int(opt.outlier_neighbors), float(opt.outlier_std))
    return pcd


def estimate_normals(pcd: o3d.geometry.PointCloud, radius: float, opt: ScanOptions) -> o3d.geometry.PointCloud:
    """Unit normals, oriented outward.

    Mode "given" keeps the cloud's own normals. Otherwise normals are estimated
    from the neighbourhood (``radius``, ``normal_max_nn``) and oriented by the
    first that applies: ``camera_location``; the cloud's own normals in mode
    "auto" (each estimate is flipped to the side of the given one, so a
    scanner's sensor-facing normals fix the side and the geometry the
    direction); else consistent tangent-plane propagation followed by one
    global flip so that normals point away from the centroid on average.
    """
    given = _given_normals(pcd)
    if opt.normals == "given":
        if given is None:
            raise ScanError(f"normals='given' but fewer than half of the {len(pcd.points)} points "
                            "have a usable normal; expected one normal per point")
        pcd.normals = o3d.utility.Vector3dVector(given)
        return pcd
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=int(opt.normal_max_nn)))
    if opt.camera_location is not None:
        pcd.orient_normals_towards_camera_location(np.asarray(opt.camera_location, dtype=np.float64))
        return pcd
    est = np.asarray(pcd.normals).copy()
    if opt.normals == "auto" and given is not None:
        # flip each estimated normal to the side of the given one
        est[np.einsum("ij,ij->i", est, given) < 0] *= -1.0
        pcd.normals = o3d.utility.Vector3dVector(est)
        return pcd
    pcd.orient_normals_consistent_tangent_plane(int(opt.orient_k))
    est = np.asarray(pcd.normals).copy()
    pts = np.asarray(pcd.points)
    # outward on average: normals point away from the centroid
    if np.einsum("ij,ij->", est, pts - pts.mean(axis=0)) < 0:
        pcd.normals = o3d.utility.Vector3dVector(-est)
    return pcd


def _given_normals(pcd: o3d.geometry.PointCloud) -> np.ndarray | None:
    """The cloud's unit normals (n, 3), or None when fewer than half are usable.

    A normal is unusable when it is missing, non-finite, or near zero (voxel
    averaging cancels opposite normals on thin parts); such a point takes the
    normal of its nearest neighbour with a usable one.
    """
    if not pcd.has_normals():
        return None
    normals = np.asarray(pcd.normals).copy()
    length = np.linalg.norm(normals, axis=1)
    ok = np.isfinite(length) & (length > 0.5)
    if ok.mean() < 0.5:
        return None
    normals[ok] /= length[ok, None]
    if not ok.all():
        pts = np.asarray(pcd.points)
        _, nearest = cKDTree(pts[ok]).query(pts[~ok], k=1)
        normals[~ok] = normals[ok][nearest]
    return normals


def reconstruct(pcd: o3d.geometry.PointCloud, opt: ScanOptions, voxel: float, spacing: float,
                params: dict) -> o3d.geometry.TriangleMesh:
    """Poisson or ball-pivoting surface from an oriented cloud; records resolved parameters."""
    if opt.method == "bpa":
        radii = list(opt.bpa_radii) if opt.bpa_radii else [spacing * f for f in (1.0, 2.0, 4.0)]
        params["bpa_radii"] = radii
        return o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(
            pcd, o3d.utility.DoubleVector(radii))
    pts = np.asarray(pcd.points)
    extent = float((pts.max(axis=0) - pts.min(axis=0)).max())
    cell = max(voxel, spacing)
    depth = opt.depth or int(np.clip(math.ceil(math.log2(1.1 * extent / cell)), 5, 10))
    trim = opt.trim_distance if opt.trim_distance is not None else 2.0 * cell
    params.update(depth=depth, trim_distance=trim)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pcd, depth=depth, samples_per_node=float(opt.samples_per_node))
    if opt.density_quantile > 0 and len(mesh.vertices):
        density = np.asarray(density)
        verts = np.asarray(mesh.vertices)
        far = cKDTree(pts).query(verts, k=1, distance_upper_bound=trim)[0] > trim
        # drop unsupported vertices: low density and away from the data
        low = density < np.quantile(density, opt.density_quantile)
        mesh.remove_vertices_by_mask(low & far)
    return mesh


def remove_small_components(mesh: o3d.geometry.TriangleMesh, fraction: float) -> o3d.geometry.TriangleMesh:
    """Drop connected pieces with fewer than ``fraction`` of all facets."""
    if fraction <= 0 or len(mesh.triangles) == 0:
        return mesh
    labels, counts, _ = mesh.cluster_connected_triangles()
    labels, counts = np.asarray(labels), np.asarray(counts)
    small = counts[labels] < fraction * len(labels)
    if small.any():
        mesh.remove_triangles_by_mask(small)
        mesh.remove_unreferenced_vertices()
    return mesh


def clean_mesh(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """Remove degenerate, duplicated and non-manifold facets and unused vertices."""
    mesh.remove_duplicated_vertices()
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_non_manifold_edges()
    mesh.remove_unreferenced_vertices()
    return mesh


def drop_degenerate(tm: trimesh.Trimesh, diameter: float) -> trimesh.Trimesh:
    """Drop facets below the project's area tolerance (``tol.AREA_REL * diameter**2``)."""
    keep = tm.area_faces > tol.AREA_REL * diameter ** 2
    if not keep.all():
        tm.update_faces(keep)
        tm.remove_unreferenced_vertices()
    return tm


def orient_outward(tm: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray) -> tuple[trimesh.Trimesh, bool]:
    """Make the winding consistent and outward; return the mesh and whether it was flipped.

    Closed mesh: the signed volume must be positive. Open mesh: vertex normals
    must agree, on average, with the normals of the nearest oriented cloud points.
    """
    if not tm.is_winding_consistent:
        # Open3D propagates a consistent winding over each connected piece
        o3m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(tm.vertices),
                                        o3d.utility.Vector3iVector(tm.faces))
        if not o3m.orient_triangles():
            log.warning("mesh is not orientable; winding left partly inconsistent")
        tm = trimesh.Trimesh(np.asarray(o3m.vertices), np.asarray(o3m.triangles), process=False)
    if tm.is_watertight:
        inward = tm.volume < 0
    else:
        _, nearest = cKDTree(points).query(tm.vertices, k=1)
        inward = np.einsum("ij,ij->", tm.vertex_normals, normals[nearest]) < 0
    if inward:
        tm.invert()
    return tm, bool(inward)


def is_cloud_file(path) -> bool:
    """Whether ``path`` is an existing point-cloud file rather than a mesh.

    PCD, XYZ (XYZN, XYZRGB, PTS) and NPY files are clouds. A PLY file is a cloud
    when its header declares no faces (``element face 0``, or no face element);
    a PLY header that cannot be read counts as a mesh, so the mesh loader reports
    the problem. Other suffixes, built-in object names and missing paths are not clouds.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        return False
    suffix = os.path.splitext(path)[1].lower()
    if suffix in CLOUD_ONLY_SUFFIXES:
        return True
    return suffix == ".ply" and ply_face_count(path) == 0


def ply_face_count(path) -> int | None:
    """Faces declared in a PLY file's header: 0 without a face element, None if unreadable."""
    with open(path, "rb") as fh:
        head = fh.read(PLY_HEADER_MAX)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return None
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) == 3 and words[:2] == ["element", "face"]:
            return int(words[2]) if words[2].isdigit() else None
    return 0


# --------------------------------------------------------------------- helpers


def _check_memory(n_points, bytes_per_point, what, advice):
    """ResourceError (one line) if n_points at bytes_per_point will not fit in memory."""
    check_fits(n_points * bytes_per_point, f"{what} a cloud of {n_points:,} points", advice)


def _load_finite(source, opt: ScanOptions) -> tuple[np.ndarray, np.ndarray | None, int]:
    """Finite points (n, 3), their normals or None, and the count read; ScanError if too few."""
    points, normals = load_cloud(source)
    n_input = len(points)
    finite = np.isfinite(points).all(axis=1)
    if normals is not None:
        # a non-finite normal counts as missing: zero, filled in by estimate_normals
        normals = np.where(np.isfinite(normals).all(axis=1)[:, None], normals, 0.0)
    points, normals = _take(points, normals, finite)
    dropped = n_input - len(points)
    what = f"cloud ({n_input} points, {dropped} NaN or infinite dropped)" if dropped else "cloud"
    check_cloud(points, opt.min_points, opt.planar_ratio, what=what)
    return points, normals, n_input


def _make_report(tm, dist, diameter: float, counts: dict, **fields) -> ScanReport:
    """ScanReport from the output mesh and the cloud -> mesh distances (m,)."""
    mean, p95, top = float(dist.mean()), float(np.percentile(dist, 95)), float(dist.max())
    return ScanReport(
        **counts, n_faces=len(tm.faces), n_vertices=len(tm.vertices),
        watertight=bool(tm.is_watertight), diameter=diameter,
        distance_mean=mean, distance_p95=p95, distance_max=top,
        distance_mean_pct=100.0 * mean / diameter, distance_p95_pct=100.0 * p95 / diameter,
        distance_max_pct=100.0 * top / diameter, **fields)


def _stepper(bar, timings: dict):
    """Context-manager factory timing one named step and ticking the bar."""
    @contextlib.contextmanager
    def step(name: str) -> Iterator[None]:
        bar.set_postfix_str(name)
        start = time.perf_counter()
        yield
        timings[name] = time.perf_counter() - start
        bar.update(1)
    return step


def _read_cloud_file(path: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Points and optional normals from a cloud file."""
    if not os.path.isfile(path):
        raise ScanError(f"cloud file {path} does not exist")
    suffix = os.path.splitext(path)[1].lower()
    if suffix == ".npy":
        try:
            array = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise ScanError(f"cannot read {path} as a numpy array: {exc}") from exc
        return _split_columns(np.asarray(array, dtype=np.float64), f"array in {path}")
    if suffix not in CLOUD_SUFFIXES:
        raise ScanError(f"cloud file {path} has suffix {suffix!r}; expected one of "
                        f"{', '.join(CLOUD_SUFFIXES + ('.npy',))}")
    pcd = o3d.io.read_point_cloud(path)
    if pcd.is_empty() and os.path.getsize(path) > 0 and suffix == ".ply":
        log.warning("%s: no points read; is it a valid PLY file?", path)
    points = np.asarray(pcd.points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(pcd.normals, dtype=np.float64) if pcd.has_normals() else None
    return points, normals


def _split_columns(array: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(n, 3) -> points; (n, 6) -> points and normals."""
    if array.ndim == 2 and array.shape[1] in (3, 6):
        normals = array[:, 3:6] if array.shape[1] == 6 else None
        return array[:, :3], normals
    if array.size == 0:
        return np.zeros((0, 3)), None
    raise ScanError(f"{what} has shape {array.shape}; expected (n, 3) points or (n, 6) points and normals")


def _as_rows(array, width: int, what: str) -> np.ndarray:
    """Array as (n, width) float, or ScanError naming the shape."""
    array = np.asanyarray(array, dtype=np.float64)
    if array.size == 0:
        return np.zeros((0, width))
    if array.ndim != 2 or array.shape[1] != width:
        raise ScanError(f"{what} have shape {array.shape}; expected (n, {width})")
    return array


def _take(points, normals, mask):
    """Rows of points (and normals) where mask holds."""
    return points[mask], None if normals is None else normals[mask]


def _to_pcd(points: np.ndarray, normals: np.ndarray | None) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return pcd


def _crop_boxes(crop) -> list:
    """Open3D boxes from the crop option, or ScanError naming the bad value."""
    bbox_types = (o3d.geometry.AxisAlignedBoundingBox, o3d.geometry.OrientedBoundingBox)
    if isinstance(crop, bbox_types):
        return [crop]
    if isinstance(crop, (list, tuple)) and crop and all(isinstance(b, bbox_types) for b in crop):
        return list(crop)
    try:
        array = np.asarray(crop, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ScanError(f"crop is {crop!r}; expected (xmin, ymin, zmin, xmax, ymax, zmax) "
                        "or Open3D bounding boxes") from exc
    if array.ndim == 1 and array.shape[0] == 6:
        array = array[None]
    if array.ndim != 2 or array.shape[1] != 6:
        raise ScanError(f"crop has shape {array.shape}; expected 6 numbers "
                        "(xmin ymin zmin xmax ymax zmax) or (k, 6) boxes")
    boxes = []
    for row in array:
        lo, hi = row[:3], row[3:]
        if not (np.isfinite(row).all() and (lo < hi).all()):
            raise ScanError(f"crop box {row.tolist()} is empty or not finite; "
                            "expected xmin < xmax, ymin < ymax, zmin < zmax")
        boxes.append(o3d.geometry.AxisAlignedBoundingBox(lo, hi))
    return boxes


def _check_mesh(mesh, stage: str) -> None:
    """ScanError when a mesh has no facets left."""
    n = len(mesh.triangles) if isinstance(mesh, o3d.geometry.TriangleMesh) else len(mesh.faces)
    if n == 0:
        raise ScanError(f"{stage} left 0 facets; the cloud may be too sparse or too noisy "
                        "(try a smaller --voxel, another --method, or a lower --depth)")


def _check_options(opt: ScanOptions) -> None:
    """ScanError for option values out of range."""
    if opt.method not in METHODS:
        raise ScanError(f"method is {opt.method!r}; expected one of {', '.join(METHODS)}")
    if opt.normals not in NORMAL_MODES:
        raise ScanError(f"normals is {opt.normals!r}; expected one of {', '.join(NORMAL_MODES)}")
    if opt.faces is not None and opt.faces < 4:
        raise ScanError(f"faces is {opt.faces}; need at least 4 facets for a closed surface")
    if opt.min_points < 4:
        raise ScanError(f"min_points is {opt.min_points}; need at least 4")
    if opt.depth is not None and not 1 <= opt.depth <= 16:
        raise ScanError(f"depth is {opt.depth}; expected an octree depth in 1..16")
    if opt.voxel is not None and opt.voxel < 0:
        raise ScanError(f"voxel is {opt.voxel}; expected a size >= 0 (0 turns downsampling off)")
    if not 0.0 <= opt.density_quantile < 1.0:
        raise ScanError(f"density_quantile is {opt.density_quantile}; expected [0, 1)")


def _fmt(value) -> str:
    """Short text for a report parameter."""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)
