"""The model cache: models built from named objects, kept in the user's cache directory so
that the next process loads them instead of building them again.

* Where: ``$CONTACTPOSE_CACHE_DIR``, else ``$XDG_CACHE_HOME/contactpose/models``, else
  ``~/.cache/contactpose/models`` (:func:`cache_dir`).
* Key: the hash of what the model is built from (the named object's mesh file, or its
  generated mesh: cli.common.source_hash), the model file's
  FORMAT_VERSION, the library's version and the build options; a file per key,
  ``NAME__HASH__fVERSION__OPTIONS.npz`` (:func:`entry_path`; NAME is the object's name, for
  people), written by the model's own atomic writer, and beside it ``.json`` with what the
  listing shows (the name, the build's seconds).
* Size: at most CACHE_LIMIT_BYTES (8 GiB; ``$CONTACTPOSE_CACHE_LIMIT_GIB`` overrides it). Before
  a model is written, the least recently used files go until it fits (a file's modification
  time is its last use: :func:`touch` sets it on every hit); a model larger than the limit is
  not kept.
* Checks: a file is loaded with the model file's full check (its content hash, its values)
  unless its size and modification time are those the note recorded when the cache last
  wrote or used it, that is, unless nothing has written to it since: 1.5 s saved on a
  1.9 GB model. A file that something else changed is checked in full, and built again when
  the check fails.

This module holds the files and the policy; :func:`cached_model` takes the build and load
functions, so that it sits below the model it stores.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

from contactpose.errors import ContactPoseError, ModelFileError, ResourceError
from contactpose.io.modelfile import FORMAT_VERSION

log = logging.getLogger(__name__)

#: Largest total size of the cached model files, by default.
CACHE_LIMIT_BYTES = 8 * 2**30
#: Environment variables: the cache's folder, and its size limit in GiB.
CACHE_DIR_ENV = "CONTACTPOSE_CACHE_DIR"
CACHE_LIMIT_ENV = "CONTACTPOSE_CACHE_LIMIT_GIB"
SUFFIX = ".npz"


@dataclass(frozen=True)
class Entry:
    """One cached model: its file, the object's name, bytes on disk (model and note), last
    use (seconds since the epoch), and the build's seconds per stage ({} when not recorded)."""

    path: Path
    name: str
    size: int
    last_used: float
    build_seconds: dict


def cache_dir():
    """The cache's folder (not created here): $CONTACTPOSE_CACHE_DIR, else
    $XDG_CACHE_HOME/contactpose/models, else ~/.cache/contactpose/models."""
    if os.environ.get(CACHE_DIR_ENV):
        return Path(os.environ[CACHE_DIR_ENV]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "contactpose" / "models"


def cache_limit():
    """Bytes the cache may hold: $CONTACTPOSE_CACHE_LIMIT_GIB GiB, else CACHE_LIMIT_BYTES."""
    text = os.environ.get(CACHE_LIMIT_ENV)
    if not text:
        return CACHE_LIMIT_BYTES
    try:
        gib = float(text)
    except ValueError:
        gib = float("nan")
    if not gib >= 0:
        raise ContactPoseError(f"${CACHE_LIMIT_ENV} must be a size in GiB >= 0, got {text!r}")
    return int(gib * 2**30)


def entry_path(name, source_hash, options, version):
    """The cache file of a model: the object's ``name`` (for people), its source's hash,
    FORMAT_VERSION, and a hash of the build ``options`` (a dict of JSON values) and of the
    library's ``version``."""
    tag = hashlib.sha256(json.dumps([options, version], sort_keys=True).encode()).hexdigest()[:12]
    slug = "".join(c if c.isalnum() or c in "-_." else "+" for c in name)
    return cache_dir() / f"{slug}__{source_hash[:20]}__f{FORMAT_VERSION}__{tag}{SUFFIX}"


def entries():
    """The cached models, most recently used first. -> [Entry]"""
    folder = cache_dir()
    if not folder.is_dir():
        return []
    found = []
    for path in folder.glob(f"*{SUFFIX}"):
        with contextlib.suppress(OSError):
            stat = path.stat()
            note = _note(path)
            found.append(Entry(path, note.get("name", path.name.split("__")[0].replace("+", ":")),
                               stat.st_size + _size(_note_path(path)), stat.st_mtime, note.get("build_seconds", {})))
    return sorted(found, key=lambda e: -e.last_used)


def clear():
    """Remove every cached model (and its note, and unfinished writes). -> (files, bytes) removed"""
    removed = [e for e in entries() if _remove(e.path)]
    folder = cache_dir()
    if folder.is_dir():
        for stale in folder.glob(f".*{SUFFIX}.*.tmp"):
            _remove(stale)
    return len(removed), sum(e.size for e in removed)


def touch(path):
    """Mark a cached file as used now (its modification time: the LRU order), and record in
    its note the size and time it now has (:func:`cached_model` trusts a file that still has them)."""
    with contextlib.suppress(OSError):
        os.utime(path)
        note = _note(path)
        if note:
            _note_path(path).write_text(json.dumps(dict(note, stamp=_stamp(path))))


def make_room(nbytes, limit=None):
    """Remove least recently used models until ``nbytes`` more fit under ``limit`` (default
    :func:`cache_limit`). -> whether they fit (False: larger than the limit itself)"""
    limit = cache_limit() if limit is None else limit
    if nbytes > limit:
        return False
    held = entries()
    total = sum(e.size for e in held)
    for e in reversed(held):  # least recently used first
        if total + nbytes <= limit:
            break
        if _remove(e.path):
            log.debug("model cache: removed %s (%d bytes), least recently used", e.path.name, e.size)
            total -= e.size
    return total + nbytes <= limit


def cached_model(name, source_hash, options, version, build, load, expected_bytes):
    """The model of a named object: read from the cache when there, else built and stored.

    name : the object's name; source_hash, options, version : the key (:func:`entry_path`;
    the hash of what the model is built from); a file is used when the model it holds
    has the mesh hash its note recorded when it was stored;
    build : () -> model (with ``build_seconds`` and ``save(path, mappable)``); load : (path, verify) ->
    model, where verify asks for the full check of the file's content (False when the file
    has the size and time its note recorded: see the module's notes), which raises
    ModelFileError for a file it cannot use (then the model is built again and stored) or
    ResourceError when it does not fit in memory (then the build runs, and its memory check
    speaks for itself);
    expected_bytes : model -> bytes its file will take (for the size limit). A cache that
    cannot be written gives one warning and the built model."""
    path = entry_path(name, source_hash, options, version)
    if path.is_file():
        note = _note(path)
        try:
            model = load(path, note.get("stamp") != _stamp(path))
        except ResourceError as exc:  # building says what memory it needs, and what to do, for itself
            log.debug("model cache: %s does not fit in memory (%s); building %s instead", path, exc, name)
        except ModelFileError as exc:
            log.warning("model cache: %s cannot be used (%s); building %s again", path, exc, name)
        else:
            if model.mesh_hash == note.get("mesh_hash"):
                touch(path)
                model.build_seconds = dict(note.get("build_seconds", {}))
                log.debug("model cache: %s from %s", name, path)
                return model
            log.warning("model cache: %s does not match its note; building %s again", path, name)
    model = build()
    _store(model, path, name, expected_bytes(model))
    return model


def _store(model, path, name, nbytes):
    """Write ``model`` to ``path`` with its note, after making room; warn (once per call) when
    the cache cannot take it."""
    if not make_room(nbytes):
        warnings.warn(f"the model of {name} ({nbytes / 2**30:.2f} GiB) is larger than the model cache's limit "
                      f"({cache_limit() / 2**30:.2f} GiB, ${CACHE_LIMIT_ENV}); it is not cached", stacklevel=3)
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        model.save(path, mappable=True)  # memory-mapped when read: ready in milliseconds
        _note_path(path).write_text(json.dumps({"name": name, "mesh_hash": model.mesh_hash, "created": time.time(),
                                                "stamp": _stamp(path), "build_seconds": dict(model.build_seconds)}))
    except (OSError, ModelFileError) as exc:
        _remove(path)
        warnings.warn(f"cannot write the model cache in {path.parent} ({exc}); {name} will be built again next time",
                      stacklevel=3)
        return
    log.debug("model cache: %s stored in %s", name, path)


def _note_path(path):
    return Path(path).with_suffix(".json")


def _note(path):
    """The note beside a cached model ({} when missing or unreadable)."""
    try:
        return json.loads(_note_path(path).read_text())
    except (OSError, ValueError):
        return {}


def _stamp(path):
    """[bytes, modification time in ns] of a file, or None when it cannot be read."""
    try:
        stat = os.stat(path)
    except OSError:
        return None
    return [stat.st_size, stat.st_mtime_ns]


def _size(path):
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


def _remove(path):
    """Remove a model file and its note. -> whether the model file went"""
    with contextlib.suppress(OSError):
        os.unlink(_note_path(path))
    try:
        os.unlink(path)
    except OSError:
        return False
    return True
