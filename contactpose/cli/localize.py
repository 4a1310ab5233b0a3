"""``contactpose localize``: contact facets and the object pose from CONTACTS.json."""

from __future__ import annotations

import argparse

from contactpose import view
from contactpose.cli.common import (
    EXIT_OK,
    EXIT_STRICT,
    add_noise_options,
    add_parser,
    is_model_file,
    library_default,
    model_or_mesh,
    warn_in_vain,
)
from contactpose.io import jsonfiles
from contactpose.localize import DEFAULT_TIME_LIMIT, SEARCHES, localize
from contactpose.options import KEEP, METHODS, OK_PROBABILITY, OUTLIER_PENALTY, ROBUST, SOLVERS, fit_threshold
from contactpose.scoring.status import DIAGNOSED
from contactpose.stages import POOR_FIT_LISTED

#: The robust kernel when --robust is not given (None in the parser, to tell a given value).
DEFAULT_ROBUST = library_default(localize, "robust")
#: Hypotheses the factor graph refines when --refine is not given (0: all).
DEFAULT_REFINE = library_default(localize, "refine")
#: What a hypothesis's printed ``cost`` is, by method and solver (``chi2`` is always the whitened fit).
COST_MEANING = {
    ("fast", "closed-form"): "the ranking cost, here chi2 itself",
    ("fast", "lm"): "the ranking cost, here chi2 itself",
    ("fast", "factor-graph"): "the ranking cost, here -log Laplace evidence of the refined pose (unitless)",
    ("paper", "closed-form"): "the ranking cost, here eq. (7)'s L, unweighted (normal terms unitless, offsets in "
                              "squared length units)",
    ("paper", "lm"): "the ranking cost, here eq. (7)'s L, unweighted (normal terms unitless, offsets in squared "
                     "length units)",
}


def register(sub):
    p = add_parser(sub, "localize", help="find contact facets and the object pose",
                   description="Find every admissible finger-to-facet assignment and the object pose behind each.")
    p.add_argument("model", help="model .npz, mesh file or built-in object name")
    p.add_argument("--contacts", required=True, metavar="CONTACTS.json", help="a point and a normal per finger")
    p.add_argument("--prior", metavar="PRIOR.json", help="pose prior: LM's start, a prior factor with the factor graph")
    add_noise_options(p)
    p.add_argument("--method", choices=METHODS, default="fast",
                   help="fast: exact pair bounds, patches, closed form; paper: the published method")
    p.add_argument("--solver", choices=SOLVERS,
                   help="pose solver (default: closed-form with --method fast, lm with paper); factor-graph refines "
                        "the best hypotheses and gives covariances")
    p.add_argument("--robust", choices=ROBUST,
                   help=f"robust kernel of --solver factor-graph and of --samples (default: {DEFAULT_ROBUST})")
    p.add_argument("--refine", type=int, metavar="K",
                   help=f"with --solver factor-graph: refine the best K hypotheses (default: {DEFAULT_REFINE}; 0: all)")
    p.add_argument("--max-outliers", type=int, default=0, metavar="Q", help="fingers that may be left unassigned")
    p.add_argument("--model-error", type=float, default=0.0, metavar="L",
                   help="extra pair distance tolerance, in mesh units, for a model that differs from the object "
                        "(a scan, say)")
    p.add_argument("--finger-radius", type=float, metavar="R",
                   help="drop hypotheses that put a contact where no fingertip of this radius fits (default: off)")
    p.add_argument("--surface", action=argparse.BooleanOptionalAction, default=None,
                   help="pose the best hypotheses on the surface contact model: contacts may lie on edges and "
                        "vertices, their normals in those features' normal cones (method fast, closed form; "
                        "default: on a model of surface regions, off on a facet table)")
    p.add_argument("--samples", type=int, default=0, metavar="N", help="posterior samples of the best pose (emcee)")
    p.add_argument("--seed", type=int, metavar="S", help="seed for --samples (default: a fresh one each run)")
    p.add_argument("--top", type=int, metavar="K", help="write only the best K hypotheses with -o (default: all)")
    p.add_argument("--keep", choices=KEEP, default="fitting",
                   help="hypotheses to list: fitting (the best and those that fit within noise; the best "
                        f"{POOR_FIT_LISTED} when none fits) or all distinct poses")
    p.add_argument("--twins", action="store_true",
                   help="on a symmetric object, list every symmetric twin of a placement (default: the best one, "
                        "unless a prior is given)")
    p.add_argument("--fix-normals", action="store_true", help="with a mesh: re-wind its faces outward first")
    p.add_argument("--time-limit", type=float, default=DEFAULT_TIME_LIMIT, metavar="SEC",
                   help="seconds the search may take; past them the hypotheses found so far come back with "
                        "status time_limit (0: no limit)")
    p.add_argument("--ok-probability", type=float, default=OK_PROBABILITY, metavar="P",
                   help="status ok needs the best pose strictly right (within 5 degrees and 5 %% of the diameter, "
                        f"modulo symmetry) with at least this probability (default: {OK_PROBABILITY:g})")
    p.add_argument("--search", choices=SEARCHES, default="auto",
                   help="the default method's search: auto (the model's facet table or surface regions) or samples "
                        "(hypothesize and verify over oriented surface samples; not yet the default)")
    p.add_argument("--strict", action="store_true",
                   help=f"exit with code {EXIT_STRICT} when the answer is empty or poor (status "
                        f"{' or '.join(DIAGNOSED)}; the hint and the JSON's diagnosis name the cause)")
    p.add_argument("-o", "--output", metavar="OUT.json", help="write the result as JSON")
    p.add_argument("--html", metavar="PAGE.html",
                   help="write a 3D page of the answer that opens offline in a browser: the object at the best "
                        "placement, the contacts and their normals, the fingertips (with --finger-radius), the other "
                        "placements (toggled in its legend) and the directions a pose family leaves free")
    p.set_defaults(func=run)


def warn_options_in_vain(args):
    """One warning for each option given that cannot change the result or the output."""
    if args.seed is not None and not args.samples:
        warn_in_vain("--seed", "without --samples")
    if args.robust is not None and args.solver != "factor-graph" and not args.samples:
        warn_in_vain("--robust", "without --solver factor-graph or --samples")
    if args.refine is not None and args.solver != "factor-graph":
        warn_in_vain("--refine", "without --solver factor-graph")
    if args.surface is not None and (args.method == "paper" or args.solver not in (None, "closed-form")):
        warn_in_vain("--surface", "with --method paper or --solver lm|factor-graph (closed form only)")
    if args.keep != "fitting" and not args.output:
        warn_in_vain("--keep", "without -o (the printed result shows the best hypothesis only)")
    if args.keep != "fitting" and args.method == "paper":
        warn_in_vain("--keep", "with --method paper (it lists every hypothesis)")
    if args.twins and not args.output:
        warn_in_vain("--twins", "without -o (the printed result shows the best hypothesis only)")
    if args.top is not None and not args.output:
        warn_in_vain("--top", "without -o (the printed result shows the best hypothesis only)")
    if args.ok_probability != OK_PROBABILITY and args.method == "paper":
        warn_in_vain("--ok-probability", "with --method paper (its status keeps the paper's rule)")
    if args.fix_normals and is_model_file(args.model):
        warn_in_vain("--fix-normals", f"with a model file ({args.model}): it applies when building from a mesh")


def run(args):
    """Localize, print the result, optionally write it as JSON and as a 3D page; 0 on success
    (3 with --strict and an empty or poor answer)."""
    if args.html:
        view.check_page_path(args.html)  # before the model is built
    model = model_or_mesh(args.model, fix_normals=args.fix_normals)
    contacts = jsonfiles.read_contacts(args.contacts)
    prior = jsonfiles.read_prior(args.prior) if args.prior else None
    result = localize(model, contacts, position_noise=args.position_noise,
                      normal_noise_deg=args.normal_noise_deg, prior=prior, method=args.method,
                      solver=args.solver, top=args.top, robust=args.robust or DEFAULT_ROBUST,
                      max_outliers=args.max_outliers, samples=args.samples, seed=args.seed,
                      finger_radius=args.finger_radius, time_limit=args.time_limit or None,
                      surface="auto" if args.surface is None else args.surface, keep=args.keep, model_error=args.model_error,
                      twins=args.twins, ok_probability=args.ok_probability, search=args.search,
                      refine=DEFAULT_REFINE if args.refine is None else args.refine)
    warn_options_in_vain(args)  # after the checks: bad input gets its one error line only
    if args.output:
        jsonfiles.write_json(args.output, result.to_dict())
    if args.html:
        result.to_html(args.html, finger_radius=args.finger_radius)
    print_result(result, contacts.n)
    return EXIT_STRICT if args.strict and result.status in DIAGNOSED else EXIT_OK


def print_result(result, n):
    """The answer in a few lines, every number with its unit. n : the number of contacts."""
    print(f"status: {result.status}" + (f" ({result.hint})" if result.hint else ""))
    if result.diagnosis is not None:
        print(f"cause: {result.diagnosis.cause}")
    took = f"  diagnosis: {result.timing['diagnose'] * 1000:.2f} ms" if "diagnose" in result.timing else ""
    print(f"hypotheses: {result.num_hypotheses}  time: {result.timing['total'] * 1000:.2f} ms{took}")
    if result.confidence is not None and result.placements:
        print(f"confidence: {result.confidence:.3f} that the best pose is strictly right (within 5 degrees and 5 % of "
              f"the diameter); distinct placements: {len(result.placements)}")
    if result.best is None:
        return
    b = result.best
    print(f"best facets: {b.facets.tolist()}" + (f"  outliers: {b.outliers.tolist()}" if len(b.outliers) else ""))
    print(f"  chi2: {b.chi2:.4g}  cost: {b.cost:.4g}")
    outliers = f", plus {OUTLIER_PENALTY:g} per unassigned finger" if len(b.outliers) else ""
    print(f"  (chi2: the contacts' squared residuals over the stated noise, unitless{outliers}; it fits within "
          f"noise up to {fit_threshold(n):.3g}. cost: {COST_MEANING[result.method, result.solver]})")
    print("  pose T_world_object (rotation | translation in mesh units):")
    for row in b.pose:
        print("  " + " ".join(f"{v: .6f}" for v in row))
