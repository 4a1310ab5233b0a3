"""Modules imported on first use, so that a command starts without the heavy ones it does not
need: trimesh (0.35 s with networkx) and Open3D (1 s) are not needed to localize on a stored
model. ``trimesh = deferred("trimesh")`` at the top of a module; ``trimesh.Trimesh`` then
imports it (through importlib, whose import lock makes the first use safe from threads).
"""

from __future__ import annotations

import importlib
import importlib.util


class Deferred:
    """A stand-in for module ``name``: each attribute is the module's, imported on first use."""

    def __init__(self, name):
        self._name = name

    def __getattr__(self, attribute):
        return getattr(importlib.import_module(self._name), attribute)

    def __repr__(self):
        return f"<module {self._name!r}, imported on first use>"


def deferred(name, required=True):
    """A :class:`Deferred` ``name``; ImportError now when ``required`` and it is not installed."""
    if required and importlib.util.find_spec(name) is None:
        raise ImportError(f"No module named {name!r}", name=name)
    return Deferred(name)
