"""``contactpose next-touch``: localize, then suggest the probe that best separates the poses left."""

from __future__ import annotations

import numpy as np

from contactpose.cli.common import add_noise_options, add_parser, model_or_mesh
from contactpose.errors import ContactPoseError
from contactpose.io import jsonfiles, output
from contactpose.localize import localize
from contactpose.tracking.next_touch import suggest_touch


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
    classes = len(result.classes)
    print(f"status: {result.status}  pose classes: {classes}"
          + (f" (probabilities {', '.join(f'{p:.2f}' for p in touch.probabilities)})" if classes > 1 else ""))
    fmt = lambda v: "[" + ", ".join(f"{x:.6g}" for x in v) + "]"
    if touch.determined:
        print("already determined: one pose class fits the contacts, no touch can separate anything; "
              "the probe below only confirms it")
    print(f"next touch: point {fmt(touch.point)}  direction {fmt(touch.direction)}")
    print(f"start: {fmt(touch.start)}  expected gain: {touch.expected_gain:.3f} bits")
    for c, o in enumerate(touch.outcomes):
        where = f" at {fmt(o['point'])}" if o["point"] is not None else ""
        print(f"  class {c}: {o['kind']}{where} (group {o['group']})")
    if args.output:
        jsonfiles.write_json(args.output, output.next_touch_dict(result, touch))
    return 0
