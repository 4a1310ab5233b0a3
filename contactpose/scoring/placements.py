"""Placement probabilities: how sure the answer is that its best pose is the object's.

The hypotheses that fit within noise are grouped into distinct placements: poses strictly
alike modulo the object's symmetry group (rotation within 5°, translation within 5 % of the
diameter) are one (:func:`strict_groups`). A near-symmetric flip (a banana turned end for
end, a box a quarter turn) is a placement of its own, though its surface lies almost where
the truth's does. Each placement is weighed by its evidence on the surface contact model
(costs.surface), Z_k = ∫ exp(-½ χ²_S) dξ over right perturbations ξ of its best pose
(:func:`posterior`): importance sampling, a pilot pass with its Laplace covariance
Σ_k = (Jᵀ J)⁻¹ (J the whitened residuals' Jacobian, Pose3 tangent order, rotation first) as
the proposal and a second with the pilot's own spread, so a placement the contacts pin
tightly holds less volume than a loose one at the same fit, and the facets' bounds and a
rough scan's broad valleys count where the Laplace approximation would ignore them. The shares
p_k = Z_k / Σ Z are the placements' probabilities.

The answer's confidence is the probability that its best pose is *strictly* right (rotation
error below 5°, translation below 5 % of the diameter, geometry.metrics.pose_success): the
share of Σ Z inside that box around the best pose, each placement's sampled evidence counting
where it lies there (a placement 5-10° from the best, a basin of the same valley, holds part
of it). A placement whose information matrix is
singular (a family of poses) holds no share and has no strict mass.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from contactpose.costs.frame import object_frame
from contactpose.costs.surface import SurfaceResiduals, land
from contactpose.geometry.metrics import SUCCESS_ROT_DEG, SUCCESS_TRANS_FRAC
from contactpose.geometry.se3 import retract
from contactpose.scoring.classes import MAX_CLASS_HYPOTHESES
from contactpose.scoring.evidence import prior_mahalanobis2

#: Standard normal draws (6,) of the importance sampler (fixed: the same answer twice).
MASS_DRAWS = 768
#: ... of which the first this many are the pilot pass that shapes the second's proposal.
PILOT_DRAWS = 256
#: The sampler's proposal is the Laplace covariance widened this many times (standard deviations).
PROPOSAL_SCALE = 1.5
#: Placements holding at least this share of the Laplace evidence are weighed by sampling.
SAMPLED_SHARE = 1e-4
#: ... and so is a lone placement whose Laplace posterior holds less than this inside the strict box.
STRICT_MASS_SURE = 0.9999
#: Placements weighed at most (each needs a covariance); the rest are left out.
MAX_PLACEMENTS = 32
#: An information matrix whose smallest eigenvalue is below this share of its largest is singular.
SINGULAR_RATIO = 1e-12

_DRAWS = np.random.default_rng(0).standard_normal((MASS_DRAWS, 6))

__all__ = ["MAX_PLACEMENTS", "Placement", "laplace_covariance", "laplace_log_evidence", "placements", "posterior",
           "strict_groups", "strictly_alike", "surface_chi2"]


def laplace_covariance(model, contacts, pose, facets, tolerance, prior=None):
    """Σ (6, 6) of the surface contact model at ``pose`` (4, 4), the contacts landing from
    ``facets`` (n,) int (-1: unassigned, left out): (Jᵀ J + Σ_prior⁻¹)⁻¹ of the whitened
    residuals (the prior's information, a PosePrior or None, taken in the pose's tangent: a
    first-order match near the prior), or None when it is singular (a direction left free)."""
    res = SurfaceResiduals(model, contacts, pose[:3, :3], pose[:3, 3], np.asarray(facets, dtype=np.int64), tolerance,
                           1.0)
    J = res.jacobian(np.zeros(6))
    info = J.T @ J
    if prior is not None:
        info = info + np.linalg.inv(prior.covariance_matrix())
    w = np.linalg.eigvalsh(info)
    if not np.all(np.isfinite(w)) or w[0] <= SINGULAR_RATIO * max(w[-1], 0.0):
        return None
    return np.linalg.inv(info)


def surface_chi2(model, contacts, poses, facets, tolerance):
    """χ²_S (costs.surface) of K poses (K, 4, 4) at once, each contact landing from its facet
    in ``facets`` (n,) int (-1: unassigned, left out). -> (K,)"""
    used = np.asarray(facets) >= 0
    p, nu = object_frame(poses[:, :3, :3], poses[:, :3, 3], contacts.points[used], contacts.finger_normals[used])
    k, n = p.shape[:2]
    got = land(model.topology, model.triangles, model.planes.normals, model.planes.valid, p.reshape(-1, 3),
               nu.reshape(-1, 3), np.tile(np.asarray(facets)[used], k), tolerance.position_noise,
               tolerance.normal_noise)
    return got.cost.reshape(k, n).sum(axis=1)


def posterior(model, contacts, pose, facets, tolerance, covariance, chi2, others=None, symmetry=None, prior=None,
              center=None):
    """(log evidence, strict mass) of one placement: the evidence log ∫ exp(-½ χ²_S) dξ over
    right perturbations ξ of ``pose`` (4, 4), and the share of it strictly alike ``center``
    (4, 4; None: ``pose`` itself, |ω| below 5° and |v|, the object origin's shift, below 5 %
    of the diameter; else modulo ``symmetry``), by importance sampling (the contacts landing
    from ``facets``, so the facets' bounds and neighbours count, which the Laplace
    approximation misses). A pilot of PILOT_DRAWS goes through the Laplace covariance (6, 6)
    widened PROPOSAL_SCALE times, the rest of MASS_DRAWS through the pilot's weighted mean and
    covariance widened alike plus the Laplace covariance (on a rough scan χ²_S is a broad
    valley of small basins, and its local curvature alone makes the proposal too narrow);
    every draw is weighed against the two proposals' mixture. others : (K, 4, 4) the other
    placements' poses: a draw nearer one of them than ``pose`` (modulo ``symmetry``, in units
    of the strict box) is theirs and counts nothing here, so no mass is counted twice. prior :
    a PosePrior, whose density (-½ its Mahalanobis distance²) joins the likelihood. Without a
    covariance (a pose family): (-½ chi2, 0.0)."""
    if covariance is None:
        return -0.5 * chi2, 0.0
    laplace = 0.5 * (covariance + covariance.T)
    args = (model, contacts, pose, facets, tolerance, others, symmetry, prior, center)
    first = PROPOSAL_SCALE * np.linalg.cholesky(laplace)
    xi = _DRAWS[:PILOT_DRAWS] @ first.T
    log_t, inside = _log_target(*args, xi)
    if not np.isfinite(log_t).any():
        return -np.inf, 0.0
    w = np.exp(log_t - log_t.max())
    mean = w @ xi / w.sum()
    second = np.linalg.cholesky(PROPOSAL_SCALE**2 * np.cov(xi.T, aweights=w, bias=True) + laplace)
    more = mean + _DRAWS[PILOT_DRAWS:] @ second.T
    t2, in2 = _log_target(*args, more)
    xi, log_t, inside = np.concatenate([xi, more]), np.concatenate([log_t, t2]), np.concatenate([inside, in2])
    pilot = PILOT_DRAWS / len(xi)
    log_w = log_t - np.logaddexp(np.log(pilot) + _log_normal(xi, np.zeros(6), first),
                                 np.log(1.0 - pilot) + _log_normal(xi, mean, second))
    top = log_w.max()
    w = np.exp(log_w - top)
    return float(top + np.log(w.mean())), float(w[inside].sum() / w.sum())


def _log_target(model, contacts, pose, facets, tolerance, others, symmetry, prior, center, xi):
    """(log of exp(-½ χ²_S) times the prior's density, -inf where the draw is another
    placement's (N,), whether each lies in the strict box (N,)) at right perturbations ξ
    (N, 6) of ``pose``, as :func:`posterior` weighs them."""
    R, t = retract(np.repeat(pose[None, :3, :3], len(xi), axis=0), np.repeat(pose[None, :3, 3], len(xi), axis=0), xi)
    poses = np.zeros((len(xi), 4, 4))
    poses[:, :3, :3], poses[:, :3, 3], poses[:, 3, 3] = R, t, 1.0
    chi2_s = surface_chi2(model, contacts, poses, facets, tolerance)
    own = _nearest_is_own(poses, pose, others, symmetry, model.diameter)
    log_t = np.where(np.isfinite(chi2_s) & own, -0.5 * (chi2_s + _prior_distance2(R, t, prior)), -np.inf)
    inside = (_inside_box(xi, model.diameter) if center is None
              else _box_distance(poses, center, symmetry, model.diameter) < 1.0)
    return log_t, inside


def _log_normal(xi, mean, L):
    """(N,) log density of N(mean, L Lᵀ) at ξ (N, 6), L lower triangular: by the Cholesky factor,
    since the covariance mixes radians² with lengths² (scipy.stats' eigenvalue cut-off calls it
    singular for an object scaled by 1,000 or 0.001, tests/test_properties.py)."""
    z = solve_triangular(L, (xi - mean).T, lower=True)
    return -0.5 * np.sum(z**2, axis=0) - np.sum(np.log(np.diag(L))) - 3.0 * np.log(2.0 * np.pi)


def _prior_distance2(R, t, prior):
    """(K,) squared Mahalanobis distances of poses (R (K, 3, 3), t (K, 3)) from a PosePrior; 0 without one."""
    return np.zeros(len(R)) if prior is None else prior_mahalanobis2(R, t, prior)


def _nearest_is_own(poses, pose, others, symmetry, diameter):
    """(N,) bool: whether each of poses (N, 4, 4) is at least as near ``pose`` as any of
    ``others`` (K, 4, 4), distances modulo the symmetry in units of the strict box."""
    own = np.ones(len(poses), dtype=bool)
    if others is None or not len(others):
        return own
    mine = _box_distance(poses, pose, symmetry, diameter)
    for other in others:
        own &= mine <= _box_distance(poses, other, symmetry, diameter)
    return own


def _box_distance(poses, pose, symmetry, diameter):
    """max(rotation / 5°, translation / 5 % of the diameter) of poses (N, 4, 4) from ``pose``,
    modulo ``symmetry``. -> (N,)"""
    rot, trans = symmetry.errors(poses, pose)
    return np.maximum(rot / SUCCESS_ROT_DEG, trans / (SUCCESS_TRANS_FRAC * diameter))


@dataclass
class Placement:
    """A distinct placement: hypotheses whose poses are strictly alike modulo the object's
    symmetry group (rotation within 5°, translation within 5 % of the diameter).

    best : rank of its best hypothesis; members : (M,) int ranks; pose : (4, 4) the best's
    pose; chi2 : its χ²; covariance : (6, 6) Laplace Σ at it, or None (a pose family);
    probability : its share of the evidence (:func:`placements`).
    """

    best: int
    members: np.ndarray
    pose: np.ndarray
    chi2: float
    covariance: np.ndarray | None
    probability: float

    def to_dict(self):
        """This placement as JSON (``$defs/placement`` of contactpose/data/result.schema.json)."""
        return {"best": int(self.best), "members": np.asarray(self.members).tolist(), "pose": self.pose.tolist(),
                "chi2": float(self.chi2), "probability": float(self.probability),
                "covariance": None if self.covariance is None else self.covariance.tolist()}


def strictly_alike(poses, pose, symmetry, diameter):
    """(N,) bool: each of poses (N, 4, 4) within 5° and 5 % of the diameter of ``pose`` (4, 4)
    modulo ``symmetry`` (model.symmetry.Symmetry): one placement."""
    rot, trans = symmetry.errors(poses, pose)
    return (rot < SUCCESS_ROT_DEG) & (trans < SUCCESS_TRANS_FRAC * diameter)


def strict_groups(poses, symmetry, diameter, limit=MAX_PLACEMENTS):
    """Greedy grouping of ranked poses (H, 4, 4), best first: each pose not yet taken leads
    and takes every later one strictly alike modulo ``symmetry`` (model.symmetry.Symmetry),
    up to ``limit`` leaders (the rest are left out). -> list of (M,) int, leaders first."""
    free = np.ones(len(poses), dtype=bool)
    groups = []
    while free.any() and len(groups) < limit:
        lead = int(np.flatnonzero(free)[0])
        rows = np.flatnonzero(free)
        members = rows[strictly_alike(poses[rows], poses[lead], symmetry, diameter)]
        members = np.union1d(members, [lead])
        free[members] = False
        groups.append(members)
    return groups


def placements(model, contacts, arrays, fits, tolerance, symmetry, prior=None):
    """The distinct placements of the ranked hypotheses (HypothesisArrays) that fit within
    noise (fits (H,) bool), best first, with their probabilities, and the confidence that the
    best's pose is strictly right: Σ_k p_k m_k, m_k the share of placement k's evidence
    strictly alike the best's pose (a placement a few degrees off, the far end of one broad
    valley, holds some of the best's box too).

    The Laplace evidence (:func:`laplace_log_evidence`) weighs them first; those holding at
    least SAMPLED_SHARE of it are weighed again by :func:`posterior`'s sampling, unless the
    best holds all but SAMPLED_SHARE and its Laplace posterior lies inside the strict box
    with STRICT_MASS_SURE (then the sampling could change nothing that matters).
    symmetry : model.symmetry.Symmetry; prior : a PosePrior or None, whose density weighs
    the placements too. -> (list of Placement, confidence)"""
    rows = np.flatnonzero(fits)[:MAX_CLASS_HYPOTHESES]  # the pose classes' own (scoring.classes)
    if not len(rows):
        return [], 0.0
    groups = [rows[g] for g in strict_groups(arrays.poses[rows], symmetry, model.diameter)]
    found = [Placement(int(g[0]), g, arrays.poses[g[0]], float(arrays.chi2[g[0]]),
                       laplace_covariance(model, contacts, arrays.poses[g[0]], arrays.facets[g[0]], tolerance, prior),
                       0.0)
             for g in groups]
    leaders = np.stack([p.pose for p in found])
    log_z = laplace_log_evidence(found) - 0.5 * _prior_distance2(leaders[:, :3, :3], leaders[:, :3, 3], prior)
    shares = _shares(log_z)
    mass = np.zeros(len(found))
    mass[0] = _box_mass(found[0].covariance, model.diameter)
    sampled = np.flatnonzero(shares >= SAMPLED_SHARE)
    if len(sampled) > 1 or mass[0] < STRICT_MASS_SURE:
        for k in sampled:
            p = found[k]
            log_z[k], mass[k] = posterior(model, contacts, p.pose, arrays.facets[p.best], tolerance, p.covariance,
                                          p.chi2, np.delete(leaders, k, axis=0), symmetry, prior,
                                          center=None if k == 0 else leaders[0])
        shares = _shares(log_z)
    for p, share in zip(found, shares):
        p.probability = float(share)
    return found, float(shares @ mass)


def laplace_log_evidence(found):
    """(K,) -½ χ² + ½ log det(2π Σ) of placements (Placement); a pose family (no Σ) holds
    -inf, unless all are families (then -½ χ²)."""
    chi2 = np.array([p.chi2 for p in found])
    families = np.array([p.covariance is None for p in found])
    if families.all():
        return -0.5 * chi2
    logdet = np.array([-np.inf if p.covariance is None else np.linalg.slogdet(2.0 * np.pi * p.covariance)[1]
                       for p in found])
    return -0.5 * chi2 + 0.5 * logdet


def _shares(log_z):
    """Softmax of log evidences (K,), -inf holding none."""
    w = np.exp(log_z - np.max(log_z))
    return w / w.sum()


def _box_mass(covariance, diameter):
    """Mass of N(0, Σ) inside the strict box, from the fixed draws; 0.0 without a covariance."""
    if covariance is None:
        return 0.0
    xi = _DRAWS @ np.linalg.cholesky(0.5 * (covariance + covariance.T)).T
    return float(np.mean(_inside_box(xi, diameter)))


def _inside_box(xi, diameter):
    """(N,) bool: right perturbations ξ = (ω, v) (N, 6) with |ω| below 5° and |v| (the object
    origin's shift) below 5 % of the diameter: the strict box."""
    return (np.linalg.norm(xi[:, :3], axis=1) < np.radians(SUCCESS_ROT_DEG)) & \
           (np.linalg.norm(xi[:, 3:], axis=1) < SUCCESS_TRANS_FRAC * diameter)
