"""The online search: pair conditions and S_ij, joined into hypotheses by the tree T.

Paper equations:

* §3.2, the measured pair characteristics Δ̃_ij, α̃_ij -> :func:`pairs.pair_conditions`;
* eq. (5), S_ij from the table K3, then the exact interval test (and the direction
  constraint of the default method) -> :func:`pairs.admissible_pairs`;
* §3.2, the tree T: level by level with the handedness test on triples (default) ->
  :func:`tree.join_tuples`, node by node as published -> :func:`tree.join_tuples_paper`;
* the search stage, S_ij and T together over the model's search units -> :func:`grow.grow_tree`.
"""

from contactpose.search.grow import find_pairs, grow_tree
from contactpose.search.pairs import PairConditions, PairSet, admissible_pairs, pair_conditions
from contactpose.search.tree import SearchTree, TripleTest, extend_tuples, join_tuples, join_tuples_paper, sorted_rows

__all__ = ["PairConditions", "PairSet", "SearchTree", "TripleTest", "admissible_pairs", "extend_tuples", "find_pairs",
           "grow_tree", "join_tuples", "join_tuples_paper", "pair_conditions", "sorted_rows"]
