"""The realistic-contacts benchmark before and after, side by side: two result folders of
experiments/realistic_contacts.py (each with its timings.csv) on the same protocol, as one
table per radius (all objects) and per object, the default method. Writes
AFTER/before_after.md and prints it::

    .venv/bin/python experiments/before_after.py results/realistic_contacts_before results/realistic_contacts
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from contactpose.harness import sweep

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run_all  # noqa: E402

rc = run_all.load("realistic_contacts")

#: (heading, summary.csv column, scale, format) of the per-object table.
COLUMNS = (("found %", "found", 100, ".0f"), ("top-1 ADD-S %", "top1_adds", 100, ".0f"),
           ("no-hyp %", "no_hypothesis", 100, ".0f"), ("rot med (°)", "rot_err_deg_median", 1, ".2f"),
           ("trans med (mm)", "trans_err_mm_median", 1, ".2f"), ("listed med", "returned_median", 1, ".0f"),
           ("online med (ms)", "online_ms_median", 1, ".0f"), ("online p95 (ms)", "online_ms_p95", 1, ".0f"))


def rows_of(folder):
    """summary rows (realistic_contacts.summarize) of a result folder's timings.csv."""
    return rc.summarize(sweep.read_columns(Path(folder) / "timings.csv"))


def pair(a, b, scale, spec):
    return f"{rc.fmt(a, spec, scale)} → {rc.fmt(b, spec, scale)}"


def by_radius(before, after):
    """Lines of the all-objects table: found, top-1, face-only and edge/vertex top-1, no-hyp count."""
    lines = ["| r (% diam.) | grasps | found % | top-1 ADD-S % | face-only top-1 % | edge/vertex top-1 % | "
             "no hypothesis |", "|---:|---:|---|---|---|---|---|"]
    for frac in sorted({float(r["radius_frac"]) for r in after}):
        b, a = rc.pooled(before, frac, "fast"), rc.pooled(after, frac, "fast")
        lines.append(f"| {100 * frac:g} | {b['all']['n']} / {a['all']['n']} | "
                     + " | ".join(pair(b[s][k], a[s][k], 100, ".1f") for s, k in
                                  (("all", "found"), ("all", "top1_adds"), ("face-only", "top1_adds"),
                                   ("edge/vertex", "top1_adds")))
                     + f" | {b['status']['no_hypothesis']} → {a['status']['no_hypothesis']} |")
    return lines


def by_object(before, after):
    key = (lambda r: (r["object"], float(r["radius_frac"])))
    old = {key(r): r for r in before if r["method"] == "fast" and r["split"] == "all"}
    lines = ["| object | r (% diam.) | " + " | ".join(h for h, *_ in COLUMNS) + " |",
             "|---|---:|" + "---|" * len(COLUMNS)]
    for r in after:
        if r["method"] != "fast" or r["split"] != "all" or key(r) not in old:
            continue
        b = old[key(r)]
        lines.append(f"| {rc.short(r['object'])} | {100 * float(r['radius_frac']):g} | "
                     + " | ".join(pair(_num(b[c]), _num(r[c]), s, f) for _, c, s, f in COLUMNS) + " |")
    return lines


def _num(v):
    return np.nan if v in ("", None) else float(v)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("before")
    parser.add_argument("after")
    args = parser.parse_args(argv)
    before, after = rows_of(args.before), rows_of(args.after)
    text = "\n".join([f"# Realistic contacts: before ({args.before}) → after ({args.after})", "",
                      "Default method, the same protocol and seeds. found and top-1 as in summary.md; listed: "
                      "hypotheses returned (median).", "", "## All objects", "", *by_radius(before, after), "",
                      "## Per object", "", *by_object(before, after)]) + "\n"
    (Path(args.after) / "before_after.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
