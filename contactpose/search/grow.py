"""The search stage: S_ij (eq. 5) and the tree T (§3.2) grown over the model's search units,
facets or, on a model of surface regions, patches; extended by more contacts when a tree of
the first ones is given (TouchSession). stages.search poses and ranks what it finds.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from contactpose.errors import ContactPoseError, ResourceError
from contactpose.search.pairs import admissible_pairs, pair_conditions
from contactpose.search.tree import SearchTree, TripleTest, expected_tuples, extend_tuples, join_tuples, sorted_rows

__all__ = ["EXPLOSION_CHECK_PAIRS", "EXPLOSION_TUPLES", "find_pairs", "grow_tree", "triple_test", "warn_explosion"]

#: The tree warns when it is estimated to hold more tuples than this, and estimates only
#: when every finger pair admits more facet pairs than EXPLOSION_CHECK_PAIRS.
EXPLOSION_TUPLES = 1e6
EXPLOSION_CHECK_PAIRS = 10_000


def grow_tree(model, contacts, tolerance, *, tree=None, deadline=None, progress=None, edges=False):
    """S_ij and the tree T over the search units (facets; patches on a model of surface
    regions; with ``edges``, on a model with a facet table, its facets, sharp edges and
    vertices, each tuple then reported once by its units' representative facets: model.units).
    -> (SearchTree, seconds: "pairs", "tree")

    tree : the SearchTree of the first k of these contacts at this tolerance: only the pairs
    (i, j), j >= k, are queried and its tuples grow by contacts k, ..., n-1
    (search.tree.extend_tuples), the same set as the tree of all pairs. Rows are in
    lexicographic order either way, so the stages after the tree see the same input.
    """
    patches = model.patch_table is not None and not edges
    units = "edges" if edges else "patches" if patches else "facets"
    since = 0 if tree is None else _check_tree(contacts, tolerance, units, tree)
    clock = [time.perf_counter()]
    S = find_pairs(model, contacts, tolerance, patches=patches, since=since, edges=edges)
    clock.append(time.perf_counter())
    triple = triple_test(model, contacts, tolerance, patches, edges)
    if since:
        tuples = extend_tuples(tree.tuples, S, contacts.n, triple, deadline=deadline, progress=progress)
    else:
        warn_explosion(S, contacts.n, tolerance, model, triple)
        tuples = join_tuples(S, contacts.n, triple, deadline=deadline, progress=progress)
        tuples = sorted_rows(np.unique(model.units.facets[tuples], axis=0) if edges else tuples)
    clock.append(time.perf_counter())
    return SearchTree(contacts, tolerance, units, tuples), dict(zip(("pairs", "tree"), np.diff(clock).tolist()))


def find_pairs(model, contacts, tolerance, *, bounds="exact", direction=True, patches=None, since=0, edges=False):
    """S_ij for every finger pair (i, j), j >= since (eq. 5, then the exact interval test):
    dict (i, j) -> PairSet.

    bounds : "exact" (triangle–triangle Δmin, erratum 4) or "paper" (vertex-only Δmin, §3.1);
    direction : the direction constraint of the default method; patches : search the model's
    patches (None: when it has a patch table); edges : its facets, sharp edges and vertices.
    """
    conditions = pair_conditions(contacts, since)
    _check_span(model, conditions, tolerance)
    patches = model.patch_table is not None if patches is None else patches
    return admissible_pairs(model, conditions, tolerance, bounds, direction=direction, patches=patches, edges=edges)


def triple_test(model, contacts, tolerance, patches, edges=False):
    """The handedness test over the search units (a patch's or an edge unit's normal cone as slack)."""
    if edges:
        return TripleTest(model.units.normals, contacts.object_normals, tolerance.per_contact_bounds()[1],
                          slack=model.units.cones)
    if patches:
        return TripleTest(model.patches.normals, contacts.object_normals, tolerance.per_contact_bounds()[1],
                          slack=model.patches.cone)
    return TripleTest(model.planes.normals, contacts.object_normals, tolerance.per_contact_bounds()[1])


def _check_tree(contacts, tolerance, units, tree):
    """The number k of contacts ``tree`` was grown for, if these contacts extend them."""
    if not isinstance(tree, SearchTree):
        raise ContactPoseError(f"tree must be a Result's tree (a SearchTree) or None, got {type(tree).__name__}")
    k = tree.contacts.n
    if tree.units != units:
        raise ContactPoseError(f"tree was grown over {tree.units}; this search runs over {units}")
    if tree.tolerance != tolerance:
        raise ContactPoseError(f"tree was grown at {tree.tolerance}, this search is at {tolerance}: same noise needed")
    if k >= contacts.n or not (np.allclose(tree.contacts.points, contacts.points[:k], rtol=0.0, atol=1e-12)
                               and np.allclose(tree.contacts.finger_normals, contacts.finger_normals[:k],
                                               rtol=0.0, atol=1e-12)):
        raise ContactPoseError(f"tree was grown for {k} contacts that are not the first {k} of these {contacts.n}")
    return k


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


def warn_explosion(S, n, tolerance, model, triple=None):
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
