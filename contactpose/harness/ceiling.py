"""The best strict top-1 a ranking by fit can reach on a grasp: does the true placement fit best?

On a nearly symmetric object another placement can fit the contacts as well as the true one, or
better. A method that ranks placements by their least surface χ² (costs.surface,
research/surface.md) then names the true one only where it fits best. Per grasp the *ceiling*
is 1 when the true placement's least χ² is below every wrong placement's, 1/m when it ties with
m − 1 of them (their surfaces coincide: a fair choice among them), and 0 when a wrong one fits
better. Its mean over grasps drawn as the benchmark draws them bounds the strict top-1 success
of any ranking by this likelihood on those grasps; a likelihood that knew more of how the
contacts arose could do better where surfaces differ (research/ceiling.md). The posteriors
p_k ∝ exp(−χ²_k / 2) are given too.

The placements are the true one (the surface fit from the true pose, each contact walking
from its nearest facet, or where that fit leaves the true placement, the χ² at the true pose
itself; joined by the search's poses that are strictly right) and the search's strictly wrong
ones (rotation >= 5° or translation >= 5 % of the diameter modulo the object's symmetry), each
fitted on the surface from its facets; wrong fits strictly right of one another are one
placement. A wrong placement the search never found, or whose fit stops above its least χ²,
is missed: the ceiling can only be lower.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contactpose.costs.association import nearest_fit_facets
from contactpose.costs.surface import surface_residuals
from contactpose.geometry.metrics import SUCCESS_ROT_DEG, SUCCESS_TRANS_FRAC
from contactpose.localize import localize
from contactpose.model.symmetry import symmetry
from contactpose.scoring.placements import Placement, laplace_covariance, laplace_log_evidence
from contactpose.solvers.surface import surface_fit

#: The search's best distinct poses fitted on the surface (placement_fits).
CHECKS = 32
#: χ² within this of the true placement's count as fitting as well (ties, wrong_fits_better).
TIE_CHI2 = 1e-6

__all__ = ["CHECKS", "PlacementFits", "placement_fits", "posteriors", "truth_share"]


@dataclass(frozen=True)
class PlacementFits:
    """true_chi2 : the least surface χ² of the true placement; wrong_chi2 (W,) : of each
    strictly wrong placement found; best_right : whether the search's best pose is strictly
    right; best_errors : its rotation (degrees) and translation error modulo the symmetry
    (inf, inf without a hypothesis); drifted : the surface fit from the true pose left the
    true placement (true_chi2 is then the χ² at the true pose, or of a strictly right pose of
    the search). posterior : (W + 1,) the true placement's first (:func:`posteriors`)."""

    true_chi2: float
    wrong_chi2: np.ndarray
    best_right: bool
    best_errors: tuple
    drifted: bool

    @property
    def posterior(self):
        return posteriors(np.concatenate([[self.true_chi2], self.wrong_chi2]))

    @property
    def ties(self):
        """How many wrong placements fit within TIE_CHI2 of the true one."""
        return int(np.count_nonzero(np.abs(self.wrong_chi2 - self.true_chi2) <= TIE_CHI2))

    @property
    def ceiling(self):
        """1 if the true placement fits best, 1/(1 + ties) if it ties, 0 if a wrong one fits better."""
        if np.any(self.wrong_chi2 < self.true_chi2 - TIE_CHI2):
            return 0.0
        return 1.0 / (1 + self.ties)

    @property
    def wrong_fits_better(self):
        """A strictly wrong placement fits at least as well as the true one."""
        return bool(len(self.wrong_chi2) and self.wrong_chi2.min() <= self.true_chi2 + TIE_CHI2)


def posteriors(chi2):
    """p_k = exp(-χ²_k / 2) / Σ_j exp(-χ²_j / 2) of placements with least χ² ``chi2`` (K,). -> (K,)"""
    chi2 = np.asarray(chi2, dtype=np.float64)
    w = np.exp(-0.5 * (chi2 - chi2.min()))
    return w / w.sum()


def placement_fits(model, contacts, true_pose, *, group=None, checks=CHECKS, **options):
    """The surface χ² of the true placement and of each strictly wrong one the search finds
    (see the module). group : the symmetry modulo which a pose is right (default
    ``symmetry(model)``); options : for ``localize`` (the noise, ``finger_radius``), which lists
    every distinct pose and twin here. -> PlacementFits"""
    group = symmetry(model) if group is None else group
    result = localize(model, contacts, keep="all", twins=True, diagnose=False, **options)
    tolerance, D = result.tolerance, model.diameter
    _, _, true_chi2, drifted = _true_fit(model, contacts, true_pose, tolerance, group)
    arrays = result.hypotheses.arrays
    wrong_poses, wrong_chi2 = [], []
    for k in range(min(checks, len(arrays.cost))):
        R, t, _, _, _, chi2 = surface_fit(model, contacts, arrays.fit.R[k], arrays.fit.t[k], arrays.facets[k],
                                          tolerance)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = R, t
        if _right(group, pose, true_pose, D):
            true_chi2 = min(true_chi2, chi2)
        else:
            wrong_poses.append(pose)
            wrong_chi2.append(chi2)
    errors = tuple(float(e) for e in group.errors(arrays.poses[0], true_pose)) if len(arrays.cost) else (np.inf,) * 2
    best_right = _strict(errors, D)
    return PlacementFits(float(true_chi2), _one_per_placement(group, wrong_poses, wrong_chi2, D), best_right, errors,
                         drifted)


def truth_share(model, contacts, result, true_pose, group=None):
    """The share of the Laplace evidence (scoring.placements.laplace_log_evidence) the true
    placement would hold among a ``localize`` Result's placements had the search found it at
    its own floor: its surface fit from the true pose (:func:`placement_fits`' true placement)
    joins the placements strictly right of the truth, the better evidence counting. What the
    answer's placement probability could be with a search that misses nothing it did not
    miss: the share of grasps where this reaches 0.99 bounds the ok share a calibrated
    confidence can give at that threshold. group : the symmetry (default ``symmetry(model)``).
    -> (share in [0, 1], the truth's own χ²_S)"""
    group = symmetry(model) if group is None else group
    pose, facets, chi2, _ = _true_fit(model, contacts, true_pose, result.tolerance, group)
    truth = Placement(-1, np.zeros(0, dtype=np.int64), pose, chi2,
                      laplace_covariance(model, contacts, pose, facets, result.tolerance), 0.0)
    listed = result.placements
    right = [_right(group, p.pose, true_pose, model.diameter) for p in listed]
    log_z = laplace_log_evidence([truth] + [p for p, r in zip(listed, right) if r]
                                 + [p for p, r in zip(listed, right) if not r])
    ours = 1 + sum(right)
    own, wrong = np.max(log_z[:ours]), log_z[ours:]
    total = np.logaddexp.reduce(np.append(wrong, own))
    return (float(np.exp(own - total)) if np.isfinite(own) else 0.0), chi2


def _true_fit(model, contacts, true_pose, tolerance, group):
    """The surface fit from the true pose, each contact walking from its facet of least
    surface cost, or, when that fit leaves the true placement, the true pose itself.
    -> (pose (4, 4), facets (n,), χ²_S, drifted)"""
    start = nearest_fit_facets(model, contacts, true_pose, tolerance, surface=True)
    R, t = true_pose[:3, :3], true_pose[:3, 3]
    fitted = surface_fit(model, contacts, R, t, start, tolerance)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = fitted[0], fitted[1]
    if _right(group, pose, true_pose, model.diameter):
        return pose, fitted[2], float(fitted[5]), False
    return (np.array(true_pose, dtype=np.float64), start,
            float(np.sum(surface_residuals(model, contacts, R, t, start, tolerance) ** 2)), True)


def _right(group, pose, true_pose, diameter):
    return _strict(group.errors(pose, true_pose), diameter)


def _strict(errors, diameter):
    """Whether (rotation degrees, translation) are strictly right."""
    return bool(errors[0] < SUCCESS_ROT_DEG and errors[1] < SUCCESS_TRANS_FRAC * diameter)


def _one_per_placement(group, poses, chi2, diameter):
    """The least χ² of each placement among wrong fits, best first: a fit strictly right of
    a better one joins it. -> (W,)"""
    order = np.argsort(chi2, kind="stable")
    kept = []
    for k in order:
        if not any(_right(group, poses[k], poses[j], diameter) for j in kept):
            kept.append(k)
    return np.array([chi2[k] for k in kept], dtype=np.float64)
