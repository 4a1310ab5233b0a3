"""Scoring of posed hypotheses: ranking, the in-facet and free-space checks, pose classes, status."""
