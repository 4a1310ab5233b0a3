"""Pose solvers for hypotheses: closed form (default), the paper's LM, and the factor graph."""
