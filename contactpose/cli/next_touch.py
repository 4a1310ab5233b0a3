"""``contactpose next-touch``: localize, then suggest the probe that best separates the poses left."""

from __future__ import annotations

import numpy as np

from contactpose.cli.common import add_noise_options, add_parser, model_or_mesh
from contactpose.errors import ContactPoseError
from contactpose.io import jsonfiles, output
from contactpose.localize import localize
from contactpose.tracking.next_touch import suggest_touch

#: Classes less probable than this are left out of the printed outcomes (the JSON has them all).
LISTED_PROBABILITY = 0.01


def register(subparsers):
    """Add ``next-touch MODEL_OR_MESH --contacts CONTACTS.json [...]``; handler :func:`run`."""
    p = add_parser(subparsers, "next-touch", help="suggest the probe that best separates the remaining poses",
                   description="Localize, then propose the next touch (a world point and approach "
                               "direction) that best separates the pose classes that still fit.")
    p.add_argument("model", metavar="MODEL_OR_MESH", help="model .npz, mesh file or built-in object name")
    p.add_argument("--contacts", required=True, metavar="CONTACTS.json", help="a point and a normal per finger")
    add_noise_options(p)
    p.add_argument("--candidates", type=int, default=200, metavar="N", help="number of candidate probes")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the candidate sampling")
    p.add_argument("-o", "--output", metavar="OUT.json", help="write the suggestion as JSON")
    p.set_defaults(func=run)


def run(args):
    """Localize, suggest a touch, print it; 0 on success."""
    if args.candidates < 1:
        raise ContactPoseError(f"--candidates must be at least 1, got {args.candidates}")
    model = model_or_mesh(args.model)
    contacts = jsonfiles.read_contacts(args.contacts)
    result = localize(model, contacts, position_noise=args.position_noise, normal_noise_deg=args.normal_noise_deg)
    touch = suggest_touch(model, result, rng=np.random.default_rng(args.seed), contacts=contacts,
                          n_candidates=args.candidates)
    print_touch(result, touch)
    if args.output:
        jsonfiles.write_json(args.output, output.next_touch_dict(result, touch))
    return 0


def print_touch(result, touch):
    """The suggestion, and per pose class at least LISTED_PROBABILITY likely what the probe
    would read; every number with its unit."""
    fmt = lambda v: "[" + ", ".join(f"{x:.6g}" for x in v) + "]"
    listed = [c for c, p in enumerate(touch.probabilities) if p >= LISTED_PROBABILITY]
    print(f"status: {result.status}  pose classes: {len(result.classes)}")
    if touch.determined:
        print("already determined: one pose class fits the contacts, no touch can separate anything; "
              "the probe below only confirms it")
    print(f"next touch: point {fmt(touch.point)} (mesh units)  direction {fmt(touch.direction)} (unit vector, "
          "into the object)")
    print(f"start: {fmt(touch.start)} (mesh units)  expected gain: {touch.expected_gain:.3f} bits")
    print("what the probe reads under each pose class (p: its probability; classes that read alike are "
          "not told apart by this probe):")
    outcomes = touch.outcomes
    for c in listed:
        o = outcomes[c]
        where = f" at {fmt(o['point'])} (mesh units)" if o["point"] is not None else ""
        alike = [k for k in range(len(outcomes)) if k != c and outcomes[k]["group"] == o["group"]]
        same = f", reads like class{'es' if len(alike) > 1 else ''} {', '.join(map(str, alike))}" if alike else ""
        print(f"  class {c} (p {touch.probabilities[c]:.2f}): {o['kind']}{where}{same}")
    left = len(outcomes) - len(listed)
    if left:
        print(f"  {left} class{'es' if left > 1 else ''} below p {LISTED_PROBABILITY:g} not listed")
