"""Pose uncertainty: the posterior of a hypothesis and its emcee samples."""
