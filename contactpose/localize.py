"""The online phase (§3.2, §4): contacts -> S_ij -> tree T -> pose per hypothesis -> ranking.

``method="fast"`` (default): exact Δmin bounds, vectorized tree, closed-form poses,
ranked by the origin-invariant χ² that includes each contact's distance outside
its facet triangle. ``method="paper"``: the paper as published — vertex-only
Δmin, the node-by-node tree, Levenberg–Marquardt on eq. (7), ranked by eq. (7).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from contactpose import residuals as res
from contactpose.contacts import Contacts, Tolerance, pair_conditions
from contactpose.errors import ContactPoseError, PriorError, ResourceError
from contactpose.hypotheses import TripleTest, admissible_pairs, join_tuples, join_tuples_paper
from contactpose.patches import nearest_members
from contactpose.metrics import SAME_CLASS_ADDS_FRAC, adds, displacement_bound
from contactpose.solvers.closed_form import PoseFit, fit_poses
from contactpose.solvers.lm import fit_lm_all

METHODS = ("fast", "paper")
SOLVERS = ("closed-form", "lm")
#: Probability that a correct hypothesis passes the fit test (χ² quantile, 3 dof per contact).
FIT_CONFIDENCE = 0.9973
#: At most this many well-fitting hypotheses are compared with the best for ambiguity.
MAX_AMBIGUITY_CHECKS = 64
#: Default position noise when none is given: this fraction of the object diameter.
DEFAULT_POSITION_NOISE_FRAC = 0.0025
STATUSES = ("ok", "no_hypothesis", "underdetermined", "ambiguous")


@dataclass(frozen=True)
class PosePrior:
    """A vision estimate of T_world_object with its uncertainty.

    pose : (4, 4) rigid transform; sigma_rot_deg, sigma_trans : standard deviations
    (degrees, length units), or covariance : (6, 6) in Pose3 tangent order (rotation first).
    """

    pose: np.ndarray
    sigma_rot_deg: float | None = None
    sigma_trans: float | None = None
    covariance: np.ndarray | None = None

    def __post_init__(self):
        pose = check_rigid(self.pose, "prior pose")
        object.__setattr__(self, "pose", pose)
        if self.covariance is not None:
            cov = np.asarray(self.covariance, dtype=np.float64)
            if cov.shape != (6, 6) or not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T, atol=1e-12):
                raise PriorError(f"prior covariance must be a finite symmetric (6, 6) matrix, got shape {cov.shape}")
            if np.linalg.eigvalsh(cov).min() <= 0:
                raise PriorError("prior covariance must be positive definite")
            object.__setattr__(self, "covariance", cov)
            return
        for name in ("sigma_rot_deg", "sigma_trans"):
            value = getattr(self, name)
            if value is None or not (np.isfinite(value) and value > 0):
                raise PriorError(f"prior {name} must be a positive number, got {value!r}")

    def covariance_matrix(self):
        """(6, 6) covariance, rotation (radians) first, then translation."""
        if self.covariance is not None:
            return self.covariance
        sig = [np.radians(self.sigma_rot_deg)] * 3 + [self.sigma_trans] * 3
        return np.diag(np.square(sig))

    def to_dict(self):
        out = {"pose": self.pose.tolist()}
        if self.covariance is not None:
            out["covariance"] = self.covariance.tolist()
        else:
            out.update(sigma_rot_deg=self.sigma_rot_deg, sigma_trans=self.sigma_trans)
        return out


def check_rigid(T, name="pose"):
    """T -> (4, 4) float64 if it is a rigid transform, else PriorError naming the defect."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise PriorError(f"{name} must be a 4x4 matrix of numbers") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise PriorError(f"{name} must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > 1e-6 or np.linalg.det(R) <= 0:
        raise PriorError(f"{name} is not rigid: |RᵀR - I| = {err:.2g}, det R = {np.linalg.det(R):.3g} (need a rotation)")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise PriorError(f"{name} last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return T


@dataclass
class Hypothesis:
    """One assignment of fingers to facets and the pose behind it.

    facets : (n,) int; pose : (4, 4) T_world_object; cost : ranking cost (χ² for
    "fast", eq. (7) ℒ for "paper"); residuals : (n, 5) columns normal x/y/z (world),
    offset (point-to-plane; the eq. (7) offset for "paper"), lateral (outside the triangle);
    chi2 : whitened fit; underdetermined : bool; free_translation : (k, 3) world
    directions; free_rotation : (3,) world axis or None.
    """

    facets: np.ndarray
    pose: np.ndarray
    cost: float
    residuals: np.ndarray
    chi2: float
    underdetermined: bool
    free_translation: np.ndarray
    free_rotation: np.ndarray | None
    covariance: np.ndarray | None = None
    probability: float | None = None

    def to_dict(self):
        out = {
            "facets": self.facets.tolist(),
            "pose": self.pose.tolist(),
            "cost": float(self.cost),
            "chi2": float(self.chi2),
            "residuals": self.residuals.tolist(),
            "underdetermined": bool(self.underdetermined),
            "free_translation": self.free_translation.tolist(),
            "free_rotation": None if self.free_rotation is None else self.free_rotation.tolist(),
        }
        if self.covariance is not None:
            out["covariance"] = self.covariance.tolist()
        if self.probability is not None:
            out["probability"] = float(self.probability)
        return out


@dataclass
class HypothesisArrays:
    """All hypotheses as arrays (ranked), so thousands cost no Python objects.

    facets (H, n) int, poses (H, 4, 4), cost (H,), chi2 (H,), residuals (H, n, 5), fit : PoseFit.
    """

    facets: np.ndarray
    poses: np.ndarray
    cost: np.ndarray
    chi2: np.ndarray
    residuals: np.ndarray
    fit: PoseFit

    def take(self, idx):
        f = self.fit
        fit = PoseFit(f.R[idx], f.t[idx], f.free_translation[idx], f.free_translation_mask[idx],
                      f.free_rotation[idx], f.free_rotation_mask[idx])
        return HypothesisArrays(self.facets[idx], self.poses[idx], self.cost[idx], self.chi2[idx],
                                self.residuals[idx], fit)


class HypothesisList(Sequence):
    """A read-only ranked list of :class:`Hypothesis`, built on access."""

    def __init__(self, arrays):
        self.arrays = arrays

    def __len__(self):
        return len(self.arrays.cost)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        a = self.arrays
        i = range(len(self))[i]
        f = a.fit
        return Hypothesis(
            facets=a.facets[i], pose=a.poses[i], cost=float(a.cost[i]), residuals=a.residuals[i],
            chi2=float(a.chi2[i]), underdetermined=bool(f.underdetermined[i]),
            free_translation=f.free_translation[i][f.free_translation_mask[i]],
            free_rotation=f.free_rotation[i] if f.free_rotation_mask[i] else None,
        )


@dataclass
class Result:
    """The outcome of :func:`localize`.

    status : "ok" | "no_hypothesis" | "underdetermined" | "ambiguous";
    hypotheses : ranked list, best first; timing : seconds per stage; hint : why, when not ok.
    """

    status: str
    hypotheses: HypothesisList
    timing: dict
    method: str
    solver: str
    tolerance: Tolerance
    hint: str = ""
    num_hypotheses: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def best(self):
        """The best hypothesis, or None."""
        return self.hypotheses[0] if len(self.hypotheses) else None

    def to_dict(self):
        """A JSON-ready dict."""
        return {
            "status": self.status,
            "hint": self.hint,
            "method": self.method,
            "solver": self.solver,
            "num_hypotheses": self.num_hypotheses,
            "tolerance": {"distance": self.tolerance.distance, "angle_deg": float(np.degrees(self.tolerance.angle))},
            "timing": self.timing,
            "hypotheses": [h.to_dict() for h in self.hypotheses],
            **self.extra,
        }


def localize(model, contacts, *, position_noise=None, normal_noise_deg=1.0, prior=None,
             method="fast", solver=None, top=None, model_error=0.0):
    """Find every admissible finger-to-facet assignment and the object pose behind each.

    model : ObjectModel; contacts : Contacts (world frame); position_noise : per-axis σ of
    the contact points in length units (default 0.25 % of the object diameter);
    normal_noise_deg : per-axis σ of the normals; prior : PosePrior or None;
    method : "fast" | "paper"; solver : "closed-form" | "lm" (default: closed-form for
    "fast", lm for "paper"); top : keep only the best K hypotheses.
    """
    method, solver = _check_options(method, solver, top, contacts, prior)
    if position_noise is None:
        position_noise = DEFAULT_POSITION_NOISE_FRAC * model.diameter
    tolerance = Tolerance.from_noise(position_noise, normal_noise_deg, model_error)
    _warn_units(model, contacts, tolerance)
    clock = [time.perf_counter()]
    bounds = "exact" if method == "fast" else "paper"
    conditions = pair_conditions(contacts)
    _check_span(model, conditions, tolerance)
    use_patches = method == "fast" and model.patch_table is not None
    S = admissible_pairs(model, conditions, tolerance, bounds, direction=method == "fast", patches=use_patches)
    clock.append(time.perf_counter())
    if use_patches:
        facets = _patch_hypotheses(model, contacts, S, tolerance, prior)
    elif method == "fast":
        triple = TripleTest(model.planes.normals, contacts.object_normals, tolerance.per_contact_bounds()[1])
        facets = join_tuples(S, contacts.n, triple)
    else:
        facets = join_tuples_paper(S, contacts.n)
    clock.append(time.perf_counter())
    fit, cost_paper = _fit(model, contacts, facets, tolerance, prior, solver, method)
    clock.append(time.perf_counter())
    arrays = _rank(model, contacts, facets, fit, cost_paper, tolerance, method)
    status, hint = _status(model, contacts, arrays, tolerance)
    if top is not None:
        arrays = arrays.take(slice(0, top))
    clock.append(time.perf_counter())
    timing = dict(zip(("pairs", "tree", "pose", "rank"), np.diff(clock).tolist()))
    timing["total"] = clock[-1] - clock[0]
    return Result(status, HypothesisList(arrays), timing, method, solver, tolerance, hint,
                  num_hypotheses=len(facets))


def _check_options(method, solver, top, contacts, prior):
    if method not in METHODS:
        raise ContactPoseError(f"method must be one of {METHODS}, got {method!r}")
    solver = solver or ("closed-form" if method == "fast" else "lm")
    if solver not in SOLVERS:
        raise ContactPoseError(f"solver must be one of {SOLVERS}, got {solver!r}")
    if top is not None and not (isinstance(top, (int, np.integer)) and top >= 1):
        raise ContactPoseError(f"top must be a positive integer or None, got {top!r}")
    if not isinstance(contacts, Contacts):
        raise ContactPoseError(f"contacts must be a contactpose.Contacts, got {type(contacts).__name__}")
    if prior is not None and not isinstance(prior, PosePrior):
        raise ContactPoseError(f"prior must be a contactpose.PosePrior or None, got {type(prior).__name__}")
    return method, solver


def _patch_hypotheses(model, contacts, S, tolerance, prior):
    """Facet tuples from the patch-level tree, one per patch tuple: pose it on the patch
    planes, give each contact the member facet nearest to it, re-pose on those facets and
    take the nearest members again (research/design.md)."""
    patches = model.patches
    angle = tolerance.per_contact_bounds()[1] + float(patches.cone.max())
    tuples = join_tuples(S, contacts.n, TripleTest(patches.normals, contacts.object_normals, angle))
    t0 = None if prior is None else np.broadcast_to(prior.pose[:3, 3], (len(tuples), 3))
    normals, offsets, centres = patches.normals[tuples], patches.offsets[tuples], patches.centres[tuples]
    for _ in range(2):
        fit = fit_poses(normals, offsets, contacts.points, contacts.finger_normals,
                        angle_tol=tolerance.normal_noise, t0=t0, centroids=centres)
        facets = nearest_members(patches, model.triangles, tuples, res.to_object_frame(fit.R, fit.t, contacts.points))
        normals, offsets, centres = model.planes.normals[facets], model.planes.offsets[facets], model.centroids[facets]
    return facets


def _fit(model, contacts, facets, tolerance, prior, solver, method):
    """Poses of all hypotheses. Returns (PoseFit, eq. (7) cost or None)."""
    normals = model.planes.normals[facets]
    offsets = model.planes.offsets[facets]
    cost_kind = "invariant" if method == "fast" else "paper"
    t0 = None if prior is None else np.broadcast_to(prior.pose[:3, 3], (len(facets), 3))
    fit = fit_poses(normals, offsets, contacts.points, contacts.finger_normals, cost=cost_kind,
                    angle_tol=tolerance.normal_noise, t0=t0, centroids=model.centroids[facets])
    if solver == "closed-form":
        return fit, None
    start = np.eye(4) if prior is None else prior.pose
    T, cost, _ = fit_lm_all(normals, offsets, contacts.points, contacts.finger_normals, start)
    fit.R, fit.t = T[:, :3, :3], T[:, :3, 3]
    return fit, cost


def _rank(model, contacts, facets, fit, cost_paper, tolerance, method):
    """Residuals and cost of every hypothesis, sorted best first."""
    normals = model.planes.normals[facets]
    offsets = model.planes.offsets[facets]
    r_n = res.normal_residuals(fit.R, normals, contacts.finger_normals)
    p_obj = res.to_object_frame(fit.R, fit.t, contacts.points)
    r_o = res.offset_residuals(p_obj, normals, offsets)
    r_l = res.lateral_residuals(p_obj, model.triangles[facets], r_o)
    chi2 = res.whitened_cost(r_n, r_o, r_l, tolerance.normal_noise, tolerance.position_noise)
    if method == "paper":
        r_p = res.paper_offset_residuals(fit.t, contacts.points, contacts.finger_normals, offsets)
        cost = res.paper_cost(r_n, r_p) if cost_paper is None else cost_paper
        offset_col = r_p
    else:
        cost, offset_col = chi2, r_o
    residual = np.concatenate([r_n, offset_col[..., None], r_l[..., None]], axis=2)
    order = np.argsort(cost, kind="stable")
    arrays = HypothesisArrays(facets, fit.poses(), cost, chi2, residual, fit)
    return arrays.take(order)


@lru_cache(maxsize=64)
def fit_threshold(n):
    """χ² bound that a correct hypothesis of n contacts passes with FIT_CONFIDENCE."""
    from scipy.stats import chi2

    return float(chi2.ppf(FIT_CONFIDENCE, 3 * n))


def _status(model, contacts, arrays, tolerance):
    """Status and hint from the ranked hypotheses."""
    if len(arrays.cost) == 0:
        return "no_hypothesis", _no_hypothesis_hint(model, contacts, tolerance)
    if arrays.fit.underdetermined[0]:
        return "underdetermined", "the hypothesised facet normals leave pose directions free; see free_translation / free_rotation"
    fits = np.flatnonzero(arrays.chi2 <= fit_threshold(contacts.n))[:MAX_AMBIGUITY_CHECKS]
    best = arrays.poses[0]
    limit = SAME_CLASS_ADDS_FRAC * model.diameter
    radius = model.surface_radius
    for i in fits[fits > 0]:
        if displacement_bound(arrays.poses[i], best, radius) <= limit:
            continue  # the same placement: ADD-S cannot exceed the displacement
        if adds(arrays.poses[i], best, model.surface_points, model.surface_tree) > limit:
            return "ambiguous", f"hypothesis {i} is a distinct pose that also fits within noise; add a prior or a touch"
    return "ok", ""


def contact_spread(contacts):
    """Largest distance between two contacts."""
    return float(np.max(np.linalg.norm(contacts.points[:, None] - contacts.points[None], axis=2)))


def _check_span(model, conditions, tolerance):
    """A span-bounded table cannot answer finger pairs farther apart than its span."""
    span = model.max_span
    if span is None:
        return
    far = np.flatnonzero(conditions.distance + tolerance.distance > span)
    if len(far):
        i, j = conditions.pairs[far[0]]
        raise ResourceError(
            f"contacts {i} and {j} are {conditions.distance[far[0]]:.4g} apart (± {tolerance.distance:.3g}), "
            f"beyond the model's max_span {span:.4g}; rebuild the model with a larger --max-span")


def _warn_units(model, contacts, tolerance):
    spread = contact_spread(contacts)
    if spread > model.diameter + tolerance.distance:
        warnings.warn(f"contacts span {spread:.4g}, more than the object's diameter {model.diameter:.4g}: "
                      "are contacts and mesh in the same units?", stacklevel=3)


def _no_hypothesis_hint(model, contacts, tolerance):
    spread = contact_spread(contacts)
    if spread > model.diameter + tolerance.distance:
        return (f"contacts are {spread:.4g} apart but the object is only {model.diameter:.4g} across: "
                "wrong units?")
    return (f"no facet tuple matches within tolerance (distance ±{tolerance.distance:.3g}, "
            f"angle ±{np.degrees(tolerance.angle):.3g}°): noise too small, wrong units, or a finger off the object?")
