"""Built-in procedural object models.

Every object is a ``trimesh.Trimesh(..., process=False)`` in meters, with faces
wound counter-clockwise seen from outside (outward normals) and no degenerate
facets. Everything is deterministic: the only randomness comes from
``numpy.random.default_rng`` with a fixed seed, passed explicitly.

Use :func:`names` to list the objects and :func:`load` to build one. The
paper's reduced banana (``"banana"``, 53 facets) is shipped as
``data/banana53.ply`` because decimator output may change between library
versions; :func:`make_banana53` regenerates it.

=========  ======  ===========================  ======
name       facets  bounding box (m)             closed
=========  ======  ===========================  ======
banana         53  0.176 x 0.046 x 0.033        no
banana512     512  0.176 x 0.048 x 0.034        yes
carton        256  0.07 x 0.07 x 0.20           yes
rock          320  0.120 x 0.117 x 0.092        yes
rock1k        980  0.150 x 0.126 x 0.095        yes
box            48  0.10 x 0.06 x 0.04           yes
cylinder       96  0.06 x 0.06 x 0.08           yes
sphere        320  0.10 x 0.10 x 0.10           yes
twin_rock     320  0.120 x 0.095 x 0.081        yes
tri_rock      320  0.114 x 0.120 x 0.080        yes
=========  ======  ===========================  ======
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from contactpose.deferred import deferred
from contactpose.errors import ContactPoseError
from contactpose.sim import ycb

trimesh = deferred("trimesh")

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
BANANA53_PATH = DATA_DIR / "banana53.ply"

#: Vertices closer than this (m) are merged when patches are stitched together.
_MERGE_TOL = 1e-9


# --------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------

def _mesh(vertices, faces) -> trimesh.Trimesh:
    """Trimesh from (V, 3) float vertices and (F, 3) int faces, face order kept."""
    return trimesh.Trimesh(np.asarray(vertices, dtype=np.float64),
                           np.asarray(faces, dtype=np.int64), process=False)


def _quad_patch(origin, u, v, nu: int, nv: int):
    """Planar grid of nu x nv quads over the parallelogram origin + [0,1]u + [0,1]v.

    Returns vertices (V, 3) and faces (2*nu*nv, 3) wound so that their normal is
    along ``u x v``.
    """
    i, j = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1), indexing="ij")
    verts = (np.asarray(origin, float)
             + (i.reshape(-1, 1) / nu) * np.asarray(u, float)
             + (j.reshape(-1, 1) / nv) * np.asarray(v, float))
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces


def _tri_patch(a, b, c, k: int):
    """Triangle (a, b, c) split into k*k similar triangles, k segments per edge.

    Returns vertices (V, 3) and faces (k*k, 3) with the winding of (a, b, c).
    """
    i, j = np.array([(i, j) for i in range(k + 1) for j in range(k + 1 - i)]).T
    a, b, c = (np.asarray(p, float) for p in (a, b, c))
    verts = a + (i[:, None] / k) * (b - a) + (j[:, None] / k) * (c - a)
    index = {(ii, jj): n for n, (ii, jj) in enumerate(zip(i, j))}
    faces = [(index[p, q], index[p + 1, q], index[p, q + 1])
             for p in range(k) for q in range(k - p)]
    faces += [(index[p + 1, q], index[p + 1, q + 1], index[p, q + 1])
              for p in range(k) for q in range(k - p - 1)]
    return verts, np.array(faces)


def _stitch(patches) -> trimesh.Trimesh:
    """Concatenate (vertices, faces) patches and merge coincident vertices.

    Vertices within ``_MERGE_TOL`` become one (the first one seen keeps its
    position); vertex order follows first appearance, face order is kept.
    """
    verts, faces, offset = [], [], 0
    for v, f in patches:
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    verts, faces = np.concatenate(verts), np.concatenate(faces)
    near = cKDTree(verts).query_ball_point(verts, _MERGE_TOL)
    rep = np.array([min(group) for group in near])
    keep, new_index = np.unique(rep, return_inverse=True)
    return _mesh(verts[keep], new_index[faces])


def _geodesic_sphere(freq: int) -> trimesh.Trimesh:
    """Unit geodesic sphere: icosahedron faces split freq x freq -> 20*freq**2 facets."""
    ico = trimesh.creation.icosahedron()
    corners = ico.vertices[ico.faces]                     # (20, 3, 3)
    mesh = _stitch(_tri_patch(*tri, freq) for tri in corners)
    directions = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    return _mesh(directions, mesh.faces)


def radial_noise(directions, rng, n_waves: int, max_freq: float):
    """Smooth random field on the unit sphere, (V, 3) directions -> (V,) values.

    A sum of ``n_waves`` plane waves cos(w * d.u + phase) with random unit
    directions u, frequencies w in [1, max_freq] and amplitudes ~ 1/w.
    """
    axes = rng.normal(size=(n_waves, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    freq = rng.uniform(1.0, max_freq, n_waves)
    phase = rng.uniform(0.0, 2 * np.pi, n_waves)
    amp = rng.uniform(0.5, 1.0, n_waves) / freq
    field = np.cos(freq * (directions @ axes.T) + phase) @ amp
    return field / np.abs(field).max()


def _star_shaped(directions, faces, radius, size: float) -> trimesh.Trimesh:
    """Mesh with vertex i at radius[i] * directions[i], scaled so its largest
    bounding-box extent is ``size`` and its bounding-box centre is the origin.

    Radii must be positive; faces of the unit sphere then stay outward-wound.
    """
    verts = directions * radius[:, None]
    verts = verts * (size / np.ptp(verts, axis=0).max())
    verts -= (verts.max(0) + verts.min(0)) / 2
    return _mesh(verts, faces)


# --------------------------------------------------------------------------
# Bananas
# --------------------------------------------------------------------------

_BANANA_SEGMENTS = 8      # vertices around each cross-section
_BANANA_RINGS = 32        # cross-sections along the centreline


def _banana_radius(u):
    """Cross-section radius (m) at arc fraction u in [0, 1]; u=1 is the stem."""
    body_end, r_max, r_stem = 0.86, 0.0175, 0.0045
    t = np.clip(u / body_end, 0.0, 1.0)
    body = r_max * (4 * t * (1 - t)) ** 0.6
    return np.where((u > 0.5) & (body < r_stem), r_stem, body)


def make_banana512() -> trimesh.Trimesh:
    """Synthetic banana, the paper's fig. 8: 512 facets, closed.

    A tube swept along a circular arc (0.19 m long, 70 deg of bend, in the x-y
    plane, bulging to +y) with 8 vertices per ring x 32 rings (496 side facets)
    and two cap fans (16 facets). The section is slightly flattened (out of
    plane 0.92) with four soft ridges; radius 17.5 mm at the middle, tapering
    to a rounded blossom end at -x and a 4.5 mm stem at +x. Bounding box
    0.176 x 0.048 x 0.034 m, centred at the origin.
    """
    length, bend = 0.19, np.deg2rad(70.0)
    arc_r = length / bend
    # Arc fractions: the two apexes at 0 and 1, rings evenly spaced in between.
    u_ring = np.arange(1, _BANANA_RINGS + 1) / (_BANANA_RINGS + 1)
    u_all = np.concatenate([[0.0], u_ring, [1.0]])
    phi = (u_all - 0.5) * bend                       # angle from the arc middle
    centre = arc_r * np.stack([np.sin(phi), np.cos(phi), np.zeros_like(phi)], 1)
    outward = np.stack([np.sin(phi), np.cos(phi), np.zeros_like(phi)], 1)
    up = np.array([0.0, 0.0, 1.0])
    # The stem is cut almost flat: its apex sits only 1 mm beyond the last ring.
    stem_dir = np.array([np.cos(phi[-2]), -np.sin(phi[-2]), 0.0])
    centre[-1] = centre[-2] + 0.001 * stem_dir

    theta = np.arange(_BANANA_SEGMENTS) * 2 * np.pi / _BANANA_SEGMENTS
    shape = 1.0 + 0.04 * np.cos(4 * theta)            # four ridges
    r = _banana_radius(u_ring)[:, None] * shape       # (rings, segments)
    ring = (centre[1:-1, None, :]
            + (r * np.cos(theta))[..., None] * outward[1:-1, None, :]
            + (0.92 * r * np.sin(theta))[..., None] * up)
    verts = np.concatenate([centre[:1], ring.reshape(-1, 3), centre[-1:]])
    verts -= (verts.max(0) + verts.min(0)) / 2
    return _mesh(verts, _tube_faces(_BANANA_RINGS, _BANANA_SEGMENTS))


def _tube_faces(rings: int, segments: int):
    """Faces of a capped tube: vertex 0 = start apex, then ``rings`` rings of
    ``segments`` vertices each (ring by ring), then the end apex.

    Returns (2*segments*rings, 3) ints: start fan, side quads, end fan. They
    are wound outward when the ring vertices advance by the right-hand rule
    about the direction from start to end apex.
    """
    ring_id = 1 + np.arange(rings * segments).reshape(rings, segments)
    nxt = np.roll(ring_id, -1, axis=1)
    a, b = ring_id[:-1].ravel(), nxt[:-1].ravel()
    c, d = nxt[1:].ravel(), ring_id[1:].ravel()
    side = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    end_apex = rings * segments + 1
    start_cap = np.stack([np.zeros(segments, int), nxt[0], ring_id[0]], 1)
    end_cap = np.stack([np.full(segments, end_apex), ring_id[-1], nxt[-1]], 1)
    return np.concatenate([start_cap, side, end_cap])


def make_banana53() -> trimesh.Trimesh:
    """The paper's reduced banana (fig. 9): 53 facets.

    ``make_banana512()`` is reduced to 54 facets by Open3D's quadric
    decimation (a closed mesh loses facets in pairs, so 53 cannot be hit
    directly), then the one facet whose centroid lies furthest toward the
    stem (+x) is cut off, as the paper allows for regions of little interest.
    The result is open at that facet. Unused vertices are dropped.
    """
    reduced = decimate(make_banana512(), 54)
    verts, faces = np.asarray(reduced.vertices), np.asarray(reduced.faces, dtype=np.int64)
    if len(faces) != 54:
        raise RuntimeError(f"quadric decimation gave {len(faces)} facets, expected 54")
    stem_tip = np.argmax(verts[faces].mean(axis=1)[:, 0])
    faces = np.delete(faces, stem_tip, axis=0)
    used, faces = np.unique(faces, return_inverse=True)
    return _mesh(verts[used], faces.reshape(-1, 3))


def write_banana53(path=BANANA53_PATH) -> Path:
    """Regenerate the shipped ``banana53.ply`` (ASCII PLY written by trimesh)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    make_banana53().export(path, file_type="ply", encoding="ascii")
    return path


def load_banana53() -> trimesh.Trimesh:
    """The shipped 53-facet banana, read from ``data/banana53.ply``."""
    return trimesh.load(BANANA53_PATH, force="mesh", process=False)


# --------------------------------------------------------------------------
# Other objects
# --------------------------------------------------------------------------

def make_carton() -> trimesh.Trimesh:
    """Milk carton: 256 facets, closed, 0.07 x 0.07 x 0.20 m.

    A 0.17 m high square body with a gabled top rising 0.03 m to a ridge along
    y. Every wall is split into a grid (4 across, 4 up), so most facets are
    coplanar with their neighbours. Bottom at z=0, centred in x and y.
    """
    w, h, rise, n = 0.07, 0.17, 0.03, 4
    x, y = w / 2, w / 2
    ex, ey, ez = np.eye(3)
    # Eave corners (counter-clockwise seen from above) and the ridge ends.
    e0, e1, e2, e3 = (np.array([sx * x, sy * y, h]) for sx, sy in
                      [(-1, -1), (1, -1), (1, 1), (-1, 1)])
    r0, r3 = np.array([0, -y, h + rise]), np.array([0, y, h + rise])
    patches = [
        _quad_patch([-x, -y, 0], w * ey, w * ex, n, n),     # bottom (-z)
        _quad_patch([-x, -y, 0], w * ex, h * ez, n, n),     # front wall (-y)
        _quad_patch([x, y, 0], -w * ex, h * ez, n, n),      # back wall (+y)
        _quad_patch([x, -y, 0], w * ey, h * ez, n, n),      # right wall (+x)
        _quad_patch([-x, y, 0], -w * ey, h * ez, n, n),     # left wall (-x)
        _quad_patch(e1, e2 - e1, r0 - e1, n, n),            # right roof
        _quad_patch(e3, e0 - e3, r3 - e3, n, n),            # left roof
        _tri_patch(e0, e1, r0, n),                          # front gable
        _tri_patch(e2, e3, r3, n),                          # back gable
    ]
    return _stitch(patches)


def make_rock() -> trimesh.Trimesh:
    """Irregular smooth stone: 320 facets, closed, about 0.12 m across.

    A geodesic sphere (frequency 4) with a smooth random radial perturbation
    (seed 314), flattened to axis ratios 1 : 0.85 : 0.7; star-shaped about
    its centre, which is the origin.
    """
    sphere = _geodesic_sphere(4)
    d = sphere.vertices
    rng = np.random.default_rng(314)
    radius = 1.0 + 0.3 * radial_noise(d, rng, n_waves=6, max_freq=3.0)
    radius *= np.linalg.norm(d * [1.0, 0.85, 0.7], axis=1)
    return _star_shaped(d, sphere.faces, radius, 0.12)


def make_rock1k() -> trimesh.Trimesh:
    """Scanned-object-like irregular body: 980 facets, closed, about 0.15 m across.

    A geodesic sphere (frequency 7), stretched into an elongated lump, with a
    smooth random radial perturbation (seed 1000), a large knob-like
    protrusion and a shallow dent, so it is clearly not sphere-like.
    """
    sphere = _geodesic_sphere(7)
    d = sphere.vertices
    rng = np.random.default_rng(1000)
    radius = 1.0 + 0.15 * radial_noise(d, rng, n_waves=8, max_freq=3.5)
    knob = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
    dent = np.array([-0.2, -0.4, 0.9]) / np.linalg.norm([-0.2, -0.4, 0.9])
    radius += 0.6 * np.exp(-(1 - d @ knob) / 0.06)
    radius -= 0.15 * np.exp(-(1 - d @ dent) / 0.1)
    radius *= np.linalg.norm(d * [1.0, 0.7, 0.6], axis=1)
    return _star_shaped(d, sphere.faces, radius, 0.15)


def make_box() -> trimesh.Trimesh:
    """Plain box 0.10 x 0.06 x 0.04 m, each side split 2 x 2: 48 facets, closed,
    centred at the origin."""
    half = np.array([0.10, 0.06, 0.04]) / 2
    patches = []
    for axis in range(3):
        u_ax, v_ax = (axis + 1) % 3, (axis + 2) % 3
        u, v = np.zeros(3), np.zeros(3)
        u[u_ax], v[v_ax] = 2 * half[u_ax], 2 * half[v_ax]
        for sign in (1.0, -1.0):
            corner = -half.copy()
            corner[axis] = sign * half[axis]
            if sign > 0:           # u x v points along +axis
                patches.append(_quad_patch(corner, u, v, 2, 2))
            else:
                patches.append(_quad_patch(corner, v, u, 2, 2))
    return _stitch(patches)


def make_cylinder() -> trimesh.Trimesh:
    """Capped cylinder, radius 0.03 m, 0.08 m tall along z, 24 segments:
    96 facets (48 side, 24 per cap fan), closed, centred at the origin."""
    segments, radius, height = 24, 0.03, 0.08
    theta = np.arange(segments) * 2 * np.pi / segments
    circle = radius * np.stack([np.cos(theta), np.sin(theta)], 1)
    z = np.array([-height / 2, height / 2])
    rings = np.concatenate([np.column_stack([circle, np.full(segments, zi)]) for zi in z])
    verts = np.concatenate([[[0, 0, z[0]]], rings, [[0, 0, z[1]]]])
    return _mesh(verts, _tube_faces(2, segments))


def make_sphere() -> trimesh.Trimesh:
    """Geodesic icosphere, radius 0.05 m: 320 facets (frequency 4), closed."""
    sphere = _geodesic_sphere(4)
    return _mesh(0.05 * sphere.vertices, sphere.faces)


def make_espresso(faces: int) -> trimesh.Trimesh:
    """The procedural espresso machine (contactpose.sim.espresso), reduced by Open3D's
    quadric decimation to about ``faces`` facets (paper §5: 83,846 scanned, 6,767
    reduced). Deterministic; about 0.35 m across. Not watertight (overlapping parts).
    """
    from contactpose.sim.espresso import espresso_machine

    return decimate(espresso_machine(max(80_000, int(faces * 1.25))), faces)


def decimate(mesh, faces):
    """``mesh`` (trimesh) reduced to about ``faces`` facets by Open3D's quadric decimation, in
    the same frame (the paper's workflow: its banana went from 512 to 53 facets before the
    search). Deterministic."""
    import open3d as o3d  # slow import, only needed here

    o3 = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(mesh.vertices, dtype=np.float64)),
                                   o3d.utility.Vector3iVector(np.asarray(mesh.faces, dtype=np.int32)))
    small = o3.simplify_quadric_decimation(target_number_of_triangles=int(faces))
    return _mesh(np.asarray(small.vertices, dtype=np.float64), np.asarray(small.triangles, dtype=np.int64))


# --------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------

_OBJECTS = {
    "banana": load_banana53,
    "banana512": make_banana512,
    "carton": make_carton,
    "rock": make_rock,
    "rock1k": make_rock1k,
    "box": make_box,
    "cylinder": make_cylinder,
    "sphere": make_sphere,
    "espresso6767": lambda: make_espresso(6_767),
    "espresso83846": lambda: make_espresso(83_846),
}


def names(ycb_objects=True) -> list[str]:
    """Names accepted by :func:`load`: the procedural objects, then the YCB meshes
    (``ycb:011_banana``; sim.ycb) unless ``ycb_objects=False``."""
    return list(_OBJECTS) + (ycb.names() if ycb_objects else [])


def is_builtin(name) -> bool:
    """Whether ``name`` names a built-in object (a procedural one, or any ``ycb:`` name)."""
    return isinstance(name, str) and (name in _OBJECTS or ycb.is_ycb_name(name))


def load(name: str) -> trimesh.Trimesh:
    """Build (or read) the built-in object ``name`` as a fresh mesh: a procedural object,
    or a YCB mesh by ``ycb:`` name (short aliases such as ``ycb:banana`` work too).

    Raises ContactPoseError naming ``name`` and the valid names if unknown.
    """
    if isinstance(name, str) and ycb.is_ycb_name(name):
        return ycb.load(name)
    if not isinstance(name, str) or name not in _OBJECTS:
        raise ContactPoseError(
            f"unknown object {name!r}; expected one of: {', '.join(_OBJECTS)}, or a YCB object "
            f"such as ycb:011_banana (contactpose objects lists them)")
    return _OBJECTS[name]()


def _symmetric_rock(directions, faces, turn, folds: int, shape) -> trimesh.Trimesh:
    """Irregular stone, 0.12 m across, that the rotation ``turn`` maps onto itself.

    directions : (V, 3) unit-sphere vertices, permuted by ``turn`` : (3, 3) of order ``folds``;
    shape : (V,) positive base radius, invariant under ``turn``. The smooth radial perturbation
    (seed 2003) is summed over the powers of ``turn``:
    r(d) = shape(d) · (1 + 0.3 / folds · Σ_m f(turn^m d)), so ``turn`` maps the surface onto itself.
    """
    field, turned = 0.0, directions
    for _ in range(folds):
        field = field + radial_noise(turned, np.random.default_rng(2003), n_waves=6, max_freq=3.0)
        turned = turned @ turn.T
    radius = (1.0 + 0.3 / folds * field) * shape
    return _star_shaped(directions, faces, radius, 0.12)


def make_twin_rock() -> trimesh.Trimesh:
    """Irregular stone with exact two-fold symmetry: 320 facets, closed, 0.12 m across.

    Like :func:`make_rock` (geodesic sphere of frequency 4, axis ratios 1 : 0.85 : 0.7), but
    the smooth radial perturbation is symmetrised (:func:`_symmetric_rock`), so a
    half turn about z maps the surface onto itself and no other rotation does. Contacts then
    fix the pose up to that half turn: two twin poses that place the surface identically.
    """
    sphere = _geodesic_sphere(4)
    d = sphere.vertices
    shape = np.linalg.norm(d * [1.0, 0.85, 0.7], axis=1)
    return _symmetric_rock(d, sphere.faces, np.diag([-1.0, -1.0, 1.0]), 2, shape)


#: Rows: an orthonormal frame whose third axis is the icosahedron's three-fold axis (1, 1, 1) / √3.
_THREEFOLD_FRAME = np.array([[1.0, -1.0, 0.0] / np.sqrt(2), [1.0, 1.0, -2.0] / np.sqrt(6),
                             [1.0, 1.0, 1.0] / np.sqrt(3)])


def make_tri_rock() -> trimesh.Trimesh:
    """Irregular stone with exact three-fold symmetry about z: 320 facets, closed, 0.12 m across.

    The geodesic sphere of :func:`make_twin_rock`, turned so that a three-fold axis of the
    icosahedron is z. Base radius: axis ratios 1 : 1 : 0.7 times a rounded triangular
    cross-section, 1 + 0.15 sin³θ cos 3φ; then the symmetrised perturbation of
    :func:`_symmetric_rock`. A third of a turn about z maps the surface onto itself and no other
    rotation does, so contacts fix the pose up to three twins 120° apart. The z axis passes
    through the origin; z is centred on the bounding box.
    """
    sphere = _geodesic_sphere(4)
    d = sphere.vertices @ _THREEFOLD_FRAME.T
    x, y = d[:, 0], d[:, 1]
    shape = np.linalg.norm(d * [1.0, 1.0, 0.7], axis=1) * (1.0 + 0.15 * (x**3 - 3 * x * y**2))
    third = trimesh.transformations.rotation_matrix(2 * np.pi / 3, [0.0, 0.0, 1.0])[:3, :3]
    rock = _symmetric_rock(d, sphere.faces, third, 3, shape)
    axis = rock.vertices.mean(axis=0) * [1.0, 1.0, 0.0]  # a symmetric vertex set's mean is on the axis
    return _mesh(rock.vertices - axis, rock.faces)


_OBJECTS["twin_rock"] = make_twin_rock
_OBJECTS["tri_rock"] = make_tri_rock
