"""What every subcommand shares: the parser conventions, exit codes, warnings and model loading."""

from __future__ import annotations

import argparse
import inspect
import os
import warnings

from contactpose.localize import localize
from contactpose.model import ObjectModel
from contactpose.options import DEFAULT_POSITION_NOISE_FRAC
from contactpose.sim import objects

#: Exit codes of ``contactpose`` (documented in the README's command-line section).
EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_BAD_INPUT = 2
EXIT_NO_HYPOTHESIS = 3
EXIT_INTERRUPTED = 130
EXIT_CLOSED_PIPE = 141  # 128 + SIGPIPE, what a shell reports for a tool stopped by a closed pipe


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's default in ``--help``; none for None (no value) or False (a flag off).

    Options whose default the library applies (``default=None`` in the parser, so that a
    given value can be told from the default) state it in their help text.
    """

    def _get_help_string(self, action):
        default = action.default
        if default is None or default is False or default is argparse.SUPPRESS or "%(default)" in (action.help or ""):
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


def model_or_mesh(path, bins=None, bounds=None, fix_normals=False, max_span=None):
    """Load a model .npz, or build one from a mesh file (or built-in object name)."""
    if is_model_file(path):
        return ObjectModel.load(path, bins=bins, bounds=bounds)
    source = objects.load(path) if objects.is_builtin(path) and not os.path.exists(path) else path
    kwargs = {k: v for k, v in (("bins", bins), ("bounds", bounds)) if v is not None}
    return ObjectModel.from_mesh(source, fix_normals=fix_normals, max_span=max_span, **kwargs)
