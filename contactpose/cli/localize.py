"""``contactpose localize``: contact facets and the object pose from CONTACTS.json."""

from __future__ import annotations

from contactpose.cli.common import model_or_mesh
from contactpose.io import jsonfiles
from contactpose.localize import localize
from contactpose.types import METHODS, ROBUST, SOLVERS


def register(sub):
    p = sub.add_parser("localize", help="find contact facets and the object pose")
    p.add_argument("model", help="model .npz, mesh file or built-in object name")
    p.add_argument("--contacts", required=True, help="CONTACTS.json")
    p.add_argument("--prior", help="PRIOR.json")
    p.add_argument("--position-noise", type=float, help="σ of contact points (length units)")
    p.add_argument("--normal-noise-deg", type=float, default=1.0, help="σ of normals (degrees)")
    p.add_argument("--method", choices=METHODS, default="fast")
    p.add_argument("--solver", choices=SOLVERS)
    p.add_argument("--robust", choices=ROBUST, default="huber",
                   help="factor graph's robust kernel (with --solver factor-graph)")
    p.add_argument("--max-outliers", type=int, default=0, help="fingers that may be left unassigned")
    p.add_argument("--finger-radius", type=float,
                   help="drop hypotheses that put a contact where no fingertip of this radius fits")
    p.add_argument("--samples", type=int, default=0, help="posterior samples of the best pose (emcee)")
    p.add_argument("--seed", type=int, help="seed for --samples (repeatable runs)")
    p.add_argument("--top", type=int, help="keep the best K hypotheses")
    p.add_argument("--fix-normals", action="store_true", help="when given a mesh: re-wind faces outward first")
    p.add_argument("-o", "--output", help="write the result as JSON")
    p.set_defaults(func=run)


def run(args):
    """Localize, print the result, optionally write it as JSON; 0 on success."""
    model = model_or_mesh(args.model, fix_normals=args.fix_normals)
    contacts = jsonfiles.read_contacts(args.contacts)
    prior = jsonfiles.read_prior(args.prior) if args.prior else None
    result = localize(model, contacts, position_noise=args.position_noise,
                      normal_noise_deg=args.normal_noise_deg, prior=prior, method=args.method,
                      solver=args.solver, top=args.top, robust=args.robust, max_outliers=args.max_outliers,
                      samples=args.samples, seed=args.seed, finger_radius=args.finger_radius)
    if args.output:
        jsonfiles.write_json(args.output, result.to_dict())
    print_result(result)
    return 0


def print_result(result):
    print(f"status: {result.status}" + (f" ({result.hint})" if result.hint else ""))
    print(f"hypotheses: {result.num_hypotheses}  time: {result.timing['total'] * 1000:.2f} ms")
    if result.best is not None:
        b = result.best
        print(f"best facets: {b.facets.tolist()}  cost: {b.cost:.4g}")
        for row in b.pose:
            print("  " + " ".join(f"{v: .6f}" for v in row))
