"""Pose classes: hypotheses that place the object's surface the same way count as one.

Symmetric twins and finer labellings of one placement (ADD-S below SAME_CLASS_ADDS_FRAC
of the diameter) form one class; the class probabilities come from the likelihood
exp(-χ²/2) summed over members, or from the factor graph's Laplace evidence.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from contactpose.geometry.metrics import SAME_CLASS_ADDS_FRAC, adds_many, pose_embedding, rms_displacement
from contactpose.model.symmetry import symmetry
from contactpose.options import fit_threshold
from contactpose.types import PoseClass

#: At most this many well-fitting hypotheses are grouped into pose classes.
MAX_CLASS_HYPOTHESES = 256
#: Hypotheses whose poses move the surface by less than this (RMS, the larger of a fraction
#: of the diameter and a multiple of the position noise) are near-copies of one pose: a finer
#: labelling of the same placement by neighbouring facets. The hypothesis list keeps the best
#: of them (:func:`distinct_poses`).
DISTINCT_RMS_FRAC = 0.05
DISTINCT_RMS_SIGMA = 3.0


def pose_classes(model, arrays, fits):
    """Group the ranked hypotheses (HypothesisArrays) that fit within noise, fits (H,) bool,
    into pose classes, best class first: :func:`classify_poses` on their poses, χ² and
    probabilities."""
    return classify_poses(model, arrays.poses, arrays.chi2, None, fits, arrays.probability)


def classify_poses(model, all_poses, chi2, n, fits=None, probability=None):
    """Pose classes of ranked poses, best class first.

    all_poses : (H, 4, 4) best first; chi2 : (H,); n : the contacts, for the default fits;
    fits : (H,) bool, the poses that fit (default: χ² <= fit_threshold(n)); probability :
    (H,) the factor graph's, else the likelihood exp(-χ²/2) weighs the classes. A pose joins the first class whose best pose
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


def distinct_poses(model, arrays, position_noise, deadline=None, merge_twins=False):
    """One hypothesis per distinct pose: the ranked hypotheses (HypothesisArrays) without the
    near-copies of a better one, and how many assignments each one stands for.

    A hypothesis is a near-copy when the surface points (model.class_points) move by less
    than max(DISTINCT_RMS_FRAC · diameter, DISTINCT_RMS_SIGMA · position_noise), RMS, from a
    better-ranked kept hypothesis that is determined or underdetermined as it is. merge_twins : on
    a symmetric object (model.symmetry), compare each pose's canonical twin (Symmetry.canonical)
    instead, so that the twins of a placement, which no contact tells apart, are one pose too.
    Once ``deadline`` (a progress.Deadline) has passed, the rows not yet grouped are kept as
    they are. Returns (arrays of the kept hypotheses in rank order, (K,) int copies per kept
    hypothesis, itself included).
    """
    h = len(arrays.cost)
    if h < 2:
        return arrays, np.ones(h, dtype=np.int64)
    poses = arrays.poses
    group = symmetry(model) if merge_twins else None
    if group is not None and not group.trivial:
        poses = group.canonical(poses)
    owner = pose_leaders(model, poses, arrays.fit.underdetermined, distinct_radius(model, position_noise), deadline)
    kept = np.flatnonzero(owner == np.arange(h))
    return arrays.take(kept), np.bincount(np.searchsorted(kept, owner), minlength=len(kept))


def distinct_radius(model, position_noise):
    """RMS displacement below which two poses are near-copies (see DISTINCT_RMS_FRAC)."""
    return max(DISTINCT_RMS_FRAC * model.diameter, DISTINCT_RMS_SIGMA * position_noise)


def pose_leaders(model, poses, underdetermined, radius, deadline=None):
    """Greedy grouping of ranked poses (H, 4, 4), best first: each pose not yet taken leads a
    group and takes every later one that moves model.class_points by at most ``radius``, RMS,
    and is underdetermined (H,) bool as it is (see :func:`_leaders` for ``deadline``).
    -> (H,) int, the leader of each pose."""
    v = np.concatenate([pose_embedding(poses, *model.class_moments), 1e3 * radius * underdetermined[:, None]], axis=1)
    return _leaders(np.ascontiguousarray(v), radius * radius, deadline)


def _leaders(v, r2, deadline=None):
    """Greedy grouping in rank order: each row not yet taken leads a group and takes every
    later free row within sqrt(r2) of it, found by a k-d tree (the poses lie near a 6-D
    manifold of the 13-D embedding, where a tree prunes and a grid does not). Once
    ``deadline`` has passed, checked before every leader after the first, each row not yet
    taken leads itself. v : (H, d)  ->  (H,) the leader of each row."""
    owner = np.full(len(v), -1)
    if not len(v):
        return owner
    tree = cKDTree(v)
    reach = np.sqrt(r2) * (1.0 + 1e-9)       # the exact test below decides at the boundary
    for lead in range(len(v)):
        if owner[lead] >= 0:
            continue
        if lead and deadline is not None and deadline.passed:
            free = np.flatnonzero(owner < 0)
            owner[free] = free
            break
        near = np.asarray(tree.query_ball_point(v[lead], reach), dtype=np.int64)
        near = near[owner[near] < 0]
        owner[near[np.sum((v[near] - v[lead]) ** 2, axis=1) <= r2]] = lead
        owner[lead] = lead
    return owner


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
