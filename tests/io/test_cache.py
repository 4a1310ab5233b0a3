"""The model cache (contactpose.io.cache): where it lives, a model built once and then read
back equal, the least recently used files evicted first under the size limit, damaged or
unwritable caches handled with one warning, and ``contactpose cache list | clear``."""

import logging
import os
import warnings

import numpy as np
import pytest

from contactpose.cli import main
from contactpose.errors import ContactPoseError
from contactpose.io import cache, modelfile
from contactpose.model import object_model
from contactpose.model.object_model import ObjectModel, load_mesh, mesh_hash
from contactpose.sim import objects

OPTIONS = {"bins": [32, 32, 64], "bounds": "exact", "fix_normals": False, "max_span": None}


@pytest.fixture
def folder(tmp_path, monkeypatch):
    monkeypatch.setenv(cache.CACHE_DIR_ENV, str(tmp_path / "models"))
    monkeypatch.delenv(cache.CACHE_LIMIT_ENV, raising=False)
    return tmp_path / "models"


def _cached(name, builds, **kwargs):
    """The model of a built-in object through the cache, counting the builds."""
    mesh = objects.load(name)

    def build():
        builds.append(name)
        return ObjectModel.from_mesh(mesh)

    return cache.cached_model(name, mesh_hash(*load_mesh(mesh)), dict(OPTIONS, **kwargs), "0.1.0", build,
                              lambda path, verify: ObjectModel.load(path, verify=verify, mmap=True),
                              lambda m: m.nbytes)


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(cache.CACHE_DIR_ENV, str(tmp_path / "mine"))
    assert cache.cache_dir() == tmp_path / "mine"
    monkeypatch.delenv(cache.CACHE_DIR_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache.cache_dir() == tmp_path / "xdg" / "contactpose" / "models"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache.cache_dir() == tmp_path / "home" / ".cache" / "contactpose" / "models"


def test_a_model_is_built_once_and_read_back_equal(folder):
    builds = []
    first = _cached("banana", builds)
    second = _cached("banana", builds)
    assert builds == ["banana"]
    for a, b in ((first.vertices, second.vertices), (first.faces, second.faces), (first.planes.normals,
                 second.planes.normals), (first.table.offsets, second.table.offsets)):
        assert np.array_equal(a, b)
    assert second.mesh_hash == first.mesh_hash and second.build_seconds == pytest.approx(first.build_seconds)
    assert isinstance(second.table.offsets, np.memmap)  # stored uncompressed, mapped when read
    [entry] = cache.entries()
    assert entry.name == "banana" and entry.size == sum(p.stat().st_size for p in folder.iterdir())
    _cached("banana", builds, max_span=0.05)  # other build options: another file
    assert builds == ["banana", "banana"] and len(cache.entries()) == 2


def test_a_damaged_file_is_built_again(folder, caplog):
    builds = []
    _cached("rock", builds)
    [entry] = cache.entries()
    data = bytearray(entry.path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    entry.path.write_bytes(bytes(data))
    later = entry.path.stat().st_mtime_ns + 10**9  # written later than the store (a coarse clock may not say so)
    os.utime(entry.path, ns=(later, later))
    with caplog.at_level(logging.WARNING, logger="contactpose.io.cache"):
        _cached("rock", builds)
    assert builds == ["rock", "rock"] and "cannot be used" in caplog.text
    assert _cached("rock", builds) is not None and builds == ["rock", "rock"]  # the rebuilt file serves


def test_an_unchanged_file_skips_the_full_check_and_a_changed_one_gets_it(folder, monkeypatch):
    """The content hash runs for a cached file that changed since the cache used it, and only then."""
    builds, hashed = [], []
    _cached("rock", builds)
    real = modelfile.content_hash
    monkeypatch.setattr(modelfile, "content_hash", lambda arrays: hashed.append(1) or real(arrays))
    monkeypatch.setattr(object_model, "content_hash", modelfile.content_hash)
    first = _cached("rock", builds)
    assert builds == ["rock"] and hashed == []
    [entry] = cache.entries()
    later = entry.path.stat().st_mtime_ns + 10**9
    os.utime(entry.path, ns=(later, later))  # as another program writing the file would leave it
    second = _cached("rock", builds)
    assert builds == ["rock"] and hashed == [1] and np.array_equal(first.table.offsets, second.table.offsets)
    _cached("rock", builds)  # the check passed and the note took the new time: trusted again
    assert hashed == [1]


def test_least_recently_used_files_go_first(folder):
    """Five files of 100 bytes used at known times; room for 250 more under a 500-byte limit
    leaves the two most recently used (the reference: sort by time of use)."""
    folder.mkdir(parents=True)
    used = {f"o{i}": t for i, t in enumerate([50, 10, 40, 20, 30])}
    for name, t in used.items():
        path = folder / f"{name}__hash__f3__tag.npz"
        path.write_bytes(b"x" * 100)
        os.utime(path, (t, t))
    assert cache.make_room(250, limit=500)
    kept = sorted(used, key=used.get)[-2:]
    assert sorted(e.name for e in cache.entries()) == sorted(kept)
    assert not cache.make_room(501, limit=500)  # larger than the limit: nothing fits
    cache.touch(folder / f"{kept[0]}__hash__f3__tag.npz")
    assert cache.entries()[0].name == kept[0]  # used now: first in the listing


def test_a_model_beyond_the_limit_is_not_kept(folder, monkeypatch):
    monkeypatch.setenv(cache.CACHE_LIMIT_ENV, "0.00001")
    with pytest.warns(UserWarning, match="larger than the model cache's limit"):
        model = _cached("banana", [])
    assert model.num_facets == 53 and cache.entries() == []
    monkeypatch.setenv(cache.CACHE_LIMIT_ENV, "lots")
    with pytest.raises(ContactPoseError, match="CONTACTPOSE_CACHE_LIMIT_GIB must be a size in GiB >= 0, got 'lots'"):
        cache.cache_limit()


def test_an_unwritable_cache_warns_once_and_still_answers(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(cache.CACHE_DIR_ENV, str(blocker / "models"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = _cached("banana", [])
    assert model.num_facets == 53
    assert len(caught) == 1 and "cannot write the model cache" in str(caught[0].message)


def test_cli_builds_a_named_object_once_then_lists_and_clears(folder, capsys, monkeypatch):
    contacts = os.path.join(os.path.dirname(__file__), "..", "..", "examples", "banana_contacts.json")
    assert main(["localize", "banana", "--contacts", contacts]) == 0
    built = capsys.readouterr().out

    def refuse(*args, **kwargs):
        raise AssertionError("built again")

    monkeypatch.setattr(ObjectModel, "from_mesh", refuse)
    assert main(["localize", "banana", "--contacts", contacts]) == 0
    timeless = lambda text: [line for line in text.splitlines() if "time:" not in line]  # noqa: E731
    assert timeless(capsys.readouterr().out) == timeless(built)  # the same answer, from the cached model
    assert main(["cache", "list"]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"model cache: {folder} (limit 8 GiB)") and "  banana " in out and "1 model," in out
    assert main(["cache", "clear"]) == 0
    assert capsys.readouterr().out.startswith("removed 1 model (") and cache.entries() == []
