"""Checks of a model file's ``.npy`` members before their data is read (issue 8).

A damaged or hand-made ``.npz`` can declare an array far larger than the bytes it
holds; ``np.load`` would then try to allocate it and fail with a MemoryError (or
worse, succeed and swap). :func:`member_sizes` reads only the headers and checks each
declared shape and dtype against the member's stored size; :func:`check_room` refuses,
before reading, arrays that will not fit in the available memory.
"""

from __future__ import annotations

import math
import zipfile

import numpy as np

from contactpose.errors import ResourceError


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


def check_room(path, nbytes):
    """ResourceError if reading nbytes of arrays from the model file at path would not fit in memory."""
    import psutil

    available = psutil.virtual_memory().available
    if nbytes > 0.8 * available:
        raise ResourceError(
            f"model file {path!r} holds {nbytes / 2**30:.3g} GiB of arrays, but only "
            f"{available / 2**30:.3g} GiB of memory is available; free memory or rebuild with a smaller "
            "--max-span")
    return nbytes
