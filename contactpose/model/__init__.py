"""The offline phase: mesh -> facet planes (eq. 2) -> pair features (§3.1) -> patches -> table K3 (eqs. 3-5)."""

from contactpose.model.object_model import ObjectModel

__all__ = ["ObjectModel"]
