"""``contactpose demo`` and ``contactpose bench``."""

from __future__ import annotations

from contactpose.cli.common import add_parser
from contactpose.harness import bench


def register(sub):
    p = add_parser(sub, "demo", help="the paper's banana protocol on the built-in banana",
                   description="Build the banana model, grasp it with four fingers (the paper's §5 protocol), "
                               "localize with both methods and draw the estimate.")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the grasp")
    p.add_argument("--out", default="results/demo", metavar="DIR", help="folder of the picture")
    p.set_defaults(func=run_demo)

    p = add_parser(sub, "bench", help="online and offline timings, fast vs paper",
                   description="Build time and peak memory of each model, then the online stage times over "
                               "random 4-finger grasps, method fast beside paper on the same grasps. Prints the "
                               "table; writes files only with --out or --json.")
    p.add_argument("--models", nargs="+", default=bench.DEFAULT_MODELS, metavar="NAME", help="built-in object names")
    p.add_argument("--runs", type=int, default=25, metavar="N", help="grasps per model")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the grasps")
    p.add_argument("--paper-cap", type=float, default=20.0, metavar="SECONDS",
                   help="stop the paper's method once one grasp takes longer")
    p.add_argument("--out", metavar="DIR",
                   help=f"write {', '.join(bench.OUTPUT_FILES)} into DIR (default: write nothing)")
    p.add_argument("--json", metavar="PATH", help="write the JSON report to PATH (instead of DIR/bench.json)")
    p.set_defaults(func=run_bench)


def run_demo(args):
    from contactpose.harness.demo import run_demo

    return run_demo(seed=args.seed, out_dir=args.out)


def run_bench(args):
    return bench.run_bench(args.models, runs=args.runs, seed=args.seed, paper_cap=args.paper_cap,
                           out_dir=args.out, json_path=args.json)
