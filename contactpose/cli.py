"""Command-line interface: ``contactpose build-model | localize | next-touch | demo | bench | scan``.

Bad input exits with code 2 and one line on stderr (``contactpose: error: ...``);
``--debug`` shows the traceback of internal errors.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
import warnings

from contactpose.errors import ContactPoseError

log = logging.getLogger("contactpose")


def _model_or_mesh(path, bins=None, bounds=None, fix_normals=False, max_span=None):
    """Load a model .npz, or build one from a mesh file (or built-in object name)."""
    from contactpose import objects
    from contactpose.model import ObjectModel

    if str(path).endswith(".npz"):
        return ObjectModel.load(path, bins=bins, bounds=bounds)
    source = objects.load(path) if path in objects.names() and not os.path.exists(path) else path
    kwargs = {k: v for k, v in (("bins", bins), ("bounds", bounds)) if v is not None}
    return ObjectModel.from_mesh(source, fix_normals=fix_normals, max_span=max_span, **kwargs)


def cmd_build_model(args):
    scanned = None
    if getattr(args, "scan_prefix", None) is not None:  # scan options registered: clouds are accepted
        from contactpose import scan

        scanned = scan.scan_if_cloud(args.mesh, args)  # None unless MESH is a point cloud file
    if scanned is not None:
        print(scanned.report.format())
        if args.save_mesh:
            scan.write_mesh(scanned.mesh, args.save_mesh)
            print(f"mesh: {args.save_mesh}")
    start = time.perf_counter()
    if scanned is None:
        model = _model_or_mesh(args.mesh, bins=args.bins, bounds=args.bounds, fix_normals=args.fix_normals,
                               max_span=args.max_span)
    else:
        from contactpose.model import ObjectModel

        kwargs = {k: v for k, v in (("bins", args.bins), ("bounds", args.bounds)) if v is not None}
        model = ObjectModel.from_mesh(scanned.mesh, fix_normals=args.fix_normals, max_span=args.max_span, **kwargs)
    seconds = time.perf_counter() - start
    out = args.output or os.path.splitext(os.path.basename(args.mesh))[0] + ".npz"
    model.save(out)
    d = model.describe()
    print(f"facets: {d['facets']} ({d['degenerate_facets']} degenerate, excluded)")
    print(f"ordered pairs: {d['ordered_pairs']}")
    print(f"build time: {seconds * 1000:.1f} ms (features {model.build_seconds['features'] * 1000:.1f} ms, "
          f"table {model.build_seconds['table'] * 1000:.1f} ms)")
    print(f"file: {out} ({os.path.getsize(out) / 1024:.1f} KiB)")
    return 0


def cmd_localize(args):
    from contactpose import io
    from contactpose.localize import localize

    model = _model_or_mesh(args.model, fix_normals=args.fix_normals)
    contacts = io.read_contacts(args.contacts)
    prior = io.read_prior(args.prior) if args.prior else None
    result = localize(model, contacts, position_noise=args.position_noise,
                      normal_noise_deg=args.normal_noise_deg, prior=prior, method=args.method,
                      solver=args.solver, top=args.top, robust=args.robust, max_outliers=args.max_outliers,
                      samples=args.samples, seed=args.seed, finger_radius=args.finger_radius)
    data = result.to_dict()
    if args.output:
        io.write_json(args.output, data)
    _print_result(result)
    return 0


def _print_result(result):
    print(f"status: {result.status}" + (f" ({result.hint})" if result.hint else ""))
    print(f"hypotheses: {result.num_hypotheses}  time: {result.timing['total'] * 1000:.2f} ms")
    if result.best is not None:
        b = result.best
        print(f"best facets: {b.facets.tolist()}  cost: {b.cost:.4g}")
        for row in b.pose:
            print("  " + " ".join(f"{v: .6f}" for v in row))


def cmd_demo(args):
    from contactpose.demo import run_demo

    return run_demo(seed=args.seed, out_dir=args.out)


def cmd_bench(args):
    from contactpose.bench import run_bench

    return run_bench(args)


def build_parser():
    parser = argparse.ArgumentParser(prog="contactpose", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("build-model", help="build a contact model (.npz) from a mesh or a point cloud")
    p.add_argument("mesh", help="mesh file (STL, OBJ, PLY, OFF, GLB), point cloud file (PLY without faces, "
                                "PCD, XYZ, NPY; meshed first with the scan options) or a built-in object name")
    p.add_argument("-o", "--output", help="output .npz (default: MESH name with .npz)")
    p.add_argument("--bins", nargs=3, type=int, metavar="P", help="bins p_dmax p_dmin p_alpha")
    p.add_argument("--bounds", choices=("exact", "paper"), default="exact")
    p.add_argument("--fix-normals", action="store_true", help="re-wind faces consistently outward (trimesh repair)")
    p.add_argument("--max-span", type=float, help="hand span L: store only facet pairs closer than L (mesh units)")
    p.set_defaults(func=cmd_build_model)
    try:  # Open3D present: a point cloud is meshed first (contactpose scan), with the same options
        from contactpose import scan

        p.add_argument("--save-mesh", metavar="MESH", help="point cloud input: also write the reconstructed mesh")
        scan.add_scan_options(p, prefix="scan-")
    except ImportError as exc:
        log.debug("build-model takes meshes only: %s", exc)

    p = sub.add_parser("localize", help="find contact facets and the object pose")
    p.add_argument("model", help="model .npz, mesh file or built-in object name")
    p.add_argument("--contacts", required=True, help="CONTACTS.json")
    p.add_argument("--prior", help="PRIOR.json")
    p.add_argument("--position-noise", type=float, help="σ of contact points (length units)")
    p.add_argument("--normal-noise-deg", type=float, default=1.0, help="σ of normals (degrees)")
    p.add_argument("--method", choices=("fast", "paper"), default="fast")
    p.add_argument("--solver", choices=("closed-form", "lm", "factor-graph"))
    p.add_argument("--robust", choices=("huber", "cauchy", "none"), default="huber",
                   help="factor graph's robust kernel (with --solver factor-graph)")
    p.add_argument("--max-outliers", type=int, default=0, help="fingers that may be left unassigned")
    p.add_argument("--finger-radius", type=float,
                   help="drop hypotheses that put a contact where no fingertip of this radius fits")
    p.add_argument("--samples", type=int, default=0, help="posterior samples of the best pose (emcee)")
    p.add_argument("--seed", type=int, help="seed for --samples (repeatable runs)")
    p.add_argument("--top", type=int, help="keep the best K hypotheses")
    p.add_argument("--fix-normals", action="store_true", help="when given a mesh: re-wind faces outward first")
    p.add_argument("-o", "--output", help="write the result as JSON")
    p.set_defaults(func=cmd_localize)

    p = sub.add_parser("demo", help="the paper's banana protocol on the built-in banana")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/demo")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("bench", help="online and offline timings, fast vs paper")
    p.add_argument("--json", help="also write the table as JSON")
    p.add_argument("--runs", type=int, default=25)
    p.add_argument("--models", nargs="*", help="built-in object names (default: banana rock1k espresso6767)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--paper-cap", type=float, default=20.0, help="stop the paper's method past this many seconds per grasp")
    p.add_argument("--out", default="results/bench")
    p.set_defaults(func=cmd_bench)

    from contactpose import touch

    touch.register_cli(sub)
    _register_optional(sub)
    return parser


def _register_optional(sub):
    """Subcommands of optional modules (scan), when they are importable."""
    try:
        from contactpose import scan
    except ImportError as exc:  # Open3D missing: the rest of the CLI still works
        log.debug("scan subcommand unavailable: %s", exc)
        return
    scan.register_cli(sub)


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
