"""Free space: a finger sits outside the object, and the object is not where the fingers passed.

A hypothesis puts contact i on facet k under the pose T = (R, t). In the object frame
the contact is p_i = Rᵀ(x̃_i - t) and the finger comes from the direction
u_i = -Rᵀñ_i, away from the object. If a ray from the surface along u_i enters the
object again within the finger radius r, the contact lies in a concavity too narrow
for the finger, and the hypothesis is rejected.

* The ray starts on facet k's plane (the foot of p_i), ``START_REL`` · diameter off it.
* Only *entering* hits count (the ray meets a facet from its outer side, u·n < 0).
  A ray that starts just inside the surface, through noise, first leaves the object:
  that exit is not a violation, so the test never depends on the sign of the noise.
* ``fingertip="ball"`` also checks the fingertip sphere of radius r resting on the
  contact: its centre p_i + r·u_i must be at least r - ``slack`` from the surface.
  This catches a finger at the bottom of a narrow slot, where the ray runs out of the
  slot freely. A true contact of a spherical fingertip of radius >= r passes both
  tests when the noise (``slack``) is accounted for: the ray segment of length r lies
  inside the fingertip's ball as long as the normal error is below 60°.

The swept free space (contacts.FreeSpace: points, balls and capsules the fingers passed
through, world frame) is evidence too: :func:`drop_intersecting` drops a hypothesis whose posed
object meets it by more than the pair distance tolerance, within a bounded cost
(:func:`intersecting_best_first` states the rule).

Rays, inside tests (ray parity, meaningful for a closed mesh) and distances are queried from the
model's :func:`~contactpose.geometry.raycast.raycaster`.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial import cKDTree

from contactpose.costs.facet import offset_residuals
from contactpose.costs.frame import object_frame
from contactpose.errors import ContactPoseError
from contactpose.geometry.metrics import pose_embedding
from contactpose.geometry.raycast import raycaster
from contactpose.model.symmetry import symmetry
from contactpose.scoring.classes import distinct_radius, pose_leaders

log = logging.getLogger(__name__)

#: Rays start this fraction of the object diameter off the facet plane.
START_REL = 1e-6
FINGERTIPS = ("ray", "ball")
#: Default clearance allowance of the "ball" test, as a fraction of the finger radius:
#: a true fingertip's centre sits r·cos θ from its facet for a normal error θ, and
#: 0.1 r covers θ up to 25° plus position error up to a tenth of the radius.
BALL_SLACK_REL = 0.1

def free_space_violations(model, facets, poses, contacts, finger_radius, *, per_contact=False,
                          fingertip="ray", slack=None):
    """Which hypotheses put a contact where no finger fits.

    model : ObjectModel; facets : (H, n) int, the facet of each contact (-1: unassigned
    finger, never a violation); poses : (H, 4, 4) T_world_object; contacts : Contacts
    (world frame); finger_radius : r > 0, length units; fingertip : "ray" (the outward
    normal ray of length r re-enters the object) or "ball" (also: the fingertip sphere of
    radius r on the contact comes closer than r - slack to the surface); slack : length,
    the noise allowance of the "ball" test (default BALL_SLACK_REL · r).
    Returns (H,) bool, True where some contact is violated, or (H, n) bool with
    ``per_contact=True``.
    """
    facets = np.asarray(facets)
    poses = np.asarray(poses, dtype=np.float64)
    if facets.ndim != 2 or facets.shape[1] != contacts.n:
        raise ContactPoseError(f"facets must have shape (H, {contacts.n}), got {facets.shape}")
    if poses.shape != (len(facets), 4, 4):
        raise ContactPoseError(f"poses must have shape ({len(facets)}, 4, 4), got {poses.shape}")
    if not (np.isfinite(finger_radius) and finger_radius > 0):
        raise ContactPoseError(f"finger_radius must be a positive length, got {finger_radius!r}")
    if fingertip not in FINGERTIPS:
        raise ContactPoseError(f"fingertip must be one of {FINGERTIPS}, got {fingertip!r}")
    h, n = facets.shape
    if h == 0:
        return np.zeros((0, n) if per_contact else 0, dtype=bool)
    assigned = facets >= 0
    k = np.where(assigned, facets, 0)
    # contacts and outward finger directions in each hypothesis' object frame: (H, n, 3)
    p, u = object_frame(poses[:, :3, :3], poses[:, :3, 3], contacts.points, contacts.finger_normals)
    # foot of each contact on its facet's plane, then a hair outward
    n_k = model.planes.normals[k]
    foot = p - offset_residuals(p, n_k, model.planes.offsets[k])[..., None] * n_k
    origins = foot + START_REL * model.diameter * u
    caster = raycaster(model)
    bad = caster.entering_within(origins.reshape(-1, 3), u.reshape(-1, 3), finger_radius).reshape(h, n)
    if fingertip == "ball":
        slack = BALL_SLACK_REL * finger_radius if slack is None else float(slack)
        # fingertip sphere resting on the contact: centre r along u, clearance r - slack
        centres = foot + finger_radius * u
        bad |= caster.distance(centres.reshape(-1, 3)).reshape(h, n) < finger_radius - slack
    bad &= assigned
    return bad if per_contact else bad.any(axis=1)


def drop_blocked(model, contacts, arrays, finger_radius):
    """The hypotheses but those whose (determined) pose puts a contact where no finger of
    ``finger_radius`` fits (:func:`free_space_violations`)."""
    bad = free_space_violations(model, arrays.facets, arrays.poses, contacts, finger_radius)
    return arrays.take(np.flatnonzero(~(bad & ~arrays.fit.underdetermined)))


# ------------------------------------------------------------ swept free space as evidence ---
#
# The fingers reached the object through free space (contacts.FreeSpace): a hypothesis whose
# posed object meets that space is not the object's placement. Every free point, sphere and
# capsule is a ball (centre c, radius ρ; a point has ρ = 0, a capsule is sampled as balls along
# its segment). Under a pose (R, t) the centre lies at p = Rᵀ(c - t) in the object frame, and
# the ball meets the object when the signed distance sd(p) of its centre from the surface
# (negative inside) is below ρ - τ. The clearance τ is the pair distance tolerance σ_Δ
# (3·√2·σ_x + model_error): a free point's error and the posed surface's error near the
# contacts, each σ_x per axis, differ by √2·σ_x. The *margin* ρ - τ - sd(p) of a ball is
# positive where it meets the object.

#: A capsule is sampled as balls of its radius at most this far apart, as a fraction of
#: max(radius, τ) (the balls lie inside the capsule, so the test stays conservative) ...
CAPSULE_SPACING_REL = 1.0
#: ... and with at most this many balls per capsule (a longer capsule's balls leave gaps:
#: the test there is weaker, never stronger).
CAPSULE_BALLS_MAX = 64
#: Hypothesis x ball pairs transformed and tested per chunk (memory: about 100 bytes a pair).
PAIRS_PER_CHUNK = 1 << 16
#: Balls tested on every hypothesis of a chunk first (those nearest the contacts, where a
#: wrong placement that fits the contacts meets the fingers' paths); the rest only on the
#: hypotheses they did not rule out.
FIRST_BALLS = 64
#: Hypotheses taken in rank order per window: each is first compared with those tested before
#: (a k-d tree over pose embeddings), then the rest are tested in chunks.
WINDOW = 512
#: At most this many hypothesis x ball pairs are tested exactly per localize call (about
#: 0.3-0.7 µs a pair with Open3D; the hypotheses past it are kept untested).
MAX_FREE_PAIRS = 1 << 20


def free_balls(free_space, clearance):
    """The free space as balls: points (ρ = 0), spheres, and capsules sampled along their
    segment CAPSULE_SPACING_REL · max(radius, clearance) apart (CAPSULE_BALLS_MAX at most).

    free_space : contacts.FreeSpace; clearance : τ > 0, length.  ->  (centres (E, 3), radii (E,))
    """
    a, b, rc = free_space.capsules
    length = np.linalg.norm(b - a, axis=1)
    spacing = CAPSULE_SPACING_REL * np.maximum(rc, clearance)
    count = np.minimum(np.ceil(length / spacing).astype(np.int64) + 1, CAPSULE_BALLS_MAX)
    owner = np.repeat(np.arange(len(rc)), count)
    step = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
    s = (step / np.maximum(count - 1, 1)[owner])[:, None]
    centres = np.concatenate([free_space.points, free_space.spheres[0], a[owner] + s * (b - a)[owner]])
    radii = np.concatenate([np.zeros(len(free_space.points)), free_space.spheres[1], rc[owner]])
    return centres, radii


def ball_margins(model, poses, centres, slack, box=None):
    """The deepest ball of each pose: how far some ball reaches into the posed object.

    poses : (H, 4, 4) T_world_object; centres : (E, 3) world; slack : (E,) radius - clearance.
    A ball's margin is slack - sd(p), sd the signed distance of its centre p (object frame) from
    the surface, negative inside (the model's raycaster: ray parity and closest points); it meets
    the object where the margin is positive. Balls whose signed distance from the model's
    bounding box (a lower bound on sd) is not below their slack are settled without a query, and
    a centre inside with a positive slack counts its slack (a lower bound: sd <= 0). box : the
    model's bounding box (:func:`bounding_box`), computed when not given.
    Returns (margin (H,) float, -inf where no ball comes near; ball (H,) int, -1 there).
    """
    caster = raycaster(model)
    mid, half = bounding_box(model) if box is None else box
    margin, ball = np.full(len(poses), -np.inf), np.full(len(poses), -1)
    per = max(1, PAIRS_PER_CHUNK // max(len(centres), 1))
    for start in range(0, len(poses) if len(centres) else 0, per):
        chunk = poses[start:start + per]
        p = (centres[None] - chunk[:, None, :3, 3]) @ chunk[:, :3, :3]      # Rᵀ(c - t), (h, E, 3)
        q = np.abs(p - mid) - half
        lower = np.linalg.norm(np.maximum(q, 0.0), axis=2) + np.minimum(q.max(axis=2), 0.0)  # sd of the box
        h, e = np.nonzero(lower < slack)
        m = _margins(caster, p[h, e], slack[e])
        first = np.lexsort((-m, h))          # by hypothesis, deepest first
        top = first[np.r_[True, h[first][1:] != h[first][:-1]]] if len(h) else first
        margin[start + h[top]], ball[start + h[top]] = m[top], e[top]
    return margin, ball


def bounding_box(model):
    """The model's axis-aligned bounding box (object frame): (centre (3,), half extents (3,))."""
    lo, hi = np.min(model.vertices, axis=0), np.max(model.vertices, axis=0)
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def _margins(caster, points, slack):
    """(N,) slack - sd(p) of points (N, 3) (object frame), slack (N,). Distances are queried
    only where the side (inside or out) does not settle whether it is positive; elsewhere the
    value is slack, which bounds it from below inside (slack > 0) and from above outside."""
    inside = caster.inside(points) if len(points) else np.zeros(0, dtype=bool)
    need = np.flatnonzero(inside != (slack > 0))  # inside with slack <= 0, or outside with slack > 0
    depth = np.zeros(len(points))
    depth[need] = caster.distance(points[need]) if len(need) else 0.0
    return slack + np.where(inside, depth, -depth)


def drop_intersecting(model, contacts, arrays, free_space, tolerance):
    """The hypotheses but those whose posed object meets the free space the fingers swept, and
    a note for the hint.

    model : ObjectModel; contacts : Contacts (world frame); arrays : HypothesisArrays, ranked;
    free_space : contacts.FreeSpace (world frame); tolerance : Tolerance (the clearance τ is its
    distance σ_Δ). A hypothesis is dropped only when its pose is shown to put a free ball into
    the object beyond τ (:func:`intersecting_best_first`, which bounds the cost); the note says
    how many placements that removed, and how many hypotheses the budget left untested.
    Returns (arrays, note).
    """
    if free_space.size == 0 or len(arrays.cost) == 0:
        return arrays, ""
    centres, radii = free_balls(free_space, tolerance.distance)
    radius = distinct_radius(model, tolerance.position_noise)
    bad, untested = intersecting_best_first(model, contacts, arrays, centres, radii - tolerance.distance, radius)
    return arrays.take(np.flatnonzero(~bad)), _free_space_note(model, arrays, bad, untested, radius)


def _free_space_note(model, arrays, bad, untested, radius):
    """'free space ruled out N placements (K facet assignments)', and how many went untested.
    Placements are the distinct poses (classes.pose_leaders) modulo the object's symmetry."""
    parts = []
    if bad.any():
        poses, group = arrays.poses[bad], symmetry(model)
        if group is not None and not group.trivial:
            poses = group.canonical(poses)
        owner = pose_leaders(model, poses, arrays.fit.underdetermined[bad], radius)
        placements, assignments = int(np.sum(owner == np.arange(len(owner)))), int(bad.sum())
        parts.append(f"free space ruled out {placements} placement{'s' * (placements != 1)} "
                     f"({assignments} facet assignment{'s' * (assignments != 1)})")
    if untested:
        parts.append(f"{untested} lower-ranked hypotheses were left untested against free space (its budget)")
    return "; ".join(parts)


def intersecting_best_first(model, contacts, arrays, centres, slack, radius):
    """Which hypotheses meet the free space, tested best first within a bounded cost.

    arrays : HypothesisArrays, ranked; centres (E, 3), slack (E,) : the free balls (world frame;
    radius - clearance); radius : RMS displacement (classes.distinct_radius) within which two
    poses are near-copies. The determined hypotheses are taken in rank order, WINDOW at a time,
    and each is compared with the exactly tested hypothesis nearest it in pose, if one lies
    within ``radius`` (a k-d tree over pose embeddings):

    * that one passed: kept untested (a near-copy of it, which distinct poses merge into it);
    * that one failed by a margin m at a ball that moves by less than m from its pose to this
      one: dropped (sd is 1-Lipschitz, so this one fails at that ball too);
    * otherwise, and with no tested one near: tested exactly against every ball (the
      FIRST_BALLS nearest the contacts first), while the exact tests stay within MAX_FREE_PAIRS
      hypothesis x ball pairs; past that kept untested.

    Underdetermined hypotheses are kept untested (their pose is one arbitrary member of a
    family). So nothing is dropped without a proof, and the cost is bounded by MAX_FREE_PAIRS
    exact pairs and one k-d tree query per hypothesis. Returns (bad (H,) bool, how many
    hypotheses the budget left untested).
    """
    order = np.argsort(_nearest_contact_distance(contacts, centres), kind="stable")
    state = _Verdicts(arrays.poses, centres[order], slack[order], bounding_box(model))
    embedding = pose_embedding(arrays.poses, *model.class_moments)
    candidates = np.flatnonzero(~arrays.fit.underdetermined)
    tree, done = None, np.zeros(0, dtype=np.int64)
    for start in range(0, len(candidates), WINDOW):
        window = candidates[start:start + WINDOW]
        if state.tested.any():
            if len(done) != state.tested.sum():
                done = np.flatnonzero(state.tested)
                tree = cKDTree(embedding[done])
            dist, near = tree.query(embedding[window], distance_upper_bound=radius)
            close = np.isfinite(dist)
            window = np.sort(np.concatenate([window[~close], state.settle(window[close], done[near[close]])]))
        _test_window(model, window, radius, state)
    return state.bad, state.untested


class _Verdicts:
    """What is known of each hypothesis (poses (H, 4, 4)) against the free balls (centres
    (E, 3), slack (E,), nearest the contacts first; box : the model's bounding_box): bad and
    tested (H,) bool, the margin and ball (H,) of its deepest ball where tested, the exact
    pairs left in the budget and how many hypotheses went untested for it."""

    def __init__(self, poses, centres, slack, box):
        h = len(poses)
        self.poses, self.centres, self.slack, self.box = poses, centres, slack, box
        self.bad, self.tested = np.zeros(h, dtype=bool), np.zeros(h, dtype=bool)
        self.margin, self.ball = np.full(h, -np.inf), np.full(h, -1)
        self.budget, self.untested = MAX_FREE_PAIRS, 0

    def test(self, model, rows):
        """Test hypotheses ``rows`` (K,) exactly, as many as the budget allows, in order."""
        rows = rows[:self.budget // len(self.centres)]
        for chunk in np.array_split(rows, -(-len(rows) * len(self.centres) // PAIRS_PER_CHUNK) or 1):
            if len(chunk):
                self.margin[chunk], self.ball[chunk], spent = _test(model, self.poses[chunk], self.centres,
                                                                    self.slack, self.box)
                self.bad[chunk], self.tested[chunk] = self.margin[chunk] > 0, True
                self.budget -= spent

    def settle(self, rows, lead):
        """Settle hypotheses ``rows`` (K,) by a tested near-copy ``lead`` (K,) each: kept untested
        where it passed, dropped where its failure is implied (:func:`_implied`). -> the rows left
        unsettled (K',) int."""
        failed = self.bad[lead]
        rows, lead = rows[failed], lead[failed]
        implied = _implied(self.poses, rows, lead, self.centres[self.ball[lead]], self.margin[lead])
        self.bad[rows[implied]] = True
        return rows[~implied]


def _test_window(model, window, radius, state):
    """Test the hypotheses ``window`` (ranked rows) into ``state`` (_Verdicts): in rounds, the
    leaders of its near-copy groups (classes.pose_leaders) exactly, then the others settled by
    their leader (_Verdicts.settle); exact tests stop once they would pass the budget."""
    while len(window):
        owner = pose_leaders(model, state.poses[window], np.zeros(len(window), dtype=bool), radius)
        leads = owner == np.arange(len(window))
        state.test(model, window[leads])
        followers = ~leads & state.tested[window[owner]]
        state.untested += int(np.sum(~state.tested[window[owner]]))     # leaders past the budget, their followers
        window = state.settle(window[followers], window[owner[followers]])


def _nearest_contact_distance(contacts, centres):
    """(E,) distance of each ball centre (E, 3) from the nearest contact (world frame)."""
    return np.sqrt(np.min(np.sum((centres[:, None, :] - contacts.points[None]) ** 2, axis=2), axis=1))


def _implied(poses, rows, lead, centres, margin):
    """(K,) bool: hypothesis rows[k] fails where its failed neighbour lead[k] did: the ball at
    centres[k] (world), where lead[k] failed by margin[k], moves by less than that between the
    two poses in the object frame. poses : (H, 4, 4); rows, lead : (K,) int."""
    def local(r):
        return np.einsum("kji,kj->ki", poses[r, :3, :3], centres - poses[r, :3, 3])
    return np.linalg.norm(local(rows) - local(lead), axis=1) < margin


def _test(model, poses, centres, slack, box):
    """Exact margins (:func:`ball_margins`) of poses (K, 4, 4): the FIRST_BALLS first, the rest
    only for the poses those did not rule out. -> (margin (K,), ball (K,), pairs tested)"""
    k = min(FIRST_BALLS, len(centres))
    margin, ball = ball_margins(model, poses, centres[:k], slack[:k], box)
    rest = np.flatnonzero(margin <= 0)
    if k < len(centres) and len(rest):
        m, b = ball_margins(model, poses[rest], centres[k:], slack[k:], box)
        deeper = m > margin[rest]
        margin[rest[deeper]], ball[rest[deeper]] = m[deeper], b[deeper] + k
    return margin, ball, len(poses) * k + len(rest) * (len(centres) - k)
