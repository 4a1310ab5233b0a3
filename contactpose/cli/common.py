"""What every subcommand shares: the parser conventions, exit codes, warnings and model loading."""

from __future__ import annotations

import argparse
import hashlib
import inspect
import os
import warnings

from contactpose import __version__
from contactpose.io import cache as model_cache
from contactpose.localize import localize
from contactpose.model import ObjectModel
from contactpose.model.object_model import load_mesh, mesh_hash
from contactpose.options import DEFAULT_POSITION_NOISE_FRAC
from contactpose.sim import objects, ycb

#: Exit codes of ``contactpose`` (documented in the README's command-line section).
EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_BAD_INPUT = 2
#: ``localize --strict`` and an empty or poor answer (status no_hypothesis or poor_fit).
EXIT_STRICT = 3
EXIT_NO_HYPOTHESIS = EXIT_STRICT  # its first name, when --strict covered no_hypothesis only
EXIT_INTERRUPTED = 130
EXIT_CLOSED_PIPE = 141  # 128 + SIGPIPE, what a shell reports for a tool stopped by a closed pipe


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's default in ``--help``; none for None (no value) or False (a flag off).

    Options whose default the library applies (``default=None`` in the parser, so that a
    given value can be told from the default) state it in their help text; a help text that
    states its default is shown as it is, so that every default appears once.
    """

    def _get_help_string(self, action):
        default, text = action.default, action.help or ""
        if default is None or default is False or default is argparse.SUPPRESS or "%(default)" in text \
                or "(default:" in text:
            return action.help
        if isinstance(default, (list, tuple)):
            return f"{action.help} (default: {' '.join(map(str, default))})"
        return super()._get_help_string(action)


def debug_parent():
    """A parent parser with ``--debug``: accepted before or after the subcommand.

    Its default is SUPPRESS, so a subcommand that is not given ``--debug`` leaves the
    top-level value alone.
    """
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show tracebacks and debug logs")
    return parent


_DEBUG = debug_parent()


def add_parser(subparsers, name, **kwargs):
    """A subcommand parser with the shared ``--debug`` option and defaults in its help."""
    return subparsers.add_parser(name, parents=[_DEBUG], formatter_class=HelpFormatter, **kwargs)


def add_noise_options(parser):
    """``--position-noise`` and ``--normal-noise-deg``, as :func:`contactpose.localize` takes them."""
    parser.add_argument("--position-noise", type=float, metavar="X",
                        help=f"σ of contact points in length units (default: {DEFAULT_POSITION_NOISE_FRAC:g} x the "
                             "object's diameter)")
    parser.add_argument("--normal-noise-deg", type=float, default=library_default(localize, "normal_noise_deg"),
                        metavar="A", help="σ of normals in degrees")


def library_default(func, name):
    """The default of keyword ``name`` of ``func``: options given as None get the library's own."""
    return inspect.signature(func).parameters[name].default


def warn_in_vain(flag, reason):
    """One warning line: ``FLAG has no effect REASON``."""
    warnings.warn(f"{flag} has no effect {reason}", stacklevel=2)


def is_model_file(path):
    """Whether ``path`` names a model file (.npz) rather than a mesh or a built-in object."""
    return str(path).endswith(".npz")


#: The model builder's defaults of the options that key a cached model.
_BUILD_DEFAULTS = {k: library_default(ObjectModel.from_mesh, k) for k in ("bins", "bounds")}


def source_hash(name):
    """SHA-256 of what a named object's model is built from, part of its cache key: a YCB
    object's mesh file, read as bytes (no mesh parsed, so a cached model is ready without
    importing trimesh), or a procedural object's generated mesh (model.object_model.mesh_hash)."""
    if ycb.is_ycb_name(name):
        return hashlib.sha256(ycb.mesh_path(name).read_bytes()).hexdigest()
    return mesh_hash(*load_mesh(objects.load(name)))


def model_or_mesh(path, bins=None, bounds=None, fix_normals=False, max_span=None, cache=True):
    """Load a model .npz, or build one from a mesh file or a built-in object name. A built-in
    or YCB name's model goes through the model cache (contactpose.io.cache; ``cache=False``
    builds it afresh): built and stored once, loaded by later calls."""
    if is_model_file(path):
        return ObjectModel.load(path, bins=bins, bounds=bounds)
    kwargs = {k: v for k, v in (("bins", bins), ("bounds", bounds)) if v is not None}
    if not (objects.is_builtin(path) and not os.path.exists(path)):
        return ObjectModel.from_mesh(path, fix_normals=fix_normals, max_span=max_span, **kwargs)
    name = ycb.resolve(path) if ycb.is_ycb_name(path) else path

    def build():
        return ObjectModel.from_mesh(objects.load(name), fix_normals=fix_normals, max_span=max_span, **kwargs)

    if not cache:
        return build()
    options = {"bins": [int(b) for b in bins or _BUILD_DEFAULTS["bins"]], "bounds": bounds or _BUILD_DEFAULTS["bounds"],
               "fix_normals": bool(fix_normals), "max_span": None if max_span is None else float(max_span)}
    return model_cache.cached_model(name, source_hash(name), options, __version__, build,
                                    lambda file, verify: ObjectModel.load(file, bins=bins, bounds=bounds, verify=verify,
                                                                          mmap=True),
                                    lambda model: model.nbytes)
