"""One hypothesis tracked touch after touch: a pose trajectory smoothed by GTSAM's iSAM2.

The object is held in a hand that moves between touches. Step k has its own pose variable
X_k = T_world_object at the time of touch k. The hand's motion between touches k-1 and k is
a known rigid transform ΔT_k of the world (x' = ΔT_k x). The object moves with the hand, up to
a slip S_k in the object frame:

    X_k = ΔT_k X_{k-1} S_k,   S_k = Exp(ξ),   ξ ~ N(0, diag(σ_r² I₃, σ_t² I₃))  (rotation first).

The variables are taken in the frame that moves with the hand, Y_k = H_k⁻¹ X_k, where
H_k = ΔT_k ··· ΔT_1 (H_0 = I). Then Y_k = Y_{k-1} S_k exactly, which is GTSAM's
``BetweenFactorPose3(Y_{k-1}, Y_k, I, slip)``, and the contacts of touch k, moved by H_k⁻¹,
enter the contact factors of :mod:`contactpose.solvers.factor_graph` on Y_k unchanged.
Touches of an object that has not moved share one variable.

A touch after a hand motion adds one variable, its slip factor and one contact factor per
contact, and ``gtsam.ISAM2`` (Gauss–Newton steps, every change back-substituted, a variable
relinearized when it moved by more than TRACK_RELINEARIZE) updates the smoothed trajectory
incrementally. The contact factors are one per contact with the kernel as GTSAM's
reweighting (factor_graph.reweighted_contact_factors; the smooth model's likewise), whose
steps do not overshoot as the batched factor's square-rooted kernel does, and the
point-to-facet rows are the in-plane vector from the contact's triangle
(costs.facet.lateral_rows), whose Gauss–Newton model holds. Gauss–Newton can still cycle
where a contact's closest feature of its triangle changes, so :meth:`PoseTrack.relinearize`
converges with Dogleg steps, and
:meth:`PoseTrack.batch` solves the same graph by Levenberg–Marquardt from the same initial
values, the reference. The two agree to 1e-6 and better (tests/tracking/test_track.py;
research/tracking.md, "Gauss–Newton steps").

On a fine tessellation (facets a few sensor sigmas wide, such as the YCB meshes) a contact's
facet is ambiguous, and the default contact model ("auto") is then the smooth one: the normal
interpolated over the facet, its noise widened by the mesh's roughness about it and by the
contact's position noise along the surface, no point-to-facet rows, so that a contact slides
from facet to facet (research/tracking.md, "Smooth normals by default on fine meshes", "The
contact's place noise in the smooth normal"). Where a rounded fingertip sits on a crease (an
edge the smooth normals do not blend across), its normal lies on the edge's arc of normals:
the association and the contact rows then take that edge when it fits better than the face
(ObjectModel.crease_edges; research/tracking.md, "Contacts on creases").
"""

from __future__ import annotations

from functools import lru_cache

import gtsam
import numpy as np

from contactpose.contacts import Contacts, Tolerance
from contactpose.costs.association import nearest_fit_facets
from contactpose.costs.facet import kernel_params, pack_contacts
from contactpose.costs.smooth import smooth_data, touch_chi2
from contactpose.errors import ContactPoseError, check_count
from contactpose.geometry.se3 import inverse
from contactpose.model.symmetry import symmetry
from contactpose.options import check_robust, chi2_quantile
from contactpose.solvers import factor_graph as fg
from contactpose.solvers.surface import surface_factor
from contactpose.types import PosePrior, check_rigid

#: A track's iSAM2 relinearizes, at every update, each variable that moved by more than this
#: since its linearization (tangent norm: 1.15° in rotation; 20 mm when lengths are metres).
#: 2e-2 tracks as 1e-2 did (YCB banana, 100 sequences: 0.001° ± 0.014° per touch, paired) and
#: is 13 % faster; 3e-2 costs 0.046° ± 0.014° (research/tracking.md, "Fewer swaps").
TRACK_RELINEARIZE = 2e-2
#: :meth:`PoseTrack.relinearize` converges with this threshold instead: the batch optimum.
RELINEARIZE_THRESHOLD = 1e-8
#: iSAM2 back-substitutes every change of the solution larger than this (0: every change).
WILDFIRE_THRESHOLD = 0.0
#: TrackSet: tracks kept, the χ² margin above the best beyond which a track is dropped
#: (χ²₆ at 1 - 1e-6: a pose that much less likely than the best), and the distance within which
#: two tracks are one pose (rotation in degrees, translation as a fraction of the diameter).
MAX_TRACKS = 20
CONTACT_MODELS = ("auto", "facets", "smooth", "surface")
#: contact_model "auto" is "smooth" on a mesh whose median facet radius is below this many
#: sensor sigmas σ_x (a contact's facet is then ambiguous: the YCB meshes, 2.2–5.4), else
#: "facets" (the built-in meshes, 17–55; research/tracking.md, "Smooth normals by default on
#: fine meshes").
SMOOTH_BELOW = 8.0
#: Associated touches: after the update, each contact takes its best-fitting facet again under
#: the updated pose, and the touch's factor is swapped while that changes to facets not yet
#: tried for the touch (a cycle keeps the last swap), at most this often.
REASSOCIATE = 5
#: Trajectories drawn by PoseTrack.association_covariance, by default.
ASSOCIATION_SAMPLES = 20
#: ... each solved by LM from the smoothed estimate with these settings.
ASSOCIATION_LM = dict(max_iterations=30, relative_tol=1e-8, absolute_tol=1e-10)
#: The contact models whose tracks associate a touch under their pose's uncertainty
#: (costs.association.association_weights): those with one normal per facet, whose neighbours'
#: normals differ by degrees. With smooth normals the neighbours' residuals differ by
#: micrometres and hundredths of a degree, the weighting changed nothing measurable (YCB
#: tracking +0.03° ± 0.015°, coverage within its noise) and cost 1 ms per touch of 20 tracks.
UNCERTAIN_ASSOCIATION = ("facets",)
#: A touch's new pose takes at most this many further iSAM2 updates (PoseTrack._settle).
SETTLE_STEPS = 3
PRUNE_CHI2 = 38.26
#: TrackSet: a touch whose χ² exceeds, for every track, χ²'s (1 - SURPRISE_P) quantile with 3
#: degrees of freedom per contact sets off a reseed from the latest touches, at least
#: RESEED_CONTACTS contacts.
SURPRISE_P = 1e-3
RESEED_CONTACTS = 4
#: TrackSet: starts tried, at most, per track kept (many of a grasp's starts coincide once refined).
START_TRIES = 4
MERGE_DEG = 2.0
MERGE_FRAC = 0.02
#: LM settings of the batch reference.
BATCH = dict(max_iterations=100, relative_tol=1e-12, absolute_tol=1e-14)


def hand_motion_noise(sigma_rot_deg, sigma_trans):
    """The slip's noise model: diagonal, rotation (radians) first, as Pose3's tangent."""
    if not (np.isfinite(sigma_rot_deg) and sigma_rot_deg > 0 and np.isfinite(sigma_trans) and sigma_trans > 0):
        raise ContactPoseError(f"slip sigmas must be positive and finite, got {sigma_rot_deg!r} deg and {sigma_trans!r}")
    s = np.r_[np.full(3, np.radians(sigma_rot_deg)), np.full(3, float(sigma_trans))]
    return gtsam.noiseModel.Diagonal.Sigmas(s)


def checked_motion(hand_motion):
    """None, or (ΔT (4, 4), σ_rot in degrees, σ_trans) -> (ΔT checked rigid, the slip's noise model)."""
    if hand_motion is None:
        return None
    delta, sigma_rot_deg, sigma_trans = hand_motion
    return check_rigid(delta, "hand motion"), hand_motion_noise(sigma_rot_deg, sigma_trans)


def resolved_contact_model(model, tolerance, contact_model):
    """The contact model that "auto" stands for on this model and sensor noise (SMOOTH_BELOW),
    or ``contact_model`` itself, checked."""
    if contact_model not in CONTACT_MODELS:
        raise ContactPoseError(f"contact_model must be one of {CONTACT_MODELS}, got {contact_model!r}")
    if contact_model != "auto":
        return contact_model
    fine = np.median(model.facet_radii[model.planes.valid]) < SMOOTH_BELOW * tolerance.position_noise
    return "smooth" if fine else "facets"


def _check_contacts(contacts):
    if not isinstance(contacts, Contacts):
        raise ContactPoseError(f"contacts must be a contactpose.Contacts, got {type(contacts).__name__}")


class PoseTrack:
    """The trajectory of one hypothesis (its facets at each touch) in an iSAM2 smoother.

    model : ObjectModel; contacts : Contacts of the first touch; facets : (n,) int, their
    facets; pose : (4, 4) T_world_object to start from (the hypothesis's pose); tolerance :
    Tolerance (σ_x, σ_n); robust : "huber" | "cauchy" | "none"; prior : PosePrior on the first
    pose, or None (then the first touch must determine the pose); contact_model : "facets"
    (factor_graph's contact factor on each contact's facet plane), "smooth" (the same with the
    normal interpolated over the facet from its corners' normals, for fine tessellations of
    smooth surfaces: factor_graph.smooth_contact_factor), "surface" (the contact on a face, an
    edge or a vertex, its normal in that feature's normal cone, solvers.surface.surface_factor;
    no robust kernel) or "auto" (default: "smooth" on a mesh whose facets are a few sensor
    sigmas wide, else "facets": :func:`resolved_contact_model`); point_to_facet : the lateral
    residual of a contact outside its triangle (factor_graph's contact factor); None (default):
    on with facet normals, off with smooth ones, where a contact slides from facet to facet.
    """

    def __init__(self, model, contacts, facets, pose, tolerance, *, robust="huber", prior=None, point_to_facet=None,
                 contact_model="auto"):
        if not isinstance(tolerance, Tolerance):
            raise ContactPoseError(f"tolerance must be a contactpose.Tolerance, got {type(tolerance).__name__}")
        self.contact_model = resolved_contact_model(model, tolerance, contact_model)
        self.point_to_facet = self.contact_model == "facets" if point_to_facet is None else bool(point_to_facet)
        self.robust = robust
        if prior is not None and not isinstance(prior, PosePrior):
            raise ContactPoseError(f"prior must be a contactpose.PosePrior or None, got {type(prior).__name__}")
        self.model, self.tolerance = model, tolerance
        check_robust(robust)
        self.hand = [np.eye(4)]  # H_k
        self.graph = gtsam.NonlinearFactorGraph()  # every factor so far (the batch reference)
        self._others = gtsam.NonlinearFactorGraph()  # the prior and slip factors, for :attr:`spread`
        self._twins = []  # per touch: its contact factors' twins for :attr:`spread`, or None: not built yet
        self.initial = gtsam.Values()
        self.touches = []  # (pose variable k, Contacts in the world, facets (n,)) of every touch
        self._slots = []  # per touch: its contact factors' indices in iSAM2 and in graph
        self._associated = []  # per touch: were its facets associated by the track (add_touch)?
        self.score = 0.0  # Σ over touches of the touch's contact χ² just after its update
        self.isam = _isam2(trust_region=self.contact_model == "surface")
        factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if prior is not None:
            factors.add(fg.prior_factor(prior, key=0))
        values.insert(0, gtsam.Pose3(check_rigid(pose, "start pose")))
        self._update(factors, values, contacts, self._checked(contacts, facets))

    def add(self, contacts, facets=None, hand_motion=None):
        """One more touch: its contacts (world frame) and facets (n,) int, or None for each
        contact's best-fitting facet under the predicted pose (costs.association.nearest_fit_facets;
        the prediction is ΔT times the last smoothed pose: no slip), taken again under the
        updated pose until it holds or comes back to facets already tried (at most
        REASSOCIATE times); hand_motion : None (the
        object has not moved: the contacts join the last pose's factor graph, no new variable)
        or (ΔT (4, 4), σ_rot in degrees, σ_trans), the hand's motion since the last touch and
        the slip (a new pose variable). Returns the smoothed current pose (4, 4)."""
        _check_contacts(contacts)
        return self._add(contacts, facets, checked_motion(hand_motion))

    def _add(self, contacts, facets, motion):
        """:meth:`add` with the hand motion checked: None or (ΔT (4, 4), slip noise model)."""
        if facets is None:
            add_touch([self], contacts, motion)
        else:
            self._step(contacts, self._checked(contacts, facets), motion, score=False)
            self._settle()
            self.score += self._last_chi2()
        return self.pose

    def _checked(self, contacts, facets):
        """A caller's facets for ``contacts``, checked. -> (n,) int"""
        _check_contacts(contacts)
        facets = np.asarray(facets)
        if facets.shape != (contacts.n,) or facets.min() < -1 or facets.max() >= self.model.num_facets:
            raise ContactPoseError(f"facets must be {contacts.n} indices into the model's {self.model.num_facets} "
                                   f"facets (-1: unassigned), got {facets.tolist()}")
        return facets

    def _hand_after(self, motion):
        """(4, 4) H_k of the next touch: ΔT H_{k-1}, or H_{k-1} when the object has not moved."""
        return self.hand[-1] if motion is None else motion[0] @ self.hand[-1]

    def _predicted(self, motion):
        """(4, 4) T_world_object predicted for the next touch: ΔT times the last smoothed pose
        (no slip), or the last pose when the object has not moved."""
        return self._hand_after(motion) @ self._last.matrix()

    def _step(self, contacts, facets, motion, score, local=None, packing=None):
        """The touch's contact factor on its facets, after a new pose variable and its slip
        factor when the hand moved: one iSAM2 update. local, packing : the touch in the hand
        frame and its :meth:`_pack`, when already at hand."""
        factors, values, hand = gtsam.NonlinearFactorGraph(), gtsam.Values(), None
        if motion is not None:
            hand = self._hand_after(motion)
            k = len(self.hand)
            factors.add(gtsam.BetweenFactorPose3(k - 1, k, gtsam.Pose3(), motion[1]))
            values.insert(k, self._last)  # Y_k predicted: no slip
        self._update(factors, values, contacts, facets, hand, score=score, local=local, packing=packing)

    def _pack(self, local, facets):
        """The packing of contacts ``local`` (hand frame) on ``facets`` (..., n): (data, smooth or
        None) from costs.facet.pack_contacts / smooth_data, or None for "surface"."""
        if self.contact_model == "surface":
            return None
        if self.contact_model == "smooth":
            return smooth_data(self.model, local, facets, self.tolerance)
        return pack_contacts(self.model, local, facets), None

    def _factors(self, local, facets, k, twin=False, packing=None):
        """The contact factors of a touch (contacts ``local`` in the hand frame) on pose k: one
        per contact with the kernel as reweighting ("facets", "smooth"), or one for the touch
        ("surface", no kernel); ``twin``: those of :attr:`spread` instead (no point-to-facet
        rows; with smooth normals, no place information from the normal:
        factor_graph.reweighted_smooth_factors); packing : :meth:`_pack` of the touch, when at
        hand. -> ([factor], packing)"""
        lateral = self.point_to_facet and not twin
        if self.contact_model == "surface":
            return [surface_factor(self.model, local, facets, self.tolerance, k)], None
        data, smooth = self._pack(local, facets) if packing is None else packing
        if smooth is not None:
            factors = fg.reweighted_smooth_factors(data, smooth, self.tolerance, self.robust, lateral, k,
                                                   place=not twin)
        else:
            factors = fg.reweighted_contact_factors(data, self.tolerance, self.robust, lateral, k)
        return factors, (data, smooth)

    @property
    def spread(self):
        """gtsam.NonlinearFactorGraph of :attr:`covariance`: :attr:`graph` with each contact factor
        replaced by its twin (:meth:`_factors` with ``twin``), each touch's twins built once."""
        graph = gtsam.NonlinearFactorGraph()
        graph.push_back(self._others)
        for i, (k, contacts, facets) in enumerate(self.touches):
            if self._twins[i] is None:
                local = contacts.transformed(inverse(self.hand[k]))
                self._twins[i] = self._factors(local, facets, k, twin=True)[0]
            for twin in self._twins[i]:
                graph.add(twin)
        return graph

    def _swap(self, facets, packing=None):
        """The last touch's contact factors replaced by those on ``facets`` (packing: their
        :meth:`_pack`, when at hand): one iSAM2 update."""
        k, contacts, _ = self.touches[-1]
        factors, self._packed = self._factors(self._local, facets, k, packing=packing)
        slots, at_graph = self._slots[-1]
        new = gtsam.NonlinearFactorGraph()
        for factor, i in zip(factors, at_graph):
            self.graph.replace(i, factor)
            new.add(factor)
        result = self.isam.update(new, gtsam.Values(), slots)
        self._slots[-1] = (list(result.getNewFactorsIndices()), at_graph)
        self.touches[-1] = (k, contacts, facets)
        self._twins[-1] = None
        self._refresh()

    def _refresh(self):
        """After an update: the last pose's estimate now, every pose's and the last pose's
        covariance when asked (:attr:`_estimate`, :meth:`_uncertainty`)."""
        self._full = self._spread_now = None
        self._last = self.isam.calculateEstimatePose3(len(self.hand) - 1)

    def _settle(self):
        """Further iSAM2 updates (at most SETTLE_STEPS) while the last pose has stepped farther
        from its linearization point (the prediction, for a new pose) than the relinearization
        threshold: each relinearizes it, so that the touch's contact factors, and their robust
        weights, are taken near the estimate rather than at the prediction, a slip away
        (research/tracking.md, "A covariance that carries the association"). Gauss–Newton
        tracks only: a "surface" track's iSAM2 relinearizes whatever moved at every update."""
        if self.contact_model == "surface":
            return
        for _ in range(SETTLE_STEPS):
            if np.abs(self.isam.getDelta().at(len(self.hand) - 1)).max() < TRACK_RELINEARIZE:
                return
            self.isam.update()
            self._refresh()

    def _uncertainty(self, motion=None):
        """(6, 6) the last pose's covariance as iSAM2 holds it (its own linearization), plus
        the slip's when the hand moves on (``motion``), under which a touch's contacts take
        their facets (costs.association.association_weights); zero where the touches so far leave
        directions free. None for smooth normals, whose facets differ too little for it to
        matter (:data:`UNCERTAIN_ASSOCIATION`)."""
        if self.contact_model not in UNCERTAIN_ASSOCIATION:
            return None
        if self._spread_now is None:
            try:
                self._spread_now = self.isam.marginalCovariance(len(self.hand) - 1)
            except RuntimeError:
                self._spread_now = np.zeros((6, 6))
        if motion is None:
            return self._spread_now
        return self._spread_now + np.diag(motion[1].sigmas() ** 2)

    @property
    def _estimate(self):
        """gtsam.Values: the smoothed estimate of every pose variable."""
        if self._full is None:
            self._full = self.isam.calculateEstimate()
        return self._full

    def _last_chi2(self):
        """χ² (2 · error) of the last touch's contact factors (on the last pose alone) at the
        estimate: Σ 2ρ(s_i) over its contacts, s_i the whitened norm of contact i's rows, from
        one compiled evaluation of the touch's packing (:meth:`_factors`; the "surface" factor:
        its GTSAM error)."""
        return float(_touch_chi2([self])[0])

    def _update(self, factors, values, contacts, facets, hand=None, score=True, local=None, packing=None):
        """The contact factor of a touch on the last pose variable (a new one, at hand pose
        ``hand``, when given), with ``factors`` and new ``values``: one iSAM2 update; ``score``
        adds the touch's χ² to :attr:`score`; local, packing : as for :meth:`_step`."""
        if hand is not None:
            self.hand.append(hand)
        k = len(self.hand) - 1
        self.touches.append((k, contacts, facets))
        self._associated.append(False)
        self._local = contacts.transformed(inverse(self.hand[k])) if local is None else local
        self._twins.append(None)
        contact_factors, self._packed = self._factors(self._local, facets, k, packing=packing)
        for i in range(factors.size()):
            self._others.add(factors.at(i))
            self.graph.add(factors.at(i))
        for factor in contact_factors:
            self.graph.add(factor)
            factors.add(factor)
        self.initial.insert(values)
        try:
            result = self.isam.update(factors, values)
        except RuntimeError as err:  # indeterminant system: the touches so far leave directions free
            raise ContactPoseError(f"pose {k}: the contacts so far leave pose directions free; give a prior "
                                   f"or more contacts ({type(err).__name__})") from None
        n = len(contact_factors)
        self._slots.append((list(result.getNewFactorsIndices())[-n:], list(range(self.graph.size() - n, self.graph.size()))))
        self._refresh()
        if score:
            self.score += self._last_chi2()

    def associate(self, contacts):
        """Each contact's best-fitting facet under the current smoothed pose (and its
        uncertainty, as a touch's association weighs it). -> (n,) int"""
        return nearest_fit_facets(self.model, contacts, self.pose, self.tolerance, self._uncertainty(),
                                     creases=self.contact_model == "smooth")

    def _y(self, k):
        return (self._last if k == len(self.hand) - 1 else self._estimate.atPose3(k)).matrix()

    @property
    def poses(self):
        """(K, 4, 4) smoothed T_world_object of every pose variable (one per hand motion, plus
        the first): X_k = H_k Y_k."""
        return np.stack([h @ self._y(k) for k, h in enumerate(self.hand)])

    @property
    def pose(self):
        """(4, 4) smoothed T_world_object at the last touch."""
        return self.hand[-1] @ self._y(len(self.hand) - 1)

    @property
    def covariance(self):
        """(6, 6) marginal covariance of the last pose at the smoothed estimate, rotation first,
        in the tangent space of Y_k (a right perturbation of X_k = H_k Y_k is the same one of
        Y_k). As the single-pose factor graph's, it leaves out the point-to-facet hinge's
        curvature (factor_graph.optimize): the marginal of :attr:`spread`, or iSAM2's own
        where that leaves directions free. It holds each touch's facets fixed. With smooth
        normals ("auto" on a fine mesh) it takes no place information from the normal, whose
        facet-to-facet roughness is in its noise. Its 95 % region held the truth in 93.5 % of
        rock and YCB banana sequences with the true facets, and in 92.0 % and 83.0 % with the
        facets that the track associated, which it holds fixed: where the track chose its
        facets, :meth:`association_covariance` also carries their uncertainty (92.0 % on the
        banana; research/tracking.md, "A covariance that carries the association")."""
        return self._joint_covariance([len(self.hand) - 1])

    def _joint_covariance(self, keys):
        """(6 len(keys), 6 len(keys)) joint covariance of the poses ``keys`` at the smoothed
        estimate: the marginal of :attr:`spread`, or iSAM2's own where that leaves directions free."""
        keys = gtsam.KeyVector(list(keys))
        try:
            return gtsam.Marginals(self.spread, self._estimate).jointMarginalCovariance(keys).fullMatrix()
        except RuntimeError:
            return self.isam.jointMarginalCovariance(keys).fullMatrix()

    def association_covariance(self, rng, samples=ASSOCIATION_SAMPLES):
        """(6, 6) covariance of the last pose that also carries the association: :attr:`covariance`
        plus the mean of δ δᵀ over ``samples`` trajectories drawn from the joint covariance of all
        poses (the marginal of :attr:`spread`). Under each, every touch whose facets the track
        associated takes its best-fitting facets again (costs.association.nearest_fit_facets), and δ
        is the last pose's move (tangent of Y_K) from the smoothed estimate to the optimum of the
        graph on those facets, solved by LM from the estimate (ASSOCIATION_LM): where the
        optimum lies under the associations that the pose's uncertainty allows, about the
        estimate. :attr:`covariance` holds the facets fixed, but they were taken under the
        estimate, whose error they then keep (YCB banana: 95 % region 92 % against 83 %;
        research/tracking.md, "A covariance that carries the association").
        rng : numpy.random.Generator; 0.1–0.16 s for 20 samples of 11 poses."""
        if not isinstance(rng, np.random.Generator):
            raise ContactPoseError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        check_count(samples, "samples", minimum=1)
        K, estimate = len(self.hand), self._estimate
        joint = self._joint_covariance(range(K))
        draws = rng.multivariate_normal(np.zeros(6 * K), joint, size=samples, method="eigh")
        graphs = [self._reassociated([self.hand[k] @ estimate.atPose3(k).retract(xi[6 * k:6 * k + 6]).matrix()
                                      for k in range(K)], joint) for xi in draws]
        own = _optimum_move(self.graph, estimate, K - 1) if any(g is None for g in graphs) else None
        moves = np.array([own if g is None else _optimum_move(g, estimate, K - 1) for g in graphs])
        return joint[-6:, -6:] + moves.T @ moves / samples  # the last pose's block: :attr:`covariance`

    def _reassociated(self, poses, joint):
        """The graph with every associated touch on its best-fitting facets under ``poses``
        (K, 4, 4) (under the poses' uncertainty, the diagonal blocks of ``joint``, where the
        track's association weighs it), or None when no facet changes."""
        graph, changed = gtsam.NonlinearFactorGraph(), False
        graph.push_back(self._others)
        uncertain = self.contact_model in UNCERTAIN_ASSOCIATION
        for (k, contacts, facets), associated in zip(self.touches, self._associated):
            if associated:
                again = nearest_fit_facets(self.model, contacts, poses[k], self.tolerance,
                                              joint[6 * k:6 * k + 6, 6 * k:6 * k + 6] if uncertain else None,
                                              creases=self.contact_model == "smooth")
                changed |= bool((again != facets).any())
                facets = again
            for factor in self._factors(contacts.transformed(inverse(self.hand[k])), facets, k)[0]:
                graph.add(factor)
        return graph if changed else None

    def seen_now(self):
        """Every touch's contacts as the object at its current pose would carry them (each moved
        by X_K X_k⁻¹ from its own smoothed pose X_k), and their facets: the residuals of all
        touches at one pose. -> (Contacts, facets (N,) int)"""
        poses = self.poses
        moved = [c.transformed(poses[-1] @ np.linalg.inv(poses[k])) for k, c, _ in self.touches]
        return moved[0].joined(*moved[1:]), np.concatenate([f for _, _, f in self.touches])

    def relinearize(self, max_updates=100, tol=1e-12):
        """The smoothed trajectory converged: an iSAM2 with Dogleg steps (a trust region;
        Gauss–Newton steps can cycle where a contact's closest feature of its triangle changes)
        takes the graph at the smoothed estimate and is updated without new factors until no
        pose moves by more than ``tol`` (tangent norm) or after ``max_updates``, every update
        relinearizing what moved by more than RELINEARIZE_THRESHOLD. The track goes on from
        the converged trajectory. -> poses"""
        converging = _isam2(trust_region=True)
        converging.update(self.graph, self._estimate)
        every = gtsam.ISAM2UpdateParams()
        every.force_relinearize = True
        estimate = converging.calculateEstimate()
        for _ in range(max_updates):
            converging.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), every)
            before, estimate = estimate, converging.calculateEstimate()
            moved = max(np.linalg.norm(before.atPose3(k).localCoordinates(estimate.atPose3(k)))
                        for k in range(len(self.hand)))
            if moved <= tol:
                break
        self.isam = _isam2(trust_region=self.contact_model == "surface")
        self.isam.update(self.graph, estimate)
        self._slots = [(list(at_graph), at_graph) for _, at_graph in self._slots]
        self._refresh()
        return self.poses

    def cost(self, poses):
        """The graph's χ² (2 · error) at a trajectory. poses : (K, 4, 4) T_world_object."""
        values = gtsam.Values()
        for k, (h, x) in enumerate(zip(self.hand, poses)):
            values.insert(k, gtsam.Pose3(np.linalg.inv(h) @ x))
        return 2.0 * self.graph.error(values)

    def batch(self):
        """The same graph solved by LM from the same initial values. -> (K, 4, 4) T_world_object"""
        result = gtsam.LevenbergMarquardtOptimizer(self.graph, self.initial, fg.lm_params(**BATCH)).optimize()
        return np.stack([h @ result.atPose3(k).matrix() for k, h in enumerate(self.hand)])


def _isam2(trust_region):
    """A gtsam.ISAM2 that back-substitutes every change and checks for relinearization at
    every update: Dogleg steps and the threshold RELINEARIZE_THRESHOLD (``trust_region``), or
    Gauss–Newton steps and TRACK_RELINEARIZE."""
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(RELINEARIZE_THRESHOLD if trust_region else TRACK_RELINEARIZE)
    params.relinearizeSkip = 1
    steps = gtsam.ISAM2DoglegParams() if trust_region else gtsam.ISAM2GaussNewtonParams()
    steps.setWildfireThreshold(WILDFIRE_THRESHOLD)
    params.setOptimizationParams(steps)
    return gtsam.ISAM2(params)


class TrackSet:
    """Several hypotheses of one object tracked side by side, best first.

    Each is a :class:`PoseTrack`, scored by its sequential χ² (:attr:`PoseTrack.score`: each
    touch's contact χ² just after its update, so a wrong hypothesis pays for every touch that
    it explains badly). After each touch, tracks whose pose coincides with a better one's
    modulo the object's symmetry (model.symmetry: rotation within ``merge_deg`` and
    translation within ``merge_frac`` of the diameter, against the nearest of the poses that
    place the surface as the better one does) are merged into it, so that the twins of one
    placement on a symmetric object are one track; those more than ``prune_chi2`` above the
    best are dropped, and at most ``max_tracks`` are kept. The starts are taken in their order until ``max_tracks`` distinct
    tracks are held after the first update, or START_TRIES · max_tracks starts were tried.

    model, contacts, tolerance : as for PoseTrack; starts : [(facets (n,) int, pose (4, 4))],
    best first (for example a Result's hypotheses); robust : the contact factor's kernel;
    seeder : None, or a callable Contacts -> [(facets, pose)], best first, that localizes
    contacts afresh (session.relocalizer): then a touch that every track explains worse than
    SURPRISE_P allows is a sign that the truth is not among them, and :meth:`_reseed` adds
    tracks from the latest touches.
    """

    def __init__(self, model, contacts, starts, tolerance, *, max_tracks=MAX_TRACKS, prune_chi2=PRUNE_CHI2,
                 merge_deg=MERGE_DEG, merge_frac=MERGE_FRAC, robust="huber", contact_model="auto", seeder=None):
        if not starts:
            raise ContactPoseError("a TrackSet needs at least one start (facets, pose)")
        self.model, self.tolerance, self.seeder = model, tolerance, seeder
        self.options = dict(robust=robust, contact_model=contact_model)
        self.history = [(contacts, None)]  # every touch: (Contacts in the world, checked hand motion or None)
        self.reseeds = 0
        self.max_tracks, self.prune_chi2 = check_count(max_tracks, "max_tracks", minimum=1), float(prune_chi2)
        self.merge = (float(merge_deg), float(merge_frac) * model.diameter, symmetry(model))
        self.tracks, taken, tried = [], 0, min(len(starts), START_TRIES * self.max_tracks)
        while taken < tried and len(self.tracks) < self.max_tracks:
            more = starts[taken:min(tried, taken + self.max_tracks - len(self.tracks))]
            taken += len(more)
            self.tracks += self._started(contacts, more)
            if self.tracks:
                self._prune()
        if not self.tracks:
            raise ContactPoseError("no start determines the pose: give starts whose contacts fix it")

    def add(self, contacts, hand_motion=None):
        """One more touch for every track (facets associated per track). -> the best pose (4, 4)"""
        _check_contacts(contacts)
        motion = checked_motion(hand_motion)
        before = [t.score for t in self.tracks]
        add_touch(self.tracks, contacts, motion)
        self.history.append((contacts, motion))
        surprise = min(t.score - b for t, b in zip(self.tracks, before))
        if self.seeder is not None and surprise > surprise_threshold(contacts.n):
            self._reseed()
        self._prune()
        return self.best.pose

    def _recent(self):
        """The latest touches' contacts, newest first until RESEED_CONTACTS, each moved with the
        hand into the current touch's world (H_K H_k⁻¹; the slip between them is not known). -> Contacts"""
        hand, moved = np.eye(4), []
        for contacts, motion in reversed(self.history):
            moved.append(contacts.transformed(hand))
            if sum(c.n for c in moved) >= RESEED_CONTACTS:
                break
            if motion is not None:
                hand = hand @ motion[0]
        return moved[0].joined(*moved[1:])

    def _reseed(self):
        """New tracks from the recent touches (:meth:`_recent`) localized afresh by the seeder,
        those that no track holds yet, at most max_tracks, each replayed over every touch so
        far (:meth:`_replayed`), so that its score weighs the same evidence as the others'."""
        poses = []
        for _, pose in self.seeder(self._recent()):
            if len(poses) == self.max_tracks:
                break
            if not _coincide(pose, np.stack([t.pose for t in self.tracks] + poses), self.merge).any():
                poses.append(pose)
        if poses:
            self.reseeds += 1
            self.tracks += self._replayed(poses)

    def _replayed(self, poses):
        """Tracks started at ``poses`` (the current touch's T_world_object, (4, 4) each), the
        object taken as still in the hand over every earlier touch, and given every touch so
        far, associated as a track associates them. -> [PoseTrack]"""
        first = self.history[0][0]
        hand = self.tracks[0].hand[-1]
        starts = [inverse(hand) @ p for p in poses]  # Y: the pose in the first touch's world
        facets = nearest_fit_facets(self.model, first, np.stack(starts), self.tolerance, None,
                                       creases=self.tracks[0].contact_model == "smooth")
        tracks = self._started(first, list(zip(facets, starts)))
        for contacts, motion in self.history[1:] if tracks else []:
            add_touch(tracks, contacts, motion)
        return tracks

    def _started(self, contacts, starts):
        """A PoseTrack on ``contacts`` from each start (facets (n,), pose (4, 4)) that determines
        the pose (a pose family cannot start a track without a prior). -> [PoseTrack]"""
        tracks = []
        for facets, pose in starts:
            try:
                tracks.append(PoseTrack(self.model, contacts, facets, pose, self.tolerance, **self.options))
            except ContactPoseError:
                continue
        return tracks

    @property
    def best(self):
        """The track with the least sequential χ²."""
        return self.tracks[0]

    def _prune(self):
        self.tracks.sort(key=lambda t: t.score)
        poses = np.stack([t.pose for t in self.tracks])
        same = _coincide(poses[:, None], poses[None], self.merge)
        kept = []
        for i, t in enumerate(self.tracks):
            if t.score > self.tracks[0].score + self.prune_chi2 or len(kept) == self.max_tracks:
                break
            if not same[i, kept].any():  # merged into a better track with the same pose
                kept.append(i)
        self.tracks = [self.tracks[i] for i in kept]


@lru_cache(maxsize=None)
def surprise_threshold(n):
    """The χ² of a touch of n contacts above which no track explains it: χ²'s (1 - SURPRISE_P)
    quantile with 3 degrees of freedom per contact (22.5 for 2 contacts)."""
    return chi2_quantile(1.0 - SURPRISE_P, 3 * n)


def _coincide(a, b, merge):
    """Whether poses a and b (..., 4, 4), broadcast, are one pose modulo the symmetry
    merge[2] (a model.symmetry.Symmetry): rotation within merge[0] degrees and translation
    within merge[1] of the nearest pose that places the surface as b does. -> bool array"""
    rot, trans = merge[2].errors(a, b)
    return (rot <= merge[0]) & (trans <= merge[1])


def add_touch(tracks, contacts, motion):
    """One touch for several tracks of one model, its facets associated per track: each
    contact takes its best-fitting facet under each track's predicted pose (one search for all
    tracks: costs.association.nearest_fit_facets), each track takes one iSAM2 update, and then,
    while a track's facets change under its updated pose to facets not yet tried for this
    touch (at most REASSOCIATE times), its touch's factor is swapped; a track whose facets come
    back to tried ones (a contact on the edge between two facets, each pushing it onto the
    other) keeps its last swap. Each track's score grows by the touch's χ² at the end. The
    touch is moved into each distinct hand frame once, packed once for all tracks that share
    it, and scored in one compiled pass (costs.smooth.touch_chi2).

    tracks : [PoseTrack] sharing one model, tolerance, contact model, point-to-facet setting
    and kernel; contacts : Contacts (world frame); motion : None or (ΔT (4, 4), slip noise
    model), as from :func:`checked_motion`."""
    model, tolerance = tracks[0].model, tracks[0].tolerance
    kind = (tracks[0].contact_model, tracks[0].point_to_facet, tracks[0].robust)
    if any(t.model is not model or t.tolerance != tolerance or (t.contact_model, t.point_to_facet, t.robust) != kind
           for t in tracks):
        raise ContactPoseError("tracks touched together must share one model, one tolerance, one contact model, "
                               "one point-to-facet setting and one robust kernel")
    facets = nearest_fit_facets(model, contacts, np.stack([t._predicted(motion) for t in tracks]), tolerance,
                                   _stacked([t._uncertainty(motion) for t in tracks]), creases=kind[0] == "smooth")
    hands, local = [t._hand_after(motion) for t in tracks], {}
    for h in hands:  # the touch in each hand frame, once per distinct hand pose
        if h.tobytes() not in local:
            local[h.tobytes()] = contacts.transformed(inverse(h))
    locals_ = [local[h.tobytes()] for h in hands]
    for t, f, here, packing in zip(tracks, facets, locals_, _packings(tracks, locals_, facets)):
        t._step(contacts, f, motion, score=False, local=here, packing=packing)
        t._associated[-1] = True
    pending = list(tracks)
    tried = {id(t): {tuple(f)} for t, f in zip(tracks, facets)}
    for _ in range(REASSOCIATE):
        again = nearest_fit_facets(model, contacts, np.stack([t.pose for t in pending]), tolerance,
                                      _stacked([t._uncertainty() for t in pending]), creases=kind[0] == "smooth")
        changed = [(t, f) for t, f in zip(pending, again) if tuple(f) not in tried[id(t)]]
        packings = _packings([t for t, _ in changed], [t._local for t, _ in changed], [f for _, f in changed])
        for (t, f), packing in zip(changed, packings):
            tried[id(t)].add(tuple(f))
            t._swap(f, packing)
        pending = [t for t, _ in changed]
        if not pending:
            break
    for t in tracks:
        t._settle()
    for t, touch in zip(tracks, _touch_chi2(tracks)):
        t.score += touch


def _optimum_move(graph, values, key):
    """(6,) the move of the Pose3 ``key`` (its tangent) from ``values`` to the optimum of
    ``graph`` that LM reaches from there."""
    solved = gtsam.LevenbergMarquardtOptimizer(graph, values, fg.lm_params(**ASSOCIATION_LM)).optimize()
    return values.atPose3(key).localCoordinates(solved.atPose3(key))


def _stacked(covariances):
    """(H, 6, 6) of the tracks' association covariances, or None when they have none."""
    return None if covariances[0] is None else np.stack(covariances)


def _packings(tracks, locals_, facets):
    """Each track's :meth:`PoseTrack._pack` of its contacts in the hand frame ``locals_[i]`` on
    ``facets[i]`` (n,), one packing for all tracks that share one Contacts object. -> [packing]"""
    out, groups = [None] * len(tracks), {}
    for i, here in enumerate(locals_):
        groups.setdefault(id(here), []).append(i)
    for members in groups.values():
        packed = tracks[members[0]]._pack(locals_[members[0]], np.stack([facets[i] for i in members]))
        if packed is None:
            continue
        for j, i in enumerate(members):
            out[i] = tuple(None if a is None else a[j] for a in packed)
    return out


def _touch_chi2(tracks):
    """Each track's :meth:`PoseTrack._last_chi2`, the "facets" and "smooth" tracks (one
    contact model, one touch size) in one compiled pass (costs.smooth.touch_chi2). -> (H,)"""
    first = tracks[0]
    if first.contact_model == "surface":
        return np.array([_surface_chi2(t) for t in tracks])
    params = kernel_params(first.tolerance, first.robust, first.point_to_facet)
    T = np.stack([t._last.matrix() for t in tracks])
    data = np.stack([t._packed[0] for t in tracks])
    smooth = None if first._packed[1] is None else np.stack([t._packed[1] for t in tracks])
    return touch_chi2(T, data, params, smooth)


def _surface_chi2(track):
    """χ² (2 · error) of a "surface" track's last touch: its factor's GTSAM error at the estimate."""
    at = gtsam.Values()
    at.insert(len(track.hand) - 1, track._last)
    return 2.0 * sum(track.graph.at(i).error(at) for i in track._slots[-1][1])
