"""How sure the default method is when it says ok: the reliability of its confidence, from
the rows of an experiments/realistic_contacts.py run.

Reads ``grasps.csv`` (the default method's rows with the columns ``confidence``,
``strict_sym``, ``truth_listed`` and ``status``) and the committed run's rows on the same
grasps (results/realistic_contacts/grasps.csv, the statuses before "ok" needed a confidence),
and writes beside the given rows:

* ``reliability.csv``: per radius (and pooled), the answers binned by confidence (tenths):
  count, mean confidence, share strictly right modulo symmetry;
* ``sure.csv``: per object and radius (and pooled per radius): grasps, ok share and the ok
  answers strictly right; ambiguous answers that list the truth; the expected calibration
  error, beside the one a perfectly calibrated confidence would show on the same answers
  (mean and 95th percentile: the binning's own noise); the share of grasps where the truth
  would hold at least the ok threshold of the evidence had the search found it at its own
  floor (``ok_reachable``, from the ``truth_share`` column: what a calibrated ok can reach);
  and, on the same grasps before, the ok share, its strict share and the strict share of all
  answers;
* ``placements.csv`` (from runs with the ``placement_*`` columns): every weighed placement's
  probability binned, against whether it is strictly right;
* ``sure.md``: all as tables.

    python experiments/sure_summary.py results/sure/grasps.csv
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from contactpose.harness import sweep
from contactpose.options import OK_PROBABILITY

ROOT = Path(__file__).resolve().parents[1]
BEFORE = ROOT / "results" / "realistic_contacts" / "grasps.csv"
BINS = np.linspace(0.0, 1.0, 11)
#: Draws of outcomes for the ECE of a perfectly calibrated confidence (:func:`calibrated_ece`).
CALIBRATED_DRAWS = 400


def rows_of(path):
    return [r for r in sweep.read_rows(path) if r["method"] == "fast"]


def flag(r, key):
    return r.get(key, "") in ("1", "True", "true")


def confidence(r):
    return float(r["confidence"]) if r.get("confidence", "") not in ("", "None") else 0.0


def reliability(rows):
    """[(bin low, count, mean confidence, share strictly right)] and the expected calibration error."""
    conf = np.array([confidence(r) for r in rows])
    right = np.array([flag(r, "strict_sym") for r in rows], dtype=float)
    return binned(conf, right)


def binned(conf, right):
    """:func:`reliability` of confidences (N,) and outcomes (N,) 0/1."""
    table, ece = [], 0.0
    for k, (lo, hi) in enumerate(zip(BINS[:-1], BINS[1:])):
        m = (conf >= lo) & ((conf < hi) if k < len(BINS) - 2 else (conf <= hi))
        if m.any():
            table.append((lo, int(m.sum()), float(conf[m].mean()), float(right[m].mean())))
            ece += m.sum() / len(conf) * abs(conf[m].mean() - right[m].mean())
    return table, float(ece)


def calibrated_ece(conf, rng, draws=CALIBRATED_DRAWS):
    """(mean, 95th percentile) of the ECE a perfectly calibrated confidence would show on these
    answers (N,): each answer right with its own confidence, ``draws`` times. With a few hundred
    answers the binning alone gives an ECE of about 0.05, so a measured ECE is judged against
    this, not against 0."""
    conf = np.asarray(conf, dtype=float)
    eces = [binned(conf, (rng.random(len(conf)) < conf).astype(float))[1] for _ in range(draws)]
    return float(np.mean(eces)), float(np.quantile(eces, 0.95))


def share(rows, test):
    return float(np.mean([test(r) for r in rows])) if rows else float("nan")


def cell(rows, before):
    """The sure.csv columns of one set of grasps and the same grasps' rows before."""
    ok = [r for r in rows if r["status"] == "ok"]
    amb = [r for r in rows if r["status"] == "ambiguous"]
    return {"grasps": len(rows), "ok": share(rows, lambda r: r["status"] == "ok"),
            "ok_strict": share(ok, lambda r: flag(r, "strict_sym")), "ok_n": len(ok),
            "ambiguous_n": len(amb), "ambiguous_truth_listed": share(amb, lambda r: flag(r, "truth_listed")),
            "ece": reliability(rows)[1], "strict": share(rows, lambda r: flag(r, "strict_sym")),
            **dict(zip(("ece_calibrated", "ece_calibrated_95"),
                       calibrated_ece([confidence(r) for r in rows], np.random.default_rng(0)) if rows
                       else (float("nan"), float("nan")))),
            "ok_reachable": share(rows, lambda r: float(r.get("truth_share") or "nan") >= OK_PROBABILITY)
            if rows and rows[0].get("truth_share") else float("nan"),
            "before_ok": share(before, lambda r: r["status"] == "ok"),
            "before_ok_strict": share([r for r in before if r["status"] == "ok"], lambda r: flag(r, "top1_strict")),
            "before_strict": share(before, lambda r: flag(r, "top1_strict"))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("grasps", help="grasps.csv of a realistic_contacts run with the confidence columns")
    args = parser.parse_args(argv)
    rows = rows_of(args.grasps)
    seen = {(r["object"], r["radius_frac"], r["seed"]) for r in rows}
    before = [r for r in rows_of(BEFORE) if (r["object"], r["radius_frac"], r["seed"]) in seen]
    radii = sorted({r["radius_frac"] for r in rows}, key=float)
    out = Path(args.grasps).parent
    sure = []
    for obj in sorted({r["object"] for r in rows}) + ["pooled"]:
        for rad in radii:
            pick = (lambda rs: [r for r in rs if r["radius_frac"] == rad and obj in ("pooled", r["object"])])
            sure.append({"object": obj, "radius_frac": rad, **cell(pick(rows), pick(before))})
    sweep.write_rows(out / "sure.csv", sure)
    rel = [{"radius_frac": rad, "bin": f"{lo:.1f}", "count": n, "confidence": c, "strict": s}
           for rad in radii + ["all"]
           for lo, n, c, s in reliability([r for r in rows if rad in ("all", r["radius_frac"])])[0]]
    sweep.write_rows(out / "reliability.csv", rel)
    every = [{"radius_frac": rad, "bin": f"{lo:.1f}", "count": n, "probability": c, "strict": s}
             for rad in radii + ["all"]
             for lo, n, c, s in binned(*placement_outcomes([r for r in rows if rad in ("all", r["radius_frac"])]))[0]]
    if every:
        sweep.write_rows(out / "placements.csv", every)
    (out / "sure.md").write_text(markdown(sure, rel, every))
    return 0


def placement_outcomes(rows):
    """Every weighed placement's probability (P,) and whether it is strictly right (P,) 0/1,
    from the rows' ``placement_probability`` and ``placement_right`` (empty without them)."""
    pairs = [(float(p), float(y)) for r in rows if r.get("placement_probability")
             for p, y in zip(r["placement_probability"].split(), r["placement_right"].split())]
    return tuple(np.array(x, dtype=float) for x in zip(*pairs)) if pairs else (np.zeros(0), np.zeros(0))


def pct(x):
    return "–" if x != x else f"{100 * x:.0f} %"


def markdown(sure, rel, every=()):
    lines = ["# How sure the default method is when it says ok", "",
             "From experiments/sure_summary.py over this folder's grasps.csv. ok: the best pose is strictly "
             "right (within 5° and 5 % of the diameter, modulo symmetry) with a confidence of at least 0.99. "
             "Before: the committed results/realistic_contacts rows of the same grasps (strict there is not "
             "modulo symmetry).", "",
             "ECE, calibrated: the ECE a perfectly calibrated confidence would show on the same answers (each "
             "right with its own confidence; mean and 95th percentile of 400 draws): the binning of a few hundred "
             "answers alone gives about 0.05.", "",
             "ok reachable: the share of grasps where the truth would hold at least 0.99 of the Laplace evidence "
             "had the search found it at its own floor, beside the placements the answer weighed "
             "(harness.ceiling.truth_share): what a calibrated ok can reach on these grasps.", "",
             "| object | r | grasps | ok | ok reachable | ok strictly right | ambiguous: truth listed | ECE | "
             "ECE, calibrated (95 %) | strict (all) | before: ok | before: ok strictly right | before: strict |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in sure:
        lines.append(f"| {s['object'].replace('ycb:', '')} | {float(s['radius_frac']):g} | {s['grasps']} | {pct(s['ok'])} | "
                     f"{pct(s['ok_reachable'])} | {pct(s['ok_strict'])} | {pct(s['ambiguous_truth_listed'])} ({s['ambiguous_n']}) | "
                     f"{s['ece']:.3f} | {s['ece_calibrated']:.3f} ({s['ece_calibrated_95']:.3f}) | {pct(s['strict'])} | "
                     f"{pct(s['before_ok'])} | {pct(s['before_ok_strict'])} | "
                     f"{pct(s['before_strict'])} |")
    lines += ["", "## Reliability of the confidence", "",
              "| r | confidence bin | answers | mean confidence | strictly right |", "|---|---|---:|---:|---:|"]
    lines += [f"| {r['radius_frac']} | {r['bin']} | {r['count']} | {r['confidence']:.3f} | {r['strict']:.3f} |"
              for r in rel]
    if every:
        lines += ["", "## Reliability of every placement's probability", "",
                  "Each weighed placement (not only the best) binned by its probability, against whether it is "
                  "strictly right (``placements.csv``). Two placements a few degrees apart can both be.", "",
                  "| r | probability bin | placements | mean probability | strictly right |", "|---|---|---:|---:|---:|"]
        lines += [f"| {r['radius_frac']} | {r['bin']} | {r['count']} | {r['probability']:.3f} | {r['strict']:.3f} |"
                  for r in every]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
