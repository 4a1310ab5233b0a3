"""Scoring of posed hypotheses: the ranking, the in-facet and free-space checks, the factor
graph's refinement ranked by evidence, pose classes and the status.

* :mod:`.rank`: the one constructor of ranked hypotheses (residuals, χ², cost);
* :mod:`.infacet`: can some pose within noise put every contact on its triangle;
* :mod:`.freespace`: does a finger of the given radius fit where a hypothesis puts it;
* :mod:`.evidence`: Laplace evidence, probabilities, the prior's agreement;
* :mod:`.refine`: which hypotheses the factor graph refines, and their ranking;
* :mod:`.classes`: distinct poses and pose classes (symmetric twins as one);
* :mod:`.status`: the one status rule.

Paper equation: the ranking by eq. (7)'s ℒ of the paper's method -> :func:`rank.hypothesis_arrays`
with ``method="paper"`` (§4: the best fitting hypothesis first).
"""

from contactpose.scoring.classes import classify_poses, distinct_poses, pose_classes, same_placement
from contactpose.scoring.evidence import agrees_with_prior, laplace_log_evidence, normalise, prior_gate
from contactpose.scoring.freespace import free_space_violations
from contactpose.scoring.infacet import within_noise
from contactpose.scoring.rank import closed_form_arrays, hypothesis_arrays, refined_arrays
from contactpose.scoring.refine import Refinement, refine_hypotheses
from contactpose.scoring.status import status

__all__ = ["Refinement", "agrees_with_prior", "classify_poses", "closed_form_arrays", "distinct_poses",
           "free_space_violations", "hypothesis_arrays", "laplace_log_evidence", "normalise", "pose_classes",
           "prior_gate", "refine_hypotheses", "refined_arrays", "same_placement", "status", "within_noise"]
