"""Pose uncertainty: the posterior of a hypothesis and its emcee samples (:mod:`.sampling`),
and the Cramér–Rao bounds of the pose from contacts (:mod:`.bounds`).

No paper equation lives here: the posterior is the facet or surface contact model of
contactpose.costs, in the chart of geometry.se3.
"""

from contactpose.uncertainty.bounds import local_quadric, pose_information
from contactpose.uncertainty.sampling import (
    MixtureSamples,
    PosePosterior,
    PoseSamples,
    run_ensemble,
    sample_hypotheses,
    sample_mixture,
    sample_pose,
)

__all__ = ["MixtureSamples", "PosePosterior", "PoseSamples", "local_quadric", "pose_information", "run_ensemble",
           "sample_hypotheses", "sample_mixture", "sample_pose"]
