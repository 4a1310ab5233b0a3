"""The online phase (§3.2, §4): contacts -> S_ij -> tree T -> pose per hypothesis -> ranking.

``method="fast"`` (default): exact Δmin bounds, vectorized tree, closed-form poses,
ranked by the origin-invariant χ² that includes each contact's distance outside
its facet triangle. ``method="paper"``: the paper as published — vertex-only
Δmin, the node-by-node tree, Levenberg–Marquardt on eq. (7), ranked by eq. (7).
"""

from __future__ import annotations

import time
import warnings
from itertools import combinations
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from contactpose import residuals as res
from contactpose.contacts import Contacts, Tolerance, pair_conditions
from contactpose.errors import ContactPoseError, PriorError, ResourceError
from contactpose.hypotheses import TripleTest, admissible_pairs, join_tuples, join_tuples_paper
from contactpose.infacet import polished_poses, within_noise
from contactpose.patches import nearest_members
from contactpose.metrics import SAME_CLASS_ADDS_FRAC, adds_many, rms_displacement
from contactpose.solvers.closed_form import PoseFit, fit_poses
from contactpose.solvers.lm import fit_lm_all

METHODS = ("fast", "paper")
SOLVERS = ("closed-form", "lm", "factor-graph")
ROBUST = ("huber", "cauchy", "none")
#: solver="factor-graph" refines this many of the best closed-form hypotheses (0: all).
DEFAULT_REFINE = 20
#: Probability that a correct hypothesis passes the fit test (χ² quantile, 3 dof per contact).
FIT_CONFIDENCE = 0.9973
#: With evidence-based probabilities (factor graph), "ambiguous" needs the classes other
#: than the best to hold more than this probability together.
AMBIGUOUS_PROBABILITY = 0.05
#: At most this many well-fitting hypotheses are grouped into pose classes.
MAX_CLASS_HYPOTHESES = 256
#: The default method moves the poses of at most this many hypotheses toward the least
#: full χ² (localize._polish), those whose plane χ² is at least POLISH_GAIN below the best.
POLISH = 256
POLISH_GAIN = 0.5
#: χ² charged per unassigned finger (max_outliers): the FIT_CONFIDENCE quantile of one
#: contact's 3 dof, so dropping a finger never beats assigning it within noise.
OUTLIER_PENALTY = 14.16
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
    directions; free_rotation : (3,) world axis or None; outliers : fingers left
    unassigned (facet -1) under ``max_outliers``.
    """

    facets: np.ndarray
    pose: np.ndarray
    cost: float
    residuals: np.ndarray
    chi2: float
    underdetermined: bool
    free_translation: np.ndarray
    free_rotation: np.ndarray | None
    outliers: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    covariance: np.ndarray | None = None
    probability: float | None = None
    samples: object | None = None
    sample_covariance: np.ndarray | None = None

    def to_dict(self):
        out = {
            "outliers": self.outliers.tolist(),
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
        if self.samples is not None:
            out["sample_covariance"] = self.sample_covariance.tolist()
            out["samples"] = self.samples.summary()
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
    covariance: np.ndarray | None = None
    probability: np.ndarray | None = None

    def take(self, idx):
        pick = (lambda a: None if a is None else a[idx])
        return HypothesisArrays(self.facets[idx], self.poses[idx], self.cost[idx], self.chi2[idx],
                                self.residuals[idx], self.fit.take(idx), pick(self.covariance),
                                pick(self.probability))

    def merged(self, other):
        """Both sets of hypotheses in one ranking (by cost)."""
        joined = HypothesisArrays(*(np.concatenate([a, b]) for a, b in zip(
            (self.facets, self.poses, self.cost, self.chi2, self.residuals),
            (other.facets, other.poses, other.cost, other.chi2, other.residuals))), self.fit.concat(other.fit))
        return joined.take(np.argsort(joined.cost, kind="stable"))

    def widened(self, fingers, n, penalty):
        """Hypotheses over a subset of fingers as hypotheses over all n: the others get
        facet -1 and NaN residuals, and ``penalty`` is added to cost and χ²."""
        h = len(self.cost)
        facets = -np.ones((h, n), dtype=self.facets.dtype)
        facets[:, fingers] = self.facets
        residuals = np.full((h, n, self.residuals.shape[2]), np.nan)
        residuals[:, fingers] = self.residuals
        return HypothesisArrays(facets, self.poses, self.cost + penalty, self.chi2 + penalty, residuals, self.fit)


class HypothesisList(Sequence):
    """A read-only ranked list of :class:`Hypothesis`, built on access."""

    def __init__(self, arrays):
        self.arrays = arrays
        self.samples = {}  # rank -> PoseSamples, filled by localize(..., samples=N)

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
            outliers=np.flatnonzero(a.facets[i] < 0),
            covariance=None if a.covariance is None else a.covariance[i],
            probability=None if a.probability is None else float(a.probability[i]),
            samples=self.samples.get(i),
            sample_covariance=None if i not in self.samples else self.samples[i].covariance,
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
    classes: list = field(default_factory=list)
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
            "classes": [c.to_dict() for c in self.classes],
            "hypotheses": [h.to_dict() for h in self.hypotheses],
            **self.extra,
        }


def localize(model, contacts, *, position_noise=None, normal_noise_deg=1.0, prior=None,
             method="fast", solver=None, top=None, model_error=0.0, max_outliers=0, robust="huber",
             refine=DEFAULT_REFINE, samples=0, seed=None, sample_top=1, finger_radius=None):
    """Find every admissible finger-to-facet assignment and the object pose behind each.

    model : ObjectModel; contacts : Contacts (world frame); position_noise : per-axis σ of
    the contact points in length units (default 0.25 % of the object diameter);
    normal_noise_deg : per-axis σ of the normals; prior : PosePrior or None;
    method : "fast" | "paper"; solver : "closed-form" | "lm" (default: closed-form for
    "fast", lm for "paper"); top : keep only the best K hypotheses; model_error : extra
    length tolerance for a model that differs from the object (a scan, say);
    max_outliers : up to this many fingers may be left unassigned (facet -1), their
    contacts excluded from the pose, at a cost of OUTLIER_PENALTY each ("fast" only);
    robust : "huber" | "cauchy" | "none", the factor graph's kernel; refine : how many of the
    best closed-form hypotheses the factor graph refines (0: all). With
    solver="factor-graph" hypotheses carry .covariance and .probability and are ranked by
    Laplace evidence. samples : draw this many posterior samples (emcee) of the pose of
    each of the best ``sample_top`` hypotheses, into .samples and .sample_covariance;
    seed makes the sampling repeatable. finger_radius : drop the hypotheses that put a
    contact where no finger of this radius fits (its outward normal ray of that length
    re-enters the posed object: contactpose.freespace); underdetermined hypotheses are
    kept, since their pose is one arbitrary member of a family.
    """
    method, solver = _check_options(method, solver, top, contacts, prior)
    if robust not in ROBUST:
        raise ContactPoseError(f"robust must be one of {ROBUST}, got {robust!r}")
    max_outliers = _check_outliers(max_outliers, method, contacts.n)
    if position_noise is None:
        position_noise = DEFAULT_POSITION_NOISE_FRAC * model.diameter
    tolerance = Tolerance.from_noise(position_noise, normal_noise_deg, model_error)
    _warn_units(model, contacts, tolerance)
    start = time.perf_counter()
    pose_solver = "closed-form" if solver == "factor-graph" else solver
    arrays, timing = _search(model, contacts, tolerance, prior, method, pose_solver)
    for dropped in _outlier_sets(contacts.n, max_outliers):
        keep = np.setdiff1d(np.arange(contacts.n), dropped)
        sub, sub_timing = _search(model, contacts.permuted(keep), tolerance, prior, method, pose_solver)
        arrays = arrays.merged(sub.widened(keep, contacts.n, len(dropped) * OUTLIER_PENALTY))
        timing = {k: timing[k] + sub_timing[k] for k in timing}
    if finger_radius is not None:
        free_start = time.perf_counter()
        arrays = _free_space(model, contacts, arrays, finger_radius)
        timing["free_space"] = time.perf_counter() - free_start
    rescue = ""
    if solver == "factor-graph":
        refine_start = time.perf_counter()
        arrays, rescue = _refine(model, contacts, arrays, tolerance, prior, robust, refine)
        timing["refine"] = time.perf_counter() - refine_start
    classes_start = time.perf_counter()
    fits = None if method == "paper" else within_noise(model, contacts, arrays, tolerance, fit_threshold(contacts.n),
                                                       enough=MAX_CLASS_HYPOTHESES)
    classes = pose_classes(model, arrays, contacts.n, fits)
    status, hint = _status(model, contacts, arrays, classes, tolerance)
    if rescue:
        hint = f"{hint}; {rescue}" if hint else rescue
    num = len(arrays.cost)
    if top is not None:
        arrays = arrays.take(slice(0, top))
    timing["rank"] += time.perf_counter() - classes_start
    result = Result(status, HypothesisList(arrays), timing, method, solver, tolerance, hint,
                    num_hypotheses=num, classes=classes)
    if samples:
        sample_start = time.perf_counter()
        _attach_samples(model, contacts, result, samples, seed, prior, robust, sample_top)
        timing["sample"] = time.perf_counter() - sample_start
    timing["total"] = time.perf_counter() - start
    return result


def _attach_samples(model, contacts, result, samples, seed, prior, robust, top):
    """Posterior samples of the best ``top`` hypotheses (contactpose.uncertainty)."""
    from contactpose.uncertainty import attach_samples

    if not (isinstance(samples, (int, np.integer)) and samples > 0):
        raise ContactPoseError(f"samples must be a positive integer, got {samples!r}")
    hyps = attach_samples(model, contacts, result, int(samples), np.random.default_rng(seed),
                          prior=prior, robust=robust, top=top)
    result.hypotheses.samples.update({i: h.samples for i, h in enumerate(hyps) if h.samples is not None})


def _search(model, contacts, tolerance, prior, method, solver):
    """S_ij -> tree -> poses -> ranked HypothesisArrays, with seconds per stage."""
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
    clock.append(time.perf_counter())
    timing = dict(zip(("pairs", "tree", "pose", "rank"), np.diff(clock).tolist()))
    if method == "fast":
        arrays = _polish(model, contacts, arrays, tolerance)
        timing["pose"] += time.perf_counter() - clock[-1]
    return arrays, timing


def _free_space(model, contacts, arrays, finger_radius):
    """The hypotheses but those whose (determined) pose puts a contact where no finger of
    ``finger_radius`` fits (issue 9, item 5)."""
    from contactpose.freespace import free_space_violations

    bad = free_space_violations(model, arrays.facets, arrays.poses, contacts, finger_radius)
    return arrays.take(np.flatnonzero(~(bad & ~arrays.fit.underdetermined)))


def _refine(model, contacts, arrays, tolerance, prior, robust, k):
    """The factor graph's refinement of the best k hypotheses, as ranked HypothesisArrays
    (by Laplace evidence), with covariance and probability. Unassigned fingers (facet -1,
    max_outliers) have no contact residual.

    With a prior, when no hypothesis both agrees with it and, refined, fits the contacts
    within noise (χ² <= fit_threshold), the search runs again at RESCUE_WIDEN times the pair
    tolerances and, if still none agrees with the prior, each contact also gets its
    best-fitting facet under the prior pose; all of these are refined together, and a
    warning says what was done (research/factor_graph.md, "Rescue"). Returns (arrays, that
    note or "")."""
    from contactpose.solvers import factor_graph as fg

    def refined(a):
        if len(a.cost) == 0:
            return a, 0
        ref = fg.refine_hypotheses(model, contacts, a, tolerance, prior=prior, robust=robust, k=k)
        return fg.hypothesis_arrays(model, contacts, ref, a.fit.take(ref.index), tolerance), ref.agreeing

    out, agreeing = refined(arrays)
    if prior is None or (agreeing > 0 and out.chi2[0] <= fit_threshold(contacts.n)):
        return out, ""
    wide = Tolerance(fg.RESCUE_WIDEN * tolerance.distance, min(fg.RESCUE_WIDEN * tolerance.angle, np.pi),
                     tolerance.position_noise, tolerance.normal_noise)
    arrays = arrays.merged(_search(model, contacts, wide, prior, "fast", "closed-form")[0])
    arrays = arrays.take(np.sort(np.unique(arrays.facets, axis=0, return_index=True)[1]))  # found twice
    how = f"searched again with {fg.RESCUE_WIDEN:g}x the pair tolerances"
    if not fg.agrees_with_prior(model, arrays, tolerance, prior):
        facets = fg.nearest_fit_facets(model, contacts, prior.pose, tolerance)
        arrays = arrays.merged(fg.closed_form_arrays(model, contacts, facets[None], tolerance))
        how += " and added each contact's best-fitting facet under the prior pose"
    note = f"no hypothesis both agreed with the vision prior and fit within noise: {how}"
    warnings.warn(note, stacklevel=3)
    return refined(arrays)[0], note


def _check_outliers(max_outliers, method, n):
    if not (isinstance(max_outliers, (int, np.integer)) and 0 <= max_outliers):
        raise ContactPoseError(f"max_outliers must be a non-negative integer, got {max_outliers!r}")
    if max_outliers and method != "fast":
        raise ContactPoseError("max_outliers needs method='fast' (the paper assigns every finger)")
    if max_outliers and n - max_outliers < 3:
        raise ContactPoseError(f"max_outliers={max_outliers} with {n} contacts leaves fewer than 3 to fit a pose")
    return int(max_outliers)


def _outlier_sets(n, max_outliers):
    """Every set of 1..max_outliers fingers to leave unassigned."""
    return [np.array(c) for q in range(1, max_outliers + 1) for c in combinations(range(n), q)]


def _check_options(method, solver, top, contacts, prior):
    if method not in METHODS:
        raise ContactPoseError(f"method must be one of {METHODS}, got {method!r}")
    solver = solver or ("closed-form" if method == "fast" else "lm")
    if solver not in SOLVERS:
        raise ContactPoseError(f"solver must be one of {SOLVERS}, got {solver!r}")
    if solver == "factor-graph" and method != "fast":
        raise ContactPoseError("solver='factor-graph' refines the default method's hypotheses: use method='fast'")
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


def _rank(model, contacts, facets, fit, cost_paper, tolerance, method, order=True):
    """Residuals and cost of every hypothesis, sorted best first (unless order=False)."""
    offsets = model.planes.offsets[facets]
    r_n, r_o, r_l = res.contact_residuals(fit.R, fit.t, model.planes.normals[facets], offsets,
                                          model.triangles[facets], contacts.points, contacts.finger_normals)
    chi2 = res.whitened_cost(r_n, r_o, r_l, tolerance.normal_noise, tolerance.position_noise)
    if method == "paper":
        r_p = res.paper_offset_residuals(fit.t, contacts.points, contacts.finger_normals, offsets)
        cost = res.paper_cost(r_n, r_p) if cost_paper is None else cost_paper
        offset_col = r_p
    else:
        cost, offset_col = chi2, r_o
    residual = np.concatenate([r_n, offset_col[..., None], r_l[..., None]], axis=2)
    arrays = HypothesisArrays(facets, fit.poses(), cost, chi2, residual, fit)
    if not order or np.all(cost[1:] >= cost[:-1]):
        return arrays
    return arrays.take(np.argsort(cost, kind="stable"))


def _polish(model, contacts, arrays, tolerance):
    """The ranked hypotheses with the poses of those that could beat the best moved toward
    the least full χ² (infacet.polished_poses), where that lowers it. The closed form fits
    the planes only, the ranking cost includes the triangles: a hypothesis whose plane χ²
    is at least POLISH_GAIN below the best full χ² (the best itself, when a contact lies
    outside its triangle) is moved, up to POLISH of them, best plane fit first. With
    patches, each moved contact gets the member facet nearest to it again."""
    lateral = arrays.residuals[..., 4]
    if not lateral.any():  # every contact inside its triangle: the plane χ² is the full χ²
        return arrays
    plane = arrays.chi2 - np.sum(lateral**2, axis=1) / tolerance.position_noise**2
    rows = np.flatnonzero(plane <= arrays.chi2.min() - POLISH_GAIN)
    rows = rows[np.argsort(plane[rows], kind="stable")[:POLISH]]
    if not len(rows):
        return arrays
    R, t = polished_poses(model, contacts, arrays, rows, tolerance, fit_threshold(contacts.n))
    facets = arrays.facets[rows]
    if model.patch_table is not None:
        labels = np.ascontiguousarray(model.patches.labels[facets])
        facets = nearest_members(model.patches, model.triangles, labels, res.to_object_frame(R, t, contacts.points))
    fit = arrays.fit.take(rows)
    fit.R, fit.t = R, t
    moved = _rank(model, contacts, facets, fit, None, tolerance, "fast", order=False)
    better = moved.chi2 < arrays.chi2[rows]
    if not better.any():
        return arrays
    arrays = arrays.take(np.arange(len(arrays.cost)))      # a copy to update
    keep, src = rows[better], np.flatnonzero(better)
    for name in ("facets", "poses", "cost", "chi2", "residuals"):
        getattr(arrays, name)[keep] = getattr(moved, name)[src]
    arrays.fit.R[keep], arrays.fit.t[keep] = R[src], t[src]
    return arrays.take(np.argsort(arrays.cost, kind="stable"))


@lru_cache(maxsize=64)
def fit_threshold(n):
    """χ² bound that a correct hypothesis of n contacts passes with FIT_CONFIDENCE."""
    from scipy.stats import chi2

    return float(chi2.ppf(FIT_CONFIDENCE, 3 * n))


@dataclass
class PoseClass:
    """Hypotheses that place the object's surface the same way (ADD-S below
    SAME_CLASS_ADDS_FRAC of the diameter): symmetric twins count as one placement.

    members : hypothesis ranks (in the full ranking); best : rank of its best member;
    pose : (4, 4) its best pose; chi2 : its best χ²; probability : share of the
    likelihood exp(-χ²/2) summed over members, normalised over classes.
    """

    members: np.ndarray
    best: int
    pose: np.ndarray
    chi2: float
    probability: float

    def to_dict(self):
        return {"members": self.members.tolist(), "best": int(self.best), "pose": self.pose.tolist(),
                "chi2": float(self.chi2), "probability": float(self.probability)}


def pose_classes(model, arrays, n, fits=None):
    """Group the hypotheses that fit within noise into pose classes, best class first.

    fits : (H,) bool, the hypotheses that fit (default: χ² <= fit_threshold(n)). A
    hypothesis joins the first class whose best pose is within ADD-S of it, else opens one:
    each new class takes the best hypothesis left, then every later one that matches it.
    """
    fits = np.flatnonzero(arrays.chi2 <= fit_threshold(n) if fits is None else fits)[:MAX_CLASS_HYPOTHESES]
    if not len(fits):
        return []
    poses = arrays.poses[fits]
    label = np.full(len(fits), -1)
    reps = []
    while (left := np.flatnonzero(label < 0)).size:
        rest = left[1:]
        label[left[0]] = len(reps)
        if len(rest):
            label[rest[same_placement(model, poses[rest], poses[left[0]])]] = len(reps)
        reps.append(fits[left[0]])
    members = [fits[label == c] for c in range(len(reps))]
    chi2 = arrays.chi2
    if arrays.probability is not None:  # the factor graph's Laplace evidence
        weight = np.array([np.sum(arrays.probability[m]) for m in members])
    else:
        weight = np.array([np.sum(np.exp(-0.5 * (chi2[m] - chi2[fits[0]]))) for m in members])
    prob = weight / weight.sum()
    return [PoseClass(m, int(r), arrays.poses[r], float(chi2[r]), float(p))
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


def _status(model, contacts, arrays, classes, tolerance):
    """Status and hint from the ranked hypotheses and their pose classes."""
    if len(arrays.cost) == 0:
        return "no_hypothesis", _no_hypothesis_hint(model, contacts, tolerance)
    if arrays.fit.underdetermined[0] and (arrays.covariance is None or not np.isfinite(arrays.covariance[0]).all()):
        return "underdetermined", "the hypothesised facet normals leave pose directions free; see free_translation / free_rotation"
    if len(classes) > 1 and (arrays.probability is None or 1.0 - classes[0].probability > AMBIGUOUS_PROBABILITY):
        return "ambiguous", (f"{len(classes)} distinct placements fit within noise (probabilities "
                             f"{', '.join(f'{c.probability:.2f}' for c in classes[:4])}); add a prior or a touch")
    if not classes:
        return "ok", f"the best hypothesis does not fit within noise (chi2 {arrays.chi2[0]:.3g} > {fit_threshold(contacts.n):.3g})"
    return "ok", ""


def contact_spread(contacts):
    """Largest distance between two contacts."""
    return contacts.spread


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
