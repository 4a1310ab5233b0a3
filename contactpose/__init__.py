"""contactpose: finger contact location and object pose from contact measurements.

The method of Haidacher & Hirzinger, *Estimating Finger Contact Location and
Object Pose from Contact Measurements in 3-D Grasping* (ICRA 2003), made exact
and faster, with the paper's own method kept as ``method="paper"``.
"""

from contactpose.contacts import Contacts, FreeSpace, Tolerance
from contactpose.errors import ContactPoseError
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.tracking.session import TouchSession
from contactpose.types import PosePrior, Result

__all__ = ["ContactPoseError", "Contacts", "FreeSpace", "ObjectModel", "PosePrior", "Result", "Tolerance", "TouchSession",
           "localize", "objects", "simulate"]
__version__ = "0.1.0"
