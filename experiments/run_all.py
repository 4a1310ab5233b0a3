"""Regenerate every experiment: `make results` (full size) or `make results-quick`.

Runs, in order, paper_banana, noise_sweep, bin_sweep, fingers_sweep, scaling and baselines
(each its own script's ``main``), afresh unless ``--resume`` is given, and says the expected
time before starting: the durations of the last run of the same size (``run_all.json``
beside the results), else the estimates below (measured on the 2-core development machine).

Full results go to results/<name>/ (committed); quick ones to results/_scratch/quick/<name>/
(not committed), unless ``--out`` says otherwise.

    .venv/bin/python experiments/run_all.py [--quick] [--resume] [--only NAME ...] [--workers N]
        [--scheduler tcp://HOST:PORT] [--out DIR]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: Experiment scripts in run order, with estimated minutes (full, quick) on 2 shared cores.
EXPERIMENTS = {
    "paper_banana": (1.0, 0.4),
    "noise_sweep": (7.0, 0.5),
    "bin_sweep": (3.5, 0.3),
    "fingers_sweep": (2.5, 0.4),
    "scaling": (8.0, 0.5),
    "baselines": (9.0, 0.6),
    "realistic_contacts": (450.0, 9.0),
}


def load(name):
    """Import experiments/<name>.py as module ``experiment_<name>`` (so Dask sends its task by value)."""
    module_name = f"experiment_{name}"
    if module_name in sys.modules:
        return sys.modules[module_name]
    spec = importlib.util.spec_from_file_location(module_name, HERE / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    spec.loader.exec_module(module)
    return module


def record_path(args):
    root = Path(args.out) if args.out else HERE.parent / "results" / ("_scratch/quick" if args.quick else "")
    return root / "run_all.json"


def expected_minutes(names, args):
    """{name: minutes} from the last run of the same size, else the built-in estimates."""
    last = {}
    path = record_path(args)
    if path.exists():
        last = json.loads(path.read_text()).get("minutes", {})
    return {n: last.get(n, EXPERIMENTS[n][1 if args.quick else 0]) for n in names}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="the small versions (about 3 minutes in all)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted run instead of starting afresh")
    parser.add_argument("--only", nargs="+", choices=list(EXPERIMENTS), help="run only these experiments")
    parser.add_argument("--workers", type=int, default=None, help="worker processes (default: each experiment's own)")
    parser.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler, tcp://HOST:PORT")
    parser.add_argument("--out", default=None, help="results root (default: results/ or results/_scratch/quick/)")
    args = parser.parse_args(argv)
    names = args.only or list(EXPERIMENTS)
    expected = expected_minutes(names, args)
    size = "quick" if args.quick else "full"
    print(f"run_all ({size}): {', '.join(names)}", flush=True)
    print(f"expected time: about {sum(expected.values()):.0f} min "
          f"({', '.join(f'{n} {m:.1f}' for n, m in expected.items())})", flush=True)
    common = (["--quick"] if args.quick else []) + ([] if args.resume else ["--fresh"])
    common += [] if args.workers is None else ["--workers", str(args.workers)]
    common += [] if args.scheduler is None else ["--scheduler", args.scheduler]
    common += [] if args.out is None else ["--out", args.out]
    minutes = {}
    start = time.perf_counter()
    for name in names:
        print(f"\n=== {name} (expected {expected[name]:.1f} min) ===", flush=True)
        t = time.perf_counter()
        load(name).main(common)
        minutes[name] = round((time.perf_counter() - t) / 60, 2)
        print(f"=== {name}: {minutes[name]:.1f} min ===", flush=True)
    total = (time.perf_counter() - start) / 60
    print(f"\nrun_all ({size}) done in {total:.1f} min: " + ", ".join(f"{n} {m:.1f}" for n, m in minutes.items()))
    path = record_path(args)
    path.parent.mkdir(parents=True, exist_ok=True)
    previous = json.loads(path.read_text()).get("minutes", {}) if path.exists() else {}
    path.write_text(json.dumps({"size": size, "minutes": {**previous, **minutes}, "total_minutes": round(total, 2)},
                               indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
