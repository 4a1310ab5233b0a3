"""Command-line interface: ``contactpose build-model | localize | next-touch | demo | bench | scan``.

One module per subcommand, each with ``register(subparsers)`` and ``run(args)``. Bad
input exits with code 2 and one line on stderr (``contactpose: error: ...``);
``--debug`` shows the traceback of internal errors.
"""

from __future__ import annotations

import argparse
import logging
import sys
import warnings

from contactpose.cli import build_model, localize, next_touch, objects, tools
from contactpose.errors import ContactPoseError

log = logging.getLogger("contactpose")


def build_parser():
    parser = argparse.ArgumentParser(prog="contactpose", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = parser.add_subparsers(dest="command", required=True)
    build_model.register(sub)
    localize.register(sub)
    tools.register(sub)
    next_touch.register(sub)
    objects.register(sub)
    try:
        from contactpose.cli import scan
    except ImportError as exc:  # Open3D missing: the rest of the CLI still works
        log.debug("scan subcommand unavailable: %s", exc)
    else:
        scan.register(sub)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.WARNING,
                        format="contactpose: %(message)s")
    with warnings.catch_warnings():  # restores warnings.showwarning when main returns
        warnings.showwarning = _show_warning
        try:
            return args.func(args)
        except ContactPoseError as exc:
            if args.debug:
                raise
            print(f"contactpose: error: {exc}", file=sys.stderr)
            return 2


def _show_warning(message, *args, **kwargs):
    """Warnings as one stderr line while :func:`main` runs."""
    print(f"contactpose: warning: {message}", file=sys.stderr)
