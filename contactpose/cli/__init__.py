"""Command-line interface: ``contactpose build-model | localize | next-touch | track | demo | bench | scan``.

One module per subcommand, each with ``register(subparsers)`` and ``run(args)``. Exit
codes (``EXIT_*`` in :mod:`contactpose.cli.common`): 0 success, 1 internal error, 2 bad
input (one line on stderr: ``contactpose: error: ...``), 3 ``localize --strict`` and an empty
or poor answer (no_hypothesis, poor_fit), 130 interrupted, 141 stdout closed early
(``| head``). ``--debug``, before or after the subcommand, shows the traceback instead of the
one line.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import warnings

from contactpose import __version__
from contactpose.cli import build_model, cache, localize, next_touch, objects, tools, track
from contactpose.cli.common import (
    EXIT_BAD_INPUT,
    EXIT_CLOSED_PIPE,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_STRICT,
    HelpFormatter,
)
from contactpose.errors import ContactPoseError

__all__ = ["build_parser", "main"]

log = logging.getLogger("contactpose")


DESCRIPTION = "Where a robot hand's fingers touch a known object mesh, and the object's pose."
EPILOG = (f"exit codes: {EXIT_OK} success, {EXIT_INTERNAL} internal error, {EXIT_BAD_INPUT} bad input, "
          f"{EXIT_STRICT} an empty or poor answer (localize --strict), {EXIT_INTERRUPTED} interrupted, "
          f"{EXIT_CLOSED_PIPE} stdout closed early. Each command has --help.")


def build_parser():
    parser = argparse.ArgumentParser(prog="contactpose", description=DESCRIPTION, epilog=EPILOG,
                                     formatter_class=HelpFormatter)
    parser.add_argument("--version", action="version", version=f"contactpose {__version__}",
                        help="show the version and exit")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs (also after the command)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    build_model.register(sub)
    try:
        from contactpose.cli import scan
    except ImportError as exc:  # Open3D missing: the rest of the CLI still works
        log.debug("scan subcommand unavailable: %s", exc)
    else:
        scan.register(sub)
    localize.register(sub)
    next_touch.register(sub)
    track.register(sub)
    tools.register(sub)
    objects.register(sub)
    cache.register(sub)
    return parser


def main(argv=None):
    """Parse ``argv`` and run its subcommand; returns the exit code.

    A closed stdout (``contactpose ... | head``) ends quietly with code 141: stdout is
    pointed at devnull so the interpreter's last flush does not fail again.
    """
    try:
        try:
            return _main(argv)
        finally:
            sys.stdout.flush()
    except BrokenPipeError:
        _stdout_to_devnull()
        return EXIT_CLOSED_PIPE


def _main(argv):
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.WARNING,
                        format="contactpose: %(message)s")
    with warnings.catch_warnings():  # restores warnings.showwarning when main returns
        warnings.showwarning = _show_warning
        try:
            return args.func(args)
        except BrokenPipeError:
            raise
        except ContactPoseError as exc:
            if args.debug:
                raise
            print(f"contactpose: error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except KeyboardInterrupt:
            if args.debug:
                raise
            return EXIT_INTERRUPTED
        except Exception as exc:
            if args.debug:
                raise
            print(f"contactpose: internal error: {type(exc).__name__}: {exc} (rerun with --debug for the traceback)",
                  file=sys.stderr)
            return EXIT_INTERNAL


def _show_warning(message, *args, **kwargs):
    """Warnings as one stderr line while :func:`main` runs."""
    print(f"contactpose: warning: {message}", file=sys.stderr)


def _stdout_to_devnull():
    """Point file descriptor 1 at devnull (the Python docs' recipe for SIGPIPE)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # a replaced stdout (tests) has no descriptor
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)
