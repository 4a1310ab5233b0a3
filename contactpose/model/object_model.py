"""The object model: facet planes of a triangle mesh (paper §2, eq. 2) and its pair table.

Facet indices are the face order of the mesh as loaded by
``trimesh.load(path, force="mesh", process=False)``. Degenerate facets are
reported, marked invalid and left out of the pair table; the others keep
their indices.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
import warnings
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from contactpose import tol
from contactpose.deferred import deferred
from contactpose.errors import ContactPoseError, MeshError, ModelFileError, check_length
from contactpose.io.modelfile import (
    COMPRESS_MIN_BYTES,
    FORMAT_VERSION,
    MMAP_MIN_BYTES,
    OPTIONAL_MODEL,
    STORED_FEATURES,
    STORED_MODEL,
    check_arrays,
    check_version,
    content_hash,
    prefixed,
    read_npz,
    write_replacing,
)
from contactpose.model.features import DERIVED_FIELDS, PairFeatures, derived_features, pair_features
from contactpose.model.memory import check_fits
from contactpose.model.patches import MemberGroups, Patches, PatchPairs, find_patches
from contactpose.model.plan import PairPlan
from contactpose.model.surface import SurfaceTopology
from contactpose.model.symmetry import Symmetry, remember, symmetry
from contactpose.model.table import DEFAULT_BINS, STORED_BYTES_PER_PAIR, PairTable, check_bins
from contactpose.model.units import SearchUnits, unit_features

trimesh = deferred("trimesh")

log = logging.getLogger(__name__)

#: trimesh metadata key: why a mesh's defects are known and cannot be mended by its user
#: (from_mesh then reports its degenerate facets and non-manifold edges as one debug line).
KNOWN_DEFECTS = "contactpose_known_defects"

#: Default patch tolerance: half the default normal noise of 1°, so a patch is flatter
#: than the sensor can tell apart (research/design.md).
DEFAULT_PATCH_TOL_DEG = 0.5
#: facet_pairs="auto" drops the facet-level table above this size when patches serve.
FACET_TABLE_AUTO_BYTES = 512 * 2**20
#: patch_tol_deg="auto": when patches at DEFAULT_PATCH_TOL_DEG do not shrink the search and
#: the facet table would exceed FACET_TABLE_AUTO_BYTES (a fine tessellation of a smooth
#: surface, such as the 16,384-facet YCB meshes), surface regions are grown at each of these
#: angles in turn until they do: connected facets whose normals lie within the angle of the
#: region's first facet. Their pair intervals hold every member pair's, so the search stays
#: complete (research/regions.md); the first angle gives 2,033 regions on the YCB banana.
REGION_DEG = (5.0, 10.0, 15.0)
BOUNDS = ("exact", "paper")
#: Pose classes measure ADD-S on at most this many surface points (localize.same_placement):
#: a mean over 256 points moves by under 0.4 % of the diameter against all of them (measured
#: on six built-in objects), and the 5 % class threshold is a convention, not a measurement.
CLASS_POINTS = 256
#: Peak bytes per facet of the mesh-level steps (planes, merged mesh, patches, their layout),
#: checked before they run; measured 750-780 B/facet (traced numpy peak) on 82 k and 328 k facets.
MESH_BYTES_PER_FACET = 1024
#: What the build allocates after the early memory check and before the pairs: the patch
#: layout (measured 390-430 B/facet), and for the diameter qhull's memory per vertex (peak RSS
#: 111 MiB on 983 k vertices: 120 B/vertex) and the blocks of hull-point differences.
LAYOUT_BYTES_PER_FACET = 512
HULL_BYTES_PER_VERTEX = 160
#: Before the diameter D is known, facet validity is decided for every D in
#: [EARLY_LOW · diagonal, diagonal] at once (the bounding-box diagonal bounds D from above).
EARLY_LOW = 0.01


@dataclass(frozen=True)
class FacetPlanes:
    """Unit outward normals and plane offsets of m facets (eq. 2, erratum 1).

    normals : (m, 3) float, offsets : (m,) float with nᵀx + d = 0 on the plane,
    areas : (m,) float, valid : (m,) bool (False for degenerate facets).
    """

    normals: np.ndarray
    offsets: np.ndarray
    areas: np.ndarray
    valid: np.ndarray


def facet_planes(triangles, diameter):
    """Planes of facets (eq. 2) with the normal made a unit vector (erratum 1).

    triangles : (m, 3, 3) float; diameter : float, sets the degeneracy scale.
    A facet is degenerate when its area or its shortest altitude is near zero.
    """
    measures = _facet_measures(triangles)
    return _planes_of(triangles, measures, _nondegenerate(measures, diameter))


def _facet_measures(triangles):
    """(cross products (m, 3), doubled areas (m,), altitudes onto the longest edge (m,))."""
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    longest_edge = np.max(
        np.linalg.norm(triangles - np.roll(triangles, 1, axis=1), axis=2), axis=1
    )
    # altitude onto the longest edge = 2·area / longest edge
    altitude = np.divide(double_area, longest_edge, out=np.zeros_like(double_area), where=longest_edge > 0)
    return cross, double_area, altitude


def _nondegenerate(measures, diameter):
    _, double_area, altitude = measures
    return (0.5 * double_area > tol.AREA_REL * diameter**2) & (altitude > tol.ALTITUDE_REL * diameter)


def _planes_of(triangles, measures, valid):
    cross, double_area, _ = measures
    normals = np.zeros_like(cross)
    normals[valid] = cross[valid] / double_area[valid, None]
    offsets = -np.einsum("ij,ij->i", normals, triangles[:, 0])
    return FacetPlanes(normals, offsets, 0.5 * double_area, valid)


def early_planes(triangles, vertices):
    """Facet planes before the diameter: (planes, diameter), the diameter None when not needed.

    Validity depends on the diameter D only through its thresholds; D lies below the
    bounding-box diagonal. When no facet changes validity for D in [EARLY_LOW · diagonal,
    diagonal], the planes are those of any such D and the diameter (a convex hull: seconds on
    10⁵ vertices) can wait until the memory guard has passed; else it is computed here.
    """
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    if not diagonal > 0:
        raise MeshError("mesh has zero extent (all vertices coincide)")
    measures = _facet_measures(triangles)
    valid = _nondegenerate(measures, diagonal)
    if np.array_equal(valid, _nondegenerate(measures, EARLY_LOW * diagonal)):
        return _planes_of(triangles, measures, valid), None
    diameter = mesh_diameter(vertices)
    return _planes_of(triangles, measures, _nondegenerate(measures, diameter)), diameter


def load_mesh(source):
    """Load a mesh with trimesh, keeping the file's face order (``process=False``).

    source : path or trimesh.Trimesh. Returns (vertices (V, 3) float, faces (m, 3) int).
    """
    if isinstance(source, trimesh.Trimesh):
        mesh = source
    else:
        path = os.fspath(source)
        if not os.path.isfile(path):
            raise MeshError(f"mesh file {path!r} does not exist or is not a file")
        mesh = _read_mesh_file(path)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    return check_mesh_arrays(vertices, faces)


def _read_mesh_file(path):
    """trimesh.Trimesh of a mesh file with at least one face, else MeshError naming the file."""
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"cannot read {path!r} as a mesh: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{path!r} holds no triangle mesh (got {type(mesh).__name__})")
    if len(mesh.faces) == 0:  # trimesh reads text or random bytes named .stl/.obj as an empty mesh
        raise MeshError(f"cannot read {path!r} as a mesh: it is not a mesh file (it has no faces: a mesh needs "
                        f"faces of shape (m, 3) with m >= 1, got shape {np.shape(mesh.faces)})")
    return mesh


def check_mesh_arrays(vertices, faces):
    """Validate vertex and face arrays; raise MeshError naming what is wrong."""
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise MeshError(f"mesh needs faces of shape (m, 3) with m >= 1, got shape {faces.shape}")
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"mesh needs vertices of shape (V, 3), got shape {vertices.shape}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(
            f"face indices must lie in [0, {len(vertices) - 1}], got range [{faces.min()}, {faces.max()}]"
        )
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(
            f"mesh has {bad.sum()} non-finite vertices (NaN or inf), first at index {np.flatnonzero(bad)[0]}"
        )
    return vertices, faces


def mesh_diameter(vertices):
    """Largest distance between two vertices, via the convex hull. vertices : (V, 3)."""
    from scipy.spatial import ConvexHull, QhullError

    pts = vertices
    if len(vertices) > 500:
        try:
            pts = vertices[ConvexHull(vertices).vertices]
        except (QhullError, ValueError):
            pass  # flat vertex sets: fall back to all vertices
    if len(pts) > 4000:
        pts = pts[:: len(pts) // 4000 + 1]
    best = 0.0
    for start in range(0, len(pts), 256):  # blocks of rows: 25 MB of differences, not 400 MB
        diff = pts[start:start + 256, None, :] - pts[None, :, :]
        best = max(best, float(np.max(np.einsum("ijk,ijk->ij", diff, diff))))
    return float(np.sqrt(best))


def _diameter_bytes(num_vertices):
    """Peak bytes of :func:`mesh_diameter`: qhull, and 256 rows of (3,) differences and their
    squares against at most 4,000 hull points."""
    return HULL_BYTES_PER_VERTEX * num_vertices + 256 * min(num_vertices, 4000) * 32


#: ObjectModel.smooth_normals blends the normals of facets at a vertex only within this angle
#: (30° lost 3 of 100 YCB scissors tracks to the mirror-image pose, 15° one; research/tracking.md).
CREASE_DEG = 15.0
#: ObjectModel.crease_edges leaves out an edge whose faces' normals are this close to opposite
#: (|n_f × n_g|, the sine of the angle between them).
ARC_MIN = 1e-9


def merged_mesh(vertices, faces):
    """A trimesh copy with coincident vertices merged (face order kept), for topology."""
    merged = trimesh.Trimesh(vertices, faces, process=False)
    merged.merge_vertices()
    return merged


def vertex_faces(count, faces):
    """(count, K) int: the faces at each of ``count`` vertices, -1 padded (trimesh's
    vertex_face_indices), leaving out the faces that repeat a vertex (zero area after merging:
    trimesh would fall back to a slow loop and log a traceback for them). faces : (m, 3) int."""
    keep = np.flatnonzero((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2]))
    sub = faces[keep]
    around = trimesh.geometry.vertex_face_indices(count, sub, trimesh.geometry.index_sparse(count, sub))
    return np.where(around >= 0, keep[np.maximum(around, 0)], -1)


def edge_uses(merged):
    """(E,) int: how many faces use each distinct edge of a vertex-merged mesh (zero-length
    edges left out); an edge used by more than two faces is non-manifold."""
    edges = np.asarray(merged.edges_sorted)
    edges = edges[edges[:, 0] != edges[:, 1]]
    if len(edges) == 0:
        return np.zeros(0, dtype=np.int64)
    _, inverse = trimesh.grouping.unique_rows(edges)
    return np.bincount(inverse)


#: The face winding of a mesh as ObjectModel.winding records it: "outward" (closed, positive
#: volume), "inward" (closed, negative volume: every facet normal points into the object),
#: "inconsistent" (neighbouring facets wound opposite ways) or "open" (consistent, but a mesh
#: that is not closed has no inside to tell the direction by).
WINDINGS = ("outward", "inward", "inconsistent", "open")
#: The warning for each winding that will keep contact normals from matching.
WINDING_PROBLEMS = {"inward": "facet normals point inward (closed mesh with negative volume)",
                    "inconsistent": "face winding is inconsistent between neighbouring facets"}


def winding_state(merged):
    """The face winding of a vertex-merged mesh, one of WINDINGS."""
    if not merged.is_winding_consistent:
        return "inconsistent"
    if not merged.is_watertight:
        return "open"
    return "inward" if merged.volume < 0 else "outward"


def rewind_outward(vertices, faces):
    """Faces re-wound consistently outward with trimesh's repair, in the same order.

    vertices : (V, 3), faces : (m, 3) int  ->  faces (m, 3) int, with flipped faces'
    last two indices swapped (facet indices are unchanged).
    """
    merged = merged_mesh(vertices, faces)
    before = _face_cross(merged)
    trimesh.repair.fix_normals(merged)
    # recomputed from the faces: Trimesh.invert() leaves the cached face_normals as they were
    flipped = np.einsum("ij,ij->i", before, _face_cross(merged)) < 0
    fixed = faces.copy()
    fixed[flipped] = fixed[flipped][:, [0, 2, 1]]
    return fixed


def _face_cross(mesh):
    """(m, 3) float: unnormalised facet normals of a trimesh, from its current faces."""
    t = mesh.vertices[mesh.faces]
    return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])


def mesh_hash(vertices, faces):
    """SHA-256 of the vertex and face arrays, as stored (float64, int64)."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(faces, dtype=np.int64).tobytes())
    return digest.hexdigest()


@dataclass
class ObjectModel:
    """A mesh refined for contact search: facet planes, pair features and the table K3.

    Build with :meth:`from_mesh`, persist with :meth:`save` / :meth:`load`. ``winding`` is
    the mesh's face winding found when it was built (one of WINDINGS), or None when not
    recorded (a model file written before it was).
    """

    vertices: np.ndarray
    faces: np.ndarray
    planes: FacetPlanes
    table: PairTable
    bounds: str
    diameter: float
    mesh_hash: str
    build_seconds: dict = field(default_factory=dict)
    patches: Patches | None = None
    patch_table: PairTable | None = None
    winding: str | None = None

    # ----------------------------------------------------------------- build
    @classmethod
    def from_mesh(cls, mesh, *, bins=DEFAULT_BINS, bounds="exact", progress=None, fix_normals=False,
                  max_span=None, patch_tol_deg="auto", facet_pairs="auto"):
        """Build the model of a mesh (§3.1).

        mesh : path or trimesh.Trimesh; bins : (p_dmax, p_dmin, p_alpha) bin counts;
        bounds : "exact" (triangle–triangle Δmin) or "paper" (vertex-only Δmin);
        progress : show a progress bar (default: only on a terminal, for large models);
        fix_normals : re-wind faces consistently outward first (face order is kept);
        max_span : the hand's span L in length units: only pairs with Δmin <= L are stored,
        found with a spatial index (None: all pairs);
        patch_tol_deg : connected facets whose normals are within this angle of a patch's
        first facet form one patch for the default method's search (0: exactly coplanar;
        None: no patches). "auto" (default): DEFAULT_PATCH_TOL_DEG, half the default normal
        noise, and on a fine mesh whose facet table would be large, regions at the first of
        REGION_DEG that shrinks the search;
        facet_pairs : keep the facet-level pair table, which the paper's method needs
        (True, False, or "auto": keep it unless patches serve the default method and the
        facet table would exceed FACET_TABLE_AUTO_BYTES).
        A trimesh whose ``metadata[KNOWN_DEFECTS]`` names why its defects are known (a shipped
        mesh, which its user cannot repair: sim.ycb.load) gets its degenerate facets and
        non-manifold edges as one debug line instead of warnings.
        """
        if bounds not in BOUNDS:
            raise MeshError(f"bounds must be one of {BOUNDS}, got {bounds!r}")
        bins = check_bins(bins)
        max_span = _check_span(max_span)
        start = time.perf_counter()
        known = mesh.metadata.get(KNOWN_DEFECTS) if isinstance(mesh, trimesh.Trimesh) else None
        vertices, faces = _load_checked(mesh, fix_normals)
        triangles = vertices[faces]
        planes, diameter = early_planes(triangles, vertices)
        defects = [_degenerate_note(planes)]
        merged = merged_mesh(vertices, faces)
        patches = _find_patches(merged, planes, bounds, patch_tol_deg)
        plan = PairPlan(triangles, planes.valid, patches, _serves(patches),
                        lambda count: _keep_facet_pairs(facet_pairs, patches, count))
        pair_count = plan.facet_pairs(max_span)
        keep = _keep_facet_pairs(facet_pairs, patches, pair_count)
        later = LAYOUT_BYTES_PER_FACET * len(faces) + (_diameter_bytes(len(vertices)) if diameter is None else 0)
        plan.check(len(faces), max_span, extra=later)  # before any pair is listed
        winding = _report_winding(merged)
        defects.append(_non_manifold_note(merged))
        _report_defects(defects, known)
        if diameter is None:
            diameter, planes, patches = _late_diameter(vertices, triangles, planes, patches,
                                                       lambda p: _find_patches(merged, p, bounds, patch_tol_deg))
        patch_pairs = PatchPairs(triangles, planes, patches, diameter, max_span) if _serves(patches) else None
        plan.check(len(faces), max_span, (pair_count if keep else 0, 0 if patch_pairs is None else patch_pairs.count))
        t_planes = time.perf_counter()
        patch_table = None if patch_pairs is None else PairTable.build(patch_pairs.features(progress), bins, max_span)
        del patch_pairs
        t_patches = time.perf_counter()
        features = pair_features(triangles, planes, bounds=bounds, progress=progress, max_span=max_span) if keep else None
        t_features = time.perf_counter()
        table = PairTable.build(features, bins, max_span) if keep else None
        t_table = time.perf_counter()
        seconds = {
            "planes": t_planes - start,
            "patches": t_patches - t_planes,
            "features": t_features - t_patches,
            "table": t_table - t_features,
            "total": t_table - start,
        }
        return cls(vertices, faces, planes, table, bounds, diameter,
                   mesh_hash(vertices, faces), seconds, patches, patch_table, winding)

    # ------------------------------------------------------------ properties
    @property
    def num_facets(self):
        """Number of facets m, degenerate ones included (indices are the file's)."""
        return len(self.faces)

    @property
    def features(self):
        """PairFeatures of the unordered valid facet pairs, in table order."""
        return self.facet_table().features

    def facet_table(self):
        """The facet-level table K3; ModelFileError if the model was built without it."""
        if self.table is None:
            raise ModelFileError("this model was built without facet pairs (facet_pairs=False, or 'auto' for a "
                                 "large model); the paper's method needs them: rebuild with facet_pairs=True")
        return self.table

    @property
    def num_pairs(self):
        """Ordered facet pairs the facet table answers for (k = l included); patch pairs without it."""
        return (self.patch_table if self.table is None else self.table).features.num_ordered

    @cached_property
    def triangles(self):
        """(m, 3, 3) float: the facet vertices in the object frame."""
        return self.vertices[self.faces]

    @cached_property
    def centroids(self):
        """(m, 3) float: facet centroids in the object frame."""
        return self.triangles.mean(axis=1)

    @property
    def has_regions(self):
        """True when the search runs over surface regions: patches grown above
        DEFAULT_PATCH_TOL_DEG on a fine tessellation (research/regions.md)."""
        return self.patch_table is not None and self.patches is not None and \
            self.patches.tol_deg > DEFAULT_PATCH_TOL_DEG

    @cached_property
    def topology(self):
        """SurfaceTopology: the facets at each edge and vertex, for the contact model (model.surface)."""
        return SurfaceTopology.of(merged_mesh(self.vertices, self.faces), self.planes.valid)

    @cached_property
    def units(self):
        """SearchUnits: the valid facets, sharp convex edges and vertices (model.units)."""
        return SearchUnits.of(self)

    @cached_property
    def unit_table(self):
        """The pair table over :attr:`units` (model.units.unit_features), built when first asked
        for, for contacts on sharp edges of a facet-table model; ModelFileError without a facet table."""
        table = self.facet_table()
        return PairTable.build(unit_features(self.units), table.bins, self.max_span)

    @cached_property
    def facet_radii(self):
        """(m,) float: distance from each facet's centroid to its farthest vertex."""
        return np.linalg.norm(self.triangles - self.centroids[:, None], axis=2).max(axis=1)

    @cached_property
    def member_groups(self):
        """MemberGroups of the patches (single facets when the model has none): their members
        in runs with bounding spheres, for nearest-member and closest-point queries."""
        return MemberGroups.of(self.triangles, self.facet_radii, self.patches)

    @cached_property
    def facet_groups(self):
        """MemberGroups with one facet per region, for models searched over facets."""
        return MemberGroups.of(self.triangles, self.facet_radii)

    @cached_property
    def surface_points(self):
        """(N, 3) float: vertices and centroids of valid facets, for ADD-S (about 1,000 at most)."""
        valid = self.planes.valid
        pts = np.concatenate([self.vertices[np.unique(self.faces[valid])], self.centroids[valid]])
        return pts[:: max(1, len(pts) // 1000)]

    @cached_property
    def class_points(self):
        """(<= CLASS_POINTS, 3) float: an even subset of :attr:`surface_points`, the points
        whose ADD-S groups pose classes (their nearest points come from all surface points)."""
        p = self.surface_points
        return p[:: -(-len(p) // CLASS_POINTS)]

    @cached_property
    def class_moments(self):
        """(mean (3,), E[p pᵀ] (3, 3)) of :attr:`class_points`, for metrics.rms_displacement."""
        p = self.class_points
        return p.mean(axis=0), p.T @ p / len(p)

    @cached_property
    def smooth_normals(self):
        """(M (m, 3, 3), corner normal (m, 3)): the normal interpolated over each facet from its
        corners' normals is m(p) = n_a + M (p - a) for a point p (object frame; the barycentric
        coordinates of its projection on the plane), to be normalised; a = the facet's first
        vertex. A corner's normal is the area-weighted mean of the normals of the facets at that
        vertex (vertex-merged mesh) within CREASE_DEG of the facet's own: across a sharp edge
        the normals are not blended. NaN on a facet without a plane (zero area: ``planes.valid``
        False), which no contact takes."""
        merged = merged_mesh(self.vertices, self.faces)
        faces = np.asarray(merged.faces)
        around = vertex_faces(len(merged.vertices), faces)[faces]  # (m, 3, K) facets at each corner, -1 padded
        normals, areas = self.planes.normals, self.planes.areas
        near = (around >= 0) & (np.einsum("mj,mckj->mck", normals, normals[np.maximum(around, 0)])
                                >= np.cos(np.radians(CREASE_DEG)))
        weight = np.where(near, areas[np.maximum(around, 0)], 0.0)
        vn = np.einsum("mck,mckj->mcj", weight, normals[np.maximum(around, 0)])
        with np.errstate(invalid="ignore", divide="ignore"):  # a zero-area facet's corners: NaN
            vn /= np.linalg.norm(vn, axis=2, keepdims=True)
        tri = self.triangles
        E = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], axis=2)  # (m, 3, 2)
        G = np.linalg.pinv(E)  # (m, 2, 3): barycentric (λ_b, λ_c) of p - a, projected
        dN = np.stack([vn[:, 1] - vn[:, 0], vn[:, 2] - vn[:, 0]], axis=2)  # (m, 3, 2)
        return dN @ G, vn[:, 0]

    def smooth_normal_at(self, points, facets=None):
        """(N, 3) :attr:`smooth_normals`' interpolated normal m(p) = n_a + M (p - a) at each
        point (N, 3) on its facet (N,) (default: facet k for point k), not normalised (NaN on a
        facet without a plane)."""
        M, corner = self.smooth_normals
        facets = np.arange(len(points)) if facets is None else facets
        return corner[facets] + np.einsum("nij,nj->ni", M[facets], points - self.triangles[facets, 0])

    @cached_property
    def crease_edges(self):
        """(m, 3, 12) per facet f and edge j (the topology's: corners j, j+1), where the edge is
        a convex crease (its neighbour g's normal more than CREASE_DEG from f's, so that
        :attr:`smooth_normals` does not blend across it): the edge's first corner a (3), the
        unit e = n_f × n_g / |n_f × n_g| (along the edge; the arc of normals from n_f to n_g
        turns about it), the unit u in f's plane across the edge, pointing into f (3), and n_g
        (3); NaN rows elsewhere, and where the two normals are opposite (a sheet folded flat:
        |n_f × n_g| ≤ ARC_MIN, no one arc between them). A rounded fingertip on the crease
        measures a normal on that arc (model.surface's edge cone), which the smooth contact
        model takes from here (costs.smooth._smooth_normal_rows)."""
        topology, normals, tri = self.topology, self.planes.normals, self.triangles
        out = np.full((self.num_facets, 3, 12), np.nan)
        f, j = np.nonzero(topology.edge_convex & (topology.edge_nbr >= 0))
        g = topology.edge_nbr[f, j]
        e = np.cross(normals[f], normals[g])
        size = np.linalg.norm(e, axis=1)
        sharp = (np.einsum("ki,ki->k", normals[f], normals[g]) < np.cos(np.radians(CREASE_DEG))) & (size > ARC_MIN)
        f, j, g, e = f[sharp], j[sharp], g[sharp], e[sharp] / size[sharp, None]
        a, b, c = tri[f, j], tri[f, (j + 1) % 3], tri[f, (j + 2) % 3]
        u = np.cross(normals[f], b - a)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u *= np.sign(np.einsum("ki,ki->k", u, c - a))[:, None]
        out[f, j] = np.concatenate([a, e, u, normals[g]], axis=1)
        return out

    @cached_property
    def normal_scatter(self):
        """(m, 3, 3) per facet, how the mesh's own normal strays from the smooth normal over it
        (:attr:`smooth_normals`): the mean over the facet's area of d dᵀ, d = n_f - n(p)/|n(p)|
        (object frame). A contact on the facet carries the facet's normal (or one between it
        and a neighbour's), not the smooth normal, so the smooth contact model adds this to the
        normal noise. It is far from isotropic: the normal strays across the direction of
        strongest curvature (YCB banana, median axes 1.56° and 0.46°). The mean is the triangle
        rule exact for cubics (corners 3/60, edge midpoints 8/60, centroid 27/60)."""
        tri = self.triangles
        scatter = np.zeros((len(tri), 3, 3))
        for weight, bary in ((1 / 20, (1, 0, 0)), (1 / 20, (0, 1, 0)), (1 / 20, (0, 0, 1)), (2 / 15, (0.5, 0.5, 0)),
                             (2 / 15, (0, 0.5, 0.5)), (2 / 15, (0.5, 0, 0.5)), (9 / 20, (1 / 3, 1 / 3, 1 / 3))):
            m = self.smooth_normal_at(np.asarray(bary) @ tri)
            d = self.planes.normals - m / np.linalg.norm(m, axis=1, keepdims=True)
            scatter += weight * d[:, :, None] * d[:, None, :]
        return scatter

    @property
    def normal_roughness(self):
        """(m,) per facet, the root mean square of :attr:`normal_scatter`'s stray per tangent
        axis, √(trace / 2) (radians, as a normal noise σ_n is; median 1.18° on the YCB banana)."""
        return np.sqrt(np.trace(self.normal_scatter, axis1=1, axis2=2) / 2.0)

    def normal_whitening(self, normal_noise, position_noise):
        """(m, 3, 3) per facet W = C^(-1/2), C = σ_n² I + S_f + σ_x² Dn Dnᵀ: the covariance of the
        smooth contact model's normal rows (object frame), S_f the facet's :attr:`normal_scatter`
        and Dn = ∂n/∂p the smooth normal's change with place at the facet's centroid, which turns
        the contact's position noise along the surface into normal noise; σ_n⁻¹ I on a facet
        without a plane (zero area), which has no smooth normal. Cached per (σ_n, σ_x)."""
        cache = self.__dict__.setdefault("_normal_whitening", {})
        key = (float(normal_noise), float(position_noise))
        if key not in cache:
            M = self.smooth_normals[0]
            m = self.smooth_normal_at(self.centroids)
            size = np.linalg.norm(m, axis=1)
            nu = m / size[:, None]
            Dn = (np.eye(3) - nu[:, :, None] * nu[:, None, :]) @ M / size[:, None, None]
            C = key[0] ** 2 * np.eye(3) + self.normal_scatter + key[1] ** 2 * Dn @ np.swapaxes(Dn, 1, 2)
            W = np.broadcast_to(np.eye(3) / key[0], C.shape).copy()
            defined = np.isfinite(C).all(axis=(1, 2))
            values, vectors = np.linalg.eigh(C[defined])
            W[defined] = np.einsum("fij,fj,fkj->fik", vectors, 1.0 / np.sqrt(values), vectors)
            cache[key] = W
        return cache[key]

    @cached_property
    def oriented(self):
        """The oriented surface samples, their pair features and field (model.oriented), built
        on first use: what the search by hypothesize and verify matches contacts against."""
        from contactpose.model.oriented import OrientedSamples

        return OrientedSamples.of(self)

    @cached_property
    def centroid_tree(self):
        """(scipy cKDTree over the valid facets' centroids, those facets (F,) int, their largest
        radius): a nearest-facet search that can bound what it has not looked at."""
        from scipy.spatial import cKDTree

        valid = np.flatnonzero(self.planes.valid)
        return cKDTree(self.centroids[valid]), valid, float(self.facet_radii[valid].max())

    @cached_property
    def surface_tree(self):
        """scipy cKDTree over :attr:`surface_points`."""
        from scipy.spatial import cKDTree

        return cKDTree(self.surface_points)

    @property
    def bins(self):
        return (self.patch_table if self.table is None else self.table).bins

    # ----------------------------------------------------------- persistence
    def save(self, path, mappable=False):
        """Write the model to one ``.npz`` (no pickle). Returns the path written.

        Compact, unless ``mappable`` or that leaves MMAP_MIN_BYTES of arrays or more: pair
        indices as int16 where they fit, the facet table without its DERIVED_FIELDS (cheap and
        exact: :meth:`load` recomputes them bit for bit), members of COMPRESS_MIN_BYTES or more
        deflated. Otherwise every array is stored as built, uncompressed, for :meth:`load` to
        memory-map (the model cache's files: read in milliseconds). The file also holds the
        object's symmetry group (model.symmetry, found here when not yet: 4 ms to 0.3 s). It is
        written beside ``path`` and renamed over it, so a process that has the old file
        memory-mapped keeps its contents."""
        path = os.fspath(path)
        arrays = self._file_arrays(compact=not mappable)
        compact = not mappable and sum(a.nbytes for a in arrays.values()) < MMAP_MIN_BYTES
        if not compact:
            arrays = self._file_arrays(compact=False)
        arrays["content_hash"] = np.array(content_hash(arrays))
        deflate = [k for k, a in arrays.items() if a.nbytes >= COMPRESS_MIN_BYTES] if compact else []
        write_replacing(path, arrays, compress=deflate)
        return path

    def _file_arrays(self, compact):
        """{name: array} of a model file (see :meth:`save`), without its content hash."""
        arrays = {
            "format_version": np.array(FORMAT_VERSION),
            "mesh_hash": np.array(self.mesh_hash),
            "bounds": np.array(self.bounds),
            "diameter": np.array(self.diameter),
            "vertices": self.vertices,
            "faces": self.faces,
            "normals": self.planes.normals,
            "offsets": self.planes.offsets,
            "areas": self.planes.areas,
            "valid": self.planes.valid,
        }
        if self.winding is not None:
            arrays["winding"] = np.array(self.winding)
        if self.table is not None:
            stored = _file_features(self.features, self.num_facets, compact, derived=compact)
            arrays.update({f"features_{k}": v for k, v in stored.items()})
            arrays.update({f"table_{k}": v for k, v in self.table.to_arrays().items()})
        if self.patches is not None:
            arrays.update({f"patches_{k}": v for k, v in self.patches.to_arrays().items()})
        if self.patch_table is not None:
            stored = _file_features(self.patch_table.features, self.patches.count, compact, derived=False)
            arrays.update({f"pfeatures_{k}": v for k, v in stored.items()})
            arrays.update({f"ptable_{k}": v for k, v in self.patch_table.to_arrays().items()})
        arrays.update({f"symmetry_{k}": v for k, v in symmetry(self).to_arrays().items()})
        return arrays

    @classmethod
    def load(cls, path, *, mesh=None, bins=None, bounds=None, verify=True, mmap=None):
        """Read a model written by :meth:`save`.

        mesh, bins, bounds : if given, the model must have been built for this mesh
        and with these settings, else ModelFileError says what differs.
        verify : check the arrays against the file's content hash and scan their values
        (finite, indices in range): 1.5 s for a 1.9 GB model. False checks names, kinds and
        shapes only, for a file the caller vouches for (the model cache's, whose size it recorded).
        mmap : memory-map the arrays of a file stored uncompressed (``save(mappable=True)``);
        None: files of MMAP_MIN_BYTES or more.
        """
        path = os.fspath(path)
        data = read_npz(path, mmap)
        check_version(path, data)
        stored = data.pop("content_hash", None)
        if verify and (stored is None or np.shape(stored) != () or str(stored) != content_hash(data)):
            raise ModelFileError(f"model file {path!r} is corrupt: its arrays do not match its content hash")
        try:
            model = cls._from_arrays(data, verify)
        except ContactPoseError as exc:  # a MeshError too: the mesh is the file's
            raise ModelFileError(f"model file {path!r} is corrupt or not a model: {exc}") from None
        model._check_expected(path, mesh=mesh, bins=bins, bounds=bounds)
        return model

    @classmethod
    def _from_arrays(cls, data, values=True):
        """The model of a file's arrays, each checked first (io.modelfile; values : their values too)."""
        sizes = {}
        check_arrays(data, STORED_MODEL, sizes, optional=OPTIONAL_MODEL, values=values)
        vertices, faces = check_mesh_arrays(data["vertices"], data["faces"])
        bounds, diameter, stored_hash = str(data["bounds"]), float(data["diameter"]), str(data["mesh_hash"])
        if bounds not in BOUNDS or not diameter > 0:
            raise ModelFileError(f"'bounds' must be one of {BOUNDS} and 'diameter' positive, got {bounds!r} "
                                 f"and {diameter}")
        if mesh_hash(vertices, faces) != stored_hash:
            raise ModelFileError("its mesh does not match its stored hash")
        planes = FacetPlanes(data["normals"], data["offsets"], data["areas"], data["valid"])
        winding = str(data["winding"]) if "winding" in data else None  # files written before: not recorded
        if winding is not None and winding not in WINDINGS:
            raise ModelFileError(f"'winding' must be one of {WINDINGS}, got {winding[:40]!r}")
        table, patches, patch_table = _stored_tables(data, sizes["m"], values)
        model = cls(vertices, faces, planes, table, bounds, diameter, stored_hash, {}, patches, patch_table, winding)
        if _has(data, "symmetry_"):  # files written before it: found on use
            remember(model, Symmetry.from_arrays(prefixed(data, "symmetry_"), values=values))
        return model

    @property
    def max_span(self):
        """The hand span the table was built for, or None (all pairs)."""
        return (self.patch_table if self.table is None else self.table).max_span

    def _check_expected(self, path, *, mesh, bins, bounds):
        if mesh is not None:
            vertices, faces = load_mesh(mesh)
            if mesh_hash(vertices, faces) != self.mesh_hash:
                raise ModelFileError(f"model file {path!r} was built for another mesh; rebuild it for this one")
        if bins is not None and tuple(check_bins(bins)) != tuple(self.bins):
            raise ModelFileError(f"model file {path!r} was built with bins={tuple(self.bins)}, but bins={tuple(bins)} was asked for")
        if bounds is not None and bounds != self.bounds:
            raise ModelFileError(f"model file {path!r} was built with bounds={self.bounds!r}, but bounds={bounds!r} was asked for")

    def __repr__(self):
        """One line: counts, settings, diameter and the arrays' memory; never the arrays."""
        d = self.describe()
        parts = [f"{d['facets']:,} facets"]
        if d["patches"] is not None:
            parts.append(f"{d['patches']:,} patches")
        parts.append(f"{d['ordered_pairs']:,} ordered {'facet' if self.table is not None else 'patch'} pairs")
        if self.table is None:
            parts.append("no facet table")
        parts += [f"bins {tuple(self.bins)}", f"bounds={self.bounds!r}", f"diameter {self.diameter:.3g} (mesh units)"]
        if self.max_span is not None:
            parts.append(f"max_span {self.max_span:.3g}")
        if self.winding in WINDING_PROBLEMS:
            parts.append(f"winding {self.winding}")
        parts.append(f"{self.nbytes / 1e6:.3g} MB")
        return f"ObjectModel({', '.join(parts)})"

    @property
    def nbytes(self):
        """Bytes of the model's arrays (mesh, planes, patches and tables)."""
        arrays = [self.vertices, self.faces, *vars(self.planes).values()]
        for table in (self.table, self.patch_table):
            if table is not None:
                arrays += [*table.features.to_arrays().values(), table.offsets]
        if self.patches is not None:
            arrays += list(self.patches.to_arrays().values())
        return int(sum(np.asarray(a).nbytes for a in arrays))

    def describe(self):
        """A dict of the model's size and settings, for reports."""
        return {
            "facets": self.num_facets,
            "degenerate_facets": int((~self.planes.valid).sum()),
            "ordered_pairs": self.num_pairs,
            "facet_table": self.table is not None,
            "bins": list(self.bins),
            "bounds": self.bounds,
            "diameter": self.diameter,
            "max_span": self.max_span,
            "patches": None if self.patches is None else self.patches.count,
        }


def _load_checked(mesh, fix_normals):
    """(vertices, faces) of a mesh, refused first if its facets alone will not fit in memory;
    faces re-wound outward when asked."""
    vertices, faces = load_mesh(mesh)
    check_fits(MESH_BYTES_PER_FACET * len(faces), f"preparing the {len(faces):,} facets of the mesh",
               "decimate the mesh")
    return vertices, (rewind_outward(vertices, faces) if fix_normals else faces)


def _late_diameter(vertices, triangles, planes, patches, find):
    """(diameter, planes, patches) once the memory guard has passed: the planes and patches
    (find : planes -> patches) are redone in the case early_planes did not cover, a diameter
    below its bracket."""
    diameter = mesh_diameter(vertices)
    if diameter < EARLY_LOW * np.linalg.norm(np.ptp(vertices, axis=0)):
        planes = facet_planes(triangles, diameter)
        patches = find(planes)
    return diameter, planes, patches


def _find_patches(merged, planes, bounds, tol_deg):
    """Patches for the default method, or None (no patches, or a paper-bounds model).
    merged : the vertex-merged mesh (for edge adjacency); tol_deg : angle, None or "auto"."""
    if tol_deg is None or bounds != "exact":
        return None
    if isinstance(tol_deg, str) and tol_deg == "auto":
        return _auto_patches(merged, planes)
    if isinstance(tol_deg, (bool, str)) or not (np.isfinite(tol_deg) and 0 <= tol_deg < 90):
        raise MeshError(f"patch_tol_deg must be an angle in [0, 90) degrees, 'auto' or None, got {tol_deg!r}")
    return find_patches(merged, planes, tol_deg)


def _auto_patches(merged, planes):
    """patch_tol_deg="auto": patches at DEFAULT_PATCH_TOL_DEG, or on a fine mesh with a large
    facet table, regions at the first angle of REGION_DEG that shrinks the search."""
    patches = find_patches(merged, planes, DEFAULT_PATCH_TOL_DEG)
    valid = int(np.count_nonzero(planes.valid))
    if patches.worthwhile or valid * (valid + 1) // 2 * STORED_BYTES_PER_PAIR <= FACET_TABLE_AUTO_BYTES:
        return patches
    for angle in REGION_DEG:
        regions = find_patches(merged, planes, angle)
        if regions.worthwhile:
            log.info("%d facets: %d surface regions within %g deg", len(planes.valid), regions.count, angle)
            return regions
    return patches


def _serves(patches):
    """Whether the default method searches patches (they shrink the search enough)."""
    return patches is not None and patches.worthwhile


def _keep_facet_pairs(facet_pairs, patches, pair_count):
    """Whether to keep the facet-level table (see ObjectModel.from_mesh)."""
    if facet_pairs not in (True, False, "auto"):
        raise MeshError(f"facet_pairs must be True, False or 'auto', got {facet_pairs!r}")
    serves = _serves(patches)
    if facet_pairs == "auto":
        return not serves or pair_count * STORED_BYTES_PER_PAIR <= FACET_TABLE_AUTO_BYTES
    if not facet_pairs and not serves:
        raise MeshError("facet_pairs=False needs patches that shrink the search (set patch_tol_deg)")
    return facet_pairs


def _file_features(features, items, compact, derived):
    """A PairFeatures' arrays as a file stores them. items : facets or patches the pairs index;
    compact : k, l as int16 when items < 2¹⁵; derived : leave out DERIVED_FIELDS."""
    arrays = features.to_arrays()
    if compact and derived:
        arrays = {k: v for k, v in arrays.items() if k not in DERIVED_FIELDS}
    if compact and items < 2**15:
        arrays["k"], arrays["l"] = arrays["k"].astype(np.int16), arrays["l"].astype(np.int16)
    return arrays


def _stored_tables(data, facets, values=True):
    """(facet table, patches, patch table) of a model file's arrays, None where absent.
    facets : (m, the array that gives it); values : scan the arrays' values too."""
    patches = Patches.from_arrays(prefixed(data, "patches_"), {"m": facets}, values=values) if _has(data, "patches_") else None
    patch_table = None
    if _has(data, "ptable_", "pfeatures_"):
        if patches is None:
            raise ModelFileError("it has a patch table ('ptable_...') but no patches ('patches_...')")
        patch_table = _stored_table(data, ("ptable_", "pfeatures_"), (patches.count, "patches_normals"),
                                    values=values)
    table = None
    if _has(data, "table_", "features_") or patch_table is None:  # a model has at least one table
        triangles = data["vertices"][data["faces"]]
        table = _stored_table(data, ("table_", "features_"), facets, (triangles, data["normals"]), values)
    return table, patches, patch_table


def _stored_table(data, prefixes, items, planes=None, values=True):
    """A PairTable from the arrays named prefixes[0] + ... and prefixes[1] + ...;
    items : (number of facets or patches its pairs index, the array that gives it);
    planes : (triangles, normals) of a facet table, whose DERIVED_FIELDS a compact file leaves out;
    values : scan the arrays' values too."""
    arrays = {k: _as_int32(v) if k in ("k", "l") else v for k, v in prefixed(data, prefixes[1]).items()}
    if planes is not None and not any(f in arrays for f in DERIVED_FIELDS):
        check_arrays(arrays, STORED_FEATURES, {"n": items}, prefixes[1], ("dmin_exact", "alpha_hi") + DERIVED_FIELDS,
                     values)
        arrays.update(derived_features(*planes, arrays["k"], arrays["l"]))
    features = PairFeatures.from_arrays(arrays)
    return PairTable.from_arrays(prefixed(data, prefixes[0]), features, {"n": items}, prefixes, values)


def _as_int32(a):
    """Pair indices stored as int16 widened to the int32 the build uses (other arrays unchanged)."""
    a = np.asanyarray(a)
    return a.astype(np.int32) if a.dtype.kind == "i" and a.dtype.itemsize < 4 else a


def _has(data, *prefixes):
    return any(key.startswith(prefixes) for key in data)


def _check_span(max_span):
    return None if max_span is None else check_length(max_span, "max_span", MeshError)


def _degenerate_note(planes):
    """What to say of the degenerate facets ("" for none); MeshError if every facet is."""
    bad = np.flatnonzero(~planes.valid)
    if len(bad) == len(planes.valid):
        raise MeshError(f"all {len(bad)} facets are degenerate (zero or near-zero area)")
    if not len(bad):
        return ""
    shown = ", ".join(map(str, bad[:10])) + (" ..." if len(bad) > 10 else "")
    return f"{len(bad)} degenerate facets excluded from pairs (indices kept): {shown}"


def _non_manifold_note(merged):
    """What to say of the non-manifold edges ("" for none). merged : the vertex-merged mesh."""
    shared = int(np.count_nonzero(edge_uses(merged) > 2))
    if not shared:
        return ""
    return (f"mesh has {shared} non-manifold edges (each shared by more than two facets): the pair bounds are per "
            "triangle and stay exact, but the winding and inside checks skip those edges; repair the mesh if "
            "contact normals look wrong there")


def _report_defects(notes, known):
    """A warning per defect, or, for a mesh whose defects are ``known`` (the reason), one
    debug line."""
    notes = [n for n in notes if n]
    if notes and known:
        log.debug("%s: %s", known, "; ".join(n.split(" (")[0] for n in notes))
    elif notes:
        for note in notes:
            warnings.warn(note, stacklevel=3)


def _report_winding(merged):
    """Warn about inward or inconsistent winding; the winding (one of WINDINGS). merged : the
    vertex-merged mesh."""
    winding = winding_state(merged)
    problem = WINDING_PROBLEMS.get(winding)
    if problem:
        warnings.warn(f"{problem}; contact normals will not match (try `--fix-normals`)", stacklevel=3)
    return winding
