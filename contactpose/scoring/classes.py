"""Pose classes: hypotheses that place the object's surface the same way count as one.

Symmetric twins and finer labellings of one placement (ADD-S below SAME_CLASS_ADDS_FRAC
of the diameter) form one class; the class probabilities come from the likelihood
exp(-χ²/2) summed over members, or from the factor graph's Laplace evidence.
"""

from __future__ import annotations

import numpy as np

from contactpose.geometry.metrics import SAME_CLASS_ADDS_FRAC, adds_many, rms_displacement
from contactpose.types import PoseClass, fit_threshold

#: At most this many well-fitting hypotheses are grouped into pose classes.
MAX_CLASS_HYPOTHESES = 256


def pose_classes(model, arrays, n, fits=None):
    """Group the ranked hypotheses (HypothesisArrays) that fit within noise into pose
    classes, best class first: :func:`classify_poses` on their poses, χ² and probabilities."""
    return classify_poses(model, arrays.poses, arrays.chi2, n, fits, arrays.probability)


def classify_poses(model, all_poses, chi2, n, fits=None, probability=None):
    """Pose classes of ranked poses, best class first.

    all_poses : (H, 4, 4) best first; chi2 : (H,); fits : (H,) bool, the poses that fit
    (default: χ² <= fit_threshold(n)); probability : (H,) the factor graph's, else the
    likelihood exp(-χ²/2) weighs the classes. A pose joins the first class whose best pose
    is within ADD-S of it, else opens one: each new class takes the best pose left, then
    every later one that matches it.
    """
    fits = np.flatnonzero(chi2 <= fit_threshold(n) if fits is None else fits)[:MAX_CLASS_HYPOTHESES]
    if not len(fits):
        return []
    poses = all_poses[fits]
    label = np.full(len(fits), -1)
    reps = []
    while (left := np.flatnonzero(label < 0)).size:
        rest = left[1:]
        label[left[0]] = len(reps)
        if len(rest):
            label[rest[same_placement(model, poses[rest], poses[left[0]])]] = len(reps)
        reps.append(fits[left[0]])
    members = [fits[label == c] for c in range(len(reps))]
    if probability is not None:  # the factor graph's Laplace evidence
        weight = np.array([np.sum(probability[m]) for m in members])
    else:
        weight = np.array([np.sum(np.exp(-0.5 * (chi2[m] - chi2[fits[0]]))) for m in members])
    prob = weight / weight.sum()
    return [PoseClass(m, int(r), all_poses[r], float(chi2[r]), float(p))
            for m, r, p in zip(members, reps, prob)]


def same_placement(model, poses, pose):
    """(K,) bool: whether each of poses (K, 4, 4) places the surface as ``pose`` does, ADD-S
    below SAME_CLASS_ADDS_FRAC of the diameter, measured on the model's class_points.

    The RMS displacement D bounds ADD from above in closed form, and ADD-S obeys
    |ADD-S(a, pose) - ADD-S(b, pose)| <= ADD(a, b) <= D(a, b). So nearest points are
    queried only for an "anchor" among the undecided poses, whose ADD-S then decides every
    pose within those bounds of it; the answer is ADD-S of each pose against the limit.
    """
    limit = SAME_CLASS_ADDS_FRAC * model.diameter
    points, moments = model.class_points, model.class_moments
    same = rms_displacement(poses, pose, *moments) <= limit
    undecided = np.flatnonzero(~same)
    while len(undecided):
        anchor, rest = undecided[0], undecided[1:]
        s = adds_many(poses[anchor][None], pose, points, model.surface_tree)[0]
        d = rms_displacement(poses[rest], poses[anchor], *moments)
        same[anchor] = s <= limit
        same[rest[s + d <= limit]] = True
        undecided = rest[(s + d > limit) & (s - d <= limit)]
    return same
