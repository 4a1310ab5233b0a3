"""Shared types of the online phase: priors, poses, hypotheses, pose classes, results.

The bottom layer: every stage above (search, solvers, scoring, the pipeline) exchanges
these, so none of them imports another stage for a type. Poses are T_world_object
(4, 4), x_w = R x_o + t; covariances are (6, 6) in Pose3 tangent order, rotation first.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from contactpose import view
from contactpose.contacts import Tolerance
from contactpose.errors import ContactPoseError, PriorError
from contactpose.schema import RESIDUAL_COLUMNS, SCHEMA_VERSION, json_array, json_number, result_units, tolerance_dict


@dataclass
class PoseFit:
    """Poses of H hypotheses with their degenerate directions.

    R : (H, 3, 3); t : (H, 3);
    free_translation : (H, 3, 3) rows are world unit directions, valid where
    free_translation_mask : (H, 3) bool; free_rotation : (H, 3) world axis, valid
    where free_rotation_mask : (H,) bool.
    """

    R: np.ndarray
    t: np.ndarray
    free_translation: np.ndarray
    free_translation_mask: np.ndarray
    free_rotation: np.ndarray
    free_rotation_mask: np.ndarray

    def take(self, idx):
        """The fits of the hypotheses ``idx``."""
        return PoseFit(*(getattr(self, f.name)[idx] for f in fields(self)))

    def concat(self, *others):
        """These fits and the others', self's first."""
        parts = (self,) + others
        return PoseFit(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(self)))

    @property
    def underdetermined(self):
        """(H,) bool: a pose family, not one pose."""
        return self.free_translation_mask.any(axis=1) | self.free_rotation_mask

    def poses(self):
        """(H, 4, 4) T_world_object."""
        T = np.zeros((len(self.R), 4, 4))
        T[:, :3, :3] = self.R
        T[:, :3, 3] = self.t
        T[:, 3, 3] = 1.0
        return T


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
        """PRIOR.json content (contactpose.io.jsonfiles.parse_prior reads it back)."""
        out = {"pose": self.pose.tolist()}
        if self.covariance is not None:
            out["covariance"] = self.covariance.tolist()
        else:
            out.update(sigma_rot_deg=float(self.sigma_rot_deg), sigma_trans=float(self.sigma_trans))
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
    "fast", -log Laplace evidence with the factor graph, eq. (7) ℒ for "paper");
    residuals : (n, 5) columns normal x/y/z (world), offset (point-to-plane; the eq. (7)
    offset for "paper"), lateral (outside the triangle); chi2 : whitened fit;
    underdetermined : bool; free_translation : (k, 3) world directions; free_rotation : (3,)
    world axis or None; outliers : fingers left unassigned (facet -1) under ``max_outliers``.
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
        """This hypothesis as JSON (``$defs/hypothesis`` of contactpose/data/result.schema.json):
        lengths in mesh units, residual columns RESIDUAL_COLUMNS, covariance (6, 6) in
        TANGENT_ORDER with rotation in radians; null for what was not computed, NaN as null;
        ``sample_covariance`` only where it comes without samples (a held TouchSession's
        association covariance), otherwise it is the samples' own."""
        out = {
            "facets": self.facets.tolist(),
            "outliers": self.outliers.tolist(),
            "pose": self.pose.tolist(),
            "cost": json_number(self.cost),
            "chi2": json_number(self.chi2),
            "residuals": json_array(self.residuals),
            "underdetermined": bool(self.underdetermined),
            "free_translation": np.asarray(self.free_translation).reshape(-1, 3).tolist(),
            "free_rotation": [] if self.free_rotation is None else [np.asarray(self.free_rotation).tolist()],
            "covariance": None if self.covariance is None else json_array(self.covariance),
            "probability": None if self.probability is None else json_number(self.probability),
            "samples": None if self.samples is None else self.samples.summary(),
        }
        if self.samples is None and self.sample_covariance is not None:
            out["sample_covariance"] = json_array(self.sample_covariance)
        return out

    def __repr__(self):
        parts = [f"facets {self.facets.tolist()}", f"chi2 {self.chi2:.3g}", f"cost {self.cost:.3g}"]
        if len(self.outliers):
            parts.append(f"outliers {self.outliers.tolist()}")
        if self.underdetermined:
            k = len(self.free_translation)
            free = [f"{k} translation{'' if k == 1 else 's'}"] * bool(k) + ["1 rotation"] * (self.free_rotation is not None)
            parts.append(f"underdetermined (free: {', '.join(free)})")
        if self.probability is not None:
            parts.append(f"probability {self.probability:.3g}")
        if self.samples is not None:
            parts.append(f"{len(self.samples.xi)} samples")
        return f"Hypothesis({', '.join(parts)})"


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

    def merged(self, *others):
        """These hypotheses and the others' in one ranking (by cost, stable: self's first on a
        tie); covariance and probability are kept where every set has them."""
        parts = (self,) + others
        every = (lambda name: [getattr(p, name) for p in parts])
        kept = (lambda name: None if any(a is None for a in every(name)) else np.concatenate(every(name)))
        joined = HypothesisArrays(*(np.concatenate(every(name)) for name in ("facets", "poses", "cost", "chi2",
                                                                                "residuals")),
                                  self.fit.concat(*(p.fit for p in others)), kept("covariance"), kept("probability"))
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
        self.sample_covariances = {}  # rank -> (6, 6) without samples (a held TouchSession's association covariance)

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
            chi2=float(a.chi2[i]), underdetermined=bool(f.free_translation_mask[i].any() or f.free_rotation_mask[i]),
            free_translation=f.free_translation[i][f.free_translation_mask[i]],
            free_rotation=f.free_rotation[i] if f.free_rotation_mask[i] else None,
            outliers=np.flatnonzero(a.facets[i] < 0),
            covariance=None if a.covariance is None else a.covariance[i],
            probability=None if a.probability is None else float(a.probability[i]),
            samples=self.samples.get(i),
            sample_covariance=self.samples[i].covariance if i in self.samples else self.sample_covariances.get(i),
        )


#: Causes of an empty or poor answer that a :class:`Diagnosis` names (contactpose.diagnosis
#: tests them in this order): contacts in other units than the mesh; the model's facet
#: normals pointing inward (its winding, recorded when it was built); the contacts' normals
#: reversed; one finger off the object (the others fit); noise stated smaller than the fit
#: needs; none of these ("unexplained").
CAUSE_UNITS = "units"
CAUSE_MODEL_NORMALS = "model_normals_inward"
CAUSE_CONTACT_NORMALS = "contact_normals_flipped"
CAUSE_FINGER_OFF = "finger_off"
CAUSE_NOISE = "noise_too_small"
CAUSE_UNEXPLAINED = "unexplained"
CAUSES = (CAUSE_UNITS, CAUSE_MODEL_NORMALS, CAUSE_CONTACT_NORMALS, CAUSE_FINGER_OFF, CAUSE_NOISE, CAUSE_UNEXPLAINED)


@dataclass(frozen=True)
class Diagnosis:
    """Why an answer came back empty or poor: the cause that a test confirmed (one of CAUSES)
    and what to change, each suggestion checked by localizing again with it.

    cause : one of CAUSES; message : one line, also carried by the Result's hint;
    finger : the finger off the object (CAUSE_FINGER_OFF); max_outliers : the value that
    lets localize fit (CAUSE_FINGER_OFF); scale : multiply the contact points by this to
    express them in the mesh's units (CAUSE_UNITS); position_noise (length units) and
    normal_noise_deg : noise at which localize fits (CAUSE_NOISE); tested : the causes
    tested, in order.
    """

    cause: str
    message: str
    finger: int | None = None
    max_outliers: int | None = None
    scale: float | None = None
    position_noise: float | None = None
    normal_noise_deg: float | None = None
    tested: tuple = ()

    def __post_init__(self):
        if self.cause not in CAUSES:
            raise ValueError(f"cause must be one of {CAUSES}, got {self.cause!r}")

    def to_dict(self):
        """This diagnosis as JSON (``$defs/diagnosis`` of contactpose/data/result.schema.json)."""
        return {"cause": self.cause, "message": self.message, "finger": self.finger,
                "max_outliers": self.max_outliers, "scale": self.scale, "position_noise": self.position_noise,
                "normal_noise_deg": self.normal_noise_deg, "tested": list(self.tested)}


@dataclass
class Result:
    """The outcome of :func:`localize`.

    status : one of options.STATUSES;
    hypotheses : ranked list, best first; timing : seconds per stage; hint : why, when not ok;
    tree : the search's tree (a search.tree.SearchTree), for ``localize(..., tree=)`` to extend;
    diagnosis : for an empty or poor answer (no_hypothesis, poor_fit) of the default method,
    the :class:`Diagnosis` of its cause; None otherwise; confidence : the probability that the
    best pose is strictly right (scoring.placements; None for the paper's method); placements :
    the distinct placements that fit within noise, modulo symmetry, best first
    (scoring.placements.Placement, each with its probability); model, contacts : the ObjectModel and
    the Contacts (world frame) that the answer is of, for :meth:`to_html` (None when not kept).
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
    num_assignments: int | None = None
    tree: object = field(default=None, repr=False, compare=False)
    diagnosis: Diagnosis | None = None
    confidence: float | None = None
    placements: list = field(default_factory=list)
    model: object = field(default=None, repr=False, compare=False)
    contacts: object = field(default=None, repr=False, compare=False)

    def __post_init__(self):
        if self.num_assignments is None:
            self.num_assignments = self.num_hypotheses

    @property
    def best(self):
        """The best hypothesis, or None."""
        return self.hypotheses[0] if len(self.hypotheses) else None

    def to_dict(self):
        """The localize JSON (contactpose/data/result.schema.json, SCHEMA_VERSION): ``units``,
        ``timing_ms`` (ms; ``timing`` stays in seconds), ``num_hypotheses`` (all found, one per
        distinct pose), ``num_assignments`` (the facet assignments behind them, near-copies
        included) and ``num_returned`` (listed, after ``top``), ``best`` (hypotheses[0] or null),
        ``diagnosis`` (Diagnosis.to_dict() or null)."""
        hypotheses = [h.to_dict() for h in self.hypotheses]
        out = {
            "schema_version": SCHEMA_VERSION,
            "units": result_units(),
            "status": self.status,
            "hint": self.hint,
            "method": self.method,
            "solver": self.solver,
            "num_hypotheses": int(self.num_hypotheses),
            "num_assignments": int(self.num_assignments),
            "num_returned": len(hypotheses),
            "tolerance": tolerance_dict(self.tolerance),
            "timing_ms": {k: 1000.0 * float(v) for k, v in self.timing.items()},
            "residual_columns": list(RESIDUAL_COLUMNS),
            "best": None if self.best is None else self.best.to_dict(),
            "classes": [c.to_dict() for c in self.classes],
            "hypotheses": hypotheses,
            "diagnosis": None if self.diagnosis is None else self.diagnosis.to_dict(),
            "confidence": None if self.confidence is None else json_number(self.confidence),
            "placements": [p.to_dict() for p in self.placements],
        }
        if self.extra:
            out["extra"] = dict(self.extra)
        return out

    def to_html(self, path, model=None, contacts=None, finger_radius=None):
        """Write this answer as one self-contained 3D page (HTML that opens offline:
        contactpose.view): the object at the best placement, the contacts with their finger
        normals, fingertips of ``finger_radius`` (None: none), the other placements translucent
        (the pose classes, else the hypotheses; named by rank and probability, toggled in the
        legend), the directions the best pose leaves free, and a title of status, best facets
        and hint. model : ObjectModel, contacts : Contacts (world frame); default: those the
        Result was made of (localize and TouchSession keep them). -> the path written"""
        model = self.model if model is None else model
        contacts = self.contacts if contacts is None else contacts
        if model is None or contacts is None:
            raise ContactPoseError("to_html needs the model and the contacts: this Result keeps none, give model= and "
                                   "contacts=")
        for name, value, attributes in (("model", model, ("vertices", "faces")),
                                        ("contacts", contacts, ("points", "finger_normals"))):
            if not all(hasattr(value, a) for a in attributes):
                raise ContactPoseError(f"{name} must have {' and '.join(attributes)} (an ObjectModel, a Contacts), "
                                       f"got {type(value).__name__}")
        best = self.best
        if best is not None and len(best.facets) != len(contacts.points):
            raise ContactPoseError(f"contacts has {len(contacts.points)} contacts, the answer's hypotheses "
                                   f"{len(best.facets)}: give the contacts it was localized from")
        best_name, others = self._page_placements()
        fig = view.localization_figure(
            model.vertices, model.faces, contacts.points, contacts.finger_normals,
            pose=None if best is None else best.pose, best_name=best_name, others=others, finger_radius=finger_radius,
            free_translation=None if best is None else best.free_translation,
            free_rotation=None if best is None else best.free_rotation, title=self._view_title())
        return view.write_html(fig, path)

    def _page_placements(self):
        """The placements a page shows: (the best's name, [(name, pose (4, 4))] of the others,
        best first, at most view.MAX_OTHERS). They are the distinct placements weighed by
        evidence (the pose classes where there are none: the paper's method), each named by its
        rank and probability, the best hypothesis's first; without either, the hypotheses,
        named by rank and χ² (and probability, where known)."""
        groups = self.placements or self.classes
        if groups:
            names = [f"placement {i + 1}, p = {c.probability:.3g}" for i, c in enumerate(groups)]
            own = next((i for i, c in enumerate(groups) if 0 in np.asarray(c.members)), None)
            best_name = "best placement" + ("" if own is None else f" ({names[own]})")
            others = [(names[i], c.pose) for i, c in enumerate(groups) if i != own]
            return best_name, others[:view.MAX_OTHERS]
        shown = self.hypotheses[:view.MAX_OTHERS + 1]
        names = [f"hypothesis {i + 1}, chi2 = {h.chi2:.3g}" + ("" if h.probability is None else
                                                                f", p = {h.probability:.3g}")
                 for i, h in enumerate(shown)]
        return ("best placement" + (f" ({names[0]})" if names else ""),
                [(name, h.pose) for name, h in zip(names[1:], shown[1:])])

    def _view_title(self):
        """The page's title: status, counts and best facets; the hint on a line of its own."""
        n = int(self.num_hypotheses)
        first = f"status {self.status}: {n} hypothes{'i' if n == 1 else 'e'}s"
        if self.best is not None:
            first += f", best facets {self.best.facets.tolist()}, chi2 {self.best.chi2:.3g}"
            if self.best.underdetermined:
                first += " (underdetermined: free directions drawn)"
        return view.title_text(first, self.hint)

    def __repr__(self):
        n, shown = int(self.num_hypotheses), len(self.hypotheses)
        found = (f"{shown} of " if shown != n else "") + f"{n} hypothes{'i' if n == 1 else 'e'}s"
        if self.best is not None:
            found += f" (best facets {self.best.facets.tolist()}, chi2 {self.best.chi2:.3g})"
        c = len(self.classes)
        total = self.timing.get("total")
        parts = [f"status={self.status!r}", found, f"{c} pose class{'' if c == 1 else 'es'}",
                 f"method={self.method!r}"]
        if self.solver != ("closed-form" if self.method == "fast" else "lm"):
            parts.append(f"solver={self.solver!r}")
        if self.diagnosis is not None:
            parts.append(f"cause={self.diagnosis.cause!r}")
        if total is not None:
            parts.append(f"{1000.0 * total:.2f} ms")
        return f"Result({', '.join(parts)})"


@dataclass
class PoseClass:
    """Hypotheses that place the object's surface the same way (ADD-S below
    SAME_CLASS_ADDS_FRAC of the diameter): symmetric twins count as one placement.

    members : hypothesis ranks (in the listed ranking, before top); best : rank of its best member;
    pose : (4, 4) its best pose; chi2 : its best χ²; probability : share of the
    likelihood exp(-χ²/2) summed over members, normalised over classes.
    """

    members: np.ndarray
    best: int
    pose: np.ndarray
    chi2: float
    probability: float

    def to_dict(self):
        """This class as JSON (``$defs/pose_class`` of contactpose/data/result.schema.json)."""
        return {"members": np.asarray(self.members).tolist(), "best": int(self.best), "pose": self.pose.tolist(),
                "chi2": json_number(self.chi2), "probability": json_number(self.probability)}
