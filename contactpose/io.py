"""File formats: CONTACTS.json and PRIOR.json (see README), and JSON output.

CONTACTS.json: ``{"contacts": [{"point": [x, y, z], "finger_normal": [..]}, ...]}``,
each contact with exactly one of "finger_normal" or "object_normal".
PRIOR.json: ``{"pose": 4x4, "sigma_rot_deg": s, "sigma_trans": s}`` or
``{"pose": 4x4, "covariance": 6x6}`` (rotation first).
"""

from __future__ import annotations

import json
import os

import numpy as np

from contactpose.contacts import Contacts
from contactpose.errors import ContactsError, PriorError
from contactpose.localize import PosePrior


def read_json(path, error):
    """Parse a JSON file; any failure becomes ``error`` naming the file."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise error(f"file {path!r} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"cannot read {path!r}: {exc}") from None
    except json.JSONDecodeError as exc:
        raise error(f"{path!r} is not valid JSON: {exc}") from None
    except RecursionError:
        raise error(f"{path!r} is nested too deeply to be a contacts or prior file") from None


def parse_contacts(data):
    """CONTACTS.json content -> Contacts."""
    if not isinstance(data, dict) or not isinstance(data.get("contacts"), list):
        raise ContactsError('contacts file must be an object {"contacts": [...]}, got ' + _brief(data))
    points, normals, kinds = [], [], set()
    for i, c in enumerate(data["contacts"]):
        if not isinstance(c, dict) or "point" not in c:
            raise ContactsError(f'contact {i} must be an object with "point" and a normal, got {_brief(c)}')
        given = [k for k in ("finger_normal", "object_normal") if k in c]
        if len(given) != 1:
            raise ContactsError(f'contact {i} needs exactly one of "finger_normal" or "object_normal", got {given or "neither"}')
        kinds.add(given[0])
        points.append(_vector(c["point"], f"contact {i} point"))
        normals.append(_vector(c[given[0]], f"contact {i} {given[0]}"))
    if len(kinds) > 1:
        raise ContactsError("all contacts must give the same kind of normal (finger_normal or object_normal), got both kinds")
    if not points:
        raise ContactsError("contacts file lists no contacts; need at least 2")
    key = "finger_normals" if kinds == {"finger_normal"} else "object_normals"
    return Contacts(np.array(points), **{key: np.array(normals)})


def parse_prior(data):
    """PRIOR.json content -> PosePrior."""
    if not isinstance(data, dict) or "pose" not in data:
        raise PriorError('prior file must be an object with "pose" and sigmas or "covariance", got ' + _brief(data))
    pose = _matrix(data["pose"], "prior pose", PriorError)
    if "covariance" in data:
        return PosePrior(pose, covariance=_matrix(data["covariance"], "prior covariance", PriorError))
    sig = {k: data.get(k) for k in ("sigma_rot_deg", "sigma_trans")}
    for k, v in sig.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise PriorError(f"prior {k} must be a number, got {_brief(v)}")
    return PosePrior(pose, **sig)


def read_contacts(path):
    return parse_contacts(read_json(path, ContactsError))


def read_prior(path):
    return parse_prior(read_json(path, PriorError))


def write_json(path, data):
    with open(os.fspath(path), "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1)
        fh.write("\n")


def _vector(value, name):
    if (not isinstance(value, list) or len(value) != 3
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)):
        raise ContactsError(f"{name} must be a list of 3 numbers, got {_brief(value)}")
    return [float(x) for x in value]


def _matrix(value, name, error):
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise error(f"{name} must be a matrix of numbers, got {_brief(value)}") from None
    if arr.ndim != 2:
        raise error(f"{name} must be a 2-D matrix, got {_brief(value)}")
    return arr


def _brief(value):
    text = json.dumps(value) if _jsonable(value) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _jsonable(value):
    try:
        json.dumps(value)
        return True
    except (TypeError, ValueError, RecursionError):
        return False
