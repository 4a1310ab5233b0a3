"""``contactpose demo`` and ``contactpose bench``."""

from __future__ import annotations


def register(sub):
    p = sub.add_parser("demo", help="the paper's banana protocol on the built-in banana")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/demo")
    p.set_defaults(func=run_demo)

    p = sub.add_parser("bench", help="online and offline timings, fast vs paper")
    p.add_argument("--json", help="also write the table as JSON")
    p.add_argument("--runs", type=int, default=25)
    p.add_argument("--models", nargs="*", help="built-in object names (default: banana rock1k espresso6767)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--paper-cap", type=float, default=20.0, help="stop the paper's method past this many seconds per grasp")
    p.add_argument("--out", default="results/bench")
    p.set_defaults(func=run_bench)


def run_demo(args):
    from contactpose.demo import run_demo

    return run_demo(seed=args.seed, out_dir=args.out)


def run_bench(args):
    from contactpose.bench import run_bench

    return run_bench(args)
