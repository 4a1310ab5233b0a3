"""File formats: CONTACTS.json and PRIOR.json (see README), and JSON output.

CONTACTS.json: ``{"contacts": [{"point": [x, y, z], "finger_normal": [..]}, ...]}``,
each contact with exactly one of "finger_normal" or "object_normal".
PRIOR.json: ``{"pose": 4x4, "sigma_rot_deg": s, "sigma_trans": s}`` or
``{"pose": 4x4, "covariance": 6x6}`` (rotation first).

The parsers accept any value (what ``json.load`` returns, or a dict built in
Python) and either return a result or raise :class:`ContactsError` /
:class:`PriorError` naming the bad value and what was expected; they never let
a raw ``TypeError``, ``OverflowError`` or ``RecursionError`` out
(tests/test_fuzz.py checks this on arbitrary input).
"""

from __future__ import annotations

import json
import numbers
import os

import numpy as np

from contactpose.contacts import Contacts
from contactpose.errors import ContactsError, PriorError
from contactpose.types import PosePrior

NORMAL_KEYS = ("finger_normal", "object_normal")
SIGMA_KEYS = ("sigma_rot_deg", "sigma_trans")
#: Longest text of a bad value quoted in an error message.
BRIEF_CHARS = 60


def read_json(path, error):
    """Parse a JSON file; any failure becomes ``error`` naming the file."""
    path = os.fspath(path)
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise error(f"file {path!r} does not exist") from None
    except json.JSONDecodeError as exc:
        raise error(f"{path!r} is not valid JSON: {exc}") from None
    except UnicodeDecodeError as exc:
        raise error(f"cannot read {path!r}: not UTF-8 text ({exc})") from None
    except OSError as exc:
        raise error(f"cannot read {path!r}: {exc}") from None
    except RecursionError:
        raise error(f"{path!r} is nested too deeply to be a contacts or prior file") from None
    except ValueError as exc:  # e.g. an integer literal beyond Python's digit limit
        raise error(f"{path!r} is not a usable JSON file: {exc}") from None


def parse_contacts(data, minimum=2):
    """CONTACTS.json content -> Contacts of at least ``minimum`` contacts."""
    if not isinstance(data, dict) or not isinstance(data.get("contacts"), list):
        raise ContactsError('contacts file must be an object {"contacts": [...]}, got ' + _brief(data))
    points, normals, kinds = [], [], set()
    for i, c in enumerate(data["contacts"]):
        if not isinstance(c, dict) or "point" not in c:
            raise ContactsError(f'contact {i} must be an object with "point" and a normal, got {_brief(c)}')
        given = [k for k in NORMAL_KEYS if k in c]
        if len(given) != 1:
            raise ContactsError(f'contact {i} needs exactly one of "finger_normal" or "object_normal", got {given or "neither"}')
        kinds.add(given[0])
        points.append(_vector(c["point"], f"contact {i} point"))
        normals.append(_vector(c[given[0]], f"contact {i} {given[0]}"))
    if len(kinds) > 1:
        raise ContactsError("all contacts must give the same kind of normal (finger_normal or object_normal), got both kinds")
    if not points:
        raise ContactsError("contacts file lists no contacts; need at least 2")
    if len(points) < minimum:
        raise ContactsError(f"need at least {minimum} contacts, got {len(points)}")
    key = "finger_normals" if kinds == {"finger_normal"} else "object_normals"
    return Contacts(np.array(points), **{key: np.array(normals)})


def parse_sequence(data):
    """SEQ.json content -> [(Contacts, hand motion (ΔT (4, 4), σ_rot_deg, σ_trans) or None,
    true pose (4, 4) or None)], one per step. Step 0 is the first grasp (at least 2 contacts,
    no hand motion); each later step holds at least one contact, and a hand motion unless the
    object did not move."""
    if not isinstance(data, dict) or not isinstance(data.get("steps"), list) or not data["steps"]:
        raise ContactsError('sequence file must be an object {"steps": [...]} with at least one step, got '
                            + _brief(data))
    steps = []
    for k, step in enumerate(data["steps"]):
        if not isinstance(step, dict):
            raise ContactsError(f'step {k} must be an object with "contacts", got {_brief(step)}')
        try:
            contacts = parse_contacts(step, minimum=2 if k == 0 else 1)
        except ContactsError as exc:
            raise ContactsError(f"step {k}: {exc}") from None
        motion = step.get("hand_motion")
        if motion is not None:
            if k == 0:
                raise ContactsError("step 0 is the first grasp: it has no hand_motion")
            if not isinstance(motion, dict) or "delta" not in motion:
                raise ContactsError(f'step {k} hand_motion must be an object with "delta", '
                                    f'"sigma_rot_deg" and "sigma_trans", got {_brief(motion)}')
            motion = (_matrix(motion["delta"], f"step {k} hand_motion delta", (4, 4)),
                      *(_number(motion.get(key), f"step {k} hand_motion {key}", ContactsError) for key in SIGMA_KEYS))
        truth = step.get("true_pose")
        steps.append((contacts, motion, None if truth is None else _matrix(truth, f"step {k} true_pose", (4, 4))))
    return steps


def read_sequence(path):
    """SEQ.json at ``path`` -> parse_sequence; ContactsError (or PriorError for a bad matrix)."""
    return parse_sequence(read_json(path, ContactsError))


def parse_prior(data):
    """PRIOR.json content -> PosePrior."""
    if not isinstance(data, dict) or "pose" not in data:
        raise PriorError('prior file must be an object with "pose" and sigmas or "covariance", got ' + _brief(data))
    pose = _matrix(data["pose"], "prior pose", (4, 4))
    if "covariance" in data:
        both = [k for k in SIGMA_KEYS if k in data]
        if both:
            raise PriorError(f'prior gives both "covariance" and {both}; give the sigmas or the covariance, not both')
        return PosePrior(pose, covariance=_matrix(data["covariance"], "prior covariance", (6, 6)))
    sig = {k: _number(data.get(k), f"prior {k}", PriorError) for k in SIGMA_KEYS}
    return PosePrior(pose, **sig)


def read_contacts(path):
    """CONTACTS.json at ``path`` -> Contacts; ContactsError for any bad file."""
    return parse_contacts(read_json(path, ContactsError))


def read_prior(path):
    """PRIOR.json at ``path`` -> PosePrior; PriorError for any bad file."""
    return parse_prior(read_json(path, PriorError))


#: A JSON text longer than this is written compact (one line): the indented writer is pure
#: Python, and a time-limited answer listing 57,000 hypotheses took 10 s to write indented.
INDENT_MAX_CHARS = 1_000_000


def write_json(path, data):
    """``data`` as JSON at ``path``: indented, or compact past INDENT_MAX_CHARS."""
    text = json.dumps(data)
    if len(text) <= INDENT_MAX_CHARS:
        text = json.dumps(data, indent=1)
    with open(os.fspath(path), "w", encoding="utf-8") as fh:
        fh.write(text + "\n")


def _is_number(x):
    """A real number that is not a bool (JSON true/false are not coordinates)."""
    return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_))


def _number(value, name, error):
    """value -> float, else ``error`` naming ``name``. Non-finite values pass (checked later)."""
    if not _is_number(value):
        raise error(f"{name} must be a number, got {_brief(value)}")
    try:
        return float(value)
    except (OverflowError, ValueError, TypeError):
        raise error(f"{name} must be a number representable as a float, got {_brief(value)}") from None


def _vector(value, name):
    """A list of 3 numbers -> [x, y, z] floats, else ContactsError."""
    if not isinstance(value, (list, tuple)) or len(value) != 3 or not all(_is_number(x) for x in value):
        raise ContactsError(f"{name} must be a list of 3 numbers, got {_brief(value)}")
    return [_number(x, name, ContactsError) for x in value]


def _matrix(value, name, shape):
    """A list of rows of numbers with the given (rows, cols) -> float64 array, else PriorError."""
    rows, cols = shape
    if (not isinstance(value, (list, tuple)) or len(value) != rows
            or not all(isinstance(r, (list, tuple)) and len(r) == cols for r in value)):
        raise PriorError(f"{name} must be a {rows}x{cols} matrix (a list of {rows} rows of {cols} numbers), "
                         f"got {_brief(value)}")
    if not all(_is_number(x) for r in value for x in r):
        raise PriorError(f"{name} must hold only numbers, got {_brief(value)}")
    return np.array([[_number(x, name, PriorError) for x in r] for r in value], dtype=np.float64)


def _brief(value):
    """A short text of any value for an error message; never raises."""
    try:
        text = json.dumps(value)
    except Exception:  # not JSON-able, too deep, an int past the digit limit, ...
        try:
            text = repr(value)
        except Exception:
            text = f"<{type(value).__name__}>"
    return text if len(text) <= BRIEF_CHARS else text[:BRIEF_CHARS - 3] + "..."
