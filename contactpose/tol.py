"""Numerical tolerances, kept in one place.

All length tolerances are relative to the object's diameter unless said otherwise.
"""

#: A facet whose area is below ``AREA_REL * diameter**2`` is degenerate.
AREA_REL = 1e-12
#: A facet whose shortest altitude is below ``ALTITUDE_REL * diameter`` is degenerate
#: (a sliver: near-zero area relative to its size).
ALTITUDE_REL = 1e-9
#: Normals whose length differs from 1 by more than this are renormalised with a warning.
UNIT_NORM = 1e-6
#: Confidence multiplier for pair tolerances: about 3 sigma for a pair of contacts.
CONFIDENCE_SIGMA = 3.0
#: Slack added to angle comparisons to absorb float32 storage of angles (radians).
ANGLE_SLACK = 1e-6
#: Relative slack added to distance comparisons to absorb float rounding.
LENGTH_SLACK_REL = 1e-7
