"""``contactpose objects``: the built-in objects, procedural and YCB, by the names the CLI takes."""

from __future__ import annotations

from contactpose.cli.common import add_parser
from contactpose.sim import objects, ycb


def register(sub):
    p = add_parser(sub, "objects", help="list the built-in objects (procedural meshes and the YCB set)",
                   description="The names build-model, localize and next-touch take as MESH.")
    p.set_defaults(func=run)


def run(args):
    """Print one line per built-in object; 0."""
    print("procedural: " + ", ".join(objects.names(ycb_objects=False)))
    print(f"YCB ({len(ycb.names())} meshes, metres, 16,384 facets each; symmetry in brackets):")
    for name in ycb.names():
        kind = ycb.symmetry(name)
        print(f"  {name}" + (f"  [{kind}]" if kind else ""))
    return 0
