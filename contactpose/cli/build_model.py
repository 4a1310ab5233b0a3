"""``contactpose build-model``: a contact model (.npz) from a mesh, a built-in object or a point cloud."""

from __future__ import annotations

import logging
import os
import time

from contactpose.cli.common import add_parser, is_model_file, library_default, model_or_mesh, warn_in_vain
from contactpose.errors import ContactPoseError
from contactpose.model import ObjectModel
from contactpose.model.object_model import BOUNDS
from contactpose.model.table import DEFAULT_BINS

log = logging.getLogger("contactpose")

#: The pair bounds when --bounds is not given (None in the parser: a model file is then not checked).
DEFAULT_BOUNDS = library_default(ObjectModel.from_mesh, "bounds")


def register(sub):
    p = add_parser(sub, "build-model", help="build a contact model (.npz) from a mesh or a point cloud",
                   description="Build the contact model (facet planes, pair table) of a mesh, a built-in object "
                               "or a point cloud, and write it as one .npz file.")
    p.add_argument("mesh", help="mesh file (STL, OBJ, PLY, OFF, GLB), point cloud file (PLY without faces, "
                                "PCD, XYZ, NPY; meshed first with the scan options) or a built-in object name")
    p.add_argument("-o", "--output", metavar="MODEL.npz",
                   help="output .npz (default: the MESH name with .npz, in the current directory)")
    p.add_argument("--bins", nargs=3, type=int, metavar="P",
                   help=f"bins p_dmax p_dmin p_alpha (default: {' '.join(map(str, DEFAULT_BINS))})")
    p.add_argument("--bounds", choices=BOUNDS,
                   help=f"pair bounds: exact, or the paper's vertex-only ones (default: {DEFAULT_BOUNDS})")
    p.add_argument("--fix-normals", action="store_true", help="re-wind faces consistently outward (trimesh repair)")
    p.add_argument("--max-span", type=float, metavar="L",
                   help="hand span L: store only facet pairs closer than L, in mesh units (default: all pairs)")
    p.set_defaults(func=run)
    try:  # Open3D present: a point cloud is meshed first (contactpose scan), with the same options
        from contactpose.cli import scan

        p.add_argument("--save-mesh", metavar="MESH", help="point cloud input: also write the reconstructed mesh")
        scan.add_scan_options(p, prefix="scan-")
    except ImportError as exc:
        log.debug("build-model takes meshes only: %s", exc)


def warn_options_in_vain(args, scanned):
    """One warning for each option given that cannot change the model written."""
    if getattr(args, "save_mesh", None) and scanned is None:
        warn_in_vain("--save-mesh", f"without a point cloud ({args.mesh} is not a point cloud file)")


def run(args):
    """Build, save and describe the model; 0 on success."""
    if is_model_file(args.mesh):
        raise ContactPoseError(f"{args.mesh} is a model file already; build-model takes a mesh, a point cloud "
                               "or a built-in object name")
    scanned = None
    if getattr(args, "scan_prefix", None) is not None:  # scan options registered: clouds are accepted
        from contactpose.cli import scan

        scanned = scan.scan_if_cloud(args.mesh, args)  # None unless MESH is a point cloud file
    if scanned is not None:
        print(scanned.report.format())
        if args.save_mesh:
            scan.write_mesh(scanned.mesh, args.save_mesh)
            print(f"mesh: {args.save_mesh}")
    start = time.perf_counter()
    if scanned is None:
        model = model_or_mesh(args.mesh, bins=args.bins, bounds=args.bounds, fix_normals=args.fix_normals,
                              max_span=args.max_span, cache=False)  # asked to build: built, not read
    else:
        kwargs = {k: v for k, v in (("bins", args.bins), ("bounds", args.bounds)) if v is not None}
        model = ObjectModel.from_mesh(scanned.mesh, fix_normals=args.fix_normals, max_span=args.max_span, **kwargs)
    seconds = time.perf_counter() - start
    warn_options_in_vain(args, scanned)  # after the checks: bad input gets its one error line only
    out = args.output or os.path.splitext(os.path.basename(args.mesh))[0] + ".npz"
    model.save(out)
    d = model.describe()
    print(f"facets: {d['facets']} ({d['degenerate_facets']} degenerate, excluded)")
    print(f"ordered pairs: {d['ordered_pairs']}")
    print(f"build time: {seconds * 1000:.1f} ms (features {model.build_seconds['features'] * 1000:.1f} ms, "
          f"table {model.build_seconds['table'] * 1000:.1f} ms)")
    print(f"file: {out} ({_file_size(os.path.getsize(out))})")
    return 0


def _file_size(nbytes):
    """'812.4 KiB' below 1 MiB, else '54.7 MB'."""
    return f"{nbytes / 1024:.1f} KiB" if nbytes < 2**20 else f"{nbytes / 1e6:.1f} MB"
