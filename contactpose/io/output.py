"""The JSON the CLI writes, and the JSON Schemas (draft 2020-12) that describe it.

Every output carries ``schema_version`` (SCHEMA_VERSION) and a ``units`` block. The
schemas ship as package data, one per kind of output (``contactpose/data/<kind>.schema.json``):

* "result": ``localize -o``, built by :meth:`contactpose.types.Result.to_dict`;
* "touch": ``next-touch -o``, built by :func:`next_touch_dict`;
* "scan_report": ``scan --report-json``, built by :func:`scan_report_dict`;
* "bench": ``bench --json``, whose header is :func:`bench_header`;
* "track": ``track -o``, built by :func:`track_dict`.

Rules shared by all: lengths in the mesh's (or cloud's) own unit, times in ms, angles in
degrees unless ``units`` says radians; null means "not computed / not applicable", [] an
empty list.
"""

from __future__ import annotations

import json
from importlib import resources

import numpy as np

from contactpose.schema import SCHEMA_VERSION, json_number

SCHEMA_KINDS = ("result", "touch", "scan_report", "bench", "track")
#: Units of the next-touch JSON: lengths in mesh units, information in bits.
TOUCH_UNITS = {"length": "mesh", "information": "bits"}
#: Units of the scan report: lengths in the cloud's unit, times in ms, ``*_pct`` in % of the diameter.
SCAN_UNITS = {"length": "cloud", "time": "ms", "relative": "percent of diameter"}
#: Units of the track JSON: lengths in mesh units, angles in degrees, covariances in radians (rotation first).
TRACK_UNITS = {"length": "mesh", "angle": "deg", "covariance_rotation": "rad"}
#: A track step's errors against its true pose: raw, and modulo the object's symmetry.
TRACK_ERRORS = ("rot_err_deg", "trans_err", "rot_err_sym_deg", "trans_err_sym")
#: Units of the bench report: lengths in mesh units, times in ms, memory in MiB, angles in degrees.
BENCH_UNITS = {"length": "mesh", "time": "ms", "memory": "MiB", "angle": "deg"}


def schema_path(kind):
    """The packaged schema file of one kind of output (SCHEMA_KINDS)."""
    if kind not in SCHEMA_KINDS:
        raise ValueError(f"schema kind must be one of {SCHEMA_KINDS}, got {kind!r}")
    return resources.files("contactpose") / "data" / f"{kind}.schema.json"


def load_schema(kind):
    """The JSON Schema (a dict) of one kind of output (SCHEMA_KINDS)."""
    return json.loads(schema_path(kind).read_text(encoding="utf-8"))


def next_touch_dict(result, touch):
    """The next-touch JSON: the localize status and pose classes, and the suggested touch.

    result : Result; touch : contactpose.touch.Touch.
    """
    return {
        "schema_version": SCHEMA_VERSION,
        "units": dict(TOUCH_UNITS),
        "status": result.status,
        "hint": result.hint,
        "classes": [c.to_dict() for c in result.classes],
        "touch": touch.to_dict(),
    }


def track_dict(status, rows, tracks, association=None, symmetry=""):
    """The track JSON: the first grasp's localize status, the object's symmetry, the best
    track's pose at every step (with its error where the sequence gives the true pose, raw and
    modulo the symmetry), and the tracks left at the end.

    rows : [dict(step, pose (4, 4), tracks, reseeds, score, rot_err_deg, trans_err, rot_err_sym_deg,
    trans_err_sym)]; tracks : TrackSet; association : None, or each final track's association
    covariance (6, 6), written as its ``association_covariance``; symmetry : the object's
    symmetry group in words (model.symmetry.Symmetry.describe), "" when it has none.
    """
    finals = [{"pose": t.pose.tolist(), "score": t.score, "covariance": t.covariance.tolist()} for t in tracks.tracks]
    for final, spread in zip(finals, association or []):
        final["association_covariance"] = np.asarray(spread).tolist()
    return {
        "schema_version": SCHEMA_VERSION,
        "units": dict(TRACK_UNITS),
        "status": status,
        "symmetry": symmetry,
        "steps": [{"step": r["step"], "pose": r["pose"].tolist(), "tracks": r["tracks"], "reseeds": r["reseeds"],
                   "score": r["score"], **{k: _number_or_none(r[k]) for k in TRACK_ERRORS}} for r in rows],
        "tracks": finals,
    }


def _number_or_none(x):
    """None stays None (no true pose), numbers become JSON numbers (NaN and inf: None)."""
    return None if x is None else json_number(x)


def scan_report_dict(report):
    """The scan report JSON: ScanReport.to_dict with timings in ms (``timings_ms``, ``total_ms``)."""
    body = report.to_dict()
    timings = body.pop("timings")
    seconds = body.pop("seconds")
    return {"schema_version": SCHEMA_VERSION, "units": dict(SCAN_UNITS), **body,
            "timings_ms": {k: 1000.0 * float(v) for k, v in timings.items()}, "total_ms": 1000.0 * float(seconds)}


def bench_header():
    """``schema_version`` and ``units`` for the top of the bench JSON."""
    return {"schema_version": SCHEMA_VERSION, "units": dict(BENCH_UNITS)}
