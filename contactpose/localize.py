"""The online phase's front: :func:`localize` checks its options and composes the stages.

``method="fast"`` (default): the stages of contactpose.stages, one call each: the search
(exact Δmin bounds with the direction constraint, the vectorized tree, closed-form poses,
ranked by the origin-invariant χ² that includes each contact's distance outside its facet
triangle, the poses polished onto the triangles), then free space, distinct poses, the
surface model, the factor graph, pose classes and status, and what is listed.
``method="paper"``: the paper as published, composed in contactpose.paper (vertex-only Δmin,
the node-by-node tree, Levenberg–Marquardt on eq. (7), ranked by eq. (7)).
"""

from __future__ import annotations

import time
import warnings
from contextlib import contextmanager

import numpy as np

from contactpose import paper, stages
from contactpose.contacts import Contacts, FreeSpace, Tolerance
from contactpose.diagnosis import diagnose as diagnose_answer
from contactpose.errors import ContactPoseError, ContactsError, check_count
from contactpose.options import (
    DEFAULT_POSITION_NOISE_FRAC,
    DEFAULT_REFINE,
    KEEP,
    METHODS,
    OK_PROBABILITY,
    SOLVERS,
    check_robust,
)
from contactpose.progress import Deadline
from contactpose.scoring.freespace import drop_blocked, drop_intersecting
from contactpose.scoring.status import units_message
from contactpose.solvers.polish import lowest_chi2_bound
from contactpose.solvers.surface import SURFACE_REFINE
from contactpose.types import HypothesisList, PosePrior, Result

#: Seconds a search may take by default before it returns what it found (status "time_limit").
DEFAULT_TIME_LIMIT = 60.0
#: The default method's searches (localize's ``search``).
SEARCHES = ("auto", "samples")
#: Contacts spread wider than this many object diameters are an input error (units).
UNITS_ERROR_RATIO = 10.0
#: warm_up calls localize at most this often, and within this many seconds: the banana's calls
#: (0.3 ms; the first, which loads the kernels, 0.1 s) settle by the tenth or so.
WARM_UP_CALLS = 20
WARM_UP_SECONDS = 0.25

__all__ = ["DEFAULT_TIME_LIMIT", "SEARCHES", "localize", "warm_up"]


def localize(model, contacts, *, position_noise=None, normal_noise_deg=1.0, prior=None,
             method="fast", solver=None, top=None, model_error=0.0, max_outliers=0, robust="huber",
             refine=DEFAULT_REFINE, samples=0, seed=None, sample_top=1, finger_radius=None,
             time_limit=DEFAULT_TIME_LIMIT, progress=None, distinct=True, surface="auto", keep="fitting", tree=None,
             diagnose=True, twins=False, ok_probability=OK_PROBABILITY, free_space=None, search="auto"):
    """Find every admissible finger-to-facet assignment and the object pose behind each.

    model : ObjectModel; contacts : Contacts (world frame); position_noise : per-axis σ of
    the contact points in length units (default 0.25 % of the object diameter);
    normal_noise_deg : per-axis σ of the normals; prior : PosePrior or None;
    method : "fast" | "paper"; solver : "closed-form" | "lm" | "factor-graph" (default:
    closed-form for "fast", lm for "paper"); top : keep only the best K hypotheses;
    model_error : extra length tolerance for a model that differs from the object (a scan, say);
    max_outliers : up to this many fingers may be left unassigned (facet -1), their
    contacts excluded from the pose, at a cost of OUTLIER_PENALTY each ("fast" only);
    robust : "huber" | "cauchy" | "none", the factor graph's kernel; refine : how many of the
    best closed-form hypotheses the factor graph refines (0: all). With
    solver="factor-graph" hypotheses carry .covariance and .probability and are ranked by
    Laplace evidence. samples : draw this many posterior samples (emcee) of the pose of
    each of the best ``sample_top`` hypotheses, into .samples and .sample_covariance;
    seed makes the sampling repeatable. finger_radius : drop the hypotheses that put a
    contact where no finger of this radius fits (its outward normal ray of that length
    re-enters the posed object: contactpose.scoring.freespace); underdetermined hypotheses are
    kept, since their pose is one arbitrary member of a family; on a facet table (no regions), a poor fit
    of rounded fingertips is searched again over the facets, sharp edges and vertices
    (stages.edge_hypotheses; an empty answer always is), on a model of surface regions with
    the normal gates widened (stages.with_widened_normals). free_space : a contactpose.FreeSpace,
    the space the fingers swept on their way to the contacts (world frame): drop the fitted hypotheses
    whose posed object meets it by more than the pair distance tolerance σ_Δ, tested best first
    within a bounded cost (scoring.freespace.drop_intersecting); the hint says how many
    placements it ruled out. time_limit : seconds for the
    search (None: unbounded); when it runs out, the hypotheses found so far are returned with
    status "time_limit". progress : tqdm bars (None: on a terminal, for work over a second).
    distinct : list one hypothesis per distinct pose, the best of its near-copies (assignments
    to neighbouring facets that move the surface by under 5 % of the diameter, RMS:
    scoring.classes.distinct_poses; "fast" only); ``result.num_assignments`` counts them all.
    False lists every facet assignment. twins : on a symmetric object (model.symmetry), list
    each symmetric twin of a placement (the poses T G over its symmetries G, which place the
    surface alike and which no contact tells apart) as a distinct pose of its own; False
    (default) lists the best-ranked twin only (research/symmetry.md), unless a ``prior`` is
    given, which tells them apart. Twins have the same χ² and differ in facets: evaluate
    facet tuples against a truth with twins=True, or poses modulo Symmetry.errors.
    surface : pose the best hypotheses on the surface
    contact model, where a contact may lie on an edge or vertex with its normal in that
    feature's normal cone (solvers.surface, research/surface.md; "fast" with the closed form
    and distinct poses only: ``distinct=False`` lists facet assignments, each posed on its
    facets). "auto" (default): on a model of surface regions (``model.has_regions``: fine
    meshes, where it lowers the pose error and turns most poor fits of rounded fingertips into
    fits, research/surface.md), off on a facet table (coarse meshes, where it does not help);
    it costs 1.6 ms per fitted hypothesis, SURFACE_REFINE of them at most, and the best two are
    fitted again from 12 starts around each (solvers.surface.multistart_poses), whose other
    ends that fit within noise are listed too, for the placements' evidence; so are the
    leaders of up to 16 other placements, while time_limit allows (stages.surface_hypotheses). The samples use the
    surface contact model's posterior with ``surface`` or on a model of surface regions
    (``model.has_regions``), where the facet posterior is far too narrow (research/surface.md).
    keep : "fitting" lists, of the distinct poses, the best and those that fit the contacts
    within noise (the pose classes' members; the best POOR_FIT_LISTED when none fits, all of
    them at the time limit); "all" lists every distinct pose. ``result.num_hypotheses``
    counts them all either way. "fast" with distinct poses only.
    tree : ``result.tree`` of an earlier localize of the first k of these contacts with the same
    noise (a search.tree.SearchTree; "fast"): only the pairs of the new contacts with the others
    are queried and its tuples grow by them, the same tree as a search of all (TouchSession
    uses it). ``result.tree`` is this search's tree (None for "paper", or when the time limit cut it).
    ok_probability : "ok" needs the best pose strictly right (within 5° and 5 % of the
    diameter, modulo symmetry) with at least this probability, from the distinct placements
    weighed by their Laplace evidence (scoring.placements; ``result.confidence``,
    ``result.placements``); short of it the answer is "ambiguous" (the placements and their
    probabilities in the hint) or "underdetermined" (how loosely the contacts pin the pose).
    On a model of surface regions with the closed form, an answer about to say "ok" is first
    checked by the search by hypothesize and verify (stages.checked_by_samples): its fitted
    poses join and the placements are weighed again, within the same time limit.
    "fast" only; the paper's rule is the classes' likelihood shares.
    search : the default method's search. "auto": the model's facet table or its surface
    regions (region tuples joined by the tree); "samples": hypothesize and verify over
    oriented surface samples (stages.verified_hypotheses, research/verify_search.md; no join,
    no widenings), its best poses fitted on the surface contact model. Not yet the default:
    its measured completeness and cost are in the note.
    diagnose : for an empty or poor answer ("fast"), test its likely causes by localizing again
    with the input changed, within what is left of time_limit, and name the one that holds in
    ``result.diagnosis`` and the hint (contactpose.diagnosis); False skips the tests
    (``result.diagnosis`` None), for sweeps that only count statuses.
    """
    method, solver = _check_options(method, solver, top, contacts, prior, tree)
    surface = _check_surface(surface, model)
    if keep not in KEEP:
        raise ContactPoseError(f"keep must be one of {KEEP}, got {keep!r}")
    deadline = Deadline(_check_time_limit(time_limit))
    check_robust(robust)
    ok_probability = _check_probability(ok_probability)
    if free_space is not None and not isinstance(free_space, FreeSpace):
        raise ContactPoseError(f"free_space must be a contactpose.FreeSpace or None, got {type(free_space).__name__}")
    max_outliers = _check_outliers(max_outliers, method, contacts.n)
    samples = check_count(samples, "samples", minimum=0)
    if position_noise is None:
        position_noise = DEFAULT_POSITION_NOISE_FRAC * model.diameter
    tolerance = Tolerance.from_noise(position_noise, normal_noise_deg, model_error)
    _warn_units(model, contacts, tolerance)
    start = time.perf_counter()
    fast, grown, notes = method == "fast", None, ()
    merge_twins = not twins and prior is None
    if search not in SEARCHES:
        raise ContactPoseError(f"search must be one of {SEARCHES}, got {search!r}")
    if search != "auto" and not fast:
        raise ContactPoseError(f"search={search!r} is the default method's; method='paper' searches its facet table")
    samples_search = fast and search == "samples"
    if samples_search and max_outliers:
        raise ContactPoseError(f"max_outliers={max_outliers} needs search='auto': search='samples' checks every "
                               "contact of a candidate")
    if samples_search:
        arrays, timing = stages.verified_hypotheses(model, contacts, tolerance, deadline=deadline)
    elif fast:
        arrays, timing, grown, widened = stages.find_hypotheses(
            model, contacts, tolerance, solver="closed-form" if solver == "factor-graph" else solver, prior=prior,
            max_outliers=max_outliers, deadline=deadline, progress=progress, tree=tree, finger_radius=finger_radius)
        notes = (widened,)
    else:
        arrays, timing = paper.search(model, contacts, tolerance, solver=solver, prior=prior, deadline=deadline,
                                      progress=progress)
    if finger_radius is not None:
        with _clock(timing, "free_space"):
            arrays = drop_blocked(model, contacts, arrays, finger_radius)
    assignments = len(arrays.cost)
    if fast and distinct:
        refit, every = (surface or samples_search) and solver == "closed-form", arrays
        if not samples_search:  # the samples' clusters are few: each is fitted, near-copies merge after
            with _clock(timing, "rank"):  # twins merge after the surface fit: it fits the same best as without
                arrays = stages.distinct(model, arrays, tolerance, deadline, merge_twins=merge_twins and not refit)
        if refit:
            with _clock(timing, "pose"):
                arrays = stages.surface_hypotheses(model, contacts, arrays, tolerance, deadline,
                                                   stages.VERIFIED_FITS if samples_search else SURFACE_REFINE,
                                                   merge_twins=merge_twins, every=every, multistart=True)
            if not samples_search:
                arrays, note = stages.with_widened_normals(model, contacts, arrays, tolerance, timing,  # own clock
                                                           finger_radius=finger_radius, prior=prior,
                                                           deadline=deadline, progress=progress,
                                                           merge_twins=merge_twins)
                notes += (note,)
    if free_space is not None:  # on the fitted poses: a near-copy's facet pose may cut a path its fit does not
        with _clock(timing, "free_space"):
            arrays, note = drop_intersecting(model, contacts, arrays, free_space, tolerance)
        notes += (note,)
    if solver == "factor-graph":
        with _clock(timing, "refine"):
            arrays, rescue = stages.refine_hypotheses(model, contacts, arrays, tolerance, prior=prior, robust=robust,
                                                      k=refine)
        notes += (rescue,)
    classify = (lambda a: stages.classify(model, contacts, a, tolerance, bound=fast, deadline=deadline, notes=notes,
                                          ok_probability=ok_probability if fast else None, prior=prior))
    with _clock(timing, "rank"):
        classes, status, hint, found, confidence = classify(arrays)
    if status == "ok" and fast and distinct and search == "auto" and solver == "closed-form" and model.has_regions:
        arrays = stages.checked_by_samples(model, contacts, arrays, tolerance, timing, finger_radius=finger_radius,
                                           free_space=free_space, merge_twins=merge_twins,
                                           deadline=deadline)  # own clock
        with _clock(timing, "rank"):
            classes, status, hint, found, confidence = classify(arrays)
    with _clock(timing, "rank"):
        num = len(arrays.cost)
        if keep == "fitting" and fast and distinct and status != "time_limit":
            arrays, classes, found = stages.listed(arrays, classes, found)
        if top is not None:
            arrays = arrays.take(slice(0, top))
    hypotheses = HypothesisList(arrays)
    if samples:
        from contactpose.uncertainty.sampling import sample_hypotheses  # emcee, only when asked

        with _clock(timing, "sample"):
            hypotheses.samples.update(sample_hypotheses(model, contacts, hypotheses, tolerance, samples,
                                                        np.random.default_rng(seed), prior=prior, robust=robust,
                                                        top=sample_top, surface=surface or model.has_regions))
    timing["total"] = time.perf_counter() - start
    diagnosis = None
    if diagnose:
        hint, diagnosis = diagnose_answer(model, contacts, tolerance, status, hint, arrays, method=method,
                                          max_outliers=max_outliers, prior=prior, deadline=deadline, timing=timing)
    return Result(status, hypotheses, timing, method, solver, tolerance, hint, num_hypotheses=num, classes=classes,
                  num_assignments=assignments, tree=grown, diagnosis=diagnosis, model=model, contacts=contacts,
                  confidence=confidence, placements=found)


@contextmanager
def _clock(timing, stage):
    """Add the seconds of the block to ``timing[stage]`` (0 when it is new)."""
    start = time.perf_counter()
    try:
        yield
    finally:
        timing[stage] = timing.get(stage, 0.0) + time.perf_counter() - start


def warm_up(model, contacts, **options):
    """Do, untimed, what the first ``localize`` calls on ``model`` do once, before ``localize`` is
    timed: one call on ``contacts``, the in-facet χ² bound on its first hypothesis, then more
    calls until they run as later ones do: WARM_UP_CALLS in all, while the next call, taking as
    long as the last, keeps the time they spend within WARM_UP_SECONDS (a slow call is warm
    after one).

    * The first call loads numba's compiled kernels, and finds the model's symmetry, once per
      model object (model.symmetry: 4 ms to 0.3 s on a model built from a mesh; a model file
      stores it), so warm up on the model that is then timed.
    * A grasp whose hypotheses all fit within noise by their planes never reaches the
      in-facet bound, so a warm-up by grasps alone can leave its kernel to load (some
      25–40 ms) inside the first timed grasp that does.
    * CPython specialises a function's bytecode over its first several calls, and loading a
      kernel leaves the next calls slow: a call of a millisecond or less (the banana's) runs
      two to three times slower for its first ten or so, and after a load.

    options : as for :func:`localize`."""
    start = time.perf_counter()
    result = localize(model, contacts, **options)
    last = time.perf_counter() - start
    if result.num_hypotheses:
        lowest_chi2_bound(model, contacts, result.hypotheses.arrays, np.zeros(1, dtype=np.int64), result.tolerance)
    start = time.perf_counter()
    for _ in range(WARM_UP_CALLS - 1):
        if time.perf_counter() - start + last > WARM_UP_SECONDS:
            break
        call = time.perf_counter()
        localize(model, contacts, **options)
        last = time.perf_counter() - call


def _check_options(method, solver, top, contacts, prior, tree):
    if method not in METHODS:
        raise ContactPoseError(f"method must be one of {METHODS}, got {method!r}")
    solver = solver or ("closed-form" if method == "fast" else "lm")
    if solver not in SOLVERS:
        raise ContactPoseError(f"solver must be one of {SOLVERS}, got {solver!r}")
    if solver == "factor-graph" and method != "fast":
        raise ContactPoseError("solver='factor-graph' refines the default method's hypotheses: use method='fast'")
    check_count(top, "top", allow_none=True)
    if not isinstance(contacts, Contacts):
        raise ContactPoseError(f"contacts must be a contactpose.Contacts, got {type(contacts).__name__}")
    if contacts.n < 2:
        raise ContactsError(f"need at least 2 contacts, got {contacts.n}")
    if prior is not None and not isinstance(prior, PosePrior):
        raise ContactPoseError(f"prior must be a contactpose.PosePrior or None, got {type(prior).__name__}")
    if tree is not None and method != "fast":
        raise ContactPoseError(f"tree extends a search of method 'fast'; method={method!r} grows its own tree")
    return method, solver


def _check_surface(surface, model):
    """True or False from ``surface`` (True, False or "auto": whether the model has surface regions)."""
    if isinstance(surface, str) and surface == "auto":
        return model.has_regions
    if not isinstance(surface, (bool, np.bool_)):
        raise ContactPoseError(f"surface must be True, False or 'auto', got {surface!r}")
    return bool(surface)


def _check_outliers(max_outliers, method, n):
    max_outliers = check_count(max_outliers, "max_outliers", minimum=0)
    if max_outliers and method != "fast":
        raise ContactPoseError("max_outliers needs method='fast' (the paper assigns every finger)")
    if max_outliers and n - max_outliers < 3:
        raise ContactPoseError(f"max_outliers={max_outliers} with {n} contacts leaves fewer than 3 to fit a pose")
    return max_outliers


def _check_probability(p):
    if isinstance(p, bool) or not isinstance(p, (int, float, np.integer, np.floating)) or not 0.0 < p <= 1.0:
        raise ContactPoseError(f"ok_probability must be a probability in (0, 1], got {p!r}")
    return float(p)


def _check_time_limit(time_limit):
    if time_limit is None:
        return None
    if isinstance(time_limit, bool) or not isinstance(time_limit, (int, float, np.integer, np.floating)) \
            or not time_limit > 0:
        raise ContactPoseError(f"time_limit must be a positive number of seconds or None, got {time_limit!r}")
    return float(time_limit)



def _warn_units(model, contacts, tolerance):
    """Contacts spread wider than the object: a warning, an error when far beyond (units)."""
    spread = contacts.spread
    if spread > UNITS_ERROR_RATIO * (model.diameter + tolerance.distance):
        raise ContactsError(units_message(spread, model.diameter))
    if spread > model.diameter + tolerance.distance:
        warnings.warn(units_message(spread, model.diameter), stacklevel=3)
