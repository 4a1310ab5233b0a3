"""What every subcommand shares: loading a model from a file or a built-in name."""

from __future__ import annotations

import os

from contactpose.model import ObjectModel
from contactpose.sim import objects


def model_or_mesh(path, bins=None, bounds=None, fix_normals=False, max_span=None):
    """Load a model .npz, or build one from a mesh file (or built-in object name)."""
    if str(path).endswith(".npz"):
        return ObjectModel.load(path, bins=bins, bounds=bounds)
    source = objects.load(path) if objects.is_builtin(path) and not os.path.exists(path) else path
    kwargs = {k: v for k, v in (("bins", bins), ("bounds", bounds)) if v is not None}
    return ObjectModel.from_mesh(source, fix_normals=fix_normals, max_span=max_span, **kwargs)
