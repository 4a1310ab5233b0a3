"""The one error type of contactpose.

Every bad input raises :class:`ContactPoseError` (or a subclass) with a message
that names the bad value and what was expected. The CLI turns it into exit code
2 and one line on stderr; anything else is an internal bug and keeps its
traceback (shown with ``--debug``).
"""


class ContactPoseError(ValueError):
    """Bad input: the message names the value and the expectation."""


class MeshError(ContactPoseError):
    """A mesh file or mesh array that cannot serve as an object model."""


class ContactsError(ContactPoseError):
    """Contact measurements that are malformed or inconsistent."""


class PriorError(ContactPoseError):
    """A pose prior that is not a rigid transform or has bad sigmas."""


class ModelFileError(ContactPoseError):
    """A model file that is corrupt, of another format version, or mismatched."""


class ResourceError(ContactPoseError):
    """A request that would exceed memory or a configured limit."""


class ScanError(ContactPoseError):
    """A point cloud that cannot be turned into a mesh."""


def check_count(value, name, *, minimum=1, allow_none=False):
    """``value`` as an int if it is an integer >= ``minimum`` (None passes when allowed),
    else ContactPoseError naming it. ``True`` and ``False`` are not counts."""
    import numbers

    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        kind = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
        raise ContactPoseError(f"{name} must be {kind}{' or None' if allow_none else ''}, got {value!r}")
    return int(value)


def check_length(value, name, error=ContactPoseError):
    """``value`` as a float if it is a positive finite length, else ``error`` naming it."""
    import math

    try:
        length = float(value)
    except (TypeError, ValueError):
        length = math.nan
    if not (math.isfinite(length) and length > 0):
        raise error(f"{name} must be a positive length in the mesh's units, got {value!r}")
    return length
