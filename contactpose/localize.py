"""The online phase (§3.2, §4) as a pipeline of public stages, and :func:`localize`.

contacts -> :func:`find_pairs` (S_ij, eq. 5) -> :func:`join_hypotheses` (the tree T)
-> :func:`pose_hypotheses` (a pose per hypothesis) -> :func:`rank_hypotheses` (residuals,
χ², order) -> :func:`refine_hypotheses` (the factor graph, optional) -> :func:`classify` (pose
classes and status). :func:`localize` composes them; experiments and users may call the
stages themselves.

``method="fast"`` (default): exact Δmin bounds, vectorized tree, closed-form poses,
ranked by the origin-invariant χ² that includes each contact's distance outside
its facet triangle. ``method="paper"``: the paper as published — vertex-only
Δmin, the node-by-node tree, Levenberg–Marquardt on eq. (7), ranked by eq. (7).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from itertools import combinations

import numpy as np

from contactpose.contacts import Contacts, Tolerance
from contactpose.costs.association import fitting_members, nearest_fit_facets
from contactpose.errors import ContactPoseError, ContactsError, ResourceError, check_count
from contactpose.options import (
    DEFAULT_POSITION_NOISE_FRAC,
    DEFAULT_REFINE,
    KEEP,
    METHODS,
    OUTLIER_PENALTY,
    SOLVERS,
    check_robust,
    fit_threshold,
)
from contactpose.progress import Deadline
from contactpose.scoring import rank as ranking
from contactpose.scoring.classes import MAX_CLASS_HYPOTHESES, distinct_poses, pose_classes
from contactpose.scoring.freespace import free_space_violations
from contactpose.scoring.infacet import lowest_chi2_bound, within_noise
from contactpose.scoring.status import status as status_of
from contactpose.scoring.status import units_message
from contactpose.search.pairs import admissible_pairs, pair_conditions
from contactpose.search.tree import (
    SearchTree,
    TripleTest,
    expected_tuples,
    extend_tuples,
    join_tuples,
    join_tuples_paper,
    sorted_rows,
)
from contactpose.solvers import factor_graph as fg
from contactpose.solvers.closed_form import fit_poses
from contactpose.solvers.lm import fit_lm_all
from contactpose.types import HypothesisList, PosePrior, Result

#: Seconds a search may take by default before it returns what it found (status "time_limit").
DEFAULT_TIME_LIMIT = 60.0
#: When nothing matches, the pair tolerances are widened by these factors in turn.
WIDEN_SCHEDULE = (1.5, 2.0)
#: Share of the time left that the tree may take; the poses and ranking get the rest.
TREE_SHARE = 0.25
#: Seconds the distinct-pose grouping may always take, even once the time limit has passed;
#: past both, the rows not yet grouped are listed as they are (status "time_limit").
GROUPING_GRACE = 2.0
#: Hypotheses posed and ranked at a time (the grain of their deadline checks).
POSE_CHUNK = 65_536
#: Contacts spread wider than this many object diameters are an input error (units).
UNITS_ERROR_RATIO = 10.0
#: The tree warns when it is estimated to hold more tuples than this, and estimates only
#: when every finger pair admits more facet pairs than EXPLOSION_CHECK_PAIRS.
EXPLOSION_TUPLES = 1e6
EXPLOSION_CHECK_PAIRS = 10_000
#: With keep="fitting", a search none of whose hypotheses fits within noise lists its best this many.
POOR_FIT_LISTED = 10

__all__ = ["classify", "drop_blocked", "find_pairs", "grow_tree", "join_hypotheses", "listed_rows", "localize",
           "pose_hypotheses", "rank_hypotheses", "refine_hypotheses", "search", "warm_up"]


def localize(model, contacts, *, position_noise=None, normal_noise_deg=1.0, prior=None,
             method="fast", solver=None, top=None, model_error=0.0, max_outliers=0, robust="huber",
             refine=DEFAULT_REFINE, samples=0, seed=None, sample_top=1, finger_radius=None,
             time_limit=DEFAULT_TIME_LIMIT, progress=None, distinct=True, surface=False, keep="fitting", tree=None):
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
    kept, since their pose is one arbitrary member of a family. time_limit : seconds for the
    search (None: unbounded); when it runs out, the hypotheses found so far are returned with
    status "time_limit". progress : tqdm bars (None: on a terminal, for work over a second).
    distinct : list one hypothesis per distinct pose, the best of its near-copies (assignments
    to neighbouring facets that move the surface by under 5 % of the diameter, RMS:
    scoring.classes.distinct_poses; "fast" only); ``result.num_assignments`` counts them all.
    False lists every facet assignment. surface : pose the best hypotheses on the surface
    contact model, where a contact may lie on an edge or vertex with its normal in that
    feature's normal cone (solvers.surface, research/surface.md; "fast" with the closed form
    and distinct poses only: ``distinct=False`` lists facet assignments, each posed on its
    facets). Off by default: it costs 5-15 ms per refined hypothesis. The samples use the
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
    """
    method, solver = _check_options(method, solver, top, contacts, prior)
    if keep not in KEEP:
        raise ContactPoseError(f"keep must be one of {KEEP}, got {keep!r}")
    deadline = Deadline(_check_time_limit(time_limit))
    check_robust(robust)
    max_outliers = _check_outliers(max_outliers, method, contacts.n)
    samples = check_count(samples, "samples", minimum=0)
    if position_noise is None:
        position_noise = DEFAULT_POSITION_NOISE_FRAC * model.diameter
    tolerance = Tolerance.from_noise(position_noise, normal_noise_deg, model_error)
    _warn_units(model, contacts, tolerance)
    start = time.perf_counter()
    pose_solver = "closed-form" if solver == "factor-graph" else solver
    arrays, timing, grown = search(model, contacts, tolerance, method=method, solver=pose_solver, prior=prior,
                                   deadline=deadline, progress=progress, tree=tree)
    for dropped in _outlier_sets(contacts.n, max_outliers):
        fingers = np.setdiff1d(np.arange(contacts.n), dropped)
        sub, sub_timing, _ = search(model, contacts.permuted(fingers), tolerance, method=method, solver=pose_solver,
                                 prior=prior, deadline=deadline, progress=progress)
        arrays = arrays.merged(sub.widened(fingers, contacts.n, len(dropped) * OUTLIER_PENALTY))
        timing = {k: timing[k] + sub_timing[k] for k in timing}
    widened = ""
    if len(arrays.cost) == 0 and method == "fast":
        arrays, widened = _widen(model, contacts, arrays, tolerance, pose_solver, prior, deadline, progress, timing)
    if finger_radius is not None:
        free_start = time.perf_counter()
        arrays = drop_blocked(model, contacts, arrays, finger_radius)
        timing["free_space"] = time.perf_counter() - free_start
    assignments = len(arrays.cost)
    if distinct and method == "fast":
        distinct_start = time.perf_counter()
        arrays = _distinct(model, arrays, tolerance, deadline)
        timing["rank"] += time.perf_counter() - distinct_start
    if surface and distinct and method == "fast" and solver == "closed-form":
        surface_start = time.perf_counter()
        arrays = ranking.surface_refined(model, contacts, arrays, tolerance)
        if distinct:
            arrays = _distinct(model, arrays, tolerance, deadline)
        timing["pose"] += time.perf_counter() - surface_start
    rescue = ""
    if solver == "factor-graph":
        refine_start = time.perf_counter()
        arrays, rescue = refine_hypotheses(model, contacts, arrays, tolerance, prior=prior, robust=robust, k=refine)
        timing["refine"] = time.perf_counter() - refine_start
    classes_start = time.perf_counter()
    classes, status, hint = classify(model, contacts, arrays, tolerance, method=method, deadline=deadline)
    for note in (widened, rescue):
        if note:
            hint = f"{hint}; {note}" if hint else note
    num = len(arrays.cost)
    if keep == "fitting" and distinct and method == "fast" and status != "time_limit":
        arrays, classes = _plausible(arrays, classes)
    if top is not None:
        arrays = arrays.take(slice(0, top))
    timing["rank"] += time.perf_counter() - classes_start
    hypotheses = HypothesisList(arrays)
    if samples:
        from contactpose.uncertainty.sampling import sample_hypotheses

        sample_start = time.perf_counter()
        hypotheses.samples.update(sample_hypotheses(model, contacts, hypotheses, tolerance, samples,
                                                    np.random.default_rng(seed), prior=prior, robust=robust,
                                                    top=sample_top, surface=surface or model.has_regions))
        timing["sample"] = time.perf_counter() - sample_start
    timing["total"] = time.perf_counter() - start
    return Result(status, hypotheses, timing, method, solver, tolerance, hint, num_hypotheses=num, classes=classes,
                  num_assignments=assignments, tree=grown)


# ------------------------------------------------------------------ stages ---

def search(model, contacts, tolerance, *, method="fast", solver=None, prior=None, deadline=None, progress=None,
           tree=None):
    """All stages up to the ranking: S_ij -> tree -> poses -> ranked HypothesisArrays.

    deadline : a progress.Deadline. The tree may spend TREE_SHARE of what is left of it;
    the poses and the ranking then run POSE_CHUNK hypotheses at a time until it passes
    (``deadline.hit`` tells whether anything stopped early). tree : a SearchTree of the first
    contacts to extend (:func:`grow_tree`). Returns (HypothesisArrays, seconds per stage:
    "pairs", "tree", "pose", "rank", the SearchTree of these contacts, or None for "paper"
    and when the deadline cut the tree short).
    """
    solver = solver or ("closed-form" if method == "fast" else "lm")
    deadline = deadline or Deadline()
    tree_deadline = Deadline(None if deadline.seconds is None else TREE_SHARE * deadline.remaining())
    grown, timing = grow_tree(model, contacts, tolerance, method=method, tree=tree, deadline=tree_deadline,
                              progress=progress)
    deadline.hit |= tree_deadline.hit
    start = time.perf_counter()
    facets = grown.tuples
    if grown.units == "patches":
        facets = _members_in_chunks(model, contacts, facets, tolerance, prior, deadline)
    timing.update(tree=timing["tree"] + time.perf_counter() - start, pose=0.0, rank=0.0)
    arrays = None
    for lo in range(0, max(len(facets), 1), POSE_CHUNK):
        if lo and deadline.passed:
            break
        part = _pose_and_rank(model, contacts, facets[lo:lo + POSE_CHUNK], tolerance, method, solver, prior,
                              deadline, progress, timing)
        arrays = part if arrays is None else arrays.merged(part)
    if method == "fast":
        start = time.perf_counter()
        arrays = ranking.polish(model, contacts, arrays, tolerance)
        timing["pose"] += time.perf_counter() - start
    return arrays, timing, None if method == "paper" or tree_deadline.hit else grown


def grow_tree(model, contacts, tolerance, *, method="fast", tree=None, deadline=None, progress=None):
    """S_ij and the tree T over the search units (facets; patches on a model of surface
    regions with "fast"). -> (SearchTree, seconds: "pairs", "tree")

    tree : the SearchTree of the first k of these contacts at this tolerance ("fast"): only
    the pairs (i, j), j >= k, are queried and its tuples grow by contacts k, ..., n-1
    (search.tree.extend_tuples), the same set as the tree of all pairs. "fast" rows are in
    lexicographic order either way, so the stages after the tree see the same input.
    """
    fast = method == "fast"
    patches = fast and model.patch_table is not None
    units = "patches" if patches else "facets"
    since = 0 if tree is None else _check_tree(contacts, tolerance, method, units, tree)
    clock = [time.perf_counter()]
    conditions = pair_conditions(contacts, since)
    _check_span(model, conditions, tolerance)
    S = admissible_pairs(model, conditions, tolerance, "exact" if fast else "paper", direction=fast, patches=patches)
    clock.append(time.perf_counter())
    if not fast:
        _warn_explosion(S, contacts.n, tolerance, model)
        tuples = join_tuples_paper(S, contacts.n, deadline=deadline, progress=progress)
    else:
        triple = _triple_test(model, contacts, tolerance, patches)
        if since:
            tuples = extend_tuples(tree.tuples, S, contacts.n, triple, deadline=deadline, progress=progress)
        else:
            _warn_explosion(S, contacts.n, tolerance, model, triple)
            tuples = sorted_rows(join_tuples(S, contacts.n, triple, deadline=deadline, progress=progress))
    clock.append(time.perf_counter())
    return SearchTree(contacts, tolerance, units, tuples), dict(zip(("pairs", "tree"), np.diff(clock).tolist()))


def _triple_test(model, contacts, tolerance, patches):
    """The handedness test over the search units (a patch's normal cone as slack)."""
    if patches:
        return TripleTest(model.patches.normals, contacts.object_normals, tolerance.per_contact_bounds()[1],
                          slack=model.patches.cone)
    return TripleTest(model.planes.normals, contacts.object_normals, tolerance.per_contact_bounds()[1])


def _check_tree(contacts, tolerance, method, units, tree):
    """The number k of contacts ``tree`` was grown for, if these contacts extend them."""
    if not isinstance(tree, SearchTree):
        raise ContactPoseError(f"tree must be a Result's tree (a SearchTree) or None, got {type(tree).__name__}")
    k = tree.contacts.n
    if method != "fast" or tree.units != units:
        raise ContactPoseError(f"tree was grown over {tree.units}; this search ({method!r}) runs over {units}")
    if tree.tolerance != tolerance:
        raise ContactPoseError(f"tree was grown at {tree.tolerance}, this search is at {tolerance}: same noise needed")
    if k >= contacts.n or not (np.allclose(tree.contacts.points, contacts.points[:k], rtol=0.0, atol=1e-12)
                               and np.allclose(tree.contacts.finger_normals, contacts.finger_normals[:k],
                                               rtol=0.0, atol=1e-12)):
        raise ContactPoseError(f"tree was grown for {k} contacts that are not the first {k} of these {contacts.n}")
    return k


def _pose_and_rank(model, contacts, facets, tolerance, method, solver, prior, deadline, progress, timing):
    """pose_hypotheses then rank_hypotheses of some tuples, adding their seconds to timing."""
    start = time.perf_counter()
    fit, paper_cost = pose_hypotheses(model, contacts, facets, tolerance, method=method, solver=solver, prior=prior,
                                      deadline=deadline, progress=progress)
    facets = facets[:len(fit.t)]  # LM stops at the deadline
    posed = time.perf_counter()
    arrays = ranking.hypothesis_arrays(model, contacts, facets, fit, tolerance, method=method, paper_cost=paper_cost)
    timing["pose"] += posed - start
    timing["rank"] += time.perf_counter() - posed
    return arrays


def find_pairs(model, contacts, tolerance, *, method="fast"):
    """S_ij for every finger pair (eq. 5, then the exact interval test): dict (i, j) -> PairSet.

    "fast" uses the exact Δmin bounds and the direction constraint, over the model's
    patches when it has a patch table; "paper" the vertex-only bounds over facets.
    """
    conditions = pair_conditions(contacts)
    _check_span(model, conditions, tolerance)
    fast = method == "fast"
    return admissible_pairs(model, conditions, tolerance, "exact" if fast else "paper", direction=fast,
                            patches=fast and model.patch_table is not None)


def join_hypotheses(model, contacts, S, tolerance, *, method="fast", prior=None, deadline=None, progress=None,
                    members_deadline=None):
    """The tree T over S_ij: facet tuples (H, n) int, one finger per column.

    "fast" joins level by level with the handedness test on triples (on patches, one
    tuple per patch tuple: see :func:`_members_in_chunks`); "paper" node by node (§3.2).
    deadline : the tree's progress.Deadline; members_deadline : the one the patch tuples'
    member choice checks between chunks of POSE_CHUNK (default: deadline).
    Warns when the pair sets predict more than EXPLOSION_TUPLES tuples (search.tree.expected_tuples).
    """
    if method == "paper":
        _warn_explosion(S, contacts.n, tolerance, model)
        return join_tuples_paper(S, contacts.n, deadline=deadline, progress=progress)
    patches = model.patch_table is not None
    triple = _triple_test(model, contacts, tolerance, patches)
    _warn_explosion(S, contacts.n, tolerance, model, triple)
    tuples = join_tuples(S, contacts.n, triple, deadline=deadline, progress=progress)
    if not patches:
        return tuples
    return _members_in_chunks(model, contacts, tuples, tolerance, prior,
                              deadline if members_deadline is None else members_deadline)


def pose_hypotheses(model, contacts, facets, tolerance, *, method="fast", solver=None, prior=None, deadline=None,
                    progress=None):
    """A pose per hypothesis: the closed form (origin-invariant cost for "fast", eq. (7)
    for "paper"), or LM on eq. (7) from the prior (or identity) with solver="lm".

    facets : (H, n) int -> (PoseFit, eq. (7) cost (H,) from LM or None). LM stops at a
    passed deadline: then the fit and cost cover the first hypotheses only.
    """
    solver = solver or ("closed-form" if method == "fast" else "lm")
    normals = model.planes.normals[facets]
    offsets = model.planes.offsets[facets]
    t0 = None if prior is None else np.broadcast_to(prior.pose[:3, 3], (len(facets), 3))
    fit = fit_poses(normals, offsets, contacts.points, contacts.finger_normals,
                    cost="invariant" if method == "fast" else "paper",
                    angle_tol=tolerance.normal_noise, t0=t0, centroids=model.centroids[facets])
    if solver == "closed-form":
        return fit, None
    T, cost, _ = fit_lm_all(normals, offsets, contacts.points, contacts.finger_normals,
                            np.eye(4) if prior is None else prior.pose, deadline=deadline, progress=progress)
    fit = fit.take(slice(0, len(T)))
    fit.R, fit.t = T[:, :3, :3], T[:, :3, 3]
    return fit, cost


#: The ranking stage (scoring.rank.hypothesis_arrays), under its pipeline name.
rank_hypotheses = ranking.hypothesis_arrays


def refine_hypotheses(model, contacts, arrays, tolerance, *, prior=None, robust="huber", k=DEFAULT_REFINE):
    """The factor graph's refinement of the best k hypotheses, as ranked HypothesisArrays
    (by Laplace evidence), with covariance and probability. Unassigned fingers (facet -1,
    max_outliers) have no contact residual.

    With a prior, when no hypothesis both agrees with it and, refined, fits the contacts
    within noise (χ² <= fit_threshold), the search runs again at RESCUE_WIDEN times the pair
    tolerances and, if still none agrees with the prior, each contact also gets its
    best-fitting facet under the prior pose; all of these are refined together, and a
    warning says what was done (research/factor_graph.md, "Rescue"). Returns (arrays, that
    note or "")."""

    def refined(a):
        if len(a.cost) == 0:
            return a, 0
        ref = fg.refine_hypotheses(model, contacts, a, tolerance, prior=prior, robust=robust, k=k)
        return ranking.refined_arrays(model, contacts, ref, a.fit.take(ref.index), tolerance), ref.agreeing

    out, agreeing = refined(arrays)
    if prior is None or (agreeing > 0 and out.chi2[0] <= fit_threshold(contacts.n)):
        return out, ""
    wide = tolerance.widened(fg.RESCUE_WIDEN)
    arrays = arrays.merged(search(model, contacts, wide, prior=prior)[0])
    arrays = arrays.take(np.sort(np.unique(arrays.facets, axis=0, return_index=True)[1]))  # found twice
    how = f"searched again with {fg.RESCUE_WIDEN:g}x the pair tolerances"
    if not fg.agrees_with_prior(model, arrays, tolerance, prior):
        facets = nearest_fit_facets(model, contacts, prior.pose, tolerance)
        arrays = arrays.merged(ranking.closed_form_arrays(model, contacts, facets[None], tolerance,
                                                          angle_tol=tolerance.angle))
        how += " and added each contact's best-fitting facet under the prior pose"
    note = f"no hypothesis both agreed with the vision prior and fit within noise: {how}"
    warnings.warn(note, stacklevel=3)
    return refined(arrays)[0], note


def drop_blocked(model, contacts, arrays, finger_radius):
    """The hypotheses but those whose (determined) pose puts a contact where no finger of
    ``finger_radius`` fits (scoring.freespace)."""
    bad = free_space_violations(model, arrays.facets, arrays.poses, contacts, finger_radius)
    return arrays.take(np.flatnonzero(~(bad & ~arrays.fit.underdetermined)))


def classify(model, contacts, arrays, tolerance, *, method="fast", deadline=None):
    """Pose classes of the hypotheses that fit within noise, and the status with its hint
    (scoring.status; deadline : the search's progress.Deadline: once passed, the fit test
    stops and the status is "time_limit").

    "fast" decides "fits" by the in-facet lower bound on the best χ² (scoring.infacet),
    "paper" by the χ² at the pose. Returns (list of PoseClass, status, hint).
    """
    if method == "paper":
        fits = arrays.chi2 <= fit_threshold(contacts.n)
    else:
        fits = within_noise(model, contacts, arrays, tolerance, fit_threshold(contacts.n), enough=MAX_CLASS_HYPOTHESES,
                            deadline=deadline)
    classes = pose_classes(model, arrays, contacts.n, fits)
    truncated = deadline is not None and deadline.hit
    status, hint = status_of(model, contacts, arrays, classes, tolerance, fits, truncated)
    return classes, status, hint


# ----------------------------------------------------------------- helpers ---

def _members_in_chunks(model, contacts, tuples, tolerance, prior, members_deadline=None):
    """Facet tuples for patch tuples (H, n), one each, their members chosen POSE_CHUNK
    tuples at a time until members_deadline passes (:func:`_member_facets`)."""
    parts = []
    for lo in range(0, max(len(tuples), 1), POSE_CHUNK):
        if lo and members_deadline is not None and members_deadline.passed:
            break
        parts.append(_member_facets(model, contacts, tuples[lo:lo + POSE_CHUNK], tolerance, prior))
    return np.concatenate(parts)


def _member_facets(model, contacts, tuples, tolerance, prior):
    """Pose patch tuples (H, n) on the patch planes, give each contact the member facet that
    fits it best (nearest, with the normal it carries: costs.association.fitting_members), re-pose
    on those facets and take the members again (research/design.md). -> (H, n) int facets"""
    patches = model.patches
    t0 = None if prior is None else np.broadcast_to(prior.pose[:3, 3], (len(tuples), 3))
    normals, offsets, centres = patches.normals[tuples], patches.offsets[tuples], patches.centres[tuples]
    for _ in range(2):
        fit = fit_poses(normals, offsets, contacts.points, contacts.finger_normals,
                        angle_tol=tolerance.normal_noise, t0=t0, centroids=centres)
        facets = fitting_members(model, contacts, tuples, fit.R, fit.t, tolerance)
        normals, offsets, centres = model.planes.normals[facets], model.planes.offsets[facets], model.centroids[facets]
    return facets


def _distinct(model, arrays, tolerance, deadline):
    """distinct_poses within what is left of the deadline, or GROUPING_GRACE seconds if more;
    a cut there counts as the deadline's."""
    grouping = Deadline(None if deadline.seconds is None else max(deadline.remaining(), GROUPING_GRACE))
    arrays = distinct_poses(model, arrays, tolerance.position_noise, grouping)[0]
    deadline.hit |= grouping.hit
    return arrays


def listed_rows(classes, count):
    """Ranks that keep="fitting" lists of ``count`` ranked distinct poses with these pose
    classes: the best and the classes' members (those that fit within noise), in rank order;
    the best POOR_FIT_LISTED when no class holds any.  ->  (K,) int"""
    if not classes:
        return np.arange(min(POOR_FIT_LISTED, count))
    return np.union1d([0], np.concatenate([c.members for c in classes]))


def _plausible(arrays, classes):
    """The hypotheses keep="fitting" lists (:func:`listed_rows`), with the classes' ranks
    moved to that list. -> (HypothesisArrays, classes)"""
    rows = listed_rows(classes, len(arrays.cost))
    moved = [dataclasses.replace(c, members=np.searchsorted(rows, c.members), best=int(np.searchsorted(rows, c.best)))
             for c in classes]
    return arrays.take(rows), moved


def _widen(model, contacts, arrays, tolerance, solver, prior, deadline, progress, timing):
    """When nothing matched: search again with the pair tolerances widened by each factor of
    WIDEN_SCHEDULE in turn (3σ gates become 4.5σ, then 6σ), stopping at the first that finds
    hypotheses, at the time limit, or when the contacts could not fit even the widest gate.
    Gaussian noise has tails beyond any fixed gate: one reading at 4σ must not empty the
    answer. Returns (arrays, what was widened), or the empty ``arrays`` and ""."""
    for factor in WIDEN_SCHEDULE:
        wide = tolerance.widened(factor)
        if deadline.passed or contacts.spread > model.diameter + wide.distance:
            break
        found, more, _ = search(model, contacts, wide, solver=solver, prior=prior, deadline=deadline,
                                progress=progress)
        for key in timing:
            timing[key] += more[key]
        if len(found.cost):
            return found, (f"nothing matched at the stated noise: the pair tolerances were widened {factor:g}x "
                            f"(distance ±{wide.distance:.3g}, angle ±{np.degrees(wide.angle):.3g}°)")
    return arrays, ""


def _check_outliers(max_outliers, method, n):
    max_outliers = check_count(max_outliers, "max_outliers", minimum=0)
    if max_outliers and method != "fast":
        raise ContactPoseError("max_outliers needs method='fast' (the paper assigns every finger)")
    if max_outliers and n - max_outliers < 3:
        raise ContactPoseError(f"max_outliers={max_outliers} with {n} contacts leaves fewer than 3 to fit a pose")
    return max_outliers


def _outlier_sets(n, max_outliers):
    """Every set of 1..max_outliers fingers to leave unassigned."""
    return [np.array(c) for q in range(1, max_outliers + 1) for c in combinations(range(n), q)]


def warm_up(model, contacts, **options):
    """Load numba's compiled kernels before ``localize`` is timed: one call on ``contacts``,
    then the in-facet χ² bound on its first hypothesis. A grasp whose hypotheses all fit within
    noise by their planes never reaches that bound, so a warm-up by grasps alone can leave its
    kernel to load (some 25–40 ms) inside the first timed grasp that does. options : as for
    :func:`localize`."""
    result = localize(model, contacts, **options)
    if result.num_hypotheses:
        lowest_chi2_bound(model, contacts, result.hypotheses.arrays, np.zeros(1, dtype=np.int64), result.tolerance)


def _check_options(method, solver, top, contacts, prior):
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
    return method, solver


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
    """Contacts spread wider than the object: a warning, an error when far beyond (units)."""
    spread = contacts.spread
    if spread > UNITS_ERROR_RATIO * (model.diameter + tolerance.distance):
        raise ContactsError(units_message(spread, model.diameter))
    if spread > model.diameter + tolerance.distance:
        warnings.warn(units_message(spread, model.diameter), stacklevel=3)


def _warn_explosion(S, n, tolerance, model, triple=None):
    """Warn when the tree would hold more than EXPLOSION_TUPLES tuples (estimated from a
    sample of its start nodes, when the smallest pair set has more than EXPLOSION_CHECK_PAIRS)."""
    if min(len(pairs) for pairs in S.values()) <= EXPLOSION_CHECK_PAIRS:
        return
    expected = expected_tuples(S, n, triple)
    if expected > EXPLOSION_TUPLES:
        warnings.warn(f"the search may explode: about {expected:.2g} hypotheses, from the tree grown on a sample "
                      f"of its start nodes (tolerances ±{tolerance.distance:.3g} and ±{np.degrees(tolerance.angle):.3g}° "
                      f"on {model.num_facets} facets); state smaller noise, use a coarser mesh or set time_limit",
                      stacklevel=4)


def _check_time_limit(time_limit):
    if time_limit is None:
        return None
    if isinstance(time_limit, bool) or not isinstance(time_limit, (int, float, np.integer, np.floating)) \
            or not time_limit > 0:
        raise ContactPoseError(f"time_limit must be a positive number of seconds or None, got {time_limit!r}")
    return float(time_limit)
