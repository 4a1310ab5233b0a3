"""The JSON the library writes: schema version, units, column and tangent names, and the
helpers that turn arrays into JSON (contactpose/data/*.schema.json describe the files)."""

from __future__ import annotations

import numpy as np

#: Version of every JSON the CLI writes (contactpose/data/*.schema.json). Bump the minor
#: number for added keys, the major one for renamed or removed keys.
SCHEMA_VERSION = "1.3"
#: The columns of a hypothesis's (n, 5) residuals: the normal residual R n_k + ñ_i (world,
#: unitless), the offset (point-to-plane; eq. (7) for "paper") and the lateral distance
#: outside the facet triangle (length units).
RESIDUAL_COLUMNS = ("normal_x", "normal_y", "normal_z", "offset", "lateral")
#: Order of every 6-vector and 6×6 covariance in the JSON: GTSAM's Pose3 tangent, rotation first.
TANGENT_ORDER = ("rot_x", "rot_y", "rot_z", "trans_x", "trans_y", "trans_z")
#: Angle unit of each angle-valued field of the localize JSON (paths inside a hypothesis
#: for the last five); the translation parts of covariances and samples are in length units.
ANGLE_UNITS = {"tolerance.angle_deg": "deg", "tolerance.normal_noise_deg": "deg", "covariance": "rad",
               "sample_covariance": "rad", "samples.mean": "rad", "samples.covariance": "rad",
               "samples.intervals": "deg"}


def result_units():
    """The ``units`` block of the localize JSON: lengths in the mesh's own unit (the library
    does not know its name; metres by default), times in ms, angles per ANGLE_UNITS."""
    return {"length": "mesh", "time": "ms", "tangent_order": list(TANGENT_ORDER), "angles": dict(ANGLE_UNITS)}


def tolerance_dict(tolerance):
    """Pair tolerances and the noise behind them: lengths in mesh units, angles in degrees."""
    return {"distance": float(tolerance.distance), "angle_deg": float(np.degrees(tolerance.angle)),
            "position_noise": float(tolerance.position_noise),
            "normal_noise_deg": float(np.degrees(tolerance.normal_noise))}


def json_number(x):
    """float(x), or None where x is NaN or infinite (JSON has no such numbers)."""
    x = float(x)
    return x if np.isfinite(x) else None


def json_array(a):
    """Nested lists of floats with None for NaN and infinite entries. a : array of any shape"""
    a = np.asarray(a, dtype=np.float64)
    if np.isfinite(a).all():
        return a.tolist()
    return np.where(np.isfinite(a), a, None).tolist()
