"""Touch after touch: :class:`TouchSession`, localization that grows with every touch.

* **A static object** (``hand_motion=None``). Each touch's contacts join the earlier ones.
  The search keeps its tree T (``Result.tree``), and a new touch queries only the pairs of
  its contacts with the others and grows the surviving tuples by them
  (search.tree.extend_tuples); the stages after the tree run as in :func:`localize`, so the
  answer is the one ``localize`` gives for all the contacts at once.
* **An object held in the hand** (``hand_motion=(ΔT, σ_rot_deg, σ_trans)``). From the first
  hand motion on, every hypothesis that determines the pose becomes a track in an iSAM2
  smoother (tracking.track.TrackSet: a pose variable per hand motion, linked by the slip,
  tracks pruned by their sequential χ² and merged when their poses coincide, at most
  ``max_tracks``). A touch without a hand motion then joins the current pose variable. A
  touch that no track explains adds tracks localized afresh from the latest touches
  (:func:`relocalizer`), each replayed over every touch so far.

research/tracking.md has the model and the measurements.
"""

from __future__ import annotations

import time

import numpy as np

from contactpose.contacts import Contacts, Tolerance
from contactpose.errors import ContactPoseError, check_count
from contactpose.localize import localize
from contactpose.options import DEFAULT_POSITION_NOISE_FRAC
from contactpose.scoring.rank import hypothesis_arrays
from contactpose.search.tree import SearchTree
from contactpose.stages import SEARCH_STAGES
from contactpose.tracking import next_touch as touchmod
from contactpose.tracking.track import MAX_TRACKS, TrackSet
from contactpose.types import HypothesisArrays, HypothesisList, PoseFit, Result

#: Seconds for the search of a reseed (relocalizer), on a touch that no track explains. The
#: tree gets a quarter of it, the pair stage included (localize.TREE_SHARE). At 1 s the pair
#: stage of a YCB mug's 4 contacts (0.1–0.3 s, with the machine's pace) cut some trees short,
#: and the answer hung on the machine's load; the slowest reseed of the mug's 100 sequences
#: grows its tree in 2.4 s (6.6 s in all), a third of this limit's share.
RESEED_TIME_LIMIT = 30.0
#: The session's localize options that its reseeds take too.
RESEED_OPTIONS = ("method", "model_error", "robust")
#: localize options a session does not take: it sets them itself.
OWN_OPTIONS = ("position_noise", "normal_noise_deg", "prior", "tree")


class TouchSession:
    """Localization over a sequence of touches, one :meth:`add` per touch.

    model : ObjectModel; position_noise, normal_noise_deg, prior : as for :func:`localize`
    (position_noise default 0.25 % of the diameter); max_tracks : hypotheses tracked once the
    hand moves; association_samples, rng : for a held object, the best track's
    ``sample_covariance`` after each touch is its association covariance from this many drawn
    trajectories (PoseTrack.association_covariance: the Laplace covariance plus the spread
    that the choice of facets adds; about 0.15 s per touch for 20), drawn with ``rng`` (a
    numpy.random.Generator); 0 (default): None; reseed : a held object's touch that no track
    explains adds tracks localized afresh from the latest touches (:func:`relocalizer`,
    TrackSet); options : further :func:`localize` keywords
    (method, solver, keep, time_limit, ...), used for every static touch.

    ``result`` is the latest Result, ``history`` every touch's, ``contacts`` the contacts so
    far (world frame; for a held object, those since the last hand motion).
    """

    def __init__(self, model, *, position_noise=None, normal_noise_deg=1.0, prior=None, max_tracks=MAX_TRACKS,
                 association_samples=0, rng=None, reseed=True, **options):
        taken = sorted(set(options) & set(OWN_OPTIONS))
        if taken:
            raise ContactPoseError(f"TouchSession sets {taken} itself; give noise and prior to TouchSession")
        self.association_samples = check_count(association_samples, "association_samples", minimum=0)
        if self.association_samples and not isinstance(rng, np.random.Generator):
            raise ContactPoseError(f"association_samples needs rng, a numpy.random.Generator; got {type(rng).__name__}")
        self.rng, self.reseed = rng, bool(reseed)
        self.model, self.prior, self.max_tracks, self.options = model, prior, max_tracks, options
        if position_noise is None:
            position_noise = DEFAULT_POSITION_NOISE_FRAC * model.diameter
        self.noise = dict(position_noise=position_noise, normal_noise_deg=normal_noise_deg)
        self.tolerance = Tolerance.from_noise(position_noise, normal_noise_deg, options.get("model_error", 0.0))
        self.contacts, self.result, self.history, self.tracks = None, None, [], None

    def add(self, contacts, hand_motion=None):
        """One touch: its contacts (world frame) and the hand's motion since the last touch,
        None (the object has not moved) or (ΔT (4, 4), σ_rot in degrees, σ_trans) with the
        slip's sigmas. The first touch's hand motion is ignored (no pose precedes it).
        -> Result, as :func:`localize` returns it (for a held object: one hypothesis per track)."""
        if not isinstance(contacts, Contacts):
            raise ContactPoseError(f"contacts must be a contactpose.Contacts, got {type(contacts).__name__}")
        if self.contacts is None:
            self.contacts = contacts
            result = self._static(None)
        elif hand_motion is None and self.tracks is None:
            tree = self.result.tree if self.result is not None else None
            self.contacts = self.contacts.joined(contacts)
            result = self._static(tree)
        else:
            result = self._held(contacts, hand_motion)
        self.result = result
        self.history.append(result)
        return result

    def suggest_touch(self, *, rng, **options):
        """The probe that best separates the current pose classes (touch.suggest_touch, given
        the session's contacts). A static object only."""
        if self.tracks is not None:
            raise ContactPoseError("suggest_touch works on a static object; this session tracks a held one")
        if self.result is None or self.contacts.n < 2:
            raise ContactPoseError("suggest_touch needs the pose classes of at least 2 contacts; add another touch")
        return touchmod.suggest_touch(self.model, self.result, rng=rng, contacts=self.contacts, **options)

    # ------------------------------------------------------------------ static ---

    def _static(self, tree):
        """localize of every contact so far, growing the last tree; one contact: no search yet."""
        if self.contacts.n >= 2:
            return localize(self.model, self.contacts, prior=self.prior, tree=tree, **self.noise, **self.options)
        units = self._units()
        tuples = np.arange(units[1], dtype=np.int64)[:, None]
        return Result("underdetermined", HypothesisList(_empty_arrays(1)), stage_times(0.0), self.options.get("method", "fast"),
                      self.options.get("solver") or "closed-form", self.tolerance,
                      f"one contact: every one of the {units[1]} {units[0]} can carry it; add another contact",
                      num_hypotheses=units[1], tree=SearchTree(self.contacts, self.tolerance, units[0], tuples),
                      model=self.model, contacts=self.contacts)

    def _units(self):
        """(what the search runs over, how many): ("patches", P) or ("facets", m)."""
        if self.options.get("method", "fast") == "fast" and self.model.patch_table is not None:
            return "patches", self.model.patches.count
        return "facets", self.model.num_facets

    # -------------------------------------------------------------------- held ---

    def _held(self, contacts, hand_motion):
        """A touch of the held object: start the tracks on the first hand motion, then one
        iSAM2 update per track."""
        clock = time.perf_counter()
        if self.tracks is None:
            self.tracks = self._start_tracks()
        self.tracks.add(contacts, hand_motion=hand_motion)
        self.contacts = contacts if hand_motion is not None else self.contacts.joined(contacts)
        return self._tracks_result(clock, time.perf_counter() - clock)

    def _start_tracks(self):
        """A TrackSet from the hypotheses so far that determine the pose."""
        starts = [(h.facets, h.pose) for h in (self.result.hypotheses if self.result is not None else [])
                  if not h.underdetermined and not len(h.outliers)]
        if not starts:
            raise ContactPoseError("the touches so far leave the pose free (or found nothing); a held object needs a "
                                   "determined pose before the hand moves: add contacts without hand_motion first")
        seeder = relocalizer(self.model, self.tolerance, **{k: self.options[k] for k in RESEED_OPTIONS
                                                              if k in self.options}) if self.reseed else None
        return TrackSet(self.model, self.contacts, starts, self.tolerance, max_tracks=self.max_tracks,
                        robust=self.options.get("robust", "huber"), seeder=seeder)

    def _tracks_result(self, clock, track_s):
        """The tracks as a Result: per track its current pose, every touch's facets, residuals
        of every contact at its own smoothed pose, cost = sequential χ², covariance of the last
        pose (and the best track's association covariance as its sample_covariance, when
        asked); status "ok" with one track, else "ambiguous"; timing (seconds) since
        ``clock`` (time.perf_counter()), of which ``track_s`` in the tracks; contacts : the best
        track's touches, each carried to its current pose (PoseTrack.seen_now)."""
        parts, seen_all = [], []
        for track in self.tracks.tracks:
            seen, facets = track.seen_now()
            seen_all.append(seen)
            T = track.pose
            fit = PoseFit(T[None, :3, :3], T[None, :3, 3], np.zeros((1, 3, 3)), np.zeros((1, 3), bool),
                          np.zeros((1, 3)), np.zeros(1, bool))
            parts.append(hypothesis_arrays(self.model, seen, facets[None], fit, self.tolerance,
                                           cost=np.array([track.score]), covariance=track.covariance[None]))
        arrays = parts[0]
        for more in parts[1:]:
            arrays = arrays.merged(more)  # the tracks are in score order: merged keeps it
        k = len(parts)
        hint = "" if k == 1 else f"{k} tracks within the pruning margin of the best; touch again to tell them apart"
        listed = HypothesisList(arrays)
        if self.association_samples:
            listed.sample_covariances[0] = self.tracks.best.association_covariance(self.rng, self.association_samples)
        timing = stage_times(time.perf_counter() - clock, track=track_s)
        extra = {"tracking": True, "touches": len(self.history) + 1, "reseeds": self.tracks.reseeds}
        return Result("ok" if k == 1 else "ambiguous", listed, timing, "fast", "factor-graph",
                      self.tolerance, hint, num_hypotheses=k, extra=extra, model=self.model, contacts=seen_all[0])


def stage_times(total, **more):
    """A Result's timing (seconds) for an answer without a search: the search's stages (pairs, tree,
    pose, rank) 0, as they did not run, ``total`` and ``more`` stages (a held touch's
    ``track``: starting and updating the tracks)."""
    return {**dict.fromkeys(SEARCH_STAGES, 0.0), **more, "total": float(total)}


def _empty_arrays(n):
    """No hypotheses of n contacts."""
    fit = PoseFit(np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3), bool),
                  np.zeros((0, 3)), np.zeros(0, bool))
    return HypothesisArrays(np.zeros((0, n), np.int64), np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0),
                            np.zeros((0, n, 5)), fit)


def relocalizer(model, tolerance, time_limit=RESEED_TIME_LIMIT, **options):
    """A TrackSet's seeder: Contacts -> [(facets, pose)], the hypotheses of :func:`localize`
    (sensor noise as ``tolerance``'s, keep="all", ``time_limit`` seconds, further ``options``)
    that determine the pose, best first."""
    def seeds(contacts):
        result = localize(model, contacts, position_noise=tolerance.position_noise,
                          normal_noise_deg=np.degrees(tolerance.normal_noise), keep="all", time_limit=time_limit,
                          progress=False, diagnose=False, **options)  # its hypotheses only: no diagnosis
        return [(h.facets, h.pose) for h in result.hypotheses if not h.underdetermined and not len(h.outliers)]
    return seeds
