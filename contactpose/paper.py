"""The paper's method as published (``localize(..., method="paper")``), composed of the stages.

Its own choices, each a stage of contactpose.stages or the search package with the paper's
setting:

* S_ij (eq. 5) from the vertex-only Δmin of §3.1 (kept although erratum 4 shows it wrong) and
  the distance and angle conditions alone, over facets;
* the tree T grown node by node (§3.2, search.tree.join_tuples_paper);
* each hypothesis posed by Levenberg–Marquardt on eq. (7) from the prior or the identity (§4),
  or with solver="closed-form" by the exact closed-form minimum of eq. (7);
* ranked by eq. (7)'s ℒ (costs.paper), its fit tested by the χ² at that pose
  (stages.classify with ``bound=False``).

No polish, no distinct-pose grouping, no surface model and no factor graph: those are the
default method's. research/errata.md lists where the two differ.
"""

from __future__ import annotations

import time

import numpy as np

from contactpose.costs.paper import paper_cost, paper_offset_residuals
from contactpose.progress import Deadline
from contactpose.scoring import rank as ranking
from contactpose.search.grow import find_pairs, warn_explosion
from contactpose.search.tree import join_tuples_paper
from contactpose.stages import TREE_SHARE, pose_hypotheses

__all__ = ["rank_paper", "search"]


def search(model, contacts, tolerance, *, solver="lm", prior=None, deadline=None, progress=None):
    """The paper's stages up to the ranking: S_ij (vertex bounds) -> the node-by-node tree
    -> poses (LM on eq. (7), or its closed form) -> ranked by ℒ.

    deadline : a progress.Deadline; the tree may spend TREE_SHARE of what is left of it, LM
    stops once it passes. -> (HypothesisArrays, seconds per stage: "pairs", "tree", "pose", "rank")
    """
    deadline = deadline or Deadline()
    tree_deadline = Deadline(None if deadline.seconds is None else TREE_SHARE * deadline.remaining())
    clock = time.perf_counter()
    S = find_pairs(model, contacts, tolerance, bounds="paper", direction=False, patches=False)
    timing = {"pairs": time.perf_counter() - clock}
    clock = time.perf_counter()
    warn_explosion(S, contacts.n, tolerance, model)
    facets = join_tuples_paper(S, contacts.n, deadline=tree_deadline, progress=progress)
    deadline.hit |= tree_deadline.hit
    timing["tree"] = time.perf_counter() - clock
    clock = time.perf_counter()
    fit, cost = pose_hypotheses(model, contacts, facets, tolerance, cost="paper", solver=solver, prior=prior,
                                deadline=deadline, progress=progress)
    facets = facets[:len(fit.t)]  # LM stops at the deadline
    timing["pose"] = time.perf_counter() - clock
    clock = time.perf_counter()
    arrays = rank_paper(model, contacts, facets, fit, tolerance, cost)
    timing["rank"] = time.perf_counter() - clock
    return arrays, timing


def rank_paper(model, contacts, facets, fit, tolerance, cost=None):
    """Hypotheses ranked by eq. (7)'s ℒ (costs.paper.paper_cost, or ``cost`` (H,) when LM
    computed it), their residual column 3 eq. (7)'s offset. -> HypothesisArrays"""
    offset = paper_offset_residuals(fit.t, contacts.points, contacts.finger_normals, model.planes.offsets[facets])
    arrays = ranking.hypothesis_arrays(model, contacts, facets, fit, tolerance, offset=offset, order=False)
    r_n = np.ascontiguousarray(arrays.residuals[..., :3])
    return ranking.ranked(arrays, paper_cost(r_n, offset) if cost is None else cost)
