"""Next touch: the probe that best separates the remaining pose classes.

A probe is a ray in the world frame: a finger starts at ``start`` and moves along
``direction`` until it touches. Under each pose class the ray is cast against the
posed object, which predicts the contact the finger would measure (point and outward
normal), or a miss.

* **Members.** A class is its best pose. An underdetermined class (the hypothesised
  normals leave translations or a turn free) is a pose family instead: with the
  contacts given, it is represented by up to ``FAMILY_POSES`` poses along its free
  directions that keep every contact on its patch (:func:`family_poses`), and its
  probability is shared among them.
* **Outcomes.** Two member poses are told apart by a probe when their predictions
  differ beyond the measurement tolerance: one touches and the other does not, or the
  points differ by more than ``separation`` pair distance tolerances, or the normals
  by more than ``separation`` pair angle tolerances. Members a probe cannot tell apart
  form one outcome group (connected components of "not separated").
* **Gain.** The outcome is fixed by the member pose, so the expected information gain
  about the class is the mutual information I(class; group) = H(group) - H(group | class)
  in bits; with one member per class it is H(P_g), P_g = Σ_{c in g} p_c. The probe's
  score adds ``FAMILY_WEIGHT`` times H(group | class), the bits about where in its
  family the object is, so that a probe also pins down free directions, and subtracts
  ``MISS_PENALTY`` times the chance that it touches nothing (a contact is a
  measurement localize can use, a miss is not).
* **Ties.** Among probes of equal score (all that split two classes, say) the one most
  likely to touch wins, then the most robust one: the largest least separation between groups, in tolerance
  units (capped at ``ROBUST_CAP``), times the least cosine of incidence of the
  predicted contacts (grazing contacts are fragile).

Default candidates: rays aimed along the inward normal at surface points sampled
(area-weighted, with ``rng``) on the object under each class's pose, starting
``STANDOFF_DIAMETERS`` diameters off the surface, so that the start lies outside the
object under every class.

Not modelled: whether the hand can reach the probe, and pose changes when the probe
pushes the object.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from contactpose.errors import ContactPoseError, check_count
from contactpose.geometry.raycast import raycaster
from contactpose.geometry.sampling import uniform_in_triangles

#: Default ray start: this many object diameters off the aimed surface point.
STANDOFF_DIAMETERS = 2.5
#: Separations beyond this many tolerances (and hit vs miss) count as equally robust.
ROBUST_CAP = 10.0
#: Probes whose score is within this many bits of the best count as ties.
GAIN_TIE_BITS = 1e-9
#: Samples per free direction when an underdetermined class is spread over its pose family.
FAMILY_GRID = 21
#: Poses kept per family (the class pose included).
FAMILY_POSES = 12
#: Weight of the bits about the pose within an underdetermined class's family, next to
#: the bits about the class, in the score of a probe.
FAMILY_WEIGHT = 0.1
#: Bits charged for the chance that the probe touches nothing (localize cannot use a miss).
MISS_PENALTY = 0.5
#: Probes are scored in chunks of at most this many (probe, member, member) entries.
MEMBER_PAIRS_PER_CHUNK = 2_000_000
PRIORS = ("likelihood", "classes", "uniform")

log = logging.getLogger(__name__)
#: Predicted outcome kinds: no contact, a contact, the start lies inside the object.
MISS, CONTACT, BLOCKED = 0, 1, 2


@dataclass
class Touch:
    """A suggested probe and what each pose class predicts for it.

    point : (3,) world point the probe aims at (its predicted contact under the most
    probable class it touches); direction : (3,) unit approach direction, into the
    object; start : (3,) where the finger starts, point - standoff·direction;
    expected_gain : bits about the class, I(class; outcome); probabilities : (C,)
    class probabilities used;
    kind : (C,) int MISS / CONTACT / BLOCKED per class; contact_points,
    contact_normals : (C, 3) predicted contact and outward object normal per class
    (NaN where no contact), at each class's own pose; groups : (C,) int, classes with
    the same label are not told apart by this probe (at their own poses); robustness : tie-break score (see module docstring).
    """

    point: np.ndarray
    direction: np.ndarray
    start: np.ndarray
    expected_gain: float
    probabilities: np.ndarray
    kind: np.ndarray
    contact_points: np.ndarray
    contact_normals: np.ndarray
    groups: np.ndarray
    robustness: float = 0.0
    contact_share: np.ndarray | None = None
    family_gain: float = 0.0

    @property
    def determined(self):
        """Nothing left to separate: one pose class, and no pose family to narrow down."""
        return len(self.probabilities) <= 1 and self.family_gain <= GAIN_TIE_BITS

    @property
    def outcomes(self):
        """Per class: {"kind": "miss" | "contact" | "blocked", "point", "normal", "group"}."""
        names = {MISS: "miss", CONTACT: "contact", BLOCKED: "blocked"}
        return [{"kind": names[int(k)], "group": int(g),
                 "point": None if k != CONTACT else p.tolist(), "normal": None if k != CONTACT else n.tolist()}
                for k, p, n, g in zip(self.kind, self.contact_points, self.contact_normals, self.groups)]

    def to_dict(self):
        return {"determined": self.determined,
                "point": self.point.tolist(), "direction": self.direction.tolist(), "start": self.start.tolist(),
                "expected_gain_bits": float(self.expected_gain), "family_gain_bits": float(self.family_gain),
                "robustness": float(self.robustness),
                "contact_share": None if self.contact_share is None else self.contact_share.tolist(),
                "probabilities": self.probabilities.tolist(), "outcomes": self.outcomes}


# ----------------------------------------------------------------- pieces

def class_poses(model, result, prior="likelihood"):
    """(C, 4, 4) poses, (C,) probabilities and (C,) best-hypothesis ranks of the result's
    distinct placements (result.placements, modulo symmetry, where localize weighed them),
    else of its pose classes (whose ADD-S grouping can hold a near-symmetric flip in one).

    prior : "likelihood" (∝ exp(-χ²/2) of each class's best hypothesis), "classes" (the
    result's class probabilities, summed over members) or "uniform". A result without
    classes (nothing fits within noise) gives its best hypothesis as the one class.
    """
    if prior not in PRIORS:
        raise ContactPoseError(f"prior must be one of {PRIORS}, got {prior!r}")
    classes = list(getattr(result, "placements", []) or []) or list(getattr(result, "classes", []) or [])
    if not classes:
        if result.best is None:
            raise ContactPoseError(f"the result has no hypothesis (status {result.status!r}); nothing to separate")
        return result.best.pose[None].copy(), np.ones(1), np.zeros(1, dtype=np.int64)
    poses = np.stack([c.pose for c in classes])
    ranks = np.array([c.best for c in classes], dtype=np.int64)
    if prior == "uniform":
        p = np.ones(len(classes))
    elif prior == "classes":
        p = np.array([c.probability for c in classes], dtype=np.float64)
    else:
        chi2 = np.array([c.chi2 for c in classes])
        p = np.exp(-0.5 * (chi2 - chi2.min()))
    return poses, p / p.sum(), ranks


def candidate_probes(model, poses, rng, n_candidates=200, standoff=None):
    """Rays aimed at surface points sampled on the object under each pose.

    poses : (C, 4, 4); the candidates are shared out evenly over the poses (each
    point area-weighted on the surface, uniform in its facet). Returns
    origins (N, 3), directions (N, 3) unit, aims (N, 3) world.
    """
    check_count(n_candidates, "n_candidates")
    standoff = STANDOFF_DIAMETERS * model.diameter if standoff is None else float(standoff)
    valid = np.flatnonzero(model.planes.valid)
    area = model.planes.areas[valid]
    facets = rng.choice(valid, size=n_candidates, p=area / area.sum())
    p_obj = uniform_in_triangles(model.triangles[facets], rng)
    which = np.arange(n_candidates) % len(poses)
    R, t = poses[which, :3, :3], poses[which, :3, 3]
    aims = np.einsum("nij,nj->ni", R, p_obj) + t
    normals = np.einsum("nij,nj->ni", R, model.planes.normals[facets])
    return aims + standoff * normals, -normals, aims


def predict_outcomes(model, poses, origins, directions):
    """Ray-cast every probe against the object under every pose.

    poses : (C, 4, 4); origins, directions : (N, 3) world rays (directions unit).
    Returns kind (C, N) int (MISS / CONTACT / BLOCKED), points (C, N, 3) world contact,
    normals (C, N, 3) world outward normal there (NaN unless CONTACT), distance (C, N)
    along the ray (inf on a miss).
    """
    poses = np.asarray(poses, dtype=np.float64)
    c, n = len(poses), len(origins)
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    # rays in each pose's object frame: (C, N, 3)
    o_obj = np.einsum("cji,cnj->cni", R, origins[None] - t[:, None])
    d_obj = np.einsum("cji,nj->cni", R, directions)
    dist, facet = raycaster(model).first_hits(o_obj.reshape(-1, 3), d_obj.reshape(-1, 3))
    dist, facet = dist.reshape(c, n), facet.reshape(c, n)
    hit = facet >= 0
    n_obj = model.planes.normals[np.where(hit, facet, 0)]
    facing = np.einsum("cni,cni->cn", n_obj, d_obj) < 0  # the ray meets the outer side
    kind = np.where(hit, np.where(facing, CONTACT, BLOCKED), MISS)
    contact = kind == CONTACT
    reach = np.where(contact, dist, 0.0)
    points = np.where(contact[..., None], origins[None] + reach[..., None] * directions[None], np.nan)
    normals = np.where(contact[..., None], np.einsum("cij,cnj->cni", R, n_obj), np.nan)
    return kind, points, normals, np.where(hit, dist, np.inf)


def separations(kind, points, normals, tol_distance, tol_angle):
    """How far apart the predictions of each pair of member poses are, in tolerance units.

    kind : (M, N); points, normals : (M, N, 3). Returns (N, M, M) float: the larger of
    |Δp| / tol_distance and angle / tol_angle where both touch, 0 where both miss (or
    both are blocked), inf where the kinds differ.
    """
    kn = kind.T  # (N, M)
    same_kind = kn[:, :, None] == kn[:, None, :]
    both = (kn[:, :, None] == CONTACT) & (kn[:, None, :] == CONTACT)
    p = np.nan_to_num(points.transpose(1, 0, 2))
    nr = np.nan_to_num(normals.transpose(1, 0, 2))
    dp = np.linalg.norm(p[:, :, None] - p[:, None, :], axis=3) / tol_distance
    da = np.arccos(np.clip(np.einsum("nai,nbi->nab", nr, nr), -1.0, 1.0)) / tol_angle
    sep = np.where(both, np.maximum(dp, da), 0.0)
    return np.where(same_kind, sep, np.inf)


def family_poses(model, hypothesis, contacts, tolerance, *, grid=None, max_poses=None):
    """Poses of an underdetermined hypothesis' family that keep every contact on its patch.

    hypothesis : localize Hypothesis (its pose, facets, free_translation (k, 3) and
    free_rotation); contacts : the Contacts it explains; tolerance : Tolerance. The
    family is sampled on a grid of ``grid`` shifts per free direction, within the range
    the patches' extents allow (±1 diameter when a turn is free too, with 2·grid turns
    about the free axis through the contacts' mean). A sample is kept when every
    assigned contact lies within ``tolerance.distance`` of its patch (its facet on a
    model without patches). Returns (V, 4, 4): the hypothesis pose first, then up to
    ``max_poses - 1`` kept samples spread by farthest-point sampling.
    """
    grid = FAMILY_GRID if grid is None else grid
    max_poses = FAMILY_POSES if max_poses is None else max_poses
    T0 = hypothesis.pose
    free_t = np.asarray(hypothesis.free_translation).reshape(-1, 3)
    axis = hypothesis.free_rotation
    if len(free_t) == 0 and axis is None:
        return T0[None]
    limit = tolerance.distance
    if axis is None:
        # shifts (in diameters) that can keep every contact on its patch, per free direction
        p = T0[:3, :3].T @ (contacts.points - T0[:3, 3]).T  # (3, n) contacts in the object frame
        axes = [np.linspace(*_shift_bounds(model, hypothesis.facets, p.T, T0[:3, :3].T @ f, limit), grid)
                for f in free_t]
    else:  # a turn about the axis moves the patches' extents around: sample shifts widely
        axes = [np.linspace(-1.0, 1.0, grid)] * len(free_t) + [np.linspace(-np.pi, np.pi, 2 * grid, endpoint=False)]
    params = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))
    poses = _family(T0, free_t, axis, params, model.diameter, contacts.points.mean(axis=0))
    keep = _on_patches(model, hypothesis.facets, poses, contacts, limit)
    params, poses = params[keep], poses[keep]
    scale = np.array([1.0 / max(np.ptp(a), 1e-12) for a in axes])
    chosen = _farthest(params * scale, max_poses - 1)
    return np.concatenate([T0[None], poses[chosen]])


def _shift_bounds(model, facets, p_obj, u, limit):
    """Range of α (in diameters) for which every contact p - α·diameter·u (object frame)
    stays within ``limit`` of its patch's extent along u. p_obj : (n, 3); u : (3,) unit."""
    lo, hi = -1.0, 1.0
    for f, p in zip(facets, p_obj):
        if f < 0:
            continue
        if model.patches is not None:
            q = model.patches.labels[f]
            members = model.patches.members[model.patches.indptr[q]:model.patches.indptr[q + 1]]
        else:
            members = np.array([f])
        proj = model.triangles[members].reshape(-1, 3) @ u
        lo = max(lo, (p @ u - proj.max() - limit) / model.diameter)
        hi = min(hi, (p @ u - proj.min() + limit) / model.diameter)
    return (lo, hi) if lo < hi else (0.0, 0.0)


def _family(T0, free_t, axis, params, diameter, centre):
    """(P, 4, 4) poses: T0 shifted by Σ params_j · diameter · free_t_j, then turned by the
    last param about ``axis`` through ``centre`` (when axis is given)."""
    T = np.repeat(T0[None], len(params), axis=0)
    k = len(free_t)
    T[:, :3, 3] += diameter * params[:, :k] @ free_t
    if axis is not None:
        from scipy.spatial.transform import Rotation

        Q = Rotation.from_rotvec(params[:, k:k + 1] * np.asarray(axis)[None]).as_matrix()
        T[:, :3, :3] = Q @ T[:, :3, :3]
        T[:, :3, 3] = np.einsum("pij,pj->pi", Q, T[:, :3, 3] - centre) + centre
    return T


def _on_patches(model, facets, poses, contacts, limit):
    """(P,) bool: every assigned contact within ``limit`` of its patch under each pose."""
    from contactpose.costs.association import nearest_members
    from contactpose.geometry.kernels import point_triangle_distance

    assigned = np.flatnonzero(np.asarray(facets) >= 0)
    f = np.asarray(facets)[assigned]
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    p = np.einsum("pji,pnj->pni", R, contacts.points[assigned][None] - t[:, None])  # (P, a, 3)
    if model.patches is not None:
        tuples = np.broadcast_to(model.patches.labels[f], (len(poses), len(f)))
        near = nearest_members(model.member_groups, model.triangles, np.ascontiguousarray(tuples), p)
    else:
        near = np.broadcast_to(f, (len(poses), len(f)))
    d = point_triangle_distance(p.reshape(-1, 3), model.triangles[near.reshape(-1)]).reshape(p.shape[:2])
    return (d <= limit).all(axis=1)


def _farthest(points, k):
    """Indices of up to k rows of points spread by farthest-point sampling from the origin."""
    if len(points) == 0 or k <= 0:
        return np.zeros(0, dtype=np.int64)
    dist = np.linalg.norm(points, axis=1)
    chosen = []
    for _ in range(min(k, len(points))):
        j = int(np.argmax(dist))
        if dist[j] <= 0:
            break
        chosen.append(j)
        dist = np.minimum(dist, np.linalg.norm(points - points[j], axis=1))
    return np.array(chosen, dtype=np.int64)


def outcome_groups(separated):
    """Connected components of "not separated". separated : (N, M, M) bool ->
    (N, M) int, each member labelled by the lowest index in its group."""
    n, m, _ = separated.shape
    linked = ~separated | np.eye(m, dtype=bool)[None]
    labels = np.broadcast_to(np.arange(m), (n, m)).copy()
    while True:
        # label propagation: each member takes the lowest label among its links
        new = np.where(linked, labels[:, None, :], m).min(axis=2)
        if np.array_equal(new, labels):
            return labels
        labels = new


def information_gain(probabilities, groups, owner=None):
    """Expected information gain about the class, in bits, of probes whose outcome is
    fixed by the member pose.

    probabilities : (M,) member probabilities summing to 1; groups : (N, M) outcome-group
    labels; owner : (M,) class of each member (default: each member its own class).
    Returns (N,) I(class; outcome) = H(outcome) - H(outcome | class); with one member per
    class this is H(P_g).
    """
    n, m = groups.shape
    owner = np.arange(m) if owner is None else np.asarray(owner)
    c = int(owner.max()) + 1
    rows = np.repeat(np.arange(n), m)
    joint = np.zeros((n, m, c))  # P(outcome group, class)
    np.add.at(joint, (rows, groups.ravel(), np.tile(owner, n)), np.tile(probabilities, n))
    return _entropy_rows(joint.sum(axis=2)) + _entropy_rows(joint.sum(axis=1)) - _entropy_rows(joint.reshape(n, -1))


def _entropy_rows(mass):
    with np.errstate(divide="ignore", invalid="ignore"):
        return -np.where(mass > 0, mass * np.log2(mass), 0.0).sum(axis=1)


def entropy(probabilities):
    """H(p) in bits."""
    p = np.asarray(probabilities, dtype=np.float64)
    p = p[p > 0]
    return float(-(p * np.log2(p)).sum())


# ----------------------------------------------------------------- the API

def suggest_touch(model, result, candidates=None, *, rng, contacts=None, n_candidates=200, prior="likelihood",
                  separation=1.0, standoff=None):
    """The probe that best separates the pose classes of ``result``.

    model : ObjectModel; result : localize's Result (its ``classes`` and ``tolerance``);
    candidates : None (sampled: see :func:`candidate_probes`) or world rays as a tuple
    (origins (N, 3), directions (N, 3)) or an (N, 6) array; rng : numpy Generator;
    contacts : the Contacts that were localized: with them, an underdetermined class is
    predicted over its pose family (:func:`family_poses`), its probability shared among
    the family's poses; without them, at the class's best pose; prior : class probabilities, see :func:`class_poses`;
    separation : predictions differ when they are more than this many pair tolerances
    apart; standoff : distance of the sampled starts from the surface (default
    STANDOFF_DIAMETERS diameters). Returns :class:`Touch`.
    """
    if not (np.isfinite(separation) and separation > 0):
        raise ContactPoseError(f"separation must be a positive number, got {separation!r}")
    poses, prob, ranks = class_poses(model, result, prior)
    if len(poses) == 1:
        log.debug("one pose class: no probe can tell classes apart (gain 0)")
    member_poses, owner = _members(model, result, poses, ranks, contacts)
    if candidates is None:
        origins, directions, _ = candidate_probes(model, poses, rng, n_candidates, standoff)
    else:
        origins, directions = _check_candidates(candidates)
    kind, points, normals, _ = predict_outcomes(model, member_poses, origins, directions)
    tol = result.tolerance
    counts = np.bincount(owner, minlength=len(poses))
    member_prob = prob[owner] / counts[owner]  # a class's probability spread over its family
    n, m = len(origins), len(owner)
    groups = np.empty((n, m), dtype=np.int64)
    robust = np.empty(n)
    step = max(1, MEMBER_PAIRS_PER_CHUNK // (m * m))
    for lo in range(0, n, step):
        # probes in chunks: the member-pair arrays are (chunk, M, M)
        part = slice(lo, lo + step)
        sep = separations(kind[:, part], points[:, part], normals[:, part],
                          separation * tol.distance, separation * tol.angle)
        groups[part] = outcome_groups(sep > 1.0)
        robust[part] = _robustness(sep, groups[part], kind[:, part], normals[:, part], directions[part])
    gain = information_gain(member_prob, groups, owner)
    # bits about where in its pose family the object is (0 without underdetermined classes)
    family_gain = information_gain(member_prob, groups) - gain
    # chance of a contact: over classes, the share of member poses that touch
    touch_prob = member_prob @ (kind == CONTACT)
    best = _pick(gain + FAMILY_WEIGHT * family_gain - MISS_PENALTY * (1.0 - touch_prob), touch_prob, robust)
    first = np.searchsorted(owner, np.arange(len(poses)))  # each class's own pose
    centre = poses[0, :3, :3] @ model.surface_points.mean(axis=0) + poses[0, :3, 3]
    share = np.bincount(owner, weights=kind[:, best] == CONTACT, minlength=len(poses)) / counts
    return _touch(origins[best], directions[best], prob, kind[first, best], points[first, best],
                  normals[first, best], groups[best][first], centre,
                  expected_gain=float(gain[best]), robustness=float(robust[best]), contact_share=share,
                  family_gain=float(family_gain[best]))


def _members(model, result, poses, ranks, contacts):
    """Member poses (M, 4, 4) of the classes and their owner class (M,), sorted by class."""
    if contacts is None:
        contacts = getattr(result, "contacts", None)
    out, owner = [], []
    for c, (pose, rank) in enumerate(zip(poses, ranks)):
        family = pose[None]
        if contacts is not None and rank < len(result.hypotheses):
            hyp = result.hypotheses[int(rank)]
            if hyp.underdetermined:
                family = family_poses(model, hyp, contacts, result.tolerance)
        out.append(family)
        owner += [c] * len(family)
    return np.concatenate(out), np.array(owner, dtype=np.int64)


def _check_candidates(candidates):
    if isinstance(candidates, tuple) and len(candidates) == 2:
        origins, directions = (np.asarray(c, dtype=np.float64) for c in candidates)
    else:
        arr = np.asarray(candidates, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 6:
            raise ContactPoseError(f"candidates must be (origins, directions) or an (N, 6) array, got shape {arr.shape}")
        origins, directions = arr[:, :3], arr[:, 3:]
    if origins.ndim != 2 or origins.shape[1] != 3 or origins.shape != directions.shape or len(origins) == 0:
        raise ContactPoseError(f"candidate origins and directions must both be (N, 3) with N >= 1, "
                               f"got {origins.shape} and {directions.shape}")
    if not (np.all(np.isfinite(origins)) and np.all(np.isfinite(directions))):
        raise ContactPoseError("candidate rays must be finite")
    length = np.linalg.norm(directions, axis=1)
    if np.any(length < 1e-12):
        raise ContactPoseError(f"candidate direction {int(np.argmin(length))} is a zero vector")
    return origins, directions / length[:, None]


def _robustness(sep, groups, kind, normals, directions):
    """(N,) least separation between member poses of different groups (capped), times the
    least cosine of incidence of the predicted contacts."""
    cross = groups[:, :, None] != groups[:, None, :]
    least = np.where(cross, np.minimum(sep, ROBUST_CAP), ROBUST_CAP).min(axis=(1, 2))
    cos = np.abs(np.einsum("mni,ni->mn", np.nan_to_num(normals), directions))
    cos = np.where(kind == CONTACT, cos, 1.0).min(axis=0)
    return least * cos


def _pick(gain, touch_prob, robust):
    """The highest score; among ties, the most probable contact, then the most robust."""
    ties = np.flatnonzero(gain >= gain.max() - GAIN_TIE_BITS)
    ties = ties[touch_prob[ties] >= touch_prob[ties].max() - 1e-9]
    return int(ties[np.argmax(robust[ties])])


def _touch(origin, direction, prob, kind, points, normals, groups, centre, **scores):
    touching = np.flatnonzero(kind == CONTACT)
    if len(touching):
        aim = points[touching[np.argmax(prob[touching])]]
    else:  # no class is touched: the ray's closest approach to the most probable object's centre
        aim = origin + max(0.0, float((centre - origin) @ direction)) * direction
    return Touch(point=aim, direction=direction, start=origin, probabilities=prob, kind=kind,
                 contact_points=points, contact_normals=normals, groups=groups, **scores)


# ----------------------------------------------------------------- simulation
