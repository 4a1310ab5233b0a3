"""``contactpose objects``: the built-in objects, procedural and YCB, by the names the CLI takes."""

from __future__ import annotations

from contactpose.sim import objects, ycb


def register(sub):
    p = sub.add_parser("objects", help="list the built-in objects (procedural meshes and the YCB set)")
    p.set_defaults(func=run)


def run(args):
    """Print one line per built-in object; 0."""
    print("procedural: " + ", ".join(objects.names(ycb_objects=False)))
    print(f"YCB ({len(ycb.names())} meshes, metres, 16,384 facets each; symmetry in brackets):")
    for name in ycb.names():
        kind = ycb.symmetry(name)
        print(f"  {name}" + (f"  [{kind}]" if kind else ""))
    return 0
