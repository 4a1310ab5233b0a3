"""The rotation group of an object: the rotations about its surface centroid that place its
surface where it was.

A turn is judged by the distances of the turned surface samples (:attr:`ObjectModel.surface_points`,
vertices and facet centroids) to the surface itself (the nearest triangle: :class:`SurfaceDistance`).
Two regimes:

* **exact** (a mesh that maps onto itself: CAD and procedural meshes). Candidate turns take a
  reference vertex to each vertex at its distance from the centroid and a second reference to
  a vertex that keeps both distances (:meth:`_Probe.exact_candidates`); a candidate is a
  symmetry when no sample lands farther than EXACT_FRAC of the diameter from the surface. The
  fold therefore goes as high as the mesh's sections (a 24-section torus is 24-fold), and
  every axis comes from the mesh itself (a cube's 3- and 4-fold axes, a prism's half turns).
  An N-fold axis is *continuous* when its half step (180°/N) and generic turns move no sample
  farther than FINE_FRAC (0.2 %) of the diameter: a faceted body of revolution. A 32-section
  cylinder moves by 0.12 % and is continuous; a 24-section torus or annulus moves by 0.30 %,
  the built-in 24-segment cylinder by 0.22 %: they are 24-sided prisms.
* **near** (scans, when nothing maps exactly): a turn is a symmetry when its ADD-S, the mean
  distance of the turned samples to the surface, is below SYMMETRY_ADDS_FRAC (0.75 %) of the
  diameter, and for a discrete fold when it is also a clear minimum (at most CLEAR times the
  least ADD-S of the generic turns). The YCB boxes pass their half turns at 0.2-0.7 %, the
  cans and the bowl every turn about their axis at 0.1-0.5 %; the 53-facet banana's best half
  turn (0.85 %), the rock's (0.88 %) and the YCB scissors' (0.83 %) do not. Candidate axes:
  the principal axes of the surface's second moment (area-weighted about the centroid), which
  hold every symmetry axis of a body whose three moments differ; where two are equal (within
  MOMENT_TOL) half turns across the third axis are swept every SWEEP_DEG; where all three are
  equal, every rotation is tried (a sphere), then the frame of the dominant facet normals (a
  cube).

The group: the symmetries closed under products, as (K, 4, 4) object-frame transforms about
the centroid (identity first), and the continuous axes; a continuous axis absorbs the turns
about it and keeps the identity and one half turn across it, if any. Found once per model
(:func:`symmetry`): 4 ms (a box) to 0.3 s (a 24-section torus) on meshes of up to 1,000 facets,
0.1-0.2 s on the 16,384-facet YCB banana, mug and drill (research/symmetry.md).
"""

from __future__ import annotations

import logging
import math
import weakref
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.geometry.kernels import point_triangle_distance
from contactpose.geometry.metrics import mssd, nearest_twins, symmetric_errors
from contactpose.io.modelfile import STORED_SYMMETRY, check_arrays

log = logging.getLogger(__name__)

#: Rotation vector (radians) of the pose a twin is chosen nearest to (Symmetry.canonical): a
#: generic one, since the identity is as far from several twins of an axis-aligned pose.
CANONICAL_REFERENCE = (0.5, -0.3, 0.2)
#: Near regime: a turn is a symmetry when ADD-S (mean distance of the turned surface samples
#: to the surface) stays below this fraction of the diameter.
SYMMETRY_ADDS_FRAC = 0.0075
#: Near regime: a discrete fold's ADD-S must also be at most this times the generic turns' least.
CLEAR = 0.5
#: Exact regime: a turn maps the mesh onto itself when no sample lands farther than this
#: fraction of the diameter from the surface (float32 STL coordinates round at 6e-8).
EXACT_FRAC = 1e-6
#: Exact regime: an axis is continuous when its half step moves no sample farther than this.
FINE_FRAC = 0.002
#: Near regime: turns by 360°/k, k = 2..MAX_FOLD, are tried about each candidate axis.
MAX_FOLD = 12
#: Generic turns (fractions of a full turn) that only a continuous axis passes.
GENERIC_TURNS = (0.1180339887, 0.2763932023, 0.381966011, 0.4472135955)
#: Principal moments within this fraction of the larger of two count as equal.
MOMENT_TOL = 0.05
#: Near regime, two equal moments: half turns across the third axis, every this many degrees.
SWEEP_DEG = 2.0
#: Near regime, three equal moments: facet normals within this angle (degrees) form a cluster.
CLUSTER_DEG = 5.0
#: Exact regime: candidate turns tried at most.
MAX_MATCHES = 2000
#: Samples of the first, cheap stage of the exact tests and the sweeps.
STAGE_POINTS = 64
#: SurfaceDistance: the facets of this many nearest centroids are measured per point, or every
#: facet when points x facets is at most BRUTE_PAIRS.
NEAREST_FACETS = 16
BRUTE_PAIRS = 100_000
#: Largest group kept (a safeguard).
MAX_ORDER = 240

_FOUND: dict = {}


@dataclass(frozen=True, eq=False)
class Symmetry:
    """The rotation group of an object, in its frame, about its surface centroid.

    rotations : (K, 4, 4) transforms G = [Q, c - Q c] that place the surface where it was,
    the identity first; axes : (C, 3) unit axes through ``centre`` about which every turn is a
    symmetry (C = 0: none; 1: an axis, the group is its turns times ``rotations``; 3: every
    rotation, a sphere); centre : (3,) c; exact : found by the exact regime (the mesh maps
    onto itself) rather than the near one (ADD-S below SYMMETRY_ADDS_FRAC of the diameter).
    """

    rotations: np.ndarray
    axes: np.ndarray
    centre: np.ndarray
    exact: bool = True

    def to_arrays(self):
        """The group as a model file stores it (io.modelfile.STORED_SYMMETRY)."""
        return {"rotations": self.rotations, "axes": self.axes, "centre": self.centre, "exact": np.array(self.exact)}

    @classmethod
    def from_arrays(cls, arrays, prefix="symmetry_", values=True):
        """The group of a model file's arrays, checked (values : their values too)."""
        check_arrays(arrays, STORED_SYMMETRY, {}, prefix, values=values)
        rotations = np.array(arrays["rotations"], dtype=np.float64)
        return cls(rotations, np.array(arrays["axes"], dtype=np.float64).reshape(-1, 3),
                   np.array(arrays["centre"], dtype=np.float64), bool(arrays["exact"]))

    @property
    def trivial(self):
        """True when only the identity places the surface where it was."""
        return len(self.rotations) == 1 and len(self.axes) == 0

    @property
    def order(self):
        """Number of rotations in the group (inf with a continuous axis)."""
        return math.inf if len(self.axes) else len(self.rotations)

    def errors(self, T_est, T_true):
        """Rotation (degrees) and translation error of T_est against T_true modulo the group:
        :func:`contactpose.geometry.metrics.symmetric_errors`. T_* : (..., 4, 4) -> ((...), (...))"""
        return symmetric_errors(T_est, T_true, self.rotations, self.axes, self.centre)

    def mssd(self, T_est, T_true, points):
        """The BOP challenge's MSSD of T_est ((K, 4, 4) or (4, 4)) against T_true (4, 4) under
        this group, over the object-frame vertices ``points`` (N, 3):
        :func:`contactpose.geometry.metrics.mssd`. -> (K,) or a float, in length units"""
        return mssd(T_est, T_true, points, self.rotations, self.axes, self.centre)

    def canonical(self, poses):
        """Each pose's twin (the poses T G that place the surface as T does) of least rotation
        from CANONICAL_REFERENCE: the same pose for every twin of a placement, so that twins
        compare as one pose (scoring.classes.distinct_poses). poses : (..., 4, 4) -> (..., 4, 4)"""
        reference = np.eye(4)
        reference[:3, :3] = Rotation.from_rotvec(CANONICAL_REFERENCE).as_matrix()
        return nearest_twins(reference, poses, self.rotations, self.axes, self.centre)

    def describe(self):
        """The group in words, e.g. "24-fold about axis (0.00, 0.00, 1.00)"."""
        if len(self.axes) >= 2:
            return "every rotation about the centroid (a sphere)"
        if len(self.axes) == 1:
            across = " and half turns across it" if len(self.rotations) > 1 else ""
            return f"rotation about axis {_text(self.axes[0])}{across}"
        folds = _axis_folds(self.rotations[:, :3, :3])
        if not folds:
            return "no symmetry"
        order = len(self.rotations)
        (main, k), *others = sorted(folds, key=lambda f: -f[1])
        if not others:
            return f"{k}-fold about axis {_text(main)}"
        if order == 4:
            a, b, c = (_text(axis) for axis, _ in folds)
            return f"4 rotations (those of a box): half turns about axes {a}, {b} and {c}"
        if order == 2 * k and all(f == 2 for _, f in others):
            return (f"{order} rotations (those of a {k}-sided prism): {k}-fold about axis {_text(main)} and {k} half "
                    "turns across it")
        solid = {12: "a tetrahedron", 24: "a cube", 60: "an icosahedron"}.get(order)
        return f"{order} rotations (those of {solid})" if solid else f"{order} rotations about {len(folds)} axes"


def symmetry(model):
    """The :class:`Symmetry` group of a model's surface, found once per model object."""
    entry = _FOUND.get(id(model))
    if entry is not None and entry[0]() is model:
        return entry[1]
    group = find_symmetry(model)
    remember(model, group)
    return group


def remember(model, group):
    """Keep ``group`` as the symmetry of ``model`` (a model file's stored one, say)."""
    key = id(model)
    _FOUND[key] = (weakref.ref(model, lambda _, key=key: _FOUND.pop(key, None)), group)


def symmetries(model):
    """[the model's :class:`Symmetry`], or [] when it has none (the status hint's list)."""
    group = symmetry(model)
    return [] if group.trivial else [group]


def find_symmetry(model):
    """The rotation group of a model's surface (see the module's notes). -> Symmetry"""
    probe = _Probe(model)
    group = _exact_group(probe)
    if group is None:
        group = _near_group(probe)
    log.debug("symmetry (%s regime): %s", "exact" if group.exact else "near", group.describe())
    return group


class SurfaceDistance:
    """Distance of points to a model's surface (its valid facets): against every facet on a
    small mesh (points x facets at most BRUTE_PAIRS), else the least over the facets whose
    centroids are the NEAREST_FACETS nearest, an upper bound that equals the distance unless
    a much larger facet lies nearer (on the YCB mug, 16 give every distance exactly, 8 within
    0.1 mm). An upper bound keeps the tests sound: a distance found below a tolerance is below
    it. Compiled kernels on a k-d tree, without Open3D's import on the path of every localize
    (the status hint names the symmetry)."""

    def __init__(self, model):
        self.tree, valid, _ = model.centroid_tree
        self.triangles = model.triangles[valid]

    def __call__(self, points):
        """points : (N, 3) object frame -> (N,) distances."""
        n, m = len(points), len(self.triangles)
        if n * m <= BRUTE_PAIRS:
            return point_triangle_distance(np.repeat(points, m, axis=0), np.tile(self.triangles, (n, 1, 1))) \
                .reshape(n, m).min(axis=1)
        k = min(NEAREST_FACETS, m)
        _, idx = self.tree.query(points, k=k)
        return point_triangle_distance(np.repeat(points, k, axis=0), self.triangles[idx.ravel()]).reshape(n, k).min(axis=1)


class _Probe:
    """A model's samples, centroid, moments and vertices, and the turn tests on them."""

    def __init__(self, model):
        valid = model.planes.valid
        self.areas = model.planes.areas[valid]
        centroids = model.centroids[valid]
        self.centre = self.areas @ centroids / self.areas.sum()
        rel = centroids - self.centre
        self.moments, self.principal = np.linalg.eigh((rel * self.areas[:, None]).T @ rel / self.areas.sum())
        self.vertices = np.unique(model.vertices[np.unique(model.faces[valid])], axis=0)
        self.normals = model.planes.normals[valid]
        self.points = model.surface_points
        self.few = self.points[:: max(1, len(self.points) // STAGE_POINTS)]
        self.diameter = model.diameter
        self.distance = SurfaceDistance(model)

    def turn(self, axis, angle):
        """(4, 4) rotation by ``angle`` about ``axis`` through the centroid."""
        return _turn_matrix(_rotation(axis, angle), self.centre)

    def moved(self, T, points=None):
        """(mean, max) distance of the samples (or ``points``) moved by T (4, 4) to the surface."""
        points = self.points if points is None else points
        d = self.distance(points @ T[:3, :3].T + T[:3, 3])
        return float(d.mean()), float(d.max())

    def exact(self, T):
        """Whether T maps every sample onto the surface within EXACT_FRAC of the diameter
        (tried on a quarter of the cheap samples first)."""
        limit = EXACT_FRAC * self.diameter
        return self.moved(T, self.few[::4])[1] <= limit and self.moved(T)[1] <= limit

    def fine(self, T):
        """Whether T moves no sample farther than FINE_FRAC of the diameter from the surface."""
        return self.moved(T)[1] <= FINE_FRAC * self.diameter

    def adds(self, T):
        """ADD-S of T as a fraction of the diameter: on the cheap samples alone when they put
        it beyond three times SYMMETRY_ADDS_FRAC, else on all."""
        few = self.moved(T, self.few)[0] / self.diameter
        return few if few > 3.0 * SYMMETRY_ADDS_FRAC else self.moved(T)[0] / self.diameter

    def exact_candidates(self):
        """Rotations (3, 3) about the centroid that could map the mesh onto itself: each takes
        a reference vertex p to a vertex at its distance from the centroid, and a second one q
        (not in line with p) to a vertex at its distance from the centroid and from p's image;
        the references are taken from the rarest such distances. The identity left out; at
        most MAX_MATCHES."""
        rel = self.vertices - self.centre
        radius = np.linalg.norm(rel, axis=1)
        tol = 10 * EXACT_FRAC * self.diameter
        order = np.argsort(radius)
        label = np.empty(len(radius), dtype=np.int64)
        label[order] = np.cumsum(np.r_[0, np.diff(radius[order]) > tol])
        size = np.bincount(label)[label]
        off = radius > 1e-3 * self.diameter
        if off.sum() < 2:
            return []
        p = int(np.flatnonzero(off)[np.argmin(size[off])])
        apart = off & (np.linalg.norm(np.cross(rel, rel[p]), axis=1) > 1e-3 * radius * radius[p])
        if not apart.any():
            return []
        q = int(np.flatnonzero(apart)[np.argmin(size[apart])])
        images_q = np.flatnonzero(label == label[q])
        span = np.linalg.norm(rel[q] - rel[p])
        frame = _frame(rel[p], rel[q])
        found = []
        for i in np.flatnonzero(label == label[p]):
            near = images_q[np.abs(np.linalg.norm(rel[images_q] - rel[i], axis=1) - span) <= tol]
            found += [_frame(rel[i], rel[j]) @ frame.T for j in near if j != i and (i, j) != (p, q)]
            if len(found) >= MAX_MATCHES:
                log.debug("symmetry: more than %d candidate turns; the exact search stops there", MAX_MATCHES)
                break
        return found[:MAX_MATCHES]

    def near_axes(self):
        """(candidate axes (A, 3), the axis across which half turns are swept or None, whether
        all three moments are equal) for the near regime."""
        w = self.moments
        equal = np.diff(w) <= MOMENT_TOL * np.maximum(w[1:], 1e-300)
        axes = self.principal.T
        if equal.all():
            return np.concatenate([axes, self._normal_frame()]), None, True
        if equal.any():
            return axes, axes[0 if equal[1] else 2], False
        return axes, None, False

    def _normal_frame(self):
        """(3, 3) rows: an orthonormal frame of the dominant facet normals (area within
        CLUSTER_DEG, opposite normals as one): the first, the first nearly across it, and
        their cross product; for a body of three equal moments that is a cube."""
        n = self.normals * np.where(self.normals @ np.array([0.5772, 0.6180, 0.5326]) < 0, -1.0, 1.0)[:, None]
        support = (np.abs(n @ n.T) >= np.cos(np.radians(CLUSTER_DEG))) @ self.areas if len(n) <= 4096 else \
            _grid_support(n, self.areas)
        a = n[np.argmax(support)]
        across = np.abs(n @ a) <= np.sin(np.radians(2 * CLUSTER_DEG))
        if not across.any():
            return np.zeros((0, 3))
        b = n[np.flatnonzero(across)[np.argmax(support[across])]]
        b = b - (b @ a) * a
        b /= np.linalg.norm(b)
        return np.array([a, b, np.cross(a, b)])


def _grid_support(n, areas):
    """(F,) the area of the facets whose normals share each normal's CLUSTER_DEG grid cell."""
    keys = np.round(n / np.radians(CLUSTER_DEG)).astype(np.int64)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    return np.bincount(inverse.ravel(), weights=areas)[inverse.ravel()]


def _frame(u, v):
    """(3, 3) right-handed orthonormal frame (columns) of u and the part of v across it."""
    a = u / np.linalg.norm(u)
    b = v - (v @ a) * a
    b /= np.linalg.norm(b)
    return np.column_stack([a, b, np.cross(a, b)])


def _exact_group(probe):
    """The group of a mesh that maps onto itself (the candidates of
    :meth:`_Probe.exact_candidates` that do), or None when only the identity does. An axis
    of fold N > 2 whose half step and first generic turns move no sample farther than
    FINE_FRAC of the diameter is continuous."""
    found = [Q for Q in probe.exact_candidates() if probe.exact(_turn_matrix(Q, probe.centre))]
    if not found:
        return None
    rotations = _closure(found)
    continuous = [axis for axis, n in _axis_folds(np.stack(rotations)) if n > 2 and all(
        probe.fine(probe.turn(axis, angle)) for angle in (np.pi / n, *(2 * np.pi * f for f in GENERIC_TURNS[:2])))]
    return _group(probe, rotations, continuous, exact=True)


def _near_group(probe):
    """The group under the near regime's ADD-S test (possibly the identity alone): about each
    candidate axis its largest clear fold whose divisors all pass, or a continuous axis; the
    swept half turns; every rotation for a sphere. The products of the folds found must pass
    too, else only the clearest fold is kept."""
    axes, unique, equal = probe.near_axes()
    if equal and _sphere(probe):
        return Symmetry(np.eye(4)[None], np.eye(3), probe.centre, exact=False)
    found, continuous = [], []
    for axis in axes:
        kind, fold, score = _near_axis(probe, axis)
        if kind == "continuous":
            continuous.append(axis)
        elif kind == "fold":
            found.append((score, _rotation(axis, 2 * np.pi / fold)))
    if unique is not None:
        flip = _swept_flip(probe, unique)
        if flip is not None:
            found.append(flip)
    if len(continuous) >= 2:
        return Symmetry(np.eye(4)[None], np.eye(3), probe.centre, exact=False)
    if continuous:
        return _group(probe, [np.eye(3)] + [Q for _, Q in found], continuous, exact=False)
    found.sort(key=lambda f: f[0])
    rotations = _closure([Q for _, Q in found])
    if not all(probe.adds(_turn_matrix(Q, probe.centre)) <= SYMMETRY_ADDS_FRAC for Q in rotations[1:]):
        log.debug("symmetry: the near symmetries' products do not pass; the clearest fold alone is kept")
        rotations = _closure([Q for _, Q in found[:1]])
    return _group(probe, rotations, [], exact=False)


def _near_axis(probe, axis):
    """("continuous" | "fold" | "none", fold, its ADD-S) about one axis: continuous when every
    fold up to MAX_FOLD and every generic turn pass; else the largest fold that passes, is a
    clear minimum (CLEAR) and whose divisors pass too."""
    folds = {k: probe.adds(probe.turn(axis, 2 * np.pi / k)) for k in range(2, MAX_FOLD + 1)}
    generic = [probe.adds(probe.turn(axis, 2 * np.pi * f)) for f in GENERIC_TURNS]
    if max(*folds.values(), *generic) <= SYMMETRY_ADDS_FRAC:
        return "continuous", 0, max(generic)
    passed = {k for k, s in folds.items() if s <= min(SYMMETRY_ADDS_FRAC, CLEAR * min(generic))}
    whole = [k for k in passed if all(d in passed for d in range(2, k + 1) if k % d == 0)]
    return ("fold", max(whole), folds[max(whole)]) if whole else ("none", 1, math.inf)


def _swept_flip(probe, axis):
    """(ADD-S, (3, 3) half turn) about the best direction across ``axis`` (swept every
    SWEEP_DEG on the cheap samples, then measured on all), or None when it does not pass."""
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    angles = np.radians(np.arange(0.0, 180.0, SWEEP_DEG))
    directions = np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2
    best = directions[np.argmin([probe.moved(probe.turn(d, np.pi), probe.few)[0] for d in directions])]
    score = probe.adds(probe.turn(best, np.pi))
    return (score, _rotation(best, np.pi)) if score <= SYMMETRY_ADDS_FRAC else None


def _sphere(probe):
    """Whether turns by generic angles about generic axes all pass the near test."""
    axes = np.array([[1.0, 2.0, 3.0], [-2.0, 1.0, 0.5], [0.3, -1.0, 2.0], [1.0, 1.0, -1.0]])
    return all(probe.adds(probe.turn(a / np.linalg.norm(a), 2 * np.pi * f)) <= SYMMETRY_ADDS_FRAC
               for a, f in zip(axes, GENERIC_TURNS))


def _group(probe, rotations, continuous, exact):
    """The Symmetry of a group's rotations (3, 3) each, identity first, and its continuous
    axes: two make every rotation; one absorbs the turns about it, and the identity and one
    half turn across it (if any) remain."""
    centre = probe.centre
    if len(continuous) >= 2:
        return Symmetry(np.eye(4)[None], np.eye(3), centre, exact)
    if continuous:
        axis = continuous[0]
        across = [Q for Q in rotations[1:] if abs(_axis_angle(Q)[0] @ axis) < 1e-3]
        rotations = [np.eye(3)] + across[:1]
    return Symmetry(np.stack([_turn_matrix(Q, centre) for Q in rotations]), np.array(continuous).reshape(-1, 3),
                    centre, exact)


def _closure(generators):
    """The group the rotations (3, 3) generate, identity first: products of the new rotations
    with the group until none is new (within 1e-6, Frobenius); at most MAX_ORDER rotations."""
    group = np.eye(3)[None]
    batch = np.asarray(generators, dtype=np.float64).reshape(-1, 3, 3)
    while len(batch) and len(group) < MAX_ORDER:
        new = []
        for Q in batch[np.linalg.norm(batch[:, None] - group[None], axis=(2, 3)).min(axis=1) > 1e-6]:
            if all(np.linalg.norm(Q - P) > 1e-6 for P in new):
                new.append(Q)
        if not new:
            break
        new = np.stack(new)[: MAX_ORDER - len(group)]
        group = np.concatenate([group, new])
        batch = np.concatenate([(new[:, None] @ group[None]).reshape(-1, 3, 3),
                                (group[:, None] @ new[None]).reshape(-1, 3, 3)])
    return list(group)


def _rotation(axis, angle):
    """(3, 3) rotation by ``angle`` about the unit ``axis``."""
    return Rotation.from_rotvec(np.asarray(axis) * angle).as_matrix()


def _turn_matrix(Q, centre):
    """(4, 4) [Q, c - Q c]: the rotation Q (3, 3) about ``centre``."""
    T = np.eye(4)
    T[:3, :3] = Q
    T[:3, 3] = centre - Q @ centre
    return T


def _axis_angle(Q):
    """(unit axis (3,), angle in radians) of a rotation matrix."""
    v = Rotation.from_matrix(Q).as_rotvec()
    angle = float(np.linalg.norm(v))
    return (v / angle if angle > 0 else np.array([0.0, 0.0, 1.0])), angle


def _axis_folds(rotations):
    """[(axis (3,), fold)] of a finite group's rotations (K, 3, 3), identity first: each axis
    once (its sign canonical), its fold the number of the group's turns about it plus one."""
    folds = []
    for Q in rotations[1:]:
        axis = _canonical(_axis_angle(Q)[0])
        for f in folds:
            if abs(f[0] @ axis) > 1 - 1e-6:
                f[1] += 1
                break
        else:
            folds.append([axis, 2])
    return [(a, k) for a, k in folds]


def _canonical(v):
    """v with its largest component made positive (an axis's sign is arbitrary)."""
    return v if v[np.argmax(np.abs(v))] > 0 else -v


def _text(axis):
    """'(0.00, 0.00, 1.00)', the axis's sign canonical, without negative zeros."""
    return "(" + ", ".join(f"{x + 0.0:.2f}" for x in np.round(_canonical(axis), 2)) + ")"
