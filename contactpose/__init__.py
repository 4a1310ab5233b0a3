"""contactpose: finger contact location and object pose from contact measurements."""

from contactpose.errors import ContactPoseError

__all__ = ["ContactPoseError"]
__version__ = "0.1.0"
