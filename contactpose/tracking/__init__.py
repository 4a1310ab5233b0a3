"""Touch after touch: poses tracked through a sequence of touches, and where to touch next.

* :mod:`.track`: :class:`PoseTrack`, one hypothesis's pose trajectory in an iSAM2 smoother
  (slip factors between hand motions, contact factors per touch), and :class:`TrackSet`,
  several tracks pruned by their sequential χ² and reseeded when no track explains a touch;
* :mod:`.session`: :class:`TouchSession`, localization that grows with every touch (a static
  object: the search's tree extended; a held one: a TrackSet);
* :mod:`.next_touch`: the probe that best separates the remaining pose classes;
* :mod:`.sure`: :func:`touch_until_sure`, probes (suggested or at random) until localize is sure.
"""

from contactpose.tracking.next_touch import Touch, suggest_touch
from contactpose.tracking.session import TouchSession, relocalizer
from contactpose.tracking.sure import SureRun, TouchStep, random_probe, touch_until_sure
from contactpose.tracking.track import PoseTrack, TrackSet, add_touch, checked_motion

__all__ = ["PoseTrack", "SureRun", "Touch", "TouchSession", "TouchStep", "TrackSet", "add_touch", "checked_motion",
           "random_probe", "relocalizer", "suggest_touch", "touch_until_sure"]
