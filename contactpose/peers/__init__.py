"""Methods that compete with the contact search, run on the same contacts and scored alike.

* :mod:`.surface`: surface samples and the contact likelihood every peer scores a pose with;
* :mod:`.icp`: point-to-plane ICP of finger pads (Open3D), from a prior or many starts;
* :mod:`.scaling_series`: particle-filter global localization after the Scaling Series, as
  published and in a budgeted variant;
* :mod:`.particle_filter`: a held object tracked by particles (for the tracks of
  tracking.track);
* :mod:`.random_touch`: a random probe, the baseline of next-touch;
* :mod:`.chsel`: CHSEL, an outside peer run by its own package (optional: ``pip install
  contactpose[peers]``; not imported here, it needs torch).

Nothing of the core imports this package (an import-linter contract in pyproject.toml).
"""

from contactpose.peers.icp import centered_start, finger_pads, icp, icp_multistart, icp_target
from contactpose.peers.particle_filter import MemoryParticleFilter
from contactpose.peers.random_touch import random_touch
from contactpose.peers.scaling_series import scaling_series, scaling_series_published
from contactpose.peers.surface import (
    MIN_PER_FACET,
    NEIGHBOUR_RADIUS,
    SURFACE_SAMPLES,
    BaselineResult,
    Surface,
    contact_cost,
    facet_neighbours,
    sample_surface,
)

__all__ = ["MIN_PER_FACET", "NEIGHBOUR_RADIUS", "SURFACE_SAMPLES", "BaselineResult", "MemoryParticleFilter",
           "Surface", "centered_start", "contact_cost", "facet_neighbours", "finger_pads", "icp",
           "icp_multistart", "icp_target", "random_touch", "sample_surface", "scaling_series", "scaling_series_published"]
