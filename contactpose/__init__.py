"""contactpose: finger contact location and object pose from contact measurements.

The method of Haidacher & Hirzinger, *Estimating Finger Contact Location and
Object Pose from Contact Measurements in 3-D Grasping* (ICRA 2003), made exact
and faster, with the paper's own method kept as ``method="paper"``.
"""

from contactpose import objects, simulate
from contactpose.contacts import Contacts, Tolerance
from contactpose.errors import ContactPoseError
from contactpose.localize import PosePrior, Result, localize
from contactpose.model import ObjectModel

__all__ = ["ContactPoseError", "Contacts", "ObjectModel", "PosePrior", "Result", "Tolerance",
           "localize", "objects", "simulate"]
__version__ = "0.1.0"
