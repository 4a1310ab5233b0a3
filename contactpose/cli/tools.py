"""``contactpose demo`` and ``contactpose bench``."""

from __future__ import annotations

from contactpose.cli.common import add_parser


def register(sub):
    p = add_parser(sub, "demo", help="the paper's banana protocol on the built-in banana",
                   description="Build the banana model, grasp it with four fingers (the paper's §5 protocol), "
                               "localize with both methods and draw the estimate.")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the grasp")
    p.add_argument("--out", default="results/demo", metavar="DIR", help="folder of the picture")
    p.set_defaults(func=run_demo)

    p = add_parser(sub, "bench", help="online and offline timings, fast vs paper")
    p.add_argument("--json", help="also write the table as JSON")
    p.add_argument("--runs", type=int, default=25, metavar="N", help="grasps per model")
    p.add_argument("--models", nargs="*", help="built-in object names (default: banana rock1k espresso6767)")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the grasps")
    p.add_argument("--paper-cap", type=float, default=20.0, help="stop the paper's method past this many seconds per grasp")
    p.add_argument("--out", default="results/bench", metavar="DIR", help="folder of bench.json")
    p.set_defaults(func=run_bench)


def run_demo(args):
    from contactpose.demo import run_demo

    return run_demo(seed=args.seed, out_dir=args.out)


def run_bench(args):
    from contactpose.bench import run_bench

    return run_bench(args)
