"""``contactpose scan CLOUD -o MESH`` and the scan options that ``build-model`` shares."""

from __future__ import annotations

import dataclasses
import warnings

from contactpose.cli.common import add_parser, warn_in_vain
from contactpose.io.jsonfiles import write_json
from contactpose.io.output import scan_report_dict
from contactpose.scan.reconstruct import (
    METHODS,
    NORMAL_MODES,
    ScanOptions,
    ScanResult,
    is_cloud_file,
    scan_to_mesh,
    write_mesh,
)


def add_scan_options(parser, prefix: str = "") -> None:
    """Add the scan pipeline's options to an argparse parser.

    ``prefix`` is put before each flag name (e.g. ``"scan-"`` gives
    ``--scan-faces``) where a command already uses a name; the destinations are
    always ``scan_<name>`` so :func:`options_from_args` reads them either way.
    """
    g = parser.add_argument_group("scan options (defaults scale with the cloud)")
    p = "--" + prefix
    parser.set_defaults(scan_prefix=prefix)

    def add(name, **kw):
        g.add_argument(p + name, dest="scan_" + name.replace("-", "_"), **kw)

    d = ScanOptions()
    add("faces", type=int, metavar="M", help="decimate to M facets (default: keep all)")
    add("crop", type=float, nargs=6, action="append", metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
        help="keep points in this axis-aligned box; repeat to keep several regions (default: keep all)")
    add("method", choices=METHODS, help=f"surface reconstruction (default: {d.method})")
    add("voxel", type=float, metavar="V", help=f"voxel size for downsampling (default: diameter/{1 / d.voxel_rel:g}; 0: off)")
    add("depth", type=int, metavar="D", help="Poisson octree depth (default: cell about one voxel)")
    add("density-quantile", type=float, metavar="Q", help=f"Poisson trimming quantile (default: {d.density_quantile})")
    add("outlier-radius", type=float, metavar="R",
        help=f"radius outlier removal radius (default: {d.outlier_radius_spacings:g} x p90 neighbour spacing)")
    add("outlier-min-neighbors", type=int, metavar="K",
        help=f"neighbours needed within the radius (default: {d.outlier_min_neighbors}; 0: off)")
    add("outlier-std", type=float, metavar="S", help=f"statistical outlier cut in std (default: {d.outlier_std:g}: off)")
    add("outlier-neighbors", type=int, metavar="K",
        help=f"neighbours for statistical outlier removal (default: {d.outlier_neighbors})")
    add("normal-radius", type=float, metavar="R", help="normal estimation radius (default: 3 voxels)")
    add("normals", choices=NORMAL_MODES,
        help=f"normals: estimate, orient by given (auto), or use given (default: {d.normals})")
    add("bpa-radii", type=float, nargs="+", metavar="R", help="ball-pivoting radii (default: spacing x 1, 2, 4)")
    add("min-points", type=int, metavar="N", help=f"fewest points accepted (default: {d.min_points})")


def options_from_args(args) -> ScanOptions:
    """ScanOptions from parsed arguments added by :func:`add_scan_options`."""
    opt = ScanOptions()
    for f in dataclasses.fields(ScanOptions):
        value = getattr(args, "scan_" + f.name, None)
        if value is not None:
            setattr(opt, f.name, value)
    if opt.crop is not None and len(opt.crop) == 1:
        opt.crop = tuple(opt.crop[0])
    return opt


def scan_options_given(args) -> list[str]:
    """Command-line flags of the scan options set in ``args`` (see :func:`add_scan_options`)."""
    prefix = "--" + getattr(args, "scan_prefix", "")
    return [prefix + f.name.replace("_", "-") for f in dataclasses.fields(ScanOptions)
            if getattr(args, "scan_" + f.name, None) is not None]


def warn_scan_options_in_vain(args, opt: ScanOptions) -> None:
    """One warning for each scan option given that the other options switch off."""
    flag = lambda name: "--" + getattr(args, "scan_prefix", "") + name
    off = []
    if opt.method != "bpa":
        off.append(("bpa-radii", f"without {flag('method')} bpa"))
    else:
        off += [(name, f"with {flag('method')} bpa (Poisson only)") for name in ("depth", "density-quantile")]
    if not opt.outlier_std > 0:
        off.append(("outlier-neighbors", f"without {flag('outlier-std')} above 0"))
    if opt.outlier_min_neighbors == 0:
        off.append(("outlier-radius", f"with {flag('outlier-min-neighbors')} 0"))
    for name, reason in off:
        if getattr(args, "scan_" + name.replace("-", "_"), None) is not None:
            warn_in_vain(flag(name), reason)


def scan_cloud(path, args) -> ScanResult:
    """:func:`scan_to_mesh` of ``path`` with the scan options in ``args``, warning about those in vain."""
    opt = options_from_args(args)
    result = scan_to_mesh(path, opt)
    warn_scan_options_in_vain(args, opt)  # after the checks: bad input gets its one error line only
    return result


def scan_if_cloud(path, args) -> ScanResult | None:
    """Reconstruct ``path`` with the scan options in ``args`` when it is a cloud file.

    For commands that take a mesh or a cloud (``build-model``): returns the
    :class:`ScanResult` of :func:`scan_to_mesh` for a cloud file, and None for
    anything else (mesh files, built-in object names, model files), warning
    when scan options were given with a mesh.
    """
    if is_cloud_file(path):
        return scan_cloud(path, args)
    given = scan_options_given(args)
    if given:
        warnings.warn(f"{path} is not a point cloud file; ignoring {', '.join(given)}", stacklevel=2)
    return None


def register(subparsers) -> None:
    """Add ``scan CLOUD -o MESH [options]``; its handler is :func:`run`."""
    p = add_parser(
        subparsers, "scan", help="mesh a point cloud (PLY, PCD, XYZ, NPY) for build-model",
        description="Point cloud -> cleaned, outward-wound triangle mesh, with a distance report.")
    p.add_argument("cloud", metavar="CLOUD", help="point cloud file: .ply .pcd .xyz or .npy (n,3)/(n,6)")
    p.add_argument("-o", "--output", required=True, metavar="MESH", help="mesh file to write (.ply .stl .obj .off)")
    p.add_argument("--report-json", metavar="PATH", help="also write the distance report as JSON")
    add_scan_options(p)
    p.set_defaults(func=run)


def run(args) -> int:
    """Run the scan subcommand: mesh, write, print the report; 0 on success."""
    result = scan_cloud(args.cloud, args)
    write_mesh(result.mesh, args.output)
    if getattr(args, "report_json", None):
        write_json(args.report_json, scan_report_dict(result.report))
    print(result.report.format())
    print(f"wrote {args.output}")
    return 0
