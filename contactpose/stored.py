"""Checks of the arrays read back from a model file: dtype kind, shape, value range.

A spec maps an array name to ``(kind, shape)`` or ``(kind, shape, (low, high))``.
kind: "i" signed integer, "f" finite float32/float64, "F" float32/float64 that may be
NaN, "b" bool, "U" text. shape: a tuple of ints, size names ("m" facets, "P" pairs,
...) and names + 1 ("p+1"); the first array that uses a name sets its size, and every
later array must agree. (low, high): every entry lies in [low, high); high may be a
size name. Every failure is a ModelFileError that names the array and the expectation.
"""

from __future__ import annotations

import numpy as np

from contactpose.errors import ModelFileError

KINDS = {"i": "signed integers", "f": "finite floats", "F": "floats", "b": "booleans", "U": "text"}

#: The model's own arrays (V vertices, m facets).
STORED_MODEL = {
    "mesh_hash": ("U", ()), "bounds": ("U", ()), "diameter": ("f", ()),
    "vertices": ("f", ("V", 3)), "faces": ("i", ("m", 3), (0, "V")),
    "normals": ("f", ("m", 3)), "offsets": ("f", ("m",)), "areas": ("f", ("m",)), "valid": ("b", ("m",)),
}
#: PairFeatures of P pairs of items (facets or patches) 0 .. n-1.
STORED_FEATURES = {
    "k": ("i", ("P",), (0, "n")), "l": ("i", ("P",), (0, "n")),
    "dmax": ("f", ("P",)), "dmin_vertex": ("f", ("P",)), "dmin_exact": ("f", ("P",)),
    "alpha": ("f", ("P",)), "alpha_hi": ("f", ("P",)), "h_kl": ("f", ("P", 2)), "h_lk": ("f", ("P", 2)),
}
#: A PairTable's arrays besides its offsets (whose length follows from bins).
STORED_TABLE = {"bins": ("i", (3,), (1, 4097)), "mins": ("f", (3,)), "widths": ("f", (3,)), "max_span": ("F", ())}
#: Patches: p patches of M member facets out of m (label -1: a degenerate facet).
STORED_PATCHES = {
    "normals": ("f", ("p", 3)), "offsets": ("f", ("p",)), "centres": ("f", ("p", 3)), "cone": ("f", ("p",)),
    "labels": ("i", ("m",), (-1, "p")), "members": ("i", ("M",), (0, "m")), "indptr": ("i", ("p+1",)),
    "tol_deg": ("f", ()),
}


def check_arrays(arrays, spec, sizes, prefix="", optional=()):
    """Check ``arrays`` (name -> ndarray) against ``spec``.

    sizes : dict size name -> (value, array that set it), updated in place;
    prefix : prepended to names in messages (the name in the file);
    optional : names that may be missing.
    """
    for name, (kind, shape, *limits) in spec.items():
        if name not in arrays:
            if name in optional:
                continue
            raise ModelFileError(f"it lacks the array {prefix + name!r}")
        a = np.asanyarray(arrays[name])
        if not (_kind_ok(a, kind) and _shape_ok(a.shape, shape, sizes, prefix + name)):
            raise ModelFileError(f"array {prefix + name!r} must hold {KINDS[kind]} of shape "
                                 f"{_describe(shape, sizes)}, got {a.dtype} of shape {a.shape}")
        if limits:
            _check_range(prefix + name, a, *limits[0], sizes)


def check_pointers(name, a, total):
    """CSR pointers ``a`` (n + 1,) int: start at 0, never decrease, end at ``total``."""
    if len(a) == 0 or a[0] != 0 or a[-1] != total or np.any(np.diff(a) < 0):
        raise ModelFileError(f"array {name!r} must rise from 0 to {total} without decreasing")


def _kind_ok(a, kind):
    if kind in "fF":  # numba's kernels take float32 and float64 only
        if a.dtype.kind != "f" or a.dtype.itemsize not in (4, 8):
            return False
        return kind == "F" or a.size == 0 or bool(np.isfinite(a.min()) and np.isfinite(a.max()))
    return a.dtype.kind == kind


def _shape_ok(actual, shape, sizes, name):
    if len(actual) != len(shape):
        return False
    for got, want in zip(actual, shape):
        if isinstance(want, str):  # a size name, or a name + 1
            base, extra = want.removesuffix("+1"), int(want.endswith("+1"))
            sizes.setdefault(base, (got - extra, name))
            want = sizes[base][0] + extra
        if got != want:
            return False
    return True


def _describe(shape, sizes):
    """'(P, 2) with P = 1176 as in 'features_k''."""
    text = "(" + ", ".join(map(str, shape)) + ("," if len(shape) == 1 else "") + ")"
    known = [f"{s} = {sizes[s][0]} as in {sizes[s][1]!r}" for s in dict.fromkeys(shape) if s in sizes]
    return text + (" with " + ", ".join(known) if known else "")


def _check_range(name, a, low, high, sizes):
    high = sizes[high][0] if isinstance(high, str) else high
    if a.size and (a.min() < low or a.max() >= high):
        raise ModelFileError(f"array {name!r} must lie in [{low}, {high - 1}], got range [{a.min()}, {a.max()}]")
