"""Touch until sure: probe the object until localize answers "ok".

Starting from a grasp's contacts, :func:`touch_until_sure` localizes; while the status is not
"ok" (the best pose is strictly right with probability ``result.confidence`` >=
``ok_probability``) and fewer than ``max_touches`` extra touches were made, it picks a probe
(``policy``: "suggested", :func:`next_touch.suggest_touch`, the probe that best tells the
placements apart; "random", :func:`random_probe`, a baseline aimed at a random surface point of
the best pose's object), asks the caller's ``touch(origin, direction)`` for the contact it
measures, adds it to a :class:`TouchSession` and localizes again. A probe that touches nothing
counts as a touch.

Not modelled: whether the hand can reach the probe, and the probe pushing the object.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from contactpose.contacts import Contacts
from contactpose.errors import ContactPoseError, check_count
from contactpose.model.object_model import ObjectModel
from contactpose.tracking.next_touch import Touch, candidate_probes, suggest_touch
from contactpose.tracking.session import TouchSession
from contactpose.types import Result

#: Probe policies: the probe that best tells the placements apart, or one at random.
POLICIES = ("suggested", "random")


@dataclass
class TouchStep:
    """One extra touch: the probe (a :class:`Touch`: ``start`` the origin, ``direction``), the
    contact measured, (point (3,), finger normal (3,)) in the world frame or None for a miss,
    the status after it and the seconds spent choosing the probe."""

    probe: Touch
    contact: tuple | None
    status: str
    plan_s: float = 0.0

    @property
    def missed(self):
        return self.contact is None


@dataclass
class SureRun:
    """What :func:`touch_until_sure` did: the final Result, the extra touches (TouchStep, in
    order), ``statuses`` (after the grasp, then after each touch: len(steps) + 1 entries), the
    TouchSession holding every contact, and ``stopped``, why the loop ended: "ok",
    "max_touches" or "no_hypothesis" (no pose to aim a probe at)."""

    result: Result
    steps: list = field(default_factory=list)
    statuses: list = field(default_factory=list)
    session: TouchSession | None = None
    stopped: str = ""

    @property
    def touches(self):
        """Extra touches made (misses included)."""
        return len(self.steps)

    @property
    def misses(self):
        return sum(step.missed for step in self.steps)

    @property
    def sure(self):
        return self.result.status == "ok"

    def touches_to_ok(self):
        """Extra touches until the status was first "ok" (0: the grasp alone), or None."""
        return next((k for k, s in enumerate(self.statuses) if s == "ok"), None)


def random_probe(model, result, rng, *, contacts=None, standoff=None):
    """A baseline probe: a ray aimed along the inward normal at one area-uniform random surface
    point of the object at ``result``'s best pose (:func:`next_touch.candidate_probes`), scored
    by :func:`suggest_touch` as its only candidate, so it is a :class:`Touch` like a suggested
    one. rng : numpy.random.Generator; contacts : the Contacts localized (default
    ``result.contacts``)."""
    _check_rng(rng)
    if result.best is None:
        raise ContactPoseError(f"random_probe needs a pose to aim at; the result has none (status {result.status!r})")
    origins, directions, _ = candidate_probes(model, result.best.pose[None], rng, 1, standoff)
    return suggest_touch(model, result, (origins, directions), rng=rng, contacts=contacts)


def touch_until_sure(session_or_model, contacts, touch, *, rng, max_touches=6, policy="suggested",
                     n_candidates=200, **localize_options):
    """Touch until localize is sure: see the module docstring.

    session_or_model : a static TouchSession (its contacts so far are kept; ``localize_options``
    must then be empty: the session has its own) or an ObjectModel (a new TouchSession with
    ``localize_options``: position_noise, normal_noise_deg, prior, ok_probability, method, ...);
    contacts : the grasp's Contacts (world frame), or None to start from the session's result;
    touch : callable(origin (3,), direction (3,) unit), both world frame -> (point (3,), finger
    normal (3,)) in the world frame, or None when the finger touches nothing; rng :
    numpy.random.Generator for the probes; max_touches : extra touches at most (>= 0);
    policy : "suggested" or "random"; n_candidates : candidate probes of a suggestion.
    Returns :class:`SureRun`.
    """
    _check_rng(rng)
    max_touches = check_count(max_touches, "max_touches", minimum=0)
    n_candidates = check_count(n_candidates, "n_candidates")
    if policy not in POLICIES:
        raise ContactPoseError(f"policy must be one of {POLICIES}, got {policy!r}")
    if not callable(touch):
        raise ContactPoseError(f"touch must be a callable(origin, direction) -> (point, finger_normal) or None, "
                               f"got {type(touch).__name__}")
    if isinstance(session_or_model, TouchSession):
        session = session_or_model
        if localize_options:
            raise ContactPoseError(f"a TouchSession has its own options; got {sorted(localize_options)} too")
        if session.tracks is not None:
            raise ContactPoseError("touch_until_sure works on a static object; this session tracks a held one")
    elif isinstance(session_or_model, ObjectModel):
        session = TouchSession(session_or_model, **localize_options)
    else:
        raise ContactPoseError(f"session_or_model must be a TouchSession or an ObjectModel, "
                               f"got {type(session_or_model).__name__}")
    if contacts is not None:
        if not isinstance(contacts, Contacts):
            raise ContactPoseError(f"contacts must be a contactpose.Contacts or None, got {type(contacts).__name__}")
        result = session.add(contacts)
    elif session.result is None:
        raise ContactPoseError("contacts is None and the session has no touch yet; give the grasp's contacts")
    else:
        result = session.result
    run = SureRun(result, statuses=[result.status], session=session)
    while result.status != "ok" and run.touches < max_touches:
        if result.best is None or session.contacts.n < 2:
            run.stopped = "no_hypothesis"
            break
        clock = time.perf_counter()
        if policy == "suggested":
            probe = suggest_touch(session.model, result, rng=rng, contacts=session.contacts, n_candidates=n_candidates)
        else:
            probe = random_probe(session.model, result, rng, contacts=session.contacts)
        plan_s = time.perf_counter() - clock
        measured = _measured(touch(probe.start.copy(), probe.direction.copy()))
        if measured is not None:
            result = session.add(Contacts(measured[0][None], finger_normals=measured[1][None]))
        run.steps.append(TouchStep(probe, measured, result.status, plan_s))
        run.statuses.append(result.status)
    run.result = result
    if not run.stopped:
        run.stopped = "ok" if result.status == "ok" else "max_touches"
    return run


def _measured(answer):
    """The touch callable's answer as (point (3,), finger normal (3,)) floats, or None."""
    if answer is None:
        return None
    try:
        point, normal = (np.asarray(a, dtype=np.float64) for a in answer)
    except (TypeError, ValueError):
        raise ContactPoseError(f"touch must return (point, finger_normal) or None, got {answer!r}") from None
    if point.shape != (3,) or normal.shape != (3,) or not (np.all(np.isfinite(point)) and np.all(np.isfinite(normal))):
        raise ContactPoseError(f"touch must return a finite point (3,) and finger normal (3,), "
                               f"got shapes {point.shape} and {normal.shape}")
    return point, normal


def _check_rng(rng):
    if not isinstance(rng, np.random.Generator):
        raise ContactPoseError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
