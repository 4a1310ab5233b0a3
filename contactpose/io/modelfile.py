"""The model file: one .npz of named arrays, written atomically, checked on the way back in.

* Writing: :func:`write_replacing` saves to a new file and renames it over the old one, so a
  reader that maps the old file keeps a valid inode. Members named in ``compress`` are
  deflated; the others are stored, so that files of MMAP_MIN_BYTES or more can be mapped.
* Reading: :func:`read_npz` first reads only the ``.npy`` headers (:func:`member_sizes`) and
  checks each declared shape and dtype against the bytes the member holds, and the total
  against the available memory (:func:`check_room`); files of MMAP_MIN_BYTES or more are
  memory-mapped (:func:`mmap_npz`). :func:`free_memory` is what "available" means: the
  system's available memory, or less under an RLIMIT_AS ceiling. Every failure is a ModelFileError (ResourceError when
  memory runs short) that names the file.
* Checking: a spec maps an array name to ``(kind, shape)`` or ``(kind, shape, (low, high))``.
  kind: "i" signed integer, "f" finite float32/float64, "F" float32/float64 that may be
  NaN, "b" bool, "U" text. shape: a tuple of ints, size names ("m" facets, "P" pairs,
  ...) and names + 1 ("p+1"); the first array that uses a name sets its size, and every
  later array must agree. (low, high): every entry lies in [low, high); high may be a
  size name. :func:`check_arrays` raises a ModelFileError naming the array and the expectation.
* Integrity: :func:`content_hash` over every array; :func:`check_version` of the format.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import secrets
import zipfile

import numpy as np

from contactpose.errors import ModelFileError, ResourceError

log = logging.getLogger(__name__)

KINDS = {"i": "signed integers", "f": "finite floats", "F": "floats", "b": "booleans", "U": "text"}

#: The model's own arrays (V vertices, m facets).
STORED_MODEL = {
    "mesh_hash": ("U", ()), "bounds": ("U", ()), "diameter": ("f", ()),
    "vertices": ("f", ("V", 3)), "faces": ("i", ("m", 3), (0, "V")),
    "normals": ("f", ("m", 3)), "offsets": ("f", ("m",)), "areas": ("f", ("m",)), "valid": ("b", ("m",)),
    "winding": ("U", ()),
}
#: The model's arrays that files written before them lack (a missing one means "not recorded"):
#: ``winding``, the mesh's face winding found at build time (ObjectModel.winding).
OPTIONAL_MODEL = ("winding",)
#: PairFeatures of P pairs of items (facets or patches) 0 .. n-1. k and l may be int16
#: (files of models with fewer than 32,768 facets or patches).
STORED_FEATURES = {
    "k": ("i", ("P",), (0, "n")), "l": ("i", ("P",), (0, "n")),
    "dmax": ("f", ("P",)), "dmin_vertex": ("f", ("P",)), "dmin_exact": ("f", ("P",)),
    "alpha": ("f", ("P",)), "alpha_hi": ("f", ("P",)), "h_kl": ("f", ("P", 2)), "h_lk": ("f", ("P", 2)),
}
#: A PairTable's arrays besides its offsets (whose length follows from bins); ``alpha_width``,
#: the widest angle interval (found on load when a file lacks it), is OPTIONAL_TABLE.
STORED_TABLE = {"bins": ("i", (3,), (1, 4097)), "mins": ("f", (3,)), "widths": ("f", (3,)), "max_span": ("F", ()),
                "alpha_width": ("f", ())}
OPTIONAL_TABLE = ("alpha_width",)
#: The object's symmetry group (model.symmetry.Symmetry), found when the model was saved
#: (found on use when a file lacks it): K transforms, C continuous axes.
STORED_SYMMETRY = {"rotations": ("f", ("K", 4, 4)), "axes": ("f", ("C", 3)), "centre": ("f", (3,)), "exact": ("b", ())}
#: Patches: p patches of M member facets out of m (label -1: a degenerate facet).
STORED_PATCHES = {
    "normals": ("f", ("p", 3)), "offsets": ("f", ("p",)), "centres": ("f", ("p", 3)), "cone": ("f", ("p",)),
    "labels": ("i", ("m",), (-1, "p")), "members": ("i", ("M",), (0, "m")), "indptr": ("i", ("p+1",)),
    "tol_deg": ("f", ()),
}


def check_arrays(arrays, spec, sizes, prefix="", optional=(), values=True):
    """Check ``arrays`` (name -> ndarray) against ``spec``.

    sizes : dict size name -> (value, array that set it), updated in place;
    prefix : prepended to names in messages (the name in the file);
    optional : names that may be missing;
    values : also scan the values (finite floats, indices in range); False checks names,
    kinds and shapes only, for a file this library wrote and vouches for.
    """
    for name, (kind, shape, *limits) in spec.items():
        if name not in arrays:
            if name in optional:
                continue
            raise ModelFileError(f"it lacks the array {prefix + name!r}")
        a = np.asanyarray(arrays[name])
        if not (_kind_ok(a, kind, values) and _shape_ok(a.shape, shape, sizes, prefix + name)):
            raise ModelFileError(f"array {prefix + name!r} must hold {KINDS[kind]} of shape "
                                 f"{_describe(shape, sizes)}, got {a.dtype} of shape {a.shape}")
        if limits and values:
            _check_range(prefix + name, a, *limits[0], sizes)


def check_pointers(name, a, total):
    """CSR pointers ``a`` (n + 1,) int: start at 0, never decrease, end at ``total``."""
    if len(a) == 0 or a[0] != 0 or a[-1] != total or np.any(np.diff(a) < 0):
        raise ModelFileError(f"array {name!r} must rise from 0 to {total} without decreasing")


def _kind_ok(a, kind, values=True):
    if kind in "fF":  # numba's kernels take float32 and float64 only
        if a.dtype.kind != "f" or a.dtype.itemsize not in (4, 8):
            return False
        return kind == "F" or a.size == 0 or not values or bool(np.isfinite(a.min()) and np.isfinite(a.max()))
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


#: Version of the .npz model file layout. Bump on any incompatible change.
#: 2: every array is checked on load (stored.py), and files are replaced, not rewritten.
#: 3: compact files: facet pair indices as int16 where they fit, the facet table's vertex-only
#: Δmin and direction intervals left out (recomputed on load), large members deflated.
FORMAT_VERSION = 3


#: Model files larger than this are memory-mapped instead of read into memory.
MMAP_MIN_BYTES = 256 * 2**20
#: A file read into memory takes up to this many times its arrays' bytes once loaded: int16
#: pair indices widen to int32 and the facet table's derived fields are recomputed.
LOAD_FACTOR = 3.0
#: Members smaller than this are stored, not deflated: compression gains little on them,
#: and a damaged stored member is reported by its CRC.
COMPRESS_MIN_BYTES = 64 * 2**10


def write_replacing(path, arrays, compress=()):
    """The arrays as an .npz in a new file in path's folder, then os.replace it over path:
    the old file's inode stays intact for whoever maps it. compress : names of the members
    to deflate (zlib level 6, as np.savez_compressed); the others are stored.
    OSError -> ModelFileError."""
    folder, name = os.path.split(os.path.abspath(path))
    tmp = os.path.join(folder, f".{name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "xb") as fh, zipfile.ZipFile(fh, "w", allowZip64=True) as zf:
            for key, a in arrays.items():
                info = zipfile.ZipInfo(key + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED if key in compress else zipfile.ZIP_STORED
                with zf.open(info, "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(a), allow_pickle=False)
        os.replace(tmp, path)
    except OSError as exc:
        raise ModelFileError(f"cannot write model file {path!r}: {exc.strerror or exc}") from None
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def mmap_npz(path):
    """Map each stored (uncompressed) .npy member of a zip in place, read-only."""
    arrays = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as fh:
        for info in zf.infolist():
            if info.compress_type != zipfile.ZIP_STORED or not info.filename.endswith(".npy"):
                raise ValueError(f"member {info.filename} is not a stored .npy")
            fh.seek(info.header_offset)
            local = fh.read(30)
            name_len, extra_len = int.from_bytes(local[26:28], "little"), int.from_bytes(local[28:30], "little")
            fh.seek(info.header_offset + 30 + name_len + extra_len)
            version = np.lib.format.read_magic(fh)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read_header(fh)
            if dtype.hasobject:
                raise ValueError("object arrays are not allowed")
            arrays[info.filename[:-4]] = np.memmap(fh.name, dtype=dtype, mode="r", offset=fh.tell(), shape=shape,
                                                   order="F" if fortran else "C") if np.prod(shape) else np.empty(shape, dtype)
    return arrays


def content_hash(arrays):
    """SHA-256 over every array's name, dtype, shape and bytes, in name order."""
    digest = hashlib.sha256()
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        digest.update(f"{key}|{a.dtype.str}|{a.shape}|".encode())
        digest.update(a.tobytes() if a.dtype.kind == "U" or a.ndim == 0 else memoryview(a.reshape(-1)).cast("B"))
    return digest.hexdigest()


def check_version(path, data):
    """The file's format version must be this library's."""
    version = data.get("format_version")
    try:
        version = int(version)
    except (TypeError, ValueError, OverflowError):
        raise ModelFileError(f"model file {path!r} has no readable format version: not a contactpose model") from None
    if version != FORMAT_VERSION:
        raise ModelFileError(
            f"model file {path!r} has format version {version}, this contactpose reads version "
            f"{FORMAT_VERSION}; rebuild it with `contactpose build-model`")


def prefixed(data, prefix):
    return {k[len(prefix):]: v for k, v in data.items() if k.startswith(prefix)}


def read_npz(path, mmap=None):
    """Every array of an .npz, turning every failure into ModelFileError (ResourceError when
    memory runs short). Each member's header is checked against its size first. Large
    files are memory-mapped (their members are stored uncompressed by ``save``); mmap=True
    maps any file stored uncompressed, False none (None: by size, MMAP_MIN_BYTES)."""
    if not os.path.isfile(path):
        raise ModelFileError(f"model file {path!r} does not exist")
    try:
        sizes = member_sizes(path)
    except Exception as exc:  # any failure to decode the headers means a damaged or foreign file
        raise ModelFileError(unreadable(path, exc)) from None
    if mmap or (mmap is None and os.path.getsize(path) >= MMAP_MIN_BYTES):
        try:
            return mmap_npz(path)
        except MemoryError:
            raise out_of_memory(path) from None
        except Exception as exc:  # a foreign layout (e.g. compressed): np.load below reads it or says why
            log.debug("cannot memory-map %s (%s: %s); reading it instead", path, type(exc).__name__, exc)
    check_room(path, sum(sizes.values()), LOAD_FACTOR)
    try:
        return _read_members(path)
    except MemoryError:
        raise out_of_memory(path) from None
    except Exception as exc:  # any failure to decode the bytes means a damaged or foreign file
        raise ModelFileError(unreadable(path, exc)) from None


def _read_members(path):
    """np.load of every member, in this thread. numpy parses each .npy header with
    ast.literal_eval, and Python 3.11 keeps that parser's recursion bookkeeping per
    interpreter, not per thread: two threads parsing at once can fail with "SystemError: AST
    constructor recursion depth mismatch" (CPython issue 106905; it failed a model load here
    when members were read on two threads)."""
    with np.load(path, allow_pickle=False) as npz:
        return {key: npz[key] for key in npz.files}


def unreadable(path, exc):
    """The ModelFileError message for a model file that cannot be decoded."""
    return (f"cannot read model file {path!r}: {type(exc).__name__}: {exc} "
            "(truncated, corrupt or not a .npz model)")


def out_of_memory(path):
    """The error for a MemoryError while reading a model file."""
    return ResourceError(f"not enough memory to read model file {path!r}; free memory or rebuild the model "
                         "with a smaller --max-span")


def member_sizes(path):
    """{member name: bytes of its array data} of every member of the zip at path.

    Raises ValueError (or a zipfile/zlib error) when a member is not a ``.npy`` array, its
    header cannot be read, or it declares a shape and dtype whose size differs from the
    bytes the member holds.
    Object arrays are left to ``np.load`` (which refuses them without pickle).
    """
    sizes = {}
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):  # np.load would return its raw bytes, not an array
                raise ValueError(f"member {info.filename!r} is not a .npy array")
            with zf.open(info) as fh:
                sizes[info.filename] = _data_bytes(info, fh)
    return sizes


def _data_bytes(info, fh):
    """Bytes of array data in the open member fh, checked against its declared shape and dtype."""
    version = np.lib.format.read_magic(fh)
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, _, dtype = read(fh)
    held = info.file_size - fh.tell()
    if dtype.hasobject:
        return held
    declared = math.prod(shape) * dtype.itemsize
    if declared != held:
        raise ValueError(f"member {info.filename!r} declares an array of shape {shape} and dtype {dtype.str} "
                         f"({declared:,} bytes) but holds {held:,} bytes of data")
    return held


def free_memory():
    """Bytes this process may still allocate: the system's available memory, or less if an
    RLIMIT_AS ceiling is set (the ceiling minus the process's current address space)."""
    import psutil

    available = psutil.virtual_memory().available
    with contextlib.suppress(ImportError, OSError, ValueError):
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft != resource.RLIM_INFINITY:
            available = min(available, max(0, soft - psutil.Process().memory_info().vms))
    return available


def check_room(path, nbytes, factor=1.0):
    """ResourceError if reading nbytes of arrays from the model file at path, which take
    factor times that once loaded, would not fit in memory."""
    available = free_memory()
    if factor * nbytes > 0.8 * available:
        raise ResourceError(
            f"model file {path!r} holds {nbytes / 2**30:.3g} GiB of arrays (about {factor * nbytes / 2**30:.3g} GiB "
            f"loaded), but only "
            f"{available / 2**30:.3g} GiB of memory is available; free memory or rebuild with a smaller "
            "--max-span")
    return nbytes
