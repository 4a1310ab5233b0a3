"""The stages of the online phase (§3.2, §4), each a public function of arrays in, arrays out.

contacts -> search.grow.grow_tree (S_ij, eq. 5, and the tree T, §3.2; :func:`join_hypotheses`
over given S_ij) -> :func:`pose_hypotheses` (a pose per hypothesis) -> :func:`rank_hypotheses`
(residuals, χ², order) -> :func:`polish_hypotheses` (the poses moved onto the triangles)
-> :func:`distinct` (one hypothesis per distinct pose) -> :func:`surface_hypotheses` and
:func:`refine_hypotheses` (optional) -> :func:`classify` (pose classes and status)
-> :func:`listed` (what keep="fitting" lists).

:func:`find_hypotheses` runs the search stages for the default method, with the finger
subsets of ``max_outliers`` and the widened tolerances of an empty answer; localize composes
it with the rest. The paper's method takes the stages it shares with ours from here and its
own choices from contactpose.paper. Experiments and users may call the stages themselves.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from itertools import combinations

import numpy as np

from contactpose.costs.association import fitting_members, nearest_fit_facets
from contactpose.geometry.metrics import rms_displacement
from contactpose.model.memory import ONLINE_BYTES, gib, online_fits
from contactpose.model.symmetry import symmetry
from contactpose.model.units import unit_table_cost
from contactpose.options import DEFAULT_REFINE, OUTLIER_PENALTY, fit_threshold
from contactpose.progress import Deadline
from contactpose.scoring import evidence, refine
from contactpose.scoring import rank as ranking
from contactpose.scoring.classes import MAX_CLASS_HYPOTHESES, distinct_poses, distinct_radius, pose_classes
from contactpose.scoring.freespace import drop_blocked, drop_intersecting
from contactpose.scoring.infacet import within_noise
from contactpose.scoring.placements import placements, strict_groups, strictly_alike
from contactpose.scoring.status import status as status_of
from contactpose.search.grow import grow_tree, triple_test, warn_explosion
from contactpose.search.tree import join_tuples
from contactpose.search.verify import candidate_poses
from contactpose.solvers.closed_form import fit_poses
from contactpose.solvers.lm import fit_lm_all
from contactpose.solvers.polish import polished
from contactpose.solvers.surface import SURFACE_REFINE, multistart_poses, surface_poses
from contactpose.types import PoseFit

#: When nothing matches, the pair tolerances are widened by these factors in turn.
WIDEN_SCHEDULE = (1.5, 2.0)
#: The surface hypotheses' placements beyond the best fitted again from starts around them, at
#: most (:func:`_placements_started`).
PLACEMENT_MULTISTARTS = 16
#: ... of the hypotheses whose χ² is within this many times the fit threshold.
PLACEMENT_REACH = 2.0
#: The note of an answer from the search over facets, sharp edges and vertices (edge_hypotheses).
EDGES_NOTE = ("no facet tuple fit the contacts' normals within noise: searched again over the facets, sharp edges "
              "and vertices (a fingertip on a sharp edge), the best poses fitted on the surface contact model")
#: The edges' search needs contacts spread wider than this many pair distance gates.
EDGES_MIN_SPREAD = 2.0
#: Hypotheses of that search posed on the surface contact model (solvers.surface.surface_poses).
EDGE_REFINE = 16
#: On a model of surface regions, a poor fit of rounded fingertips has the regions searched
#: again with the angle gates this many times wider (with_widened_normals).
NORMAL_WIDEN = 2.0
#: The note of an answer that search joined.
NORMALS_NOTE = (f"no region tuple fit the contacts within noise: searched again with the normal gates {NORMAL_WIDEN:g}x "
                "wider (a rounded fingertip on a vertex or edge of the mesh has a normal between its faces'), the "
                "best poses fitted on the surface contact model")
#: Share of the time left that the tree may take; the poses and ranking get the rest.
TREE_SHARE = 0.25
#: Seconds the distinct-pose grouping may always take, even once the time limit has passed;
#: past both, the rows not yet grouped are listed as they are (status "time_limit").
GROUPING_GRACE = 2.0
#: ... but at most this share of the time limit.
GRACE_SHARE = 0.05
#: A best surface pose that does not fit within noise has up to NEAR_COPY_REFITS of its
#: near-copies fitted too, those within NEAR_COPY_REACH near-copy radii of it (_refit_near_copies).
NEAR_COPY_REFITS = 64
NEAR_COPY_REACH = 2.0
#: Hypotheses posed and ranked at a time (the grain of their deadline checks).
POSE_CHUNK = 65_536
#: Copies of the ranked arrays a search holds at its peak (the chunks, their merge, its order).
ROW_COPIES = 3
#: Seconds a posed hypothesis costs after the chunks (merge, polish, distinct poses), reserved
#: before the deadline: about 2 µs measured on 660 k hypotheses of a 4,212-facet mesh; doubled.
POST_SECONDS_PER_ROW = 4e-6
#: With keep="fitting", a search none of whose hypotheses fits within noise lists its best this many.
POOR_FIT_LISTED = 10
#: Clusters of the search by hypothesize and verify that become hypotheses, best first.
VERIFIED_FITS = 64
#: Rounds of iterated closest facets from each cluster's pose (verified_hypotheses).
CLOSEST_FACET_ROUNDS = 2
#: The search's stage times, in seconds, as every Result's timing starts.
SEARCH_STAGES = ("pairs", "tree", "pose", "rank")

__all__ = ["POOR_FIT_LISTED", "SEARCH_STAGES", "checked_by_samples", "classify", "distinct", "find_hypotheses",
           "join_hypotheses", "listed", "listed_rows", "polish_hypotheses", "pose_hypotheses", "rank_hypotheses",
           "refine_hypotheses", "search", "surface_hypotheses", "edge_hypotheses", "verified_hypotheses",
           "with_widened_normals"]


# ------------------------------------------------------------------ search ---

def find_hypotheses(model, contacts, tolerance, *, solver="closed-form", prior=None, max_outliers=0, deadline=None,
                    progress=None, tree=None, finger_radius=None):
    """Every hypothesis of the default method: :func:`search` of all contacts, then of every
    subset that leaves 1..max_outliers fingers unassigned (facet -1, OUTLIER_PENALTY each, their
    contacts out of the pose), and, when nothing matched, of all contacts with the pair
    tolerances widened by each factor of WIDEN_SCHEDULE in turn (3σ gates become 4.5σ, then
    6σ), until one finds hypotheses, the time limit passes or the contacts could not fit even
    the widest gate: Gaussian noise has tails beyond any fixed gate, and one reading at 4σ must
    not empty the answer. Then, on a model with a facet table, when no hypothesis fits within
    noise and an edge may be why (:func:`_edges_may_help`: none at all, or any poor fit with a
    ``finger_radius`` stated), all contacts are
    searched again at the stated noise over its facets, sharp edges and vertices
    (:func:`edge_hypotheses`); those of its hypotheses that fit within noise join the answer.
    solver : as for :func:`pose_hypotheses`. -> (HypothesisArrays ranked, seconds per stage
    (SEARCH_STAGES), the SearchTree of all contacts or None, a note on the widening or the
    edges' search or "")"""
    deadline = deadline or Deadline()
    every = np.arange(contacts.n)
    subsets = [every] + [np.setdiff1d(every, c) for q in range(1, max_outliers + 1) for c in combinations(every, q)]
    attempts = [(f, tolerance, 1.0) for f in subsets] + [(every, tolerance.widened(f), f) for f in WIDEN_SCHEDULE]
    arrays = timing = grown = None
    widened = ""
    for fingers, gates, factor in attempts:
        if timing is not None and deadline.passed:
            break
        if factor > 1.0 and (len(arrays.cost) or contacts.spread > model.diameter + gates.distance):
            break
        found, more, sub_tree = search(model, contacts.permuted(fingers), gates, solver=solver, prior=prior,
                                       deadline=deadline, progress=progress, tree=tree if timing is None else None)
        if timing is None:
            arrays, timing, grown = found, more, sub_tree
            continue
        timing = {k: timing[k] + more[k] for k in timing}
        if factor == 1.0:
            arrays = arrays.merged(found.widened(fingers, contacts.n, (contacts.n - len(fingers)) * OUTLIER_PENALTY))
        elif len(found.cost):
            arrays = found
            widened = (f"nothing matched at the stated noise: the pair tolerances were widened {factor:g}x "
                       f"(distance ±{gates.distance:.3g}, angle ±{np.degrees(gates.angle):.3g}°)")
    if _edges_may_help(model, contacts, tolerance, arrays, deadline, finger_radius):
        skipped = _edges_unaffordable(model, deadline)
        if skipped:
            return arrays, timing, grown, "; ".join(note for note in (widened, skipped) if note)
        found = edge_hypotheses(model, contacts, tolerance, timing, prior=prior, deadline=deadline, progress=progress)
        fitting = np.flatnonzero(found.chi2 <= fit_threshold(contacts.n))
        if len(fitting):
            arrays = arrays.merged(found.take(fitting))
            arrays = _first_of_each_tuple(arrays)
            widened = EDGES_NOTE
    return arrays, timing, grown, widened


def verified_hypotheses(model, contacts, tolerance, *, deadline=None):
    """The hypotheses of the search by hypothesize and verify (search.verify,
    research/verify_search.md): the best VERIFIED_FITS of its clusters, each contact assigned
    its best-fitting facet at the cluster's pose (costs.association.nearest_fit_facets), and
    beside each the poses of CLOSEST_FACET_ROUNDS rounds of iterated closest facets (the
    closed-form pose on the facets, the contacts assigned again there: a cluster's pose is a
    few degrees off, so its assignment can be a neighbour's); ranked, a facet tuple found
    twice kept once.
    -> (HypothesisArrays ranked, seconds per stage (SEARCH_STAGES))"""
    start = time.perf_counter()
    found = candidate_poses(model.oriented, contacts, tolerance, model.diameter, deadline).take(slice(0, VERIFIED_FITS))
    searched = time.perf_counter()
    if not len(found):
        arrays = ranking.closed_form_arrays(model, contacts, np.zeros((0, contacts.n), dtype=np.int64), tolerance)
        return arrays, {"pairs": 0.0, "tree": searched - start, "pose": 0.0, "rank": 0.0}
    fit = PoseFit(found.R, found.t, np.zeros((len(found), 3, 3)), np.zeros((len(found), 3), dtype=bool),
                  np.zeros((len(found), 3)), np.zeros(len(found), dtype=bool))
    facets = nearest_fit_facets(model, contacts, fit.poses(), tolerance)
    rounds = [ranking.hypothesis_arrays(model, contacts, facets, fit, tolerance)]
    for _ in range(CLOSEST_FACET_ROUNDS):
        rounds.append(ranking.closed_form_arrays(model, contacts, facets, tolerance, order=False))
        facets = nearest_fit_facets(model, contacts, rounds[-1].poses, tolerance)
    rounds.append(ranking.closed_form_arrays(model, contacts, facets, tolerance))
    done = time.perf_counter()
    arrays = _first_of_each_tuple(rounds[0].merged(*rounds[1:]))
    return arrays, {"pairs": 0.0, "tree": searched - start, "pose": done - searched,
                    "rank": time.perf_counter() - done}


def checked_by_samples(model, contacts, arrays, tolerance, timing, *, finger_radius=None, free_space=None,
                       merge_twins=False, deadline=None):
    """The ranked hypotheses of an answer about to say "ok", joined by those of the search by
    hypothesize and verify (:func:`verified_hypotheses`), fitted on the surface as that
    search's are, those that meet ``free_space`` (a contacts.FreeSpace or None) dropped, one
    per distinct pose; its seconds are added to ``timing`` ("tree": the candidates; "pose":
    the rest). Where a rounded fingertip rests at an edge or a vertex of a
    rough scan, the table and the tree can lose the true placement while a wrong one fits
    within noise, and nothing in the answer tells; a search that shares no stage with them
    finds it in most of those grasps (research/sure.md, "A second search before ok").
    -> HypothesisArrays ranked"""
    deadline = deadline or Deadline()
    found, more = verified_hypotheses(model, contacts, tolerance, deadline=deadline)
    start = time.perf_counter()
    if finger_radius is not None:
        found = drop_blocked(model, contacts, found, finger_radius)
    found = surface_hypotheses(model, contacts, found, tolerance, deadline, VERIFIED_FITS, merge_twins=merge_twins,
                               every=found, multistart=True)
    if free_space is not None:
        found = drop_intersecting(model, contacts, found, free_space, tolerance)[0]
    arrays = distinct(model, _first_of_each_tuple(arrays.merged(found)), tolerance, deadline, merge_twins)
    timing["tree"] += more["tree"]
    timing["pose"] += more["pose"] + more["rank"] + time.perf_counter() - start
    return arrays


def _edges_unaffordable(model, deadline):
    """Why the search over facets, sharp edges and vertices cannot run on this model now, or
    "": its unit table, built on first use, would need more than the online memory guard
    (model.memory.online_fits) or more time than is left. A table built once is free."""
    if "unit_table" in vars(model):
        return ""
    n = len(model.units)
    need, seconds = unit_table_cost(n)
    if online_fits(need) and seconds <= deadline.remaining():
        return ""
    return (f"the search over sharp edges did not run: its table of {n:,} facets, edges and vertices would take "
            f"about {gib(need)} GiB and {seconds:.3g} s to build (the guard: {gib(ONLINE_BYTES)} GiB, "
            f"{deadline.remaining():.3g} s left)")


def with_widened_normals(model, contacts, arrays, tolerance, timing, *, finger_radius, prior=None, deadline=None,
                        progress=None, merge_twins=False):
    """The ranked surface poses of a model of surface regions, joined, when none fits within
    noise and rounded fingertips are stated (``finger_radius`` > 0), by those of a search with
    the angle gates NORMAL_WIDEN times wider that do. A fingertip resting on a vertex or edge
    of a rough scan has a normal anywhere between its faces' normals, farther than the gate
    from every region's (research/surface.md, "A fingertip on a vertex of a rough scan"). The
    new hypotheses keep the free-space test, are ranked at the stated noise and fitted on the
    surface contact model as the first search's are (:func:`surface_hypotheses`); the search's
    seconds are added to ``timing``. -> (HypothesisArrays ranked, one per distinct pose; the
    note NORMALS_NOTE, or "" when nothing joined)"""
    deadline = deadline or Deadline()
    if (not finger_radius or not model.has_regions or deadline.passed
            or np.any(arrays.chi2 <= fit_threshold(contacts.n))):
        return arrays, ""
    found, more, _ = search(model, contacts, tolerance.normals_widened(NORMAL_WIDEN), prior=prior, deadline=deadline,
                            progress=progress)
    for k in more:
        timing[k] += more[k]
    start = time.perf_counter()
    found = drop_blocked(model, contacts, found, finger_radius)
    found = ranking.hypothesis_arrays(model, contacts, found.facets, found.fit, tolerance)
    found = surface_hypotheses(model, contacts, distinct(model, found, tolerance, deadline), tolerance, deadline,
                               merge_twins=merge_twins, multistart=True)
    fitting = np.flatnonzero(found.chi2 <= fit_threshold(contacts.n))
    if len(fitting):
        arrays = distinct(model, _first_of_each_tuple(arrays.merged(found.take(fitting))), tolerance, deadline,
                          merge_twins)
    timing["pose"] += time.perf_counter() - start
    return arrays, NORMALS_NOTE if len(fitting) else ""


def _edges_may_help(model, contacts, tolerance, arrays, deadline, finger_radius=None):
    """Whether the search over facets, sharp edges and vertices should run (find_hypotheses):
    a model with a facet table that is not searched over surface regions (a fine mesh, whose
    edges and vertices would make a unit table of GiBs: its regions widen their normal gates
    instead, :func:`with_widened_normals`), time left, no hypothesis that fits within noise, contacts
    spread wider than EDGES_MIN_SPREAD pair distance gates (closer ones fit any vertex whose
    cone holds their normals), and either no hypothesis at all or rounded fingertips stated
    (``finger_radius`` > 0: a point contact lands on an edge almost never, a rounded one
    often). Without a stated radius a poor fit keeps its diagnosis: cones wide enough for an
    edge also absorb a normal noise stated too small."""
    if (model.table is None or model.has_regions or deadline.passed
            or contacts.spread <= EDGES_MIN_SPREAD * tolerance.distance):
        return False
    if np.any(arrays.chi2 <= fit_threshold(contacts.n)):
        return False
    return not len(arrays.cost) or bool(finger_radius)


def edge_hypotheses(model, contacts, tolerance, timing, *, prior=None, deadline=None, progress=None):
    """The hypotheses of :func:`search` over the model's facets, sharp edges and vertices
    (model.units) at ``tolerance``, posed by the closed form whatever the solver (the units
    admit many more tuples than the facets, too many for one LM each), one per distinct pose,
    the best EDGE_REFINE posed on the
    surface contact model (:func:`surface_hypotheses`), so that their χ² charges an edge
    contact nothing for a normal on its arc; the search's seconds are added to ``timing``. A
    rounded fingertip on a sharp edge of a coarse mesh has a normal no facet's matches."""
    deadline = deadline or Deadline()
    found, more, _ = search(model, contacts, tolerance, prior=prior, deadline=deadline, progress=progress, edges=True)
    for k in timing:
        timing[k] += more[k]
    start = time.perf_counter()
    found = surface_hypotheses(model, contacts, distinct(model, found, tolerance, deadline), tolerance, deadline,
                               EDGE_REFINE)
    timing["pose"] += time.perf_counter() - start
    return found


def search(model, contacts, tolerance, *, solver="closed-form", prior=None, deadline=None, progress=None, tree=None,
           edges=False):
    """The default method's stages up to the ranking: S_ij -> tree -> poses -> ranked and
    polished HypothesisArrays.

    deadline : a progress.Deadline. The tree may spend TREE_SHARE of what is left of it;
    the poses and the ranking then run POSE_CHUNK hypotheses at a time until it passes
    (``deadline.hit`` tells whether anything stopped early). solver : as for
    :func:`pose_hypotheses`. tree : a SearchTree of the first contacts to extend
    (search.grow.grow_tree). edges : over the facets, sharp edges and vertices (model.units),
    each tuple posed on its units' representative facets. Returns (HypothesisArrays, seconds per stage: "pairs", "tree",
    "pose", "rank", the SearchTree of these contacts, or None when the deadline cut the tree
    short).
    """
    deadline = deadline or Deadline()
    tree_deadline = Deadline(None if deadline.seconds is None else TREE_SHARE * deadline.remaining())
    grown, timing = grow_tree(model, contacts, tolerance, tree=tree, deadline=tree_deadline, progress=progress,
                              edges=edges)
    deadline.hit |= tree_deadline.hit
    start = time.perf_counter()
    facets = grown.tuples
    if grown.units == "patches":
        facets = _members_in_chunks(model, contacts, facets, tolerance, prior, deadline)
    timing.update(tree=timing["tree"] + time.perf_counter() - start, pose=0.0, rank=0.0)
    parts, chunk_start = [], time.perf_counter()
    for lo in range(0, max(len(facets), 1), POSE_CHUNK):
        if lo and (deadline.passed or _chunks_spent(parts, deadline, time.perf_counter() - chunk_start)):
            break
        chunk_start = time.perf_counter()
        parts.append(_pose_and_rank(model, contacts, facets[lo:lo + POSE_CHUNK], tolerance, solver, prior, deadline,
                                    progress, timing))
    start = time.perf_counter()
    arrays = parts[0].merged(*parts[1:]) if len(parts) > 1 else parts[0]
    arrays = polish_hypotheses(model, contacts, arrays, tolerance)
    timing["pose"] += time.perf_counter() - start
    return arrays, timing, None if tree_deadline.hit else grown


def join_hypotheses(model, contacts, S, tolerance, *, prior=None, deadline=None, progress=None,
                    members_deadline=None):
    """The tree T over S_ij: facet tuples (H, n) int, one finger per column, joined level by
    level with the handedness test on triples (on patches, one tuple per patch tuple: see
    :func:`_members_in_chunks`). deadline : the tree's progress.Deadline; members_deadline :
    the one the patch tuples' member choice checks between chunks of POSE_CHUNK (default:
    deadline). Warns when the pair sets predict more than EXPLOSION_TUPLES tuples
    (search.tree.expected_tuples)."""
    patches = model.patch_table is not None
    triple = triple_test(model, contacts, tolerance, patches)
    warn_explosion(S, contacts.n, tolerance, model, triple)
    tuples = join_tuples(S, contacts.n, triple, deadline=deadline, progress=progress)
    if not patches:
        return tuples
    return _members_in_chunks(model, contacts, tuples, tolerance, prior,
                              deadline if members_deadline is None else members_deadline)


def pose_hypotheses(model, contacts, facets, tolerance, *, cost="invariant", solver="closed-form", prior=None,
                    deadline=None, progress=None):
    """A pose per hypothesis: the closed form (solvers.closed_form) of the origin-invariant
    cost (``cost="invariant"``) or of eq. (7) (``"paper"``), a translation family's member
    nearest the prior's translation; or, with solver="lm", Levenberg–Marquardt on eq. (7) from
    the prior (or the identity), as §4 does (solvers.lm).

    facets : (H, n) int -> (PoseFit, eq. (7) cost (H,) from LM or None). LM stops at a passed
    deadline: then the fit and cost cover the first hypotheses only.
    """
    normals, offsets = model.planes.normals[facets], model.planes.offsets[facets]
    t0 = None if prior is None else np.broadcast_to(prior.pose[:3, 3], (len(facets), 3))
    fit = fit_poses(normals, offsets, contacts.points, contacts.finger_normals, cost=cost,
                    angle_tol=tolerance.normal_noise, t0=t0, centroids=model.centroids[facets])
    if solver == "closed-form":
        return fit, None
    T, lm_cost, _ = fit_lm_all(normals, offsets, contacts.points, contacts.finger_normals,
                               np.eye(4) if prior is None else prior.pose, deadline=deadline, progress=progress)
    fit = fit.take(slice(0, len(T)))
    fit.R, fit.t = T[:, :3, :3], T[:, :3, 3]
    return fit, lm_cost


#: The ranking stage (scoring.rank.hypothesis_arrays), under its pipeline name.
rank_hypotheses = ranking.hypothesis_arrays


def polish_hypotheses(model, contacts, arrays, tolerance):
    """The ranked hypotheses with the poses of those that could beat the best moved toward
    the least full χ² (solvers.polish.polished), where that lowers it; re-ranked."""
    rows, fit, facets = polished(model, contacts, arrays, tolerance)
    if not len(rows):
        return arrays
    moved = ranking.hypothesis_arrays(model, contacts, facets, fit, tolerance, order=False)
    better = moved.chi2 < arrays.chi2[rows]
    if not better.any():
        return arrays
    return ranking.replaced(arrays, rows[better], moved.take(np.flatnonzero(better)))


# ------------------------------------------------------------ after search ---

def distinct(model, arrays, tolerance, deadline, merge_twins=False):
    """One hypothesis per distinct pose (scoring.classes.distinct_poses; merge_twins : the
    symmetric twins of a placement count as one pose), within what is left of the deadline (a
    progress.Deadline), or GROUPING_GRACE seconds if more; a cut there counts as the deadline's."""
    grace = None if deadline.seconds is None else min(GROUPING_GRACE, GRACE_SHARE * deadline.seconds)
    grouping = Deadline(None if deadline.seconds is None else max(deadline.remaining(), grace))
    arrays = distinct_poses(model, arrays, tolerance.position_noise, grouping, merge_twins)[0]
    deadline.hit |= grouping.hit
    return arrays


def surface_hypotheses(model, contacts, arrays, tolerance, deadline, k=SURFACE_REFINE, merge_twins=False,
                       every=None, multistart=False):
    """The best hypotheses posed on the surface contact model where it fits better than their
    facets (solvers.surface.surface_poses): their facets those the contacts land on, their
    residuals the contact model's; re-ranked, then one per distinct pose (:func:`distinct`).
    multistart : the best MULTISTART_ROWS of those then fitted again from starts around their
    poses too, where that lowers χ² (solvers.surface.multistart_poses), and the other ends
    that fit within noise listed beside the distinct poses (:func:`_with_basins`); after the
    grouping, so are the leaders of the other placements that fit (:func:`_placements_started`),
    while the deadline allows. every : the
    assignments before the distinct-pose grouping; when the best still does not fit within
    noise, its near-copies among them are fitted too (:func:`_refit_near_copies`)."""
    arrays = _moved(model, contacts, arrays, tolerance, surface_poses(model, contacts, arrays, tolerance, k))
    basins = None
    if multistart and len(arrays.cost) and not deadline.passed:
        lowered, basins = multistart_poses(model, contacts, arrays, tolerance)
        arrays = _moved(model, contacts, arrays, tolerance, lowered)
    if every is not None and len(arrays.cost) and arrays.chi2[0] > fit_threshold(contacts.n) and not deadline.passed:
        arrays = _refit_near_copies(model, contacts, arrays, every, tolerance)
    arrays = distinct(model, arrays, tolerance, deadline, merge_twins)
    if basins is None:
        return arrays
    return _placements_started(model, contacts, _with_basins(model, contacts, arrays, tolerance, basins), tolerance,
                               deadline)


def _placements_started(model, contacts, arrays, tolerance, deadline):
    """The ranked hypotheses with every placement that fits (:func:`_unstarted_placements`)
    fitted again from starts around its leader (solvers.surface.multistart_poses): its row
    moved to the least end where that lowers its χ², the other ends that fit within noise
    listed beside (:func:`_with_basins`). Rounds run while new placements appear (an end
    can be one), up to PLACEMENT_MULTISTARTS leaders in all and while the deadline allows.
    A placement's own fit can stop in a small basin far above its valley's floor on a rough
    scan (the apple, r = 5 %: a placement 0.9° from the truth at χ² 24.5, its multistart at
    7.7 2.4° from it; the hammer, r = 1 %: an end 2° from the truth at χ² 21.6, its own
    multistart at 2.7, below the best's 9.1), and the placements' evidence would then count
    it as all but impossible (research/sure.md)."""
    started, left = arrays.poses[:1], PLACEMENT_MULTISTARTS  # the best's multistart ran
    while left > 0 and len(arrays.cost) and not deadline.passed:
        rows = _unstarted_placements(model, contacts, arrays, started)[:left]
        if not len(rows):
            break
        lowered, more = multistart_poses(model, contacts, arrays, tolerance, rows=rows, deadline=deadline)
        started, left = np.concatenate([started, arrays.poses[rows]]), left - len(rows)
        arrays = _with_basins(model, contacts, _moved(model, contacts, arrays, tolerance, lowered), tolerance, more)
    return arrays


def _unstarted_placements(model, contacts, arrays, started):
    """(m,) int: the rows leading the distinct placements (scoring.placements.strict_groups)
    of the determined hypotheses within PLACEMENT_REACH times the fit threshold (a fit from
    starts around them may drop within it), but for those strictly alike a pose of
    ``started`` (K, 4, 4), whose multistart ran."""
    fits = np.flatnonzero((arrays.chi2 <= PLACEMENT_REACH * fit_threshold(contacts.n)) & ~arrays.fit.underdetermined)
    fits = fits[:MAX_CLASS_HYPOTHESES]
    group = symmetry(model)
    leaders = fits[[g[0] for g in strict_groups(arrays.poses[fits], group, model.diameter)]] if len(fits) else fits
    fresh = np.ones(len(leaders), dtype=bool)
    for pose in started:
        fresh &= ~strictly_alike(arrays.poses[leaders], pose, group, model.diameter)
    return leaders[fresh]


def _moved(model, contacts, arrays, tolerance, posed):
    """The ranked hypotheses with the rows of ``posed`` (rows, fit, facets, landing, as
    solvers.surface.surface_poses returns) moved to their surface poses, re-ranked, a tuple
    found twice kept once."""
    rows, fit, facets, landed = posed
    if not len(rows):
        return arrays
    moved = ranking.hypothesis_arrays(model, contacts, facets, fit, tolerance, order=False, surface=landed)
    return _first_of_each_tuple(ranking.replaced(arrays, rows, moved))


def _with_basins(model, contacts, arrays, tolerance, basins):
    """The ranked hypotheses and, as hypotheses of their own, the multistart's other ends
    that fit within noise (rows, fit, facets, landing, as solvers.surface.multistart_poses
    returns them), re-ranked, a tuple found twice kept once. They are near-copies of the
    pose they started from (scoring.classes.distinct_radius), but on a rough scan a pose a
    few degrees from the best may fit nearly as well, and the placements weigh it only if it
    is listed (research/sure.md, "Basins beside the best")."""
    rows, fit, facets, landed = basins
    if not len(rows):
        return arrays
    ends = ranking.hypothesis_arrays(model, contacts, facets, fit, tolerance, order=False, surface=landed)
    return _first_of_each_tuple(arrays.merged(ends))


def _refit_near_copies(model, contacts, arrays, every, tolerance):
    """The ranked hypotheses with the best near-copy of the first posed on the surface, when it
    ranks better: up to NEAR_COPY_REFITS of the assignments ``every`` (HypothesisArrays, ranked)
    within NEAR_COPY_REACH near-copy radii of the first pose, each fitted from its own facet
    pose. On a rough scan the surface fit's basin is narrower than the spread of one
    placement's near-copies, and the first of them need not start inside it
    (research/surface.md, "the surface fit's basin")."""
    reach = NEAR_COPY_REACH * distinct_radius(model, tolerance.position_noise)
    near = np.flatnonzero(rms_displacement(every.poses, arrays.poses[0], *model.class_moments) <= reach)
    rows, fit, facets, landed = surface_poses(model, contacts, every.take(near), tolerance, NEAR_COPY_REFITS)
    if not len(rows):
        return arrays
    moved = ranking.hypothesis_arrays(model, contacts, facets, fit, tolerance, order=False, surface=landed)
    best = int(np.argmin(moved.cost))
    if moved.cost[best] >= arrays.cost[0]:
        return arrays
    return _first_of_each_tuple(arrays.merged(moved.take([best])))


def _first_of_each_tuple(arrays):
    """The ranked hypotheses without a later one of the same facet tuple (found twice, or two
    fits that land alike)."""
    _, first = np.unique(arrays.facets, axis=0, return_index=True)
    return arrays if len(first) == len(arrays.cost) else arrays.take(np.sort(first))


def refine_hypotheses(model, contacts, arrays, tolerance, *, prior=None, robust="huber", k=DEFAULT_REFINE):
    """The factor graph's refinement of the best k hypotheses (scoring.refine), as ranked
    HypothesisArrays (by Laplace evidence), with covariance and probability. Unassigned
    fingers (facet -1, max_outliers) have no contact residual.

    With a prior, when no hypothesis both agrees with it and, refined, fits the contacts
    within noise (χ² <= fit_threshold), the search runs again at RESCUE_WIDEN times the pair
    tolerances and, if still none agrees with the prior, each contact also gets its
    best-fitting facet under the prior pose; all of these are refined together, and a
    warning says what was done (research/factor_graph.md, "Rescue"). Returns (arrays, that
    note or "")."""

    def refined(a):
        if len(a.cost) == 0:
            return a, 0
        ref = refine.refine_hypotheses(model, contacts, a, tolerance, prior=prior, robust=robust, k=k)
        return ranking.refined_arrays(model, contacts, ref, a.fit.take(ref.index), tolerance), ref.agreeing

    out, agreeing = refined(arrays)
    if prior is None or (agreeing > 0 and out.chi2[0] <= fit_threshold(contacts.n)):
        return out, ""
    wide = tolerance.widened(refine.RESCUE_WIDEN)
    arrays = arrays.merged(search(model, contacts, wide, prior=prior)[0])
    arrays = _first_of_each_tuple(arrays)  # found twice
    how = f"searched again with {refine.RESCUE_WIDEN:g}x the pair tolerances"
    if not evidence.agrees_with_prior(model, arrays, tolerance, prior):
        facets = nearest_fit_facets(model, contacts, prior.pose, tolerance)
        arrays = arrays.merged(ranking.closed_form_arrays(model, contacts, facets[None], tolerance,
                                                          angle_tol=tolerance.angle))
        how += " and added each contact's best-fitting facet under the prior pose"
    note = f"no hypothesis both agreed with the vision prior and fit within noise: {how}"
    warnings.warn(note, stacklevel=3)
    return refined(arrays)[0], note


def classify(model, contacts, arrays, tolerance, *, bound=True, deadline=None, notes=(), ok_probability=None,
             prior=None):
    """Pose classes of the hypotheses that fit within noise, their distinct placements, and
    the status with its hint (scoring.status; deadline : the search's progress.Deadline:
    once passed, the fit test stops and the status is "time_limit").

    bound : the fit test, the in-facet lower bound on each hypothesis's best χ²
    (scoring.infacet), or, False, the χ² at its pose (the paper's). ok_probability : with it,
    the placements modulo symmetry are weighed by their evidence (scoring.placements) and
    "ok" needs the best pose strictly right with at least this
    probability; None: the placements are not weighed (the paper's rule); prior : a
    PosePrior, whose density weighs the placements too. notes : what
    earlier stages did, joined to the hint. Returns (list of PoseClass, status, hint, list of
    Placement, confidence or None).
    """
    if bound:
        fits = within_noise(model, contacts, arrays, tolerance, fit_threshold(contacts.n), enough=MAX_CLASS_HYPOTHESES,
                            deadline=deadline)
    else:
        fits = arrays.chi2 <= fit_threshold(contacts.n)
    classes = pose_classes(model, arrays, fits)
    found, confidence = [], None
    if ok_probability is not None:
        found, confidence = placements(model, contacts, arrays, fits, tolerance, symmetry(model), prior)
    truncated = deadline is not None and deadline.hit
    status, hint = status_of(model, contacts, arrays, classes, tolerance, fits, truncated, placements=found,
                             confidence=confidence, ok_probability=ok_probability)
    for note in notes:
        if note:
            hint = f"{hint}; {note}" if hint else note
    return classes, status, hint, found, confidence


def listed_rows(classes, count):
    """Ranks that keep="fitting" lists of ``count`` ranked distinct poses with these pose
    classes: the best and the classes' members (those that fit within noise), in rank order;
    the best POOR_FIT_LISTED when no class holds any.  ->  (K,) int"""
    if not classes:
        return np.arange(min(POOR_FIT_LISTED, count))
    return np.union1d([0], np.concatenate([c.members for c in classes]))


def listed(arrays, classes, found=()):
    """The hypotheses keep="fitting" lists (:func:`listed_rows`), with the ranks of the
    classes and of the placements ``found`` (whose members are the classes') moved to that
    list. -> (HypothesisArrays, classes, placements)"""
    rows = listed_rows(classes, len(arrays.cost))
    move = (lambda c: dataclasses.replace(c, members=np.searchsorted(rows, c.members),
                                          best=int(np.searchsorted(rows, c.best))))
    return arrays.take(rows), [move(c) for c in classes], [move(p) for p in found]


# ----------------------------------------------------------------- helpers ---

def _pose_and_rank(model, contacts, facets, tolerance, solver, prior, deadline, progress, timing):
    """pose_hypotheses then rank_hypotheses of some tuples, adding their seconds to timing."""
    start = time.perf_counter()
    fit, _ = pose_hypotheses(model, contacts, facets, tolerance, solver=solver, prior=prior, deadline=deadline,
                             progress=progress)
    facets = facets[:len(fit.t)]  # LM stops at the deadline
    posed = time.perf_counter()
    arrays = ranking.hypothesis_arrays(model, contacts, facets, fit, tolerance)
    timing["pose"] += posed - start
    timing["rank"] += time.perf_counter() - posed
    return arrays


def _chunks_spent(parts, deadline, seconds):
    """Whether the posed chunks ``parts`` (HypothesisArrays), the last of which took
    ``seconds``, leave no room for one more: with it, the answer would pass the online memory
    guard (model.memory.online_fits, the ranked arrays held about ROW_COPIES times over), or
    the deadline once it and the merge and polish (POST_SECONDS_PER_ROW a row) ran. Either
    cut counts as the deadline's, so the answer says it is truncated."""
    rows = sum(len(p.cost) for p in parts) + POSE_CHUNK
    nbytes = sum(_nbytes(p) for p in parts) * rows / max(rows - POSE_CHUNK, 1)
    if not online_fits(ROW_COPIES * nbytes) or deadline.remaining() < seconds + POST_SECONDS_PER_ROW * rows:
        deadline.hit = True
    return deadline.hit


def _nbytes(arrays):
    """Bytes held by the arrays of a HypothesisArrays."""
    return sum(a.nbytes for a in (*vars(arrays).values(), *vars(arrays.fit).values()) if isinstance(a, np.ndarray))


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
    fits it best (nearest, with the normal it carries: costs.association.fitting_members),
    re-pose on those facets and take the members again (research/design.md). -> (H, n) int facets"""
    patches = model.patches
    t0 = None if prior is None else np.broadcast_to(prior.pose[:3, 3], (len(tuples), 3))
    normals, offsets, centres = patches.normals[tuples], patches.offsets[tuples], patches.centres[tuples]
    for _ in range(2):
        fit = fit_poses(normals, offsets, contacts.points, contacts.finger_normals,
                        angle_tol=tolerance.normal_noise, t0=t0, centroids=centres)
        facets = fitting_members(model, contacts, tuples, fit.R, fit.t, tolerance)
        normals, offsets, centres = model.planes.normals[facets], model.planes.offsets[facets], model.centroids[facets]
    return facets
