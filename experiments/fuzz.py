"""Long fuzzing and property run: count inputs and uncaught exceptions.

Runs tests/test_fuzz.py and tests/test_properties.py under pytest with large example
counts (``CONTACTPOSE_FUZZ_EXAMPLES`` per fuzz test, ``CONTACTPOSE_PROPERTY_EXAMPLES``
per property); the test modules append what each test actually ran to a JSON-lines log
(``CONTACTPOSE_FUZZ_LOG``): outcome counts per fuzz test ("result", "ContactPoseError:...",
"known:..." for exceptions of a listed library bug, "uncaught:..."), and cases per property.

Writes results/fuzz/:

* ``summary.json``: fuzzed inputs, uncaught exceptions (known bugs and new), cases per
  property, test outcomes and failures, run time;
* ``outcomes.csv``: one row per (test, outcome) with its count; ``outcomes.png`` drawn from it;
* ``config.json``: the settings; ``pytest.log``: pytest's output (falsifying examples).

::

    .venv/bin/python experiments/fuzz.py                  # 1,000 inputs per fuzz test, 1,000 cases per property
    .venv/bin/python experiments/fuzz.py --quick          # 50 and 10: smoke run, about a minute
    .venv/bin/python experiments/fuzz.py --plot-only      # redraw outcomes.png from outcomes.csv
"""

from __future__ import annotations

import argparse
import collections
import csv
import json
import os
import platform
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEST_FILES = ("tests/test_fuzz.py", "tests/test_properties.py")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fuzz-examples", type=int, default=1000, help="inputs per fuzz test (13 tests)")
    p.add_argument("--property-examples", type=int, default=1000, help="cases per property (5 properties)")
    p.add_argument("--quick", action="store_true", help="50 inputs per fuzz test, 10 cases per property")
    p.add_argument("--out", default=str(ROOT / "results" / "fuzz"))
    p.add_argument("--plot-only", action="store_true", help="only redraw outcomes.png from outcomes.csv")
    args = p.parse_args(argv)
    if args.quick:
        args.fuzz_examples, args.property_examples = 50, 10
    return args


def run_pytest(args, out):
    """Run the two test files with the example counts; returns (exit code, seconds)."""
    log = out / "outcomes.jsonl"
    log.unlink(missing_ok=True)
    env = dict(os.environ, CONTACTPOSE_FUZZ_EXAMPLES=str(args.fuzz_examples),
               CONTACTPOSE_PROPERTY_EXAMPLES=str(args.property_examples), CONTACTPOSE_FUZZ_LOG=str(log))
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rxXf", "--durations=0",
           f"--junitxml={out / 'junit.xml'}", *TEST_FILES]
    start = time.perf_counter()
    with open(out / "pytest.log", "w", encoding="utf-8") as fh:
        code = subprocess.call(cmd, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT)
    return code, time.perf_counter() - start


def read_log(path):
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    fuzz = {r["test"]: collections.Counter(r["outcomes"]) for r in rows if r["module"] == "test_fuzz"}
    props = {r["test"]: r["cases"] for r in rows if r["module"] == "test_properties"}
    return fuzz, props


def read_junit(path):
    """{test name: {"outcome", "seconds", "message"}} from pytest's junit xml."""
    tests = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        outcome, message = "passed", ""
        for child in case:
            if child.tag in ("failure", "error"):
                outcome, message = "failed", (child.get("message") or "")[:500]
            elif child.tag == "skipped":
                kind = child.get("type", "")
                outcome = "xfailed" if "xfail" in kind else "skipped"
                message = (child.get("message") or "")[:200]
        tests[f"{case.get('classname').split('.')[-1]}::{case.get('name')}"] = {
            "outcome": outcome, "seconds": round(float(case.get("time", 0)), 2), "message": message}
    return tests


def summarise(fuzz, props, tests, code, seconds, args):
    by_class = collections.Counter()
    for counts in fuzz.values():
        for outcome, n in counts.items():
            by_class[outcome.split(":")[0] if outcome.startswith("ContactPoseError") else outcome] += n
    known = {k: n for k, n in by_class.items() if k.startswith("known:")}
    new = {k: n for k, n in by_class.items() if k.startswith("uncaught:")}
    failures = {name: t["message"] for name, t in tests.items() if t["outcome"] == "failed"}
    return {
        "command": "python experiments/fuzz.py" + (" --quick" if args.quick else
                                                   f" --fuzz-examples {args.fuzz_examples} "
                                                   f"--property-examples {args.property_examples}"),
        "pytest_exit_code": code,
        "seconds": round(seconds, 1),
        "fuzz": {
            "inputs": sum(sum(c.values()) for c in fuzz.values()),
            "results": by_class.get("result", 0),
            "contactpose_errors": by_class.get("ContactPoseError", 0),
            "uncaught_exceptions": sum(known.values()) + sum(new.values()),
            "uncaught_known_bugs": known,
            "uncaught_new": new,
            "per_test": {name: dict(c) for name, c in sorted(fuzz.items())},
        },
        "properties": {name: {"cases": n, "outcome": tests.get(f"test_properties::{name}", {}).get("outcome")}
                       for name, n in sorted(props.items())},
        "property_failures": sum(1 for k, t in tests.items() if k.startswith("test_properties")
                                 and t["outcome"] == "failed"),
        "tests": tests,
        "failures": failures,
    }


def write_csv(fuzz, path):
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["test", "outcome", "count"])
        for name, counts in sorted(fuzz.items()):
            for outcome, n in sorted(counts.items()):
                w.writerow([name, outcome, n])


def plot(csv_path, png_path):
    """Stacked bars of outcomes per fuzz test, from outcomes.csv alone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(open(csv_path, encoding="utf-8")))
    tests = sorted({r["test"] for r in rows})
    kinds = sorted({r["outcome"] for r in rows}, key=lambda k: (k != "result", k))
    counts = {(r["test"], r["outcome"]): int(r["count"]) for r in rows}
    fig, ax = plt.subplots(figsize=(12, 0.45 * len(tests) + 1.5))
    colours = plt.get_cmap("tab20").colors
    left = [0] * len(tests)
    for i, kind in enumerate(kinds):
        widths = [counts.get((t, kind), 0) for t in tests]
        ax.barh(tests, widths, left=left, label=kind, color=colours[i % len(colours)])
        left = [a + b for a, b in zip(left, widths)]
    ax.set_xlabel("fuzzed inputs")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title("fuzzing outcomes per target (known:/uncaught: are uncaught exceptions)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png_path, dpi=120)
    plt.close(fig)


def main(argv=None):
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.plot_only:
        plot(out / "outcomes.csv", out / "outcomes.png")
        return 0
    config = {"fuzz_examples_per_test": args.fuzz_examples, "property_examples": args.property_examples,
              "test_files": list(TEST_FILES), "python": platform.python_version(), "cores": os.cpu_count()}
    (out / "config.json").write_text(json.dumps(config, indent=1) + "\n")
    code, seconds = run_pytest(args, out)
    fuzz, props = read_log(out / "outcomes.jsonl")
    tests = read_junit(out / "junit.xml")
    summary = summarise(fuzz, props, tests, code, seconds, args)
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    write_csv(fuzz, out / "outcomes.csv")
    plot(out / "outcomes.csv", out / "outcomes.png")
    f = summary["fuzz"]
    print(f"fuzzed inputs: {f['inputs']}  results: {f['results']}  ContactPoseError: {f['contactpose_errors']}  "
          f"uncaught: {f['uncaught_exceptions']} (known bugs {sum(f['uncaught_known_bugs'].values())}, "
          f"new {sum(f['uncaught_new'].values())})")
    for name, p in summary["properties"].items():
        print(f"property {name}: {p['cases']} cases, {p['outcome']}")
    print(f"failed tests: {len(summary['failures'])}  pytest exit {code}  {seconds:.0f} s  -> {out / 'summary.json'}")
    return 0 if not summary["failures"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
