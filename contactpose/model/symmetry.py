"""Rotational symmetries of an object: rotations that place its surface (nearly) where it was.

A rotation Q about the surface centroid is a symmetry when ADD-S(Q, I) is below
SYMMETRY_ADDS_FRAC (1 %) of the diameter: tighter than the 5 % that makes two poses one
placement (scoring.classes), which a round but irregular body (the rock) passes at 45°.
Candidates are the turns by 360°/k (k = 2..MAX_FOLD) about the
principal axes of the surface points, which holds the axes of every symmetry of a body
whose inertia has distinct principal moments, and of the symmetry axis of a body of
revolution. An axis that passes every k up to MAX_FOLD is called continuous.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from contactpose.geometry.metrics import adds_many

#: Turns by 360°/k for k up to this are tried about each principal axis.
MAX_FOLD = 8
#: A turn is a symmetry when ADD-S stays below this fraction of the diameter.
SYMMETRY_ADDS_FRAC = 0.01

_FOUND: dict = {}


@dataclass(frozen=True)
class Symmetry:
    """Symmetries about one axis: axis (3,) unit (object frame), through centre (3,);
    folds : the k whose 360°/k turn is a symmetry; continuous : every k up to MAX_FOLD."""

    axis: np.ndarray
    centre: np.ndarray
    folds: tuple
    continuous: bool

    def describe(self):
        axis = ", ".join(f"{v:.2f}" for v in self.axis)
        kind = "rotation" if self.continuous else f"{max(self.folds)}-fold"
        return f"{kind} about axis ({axis})"


def find_symmetries(points, tree, diameter, limit_frac=SYMMETRY_ADDS_FRAC):
    """The object's symmetry axes. points : (N, 3) surface samples (object frame) with
    their cKDTree; diameter : the object's. -> list of Symmetry (empty: none found)."""
    centre = points.mean(axis=0)
    _, axes = np.linalg.eigh(np.cov((points - centre).T))
    limit = limit_frac * diameter
    found = []
    for axis in axes.T:
        turns = [_turn(axis, 2 * np.pi / k, centre) for k in range(2, MAX_FOLD + 1)]
        ok = adds_many(np.stack(turns), np.eye(4), points, tree) <= limit
        folds = tuple(k for k, good in zip(range(2, MAX_FOLD + 1), ok) if good)
        if folds:
            found.append(Symmetry(axis, centre, folds, bool(ok.all())))
    return found


def symmetries(model):
    """:func:`find_symmetries` of a model's surface points, found once per model."""
    key = id(model)
    entry = _FOUND.get(key)
    if entry is not None and entry[0]() is model:
        return entry[1]
    found = find_symmetries(model.surface_points, model.surface_tree, model.diameter)
    _FOUND[key] = (weakref.ref(model, lambda _, key=key: _FOUND.pop(key, None)), found)
    return found


def _turn(axis, angle, centre):
    """(4, 4) rotation by ``angle`` about ``axis`` through ``centre``."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(axis * angle).as_matrix()
    T[:3, 3] = centre - T[:3, :3] @ centre
    return T
