"""Contact measurements (paper eq. 1) and the tolerances they are matched with.

A contact is an oriented point: the contact point x̃_i and the finger surface
normal ñ_i, which is anti-parallel to the object's outward normal there.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from contactpose import tol
from contactpose.errors import ContactsError


def _as_vectors(name, values, n=None):
    """values -> (n, 3) float64 with all entries finite, else ContactsError naming ``name``."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ContactsError(f"{name} must be numbers of shape (n, 3), got {values!r:.80}") from None
    if arr.ndim != 2 or arr.shape[1] != 3 or (n is not None and arr.shape[0] != n):
        want = "(n, 3)" if n is None else f"({n}, 3)"
        raise ContactsError(f"{name} must have shape {want}, got shape {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = np.flatnonzero(bad)[0]
        raise ContactsError(f"{name} has a NaN or inf entry in row {i}: {arr[i].tolist()}; "
                            "every entry must be a finite number")
    return arr


def _unit(name, normals):
    """Normalise rows; zero rows and rows whose length overflows raise, non-unit rows warn."""
    with np.errstate(over="ignore"):
        norms = np.linalg.norm(normals, axis=1)
    if not np.isfinite(norms).all():
        i = np.flatnonzero(~np.isfinite(norms))[0]
        raise ContactsError(f"{name} row {i} is too long to normalise (its length overflows a float): "
                            f"{normals[i].tolist()}; give unit normals")
    if np.any(norms < 1e-12):
        raise ContactsError(f"{name} row {np.flatnonzero(norms < 1e-12)[0]} is a zero vector; a normal needs a direction")
    off = np.abs(norms - 1.0) > tol.UNIT_NORM
    if off.any():
        warnings.warn(
            f"{name}: {off.sum()} non-unit normals normalised (lengths {np.round(norms[off][:3], 6).tolist()})",
            stacklevel=3,
        )
    return normals / norms[:, None]


@dataclass(frozen=True, init=False)
class Contacts:
    """n >= 1 measured contacts in the world frame (``localize`` needs n >= 2; a touch of a
    tracked object may bring one).

    points : (n, 3) float; finger_normals : (n, 3) float, unit; spread : the largest
    distance between two contacts. Give exactly one of
    ``finger_normals`` (the paper's ñ) or ``object_normals`` (= -ñ) to the constructor.
    """

    points: np.ndarray
    finger_normals: np.ndarray
    spread: float

    def __init__(self, points, finger_normals=None, object_normals=None):
        if (finger_normals is None) == (object_normals is None):
            raise ContactsError("give exactly one of finger_normals or object_normals")
        pts = _as_vectors("points", points)
        if len(pts) < 1:
            raise ContactsError("need at least 1 contact, got 0")
        if finger_normals is not None:
            normals = _unit("finger_normals", _as_vectors("finger_normals", finger_normals, len(pts)))
        else:
            normals = -_unit("object_normals", _as_vectors("object_normals", object_normals, len(pts)))
        spread = _check_spacing(pts)
        pts.flags.writeable = False
        normals.flags.writeable = False
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "finger_normals", normals)
        object.__setattr__(self, "spread", spread)

    @property
    def n(self):
        return len(self.points)

    @property
    def object_normals(self):
        """(n, 3) float: the object's outward normals at the contacts, -ñ."""
        return -self.finger_normals

    def transformed(self, T):
        """These contacts moved by the rigid transform T (4, 4). A rigid motion keeps the
        spacing and the unit normals, so they are not checked again (trackers move every
        touch's contacts at every step)."""
        R, t = T[:3, :3], T[:3, 3]
        moved = object.__new__(Contacts)
        for name, value in (("points", self.points @ R.T + t), ("finger_normals", self.finger_normals @ R.T)):
            value.flags.writeable = False
            object.__setattr__(moved, name, value)
        object.__setattr__(moved, "spread", self.spread)
        return moved

    def joined(self, *others):
        """These contacts followed by those of ``others`` (Contacts), in order."""
        every = (self, *others)
        return Contacts(np.vstack([c.points for c in every]), finger_normals=np.vstack([c.finger_normals for c in every]))

    def permuted(self, order):
        """The contacts in another finger order (these same contacts for their own order).
        order : (k,) int, a selection of the n fingers."""
        if np.array_equal(order, np.arange(self.n)):
            return self
        return Contacts(self.points[order], finger_normals=self.finger_normals[order])

    def to_dict(self):
        return {"contacts": [{"point": p.tolist(), "finger_normal": n.tolist()}
                             for p, n in zip(self.points, self.finger_normals)]}


def _check_spacing(points):
    """Distinct contacts whose distances fit in a float, else ContactsError; returns the
    largest distance. points : (n, 3) finite."""
    with np.errstate(over="ignore", invalid="ignore"):
        diff = points[:, None, :] - points[None, :, :]
        dist = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    if not np.isfinite(dist).all():
        i, j = np.argwhere(np.triu(~np.isfinite(dist), 1))[0]
        raise ContactsError(f"contacts {i} and {j} are too far apart to compute with ({points[i].tolist()} and "
                            f"{points[j].tolist()}); check the units")
    scale = max(float(dist.max()), 1.0)
    i, j = np.nonzero(np.triu(dist <= 1e-12 * scale, 1))
    if len(i):
        raise ContactsError(f"contacts {i[0]} and {j[0]} are at the same point {points[i[0]].tolist()}; each finger needs its own contact")
    return float(dist.max())


@dataclass(frozen=True)
class Tolerance:
    """Pair tolerances σ_Δ (length units) and σ_α (radians) of eq. (5).

    From per-axis sensor noise σ_x and per-axis normal noise σ_n: the difference of
    two contacts' errors has standard deviation √2·σ along the pair direction, and the
    tolerance is ``CONFIDENCE_SIGMA`` (3) times that (research/noise_model.md).
    """

    distance: float
    angle: float
    position_noise: float
    normal_noise: float

    @classmethod
    def from_noise(cls, position_noise, normal_noise_deg, model_error=0.0):
        """position_noise σ_x (length), normal_noise_deg σ_n (degrees), model_error added to σ_Δ."""
        for name, value in (("position_noise", position_noise), ("normal_noise_deg", normal_noise_deg)):
            if not (np.isfinite(value) and value > 0):
                raise ContactsError(f"{name} must be a positive number, got {value!r}")
        if not (np.isfinite(model_error) and model_error >= 0):
            raise ContactsError(f"model_error must be >= 0, got {model_error!r}")
        k = tol.CONFIDENCE_SIGMA * np.sqrt(2.0)
        sigma_n = np.radians(normal_noise_deg)
        return cls(k * position_noise + model_error, min(k * sigma_n, np.pi), float(position_noise), float(sigma_n))

    def widened(self, factor):
        """The same noise with the pair tolerances (distance, angle) ``factor`` times wider."""
        return Tolerance(factor * self.distance, min(factor * self.angle, np.pi), self.position_noise,
                         self.normal_noise)

    def normals_widened(self, factor):
        """The same noise with the angle tolerance ``factor`` times wider, the distance's as it is
        (the direction constraint and the handedness test follow the angle)."""
        return Tolerance(self.distance, min(factor * self.angle, np.pi), self.position_noise, self.normal_noise)

    def direction(self, distance):
        """σ_h for finger pairs Δ̃ apart (scalar or array): σ_Δ + (Δ̃ + σ_Δ)·σ_α.

        A tilt of the measured normal by at most the angle bound moves the other
        contact's height by at most the true distance times that angle (research/errata.md).
        """
        return self.distance + (distance + self.distance) * self.angle

    def per_contact_bounds(self):
        """Error bounds per contact (position, angle) that keep every pair within tolerance."""
        return 0.5 * self.distance, 0.5 * self.angle


def _as_radii(name, values, k):
    """values -> (k,) float64, finite and >= 0, else ContactsError naming ``name``."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ContactsError(f"{name} must be numbers of shape ({k},), got {values!r:.80}") from None
    if arr.shape != (k,):
        raise ContactsError(f"{name} must have shape ({k},), one radius per row, got shape {arr.shape}")
    bad = ~(np.isfinite(arr) & (arr >= 0))
    if bad.any():
        i = np.flatnonzero(bad)[0]
        raise ContactsError(f"{name} entry {i} is {float(arr[i])!r}; every radius must be a finite length >= 0")
    return arr


def _as_tuple(name, value, parts):
    """``value`` as a tuple of len(parts) arrays, else ContactsError naming ``name`` and ``parts``."""
    if isinstance(value, np.ndarray) or not isinstance(value, (tuple, list)) or len(value) != len(parts):
        if isinstance(value, np.ndarray):
            got = f"an array of shape {value.shape}"
        elif isinstance(value, (tuple, list)):
            got = f"a {type(value).__name__} of {len(value)}"
        else:
            got = f"{value!r:.80}".replace("\n", " ")
        raise ContactsError(f"{name} must be a tuple ({', '.join(parts)}), got {got}")
    return tuple(value)


def _frozen(*arrays):
    for a in arrays:
        a.flags.writeable = False
    return arrays


@dataclass(frozen=True, init=False)
class FreeSpace:
    """Space the fingers swept on their way to the contacts (world frame), where the object is not.

    points : (M, 3) float64, free points; spheres : (centres (K, 3), radii (K,)) float64, free
    balls; capsules : (a (L, 3), b (L, 3), radii (L,)) float64, the points within a radius of the
    segment a–b (a finger's approach). Each may be None (none of that kind); radii are >= 0.
    ``localize(..., free_space=...)`` drops the hypotheses whose posed object meets this space
    (contactpose.scoring.freespace).
    """

    points: np.ndarray
    spheres: tuple
    capsules: tuple

    def __init__(self, points=None, spheres=None, capsules=None):
        pts = np.zeros((0, 3)) if points is None else _as_vectors("free_space points", points)
        if spheres is None:
            spheres = (np.zeros((0, 3)), np.zeros(0))
        else:
            centres, radii = _as_tuple("free_space spheres", spheres, ("centres (K, 3)", "radii (K,)"))
            centres = _as_vectors("free_space sphere centres", centres)
            spheres = (centres, _as_radii("free_space sphere radii", radii, len(centres)))
        if capsules is None:
            capsules = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        else:
            a, b, radii = _as_tuple("free_space capsules", capsules, ("a (L, 3)", "b (L, 3)", "radii (L,)"))
            a = _as_vectors("free_space capsule ends a", a)
            b = _as_vectors("free_space capsule ends b", b, len(a))
            capsules = (a, b, _as_radii("free_space capsule radii", radii, len(a)))
        object.__setattr__(self, "points", _frozen(pts)[0])
        object.__setattr__(self, "spheres", _frozen(*spheres))
        object.__setattr__(self, "capsules", _frozen(*capsules))

    @property
    def size(self):
        """How many points, spheres and capsules in all."""
        return len(self.points) + len(self.spheres[1]) + len(self.capsules[2])
