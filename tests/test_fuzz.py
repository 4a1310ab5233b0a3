"""Fuzzing of the contacts and prior parsers and the model loader.

The contract: whatever the input, the outcome is a result or a ContactPoseError.
Inputs are drawn by hypothesis: arbitrary JSON-like values, mutated valid
documents, arbitrary bytes as files, and model files that are truncated,
bit-flipped (uniformly, or aimed at the zip headers), random, rewritten with
altered arrays, or rebuilt with .npy headers that do not match their data.

Exceptions of a known library bug (``KNOWN_BUGS``, each reproduced by a strict
xfail test in tests/test_errors.py) are counted but do not fail a test; any
other exception does. Remove an entry once its xfail test starts passing.

Example counts: ``CONTACTPOSE_FUZZ_EXAMPLES`` per test (default 100).
``CONTACTPOSE_FUZZ_LOG=path`` appends each test's outcome counts as JSON lines
(experiments/fuzz.py uses it).
"""

import collections
import contextlib
import io as pyio
import itertools
import json
import math
import os
import traceback
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from contactpose.errors import ContactPoseError
from contactpose.io import jsonfiles as io
from contactpose.io import modelfile as model_module
from contactpose.model.object_model import ObjectModel

EXAMPLES = int(os.environ.get("CONTACTPOSE_FUZZ_EXAMPLES", "100"))
#: derandomize comes from the profile conftest.py loads: the same cases on every run (a CI
#: failure can be reproduced), new ones with CONTACTPOSE_HYPOTHESIS=explore.
FUZZ = settings(max_examples=EXAMPLES, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.filter_too_much, HealthCheck.large_base_example])
#: Of the structured contacts documents, 3 in 4 are drawn well-formed (each must then parse).
WELL_FORMED_DRAWS = (True, True, True, False)
EXAMPLES_DIR = Path(__file__).resolve().parents[1] / "examples"

#: Uncaught exceptions of known library bugs: (exception class, a contactpose function on
#: the stack) -> the xfail test in tests/test_errors.py that reproduces it. Empty: the
#: loader bugs of the first run (BadZipFile/TokenError in model._mmap_npz, TypeError/
#: ValueError in model._from_arrays) are fixed.
KNOWN_BUGS = {}

#: test name -> Counter of outcomes ("result", "ContactPoseError", "known:...", "uncaught:...").
OUTCOMES = collections.defaultdict(collections.Counter)


def stack(exc):
    """'module.function' of the named traceback frames inside the contactpose package, outermost first."""
    frames = []
    for frame in traceback.extract_tb(exc.__traceback__):
        parts = Path(frame.filename).parts
        if "contactpose" in parts and "tests" not in parts and not frame.name.startswith("<"):
            frames.append(f"{Path(frame.filename).stem}.{frame.name}")
    return frames or ["outside"]


def known_bug(exc):
    """The KNOWN_BUGS key that exc belongs to, or None."""
    frames = stack(exc)
    for kind, function in KNOWN_BUGS:
        if isinstance(exc, kind) and function in frames:
            return kind, function
    return None


def outcome(test, fn, *args, **kwargs):
    """Run fn; count the outcome under ``test``; re-raise anything but a result,
    a ContactPoseError, or a known bug. Returns the result or None."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unit warnings, numpy overflow warnings: not failures
        try:
            result = fn(*args, **kwargs)
        except ContactPoseError as exc:
            OUTCOMES[test][f"ContactPoseError:{type(exc).__name__}"] += 1
            return None
        except Exception as exc:
            label = f"{type(exc).__name__}@{stack(exc)[-1]}"
            if known_bug(exc):
                OUTCOMES[test][f"known:{label}"] += 1
                return None
            OUTCOMES[test][f"uncaught:{label}"] += 1
            raise
    OUTCOMES[test]["result"] += 1
    return result


@pytest.fixture(scope="module", autouse=True)
def _outcome_log():
    yield
    path = os.environ.get("CONTACTPOSE_FUZZ_LOG")
    if path:
        with open(path, "a", encoding="utf-8") as fh:
            for test, counts in OUTCOMES.items():
                fh.write(json.dumps({"module": "test_fuzz", "test": test, "examples": EXAMPLES,
                                     "outcomes": dict(counts)}) + "\n")


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


# ------------------------------------------------------------------ strategies

KEYS = ["contacts", "point", "finger_normal", "object_normal", "pose", "sigma_rot_deg", "sigma_trans",
        "covariance"]
numbers = (st.integers() | st.floats() | st.sampled_from([0, -0.0, 1e-320, 1e308, -1e308, 10 ** 400, math.nan,
                                                          math.inf, -math.inf]))
scalars = st.none() | st.booleans() | numbers | st.text(max_size=8)
json_values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=6)
    | st.dictionaries(st.sampled_from(KEYS) | st.text(max_size=6), inner, max_size=5),
    max_leaves=30,
)
finite = st.floats(-1.0, 1.0) | st.floats(allow_nan=False, allow_infinity=False)
good_vectors = st.lists(finite, min_size=3, max_size=3)
vectors = good_vectors | st.lists(numbers, min_size=3, max_size=3) | st.lists(numbers, max_size=5) | json_values
messy_contacts = st.fixed_dictionaries(
    {}, optional={"point": vectors, "finger_normal": vectors, "object_normal": vectors, "extra": json_values})


def mostly(good, bad, odds=5):
    """good, except one draw in ``odds`` from bad."""
    return st.integers(0, odds - 1).flatmap(lambda k: good if k else bad)


#: A contact point of a grasp: coordinates within a few metres, in any unit's range of values.
coordinates = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
#: A normal with a direction: its length between 1e-3 and 10 (non-unit lengths are normalised).
usable_normals = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(
    lambda v: 1e-3 < math.hypot(*v) < 10.0)


@st.composite
def well_formed_contacts(draw):
    """A valid contacts document: 2-6 contacts at distinct points (at least 1e-6 apart), each
    with a usable normal, all of one kind. -> (document, points (n, 3), unit outward normals (n, 3))"""
    kind = draw(st.sampled_from(["finger_normal", "object_normal"]))
    points = draw(st.lists(st.lists(coordinates, min_size=3, max_size=3), min_size=2, max_size=6,
                           unique_by=lambda p: tuple(round(x, 5) for x in p)))
    normals = draw(st.lists(usable_normals, min_size=len(points), max_size=len(points)))
    doc = {"contacts": [{"point": p, kind: n} for p, n in zip(points, normals)]}
    unit = np.array(normals) / np.linalg.norm(normals, axis=1, keepdims=True)
    return doc, np.array(points), unit if kind == "object_normal" else -unit


@st.composite
def contact_docs(draw):
    """Contacts documents, most of them well-formed (WELL_FORMED_DRAWS, :func:`well_formed_contacts`),
    the others messy: special or arbitrary vectors, missing fields, a duplicate contact.
    -> (document, the expected (points, outward normals) or None when it may be refused)"""
    if draw(st.sampled_from(WELL_FORMED_DRAWS)):
        doc, points, normals = draw(well_formed_contacts())
        return doc, (points, normals)
    if draw(st.booleans()):
        return {"contacts": draw(st.lists(messy_contacts, max_size=6))}, None
    kind = draw(st.sampled_from(["finger_normal", "object_normal"]))
    special = st.sampled_from([[0, 0, 0], [0, 0, 1], [1e-300, 0, 0], [1e308, 1e308, 0], [1e200, 0, 0]])
    vec = mostly(good_vectors, special | vectors)
    contacts = draw(st.lists(st.fixed_dictionaries({"point": vec, kind: vec}), min_size=2, max_size=6))
    if contacts and draw(st.booleans()):
        contacts.append(dict(draw(st.sampled_from(contacts))))  # a duplicate contact
    return {"contacts": contacts}, None


def matrices(rows, cols):
    exact = st.lists(st.lists(numbers, min_size=cols, max_size=cols), min_size=rows, max_size=rows)
    return exact | st.lists(st.lists(numbers, max_size=cols + 1), max_size=rows + 1) | json_values


@st.composite
def rigid_poses(draw):
    """A 4x4 pose: a rotation from a random quaternion, sometimes perturbed, as nested lists."""
    q = np.array(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)))
    q = q / np.linalg.norm(q) if np.linalg.norm(q) > 1e-3 else np.array([1.0, 0, 0, 0])
    w, x, y, z = q
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = draw(st.lists(finite, min_size=3, max_size=3))
    if draw(st.booleans()):
        i, j = draw(st.integers(0, 3)), draw(st.integers(0, 3))
        T[i, j] += draw(st.sampled_from([1e-9, 1e-6, 1e-3, -1.0, math.nan]))
    return T.tolist()


@st.composite
def prior_docs(draw):
    """Mostly well-formed prior documents (4x4 pose, sigmas or a 6x6 covariance), some messy."""
    if draw(st.integers(0, 3)) == 0:
        return draw(st.fixed_dictionaries(
            {}, optional={"pose": matrices(4, 4), "sigma_rot_deg": numbers | json_values,
                          "sigma_trans": numbers | json_values, "covariance": matrices(6, 6)}))
    doc = {"pose": draw(mostly(rigid_poses(), matrices(4, 4)))}
    if draw(st.booleans()):
        A = np.array(draw(st.lists(st.floats(-10.0, 10.0), min_size=36, max_size=36))).reshape(6, 6)
        doc["covariance"] = draw(st.sampled_from([A @ A.T, A, A + A.T])).tolist()
    else:
        sigma = mostly(st.floats(1e-6, 100.0), numbers)
        doc.update(sigma_rot_deg=draw(sigma), sigma_trans=draw(sigma))
    return doc


def valid_contacts():
    return json.loads((EXAMPLES_DIR / "banana_contacts.json").read_text())


def valid_prior():
    return json.loads((EXAMPLES_DIR / "banana_prior.json").read_text())


@st.composite
def mutated(draw, base):
    """A valid JSON document with 1-4 random edits at random places."""
    doc = base()
    for _ in range(draw(st.integers(1, 4))):
        doc = _edit(draw, doc)
    return doc


def _paths(doc, prefix=()):
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, prefix + (i,))


def _edit(draw, doc):
    paths = list(_paths(doc))
    path = draw(st.sampled_from(paths))
    if not path:
        return draw(json_values) if draw(st.integers(0, 9)) == 0 else doc
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    key, value = path[-1], parent[path[-1]]
    action = draw(st.sampled_from(["replace", "delete", "scale", "duplicate", "rename", "wrap"]))
    if action == "replace":
        parent[key] = draw(json_values)
    elif action == "delete":
        del parent[key]
    elif action == "scale" and isinstance(value, (int, float)) and not isinstance(value, bool):
        factor = draw(st.sampled_from([0, -1, 1e-9, 1000, 1e300, math.nan, math.inf]))
        try:
            parent[key] = value * factor
        except OverflowError:  # an int beyond float range times a float
            parent[key] = factor
    elif action == "duplicate" and isinstance(parent, list):
        parent.insert(key, json.loads(json.dumps(value)))
    elif action == "rename" and isinstance(parent, dict):
        parent[draw(st.sampled_from(KEYS) | st.text(max_size=4))] = parent.pop(key)
    elif action == "wrap":
        parent[key] = [value]
    return doc


# ---------------------------------------------------------------- the parsers

@FUZZ
@given(json_values)
def test_parse_contacts_any_value(data):
    outcome("parse_contacts_any_value", io.parse_contacts, data)


@FUZZ
@given(contact_docs())
def _parse_structured(case):
    data, expected = case
    result = outcome("parse_contacts_structured", io.parse_contacts, data)
    if expected is not None:  # a well-formed document parses to exactly its contacts
        assert result is not None, data
        np.testing.assert_allclose(result.points, expected[0], rtol=0, atol=0)
        np.testing.assert_allclose(result.object_normals, expected[1], rtol=1e-12, atol=1e-12)


def test_parse_contacts_structured():
    """Structured documents: each a result or a ContactPoseError, each well-formed one its
    own contacts; and valid input is what is mostly fuzzed."""
    OUTCOMES["parse_contacts_structured"].clear()
    _parse_structured()
    counts = OUTCOMES["parse_contacts_structured"]
    assert counts["result"] >= 0.5 * sum(counts.values()), dict(counts)


def test_fuzzing_draws_the_same_cases_on_every_run():
    """The default profile (conftest.py) derandomizes the fuzz settings: two runs draw the
    same documents, so a failure in CI is one that a rerun reproduces."""
    if os.environ.get("CONTACTPOSE_HYPOTHESIS", "repeatable") != "repeatable":
        pytest.skip("CONTACTPOSE_HYPOTHESIS asks for new cases")
    drawn = []

    @settings(FUZZ, max_examples=25)
    @given(contact_docs())
    def record(case):
        drawn.append(json.dumps(case[0], default=str))

    record()
    first, drawn[:] = list(drawn), []
    record()
    assert FUZZ.derandomize and drawn == first


@FUZZ
@given(mutated(valid_contacts))
def test_parse_contacts_mutated(data):
    outcome("parse_contacts_mutated", io.parse_contacts, data)


@FUZZ
@given(json_values)
def test_parse_prior_any_value(data):
    outcome("parse_prior_any_value", io.parse_prior, data)


@FUZZ
@given(prior_docs())
def test_parse_prior_structured(data):
    outcome("parse_prior_structured", io.parse_prior, data)


@FUZZ
@given(mutated(valid_prior))
def test_parse_prior_mutated(data):
    outcome("parse_prior_mutated", io.parse_prior, data)


@st.composite
def file_bytes(draw, example):
    """Arbitrary bytes, or the example file's text with random byte edits."""
    if draw(st.booleans()):
        return draw(st.binary(max_size=600))
    raw = bytearray((EXAMPLES_DIR / example).read_bytes())
    for _ in range(draw(st.integers(1, 6))):
        i = draw(st.integers(0, len(raw) - 1))
        op = draw(st.sampled_from(["set", "delete", "insert"]))
        if op == "set":
            raw[i] = draw(st.integers(0, 255))
        elif op == "delete":
            del raw[i]
        else:
            raw[i:i] = draw(st.binary(min_size=1, max_size=8))
    return bytes(raw)


@FUZZ
@given(file_bytes("banana_contacts.json"))
def test_read_contacts_any_bytes(scratch, raw):
    path = scratch / "contacts.json"
    path.write_bytes(raw)
    outcome("read_contacts_any_bytes", io.read_contacts, path)


@FUZZ
@given(file_bytes("banana_prior.json"))
def test_read_prior_any_bytes(scratch, raw):
    path = scratch / "prior.json"
    path.write_bytes(raw)
    outcome("read_prior_any_bytes", io.read_prior, path)


# ----------------------------------------------------------- the model loader

def _tiny_mesh():
    """A 20-facet irregular closed mesh: a jittered icosahedron (fixed seed)."""
    ico = trimesh.creation.icosahedron()
    rng = np.random.default_rng(3)
    v = ico.vertices * (1.0 + 0.25 * rng.uniform(-1.0, 1.0, (len(ico.vertices), 1))) * 0.05
    return trimesh.Trimesh(v, ico.faces, process=False)


@pytest.fixture(scope="module")
def model_files(scratch):
    """(model, {"plain": bytes, "compressed": bytes}, arrays) of a small model file."""
    model = ObjectModel.from_mesh(_tiny_mesh(), bins=(3, 3, 3))
    plain = Path(model.save(scratch / "model.npz")).read_bytes()
    with np.load(scratch / "model.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    buf = pyio.BytesIO()
    np.savez_compressed(buf, **arrays)
    return model, {"plain": plain, "compressed": buf.getvalue()}, arrays


def _header_offsets(raw):
    """Byte offsets of the zip structure: local headers, central directory entries, end record."""
    spots = []
    for sig, width in ((b"PK\x03\x04", 30), (b"PK\x01\x02", 46), (b"PK\x05\x06", 22), (b"\x93NUMPY", 10)):
        start = raw.find(sig)
        while start >= 0:
            spots.extend(range(start, min(start + width, len(raw))))
            start = raw.find(sig, start + 1)
    return spots


def _same_model(a, b):
    """Every stored array of b equals a's (a corrupted file must not load a different model)."""
    assert a.mesh_hash == b.mesh_hash and a.bounds == b.bounds and a.diameter == b.diameter
    for name in ("k", "l", "dmax", "dmin_exact", "alpha"):
        assert np.array_equal(getattr(a.features, name), getattr(b.features, name))
    assert np.array_equal(a.table.offsets, b.table.offsets) and tuple(a.bins) == tuple(b.bins)


_serial = itertools.count()


@contextlib.contextmanager
def memory_mapped(on):
    """Make ObjectModel.load take its memory-mapped path (files >= MMAP_MIN_BYTES) for every file."""
    old = getattr(model_module, "MMAP_MIN_BYTES", None)
    if on and old is not None:
        model_module.MMAP_MIN_BYTES = 0
    try:
        yield
    finally:
        if old is not None:
            model_module.MMAP_MIN_BYTES = old


def _load_bytes(scratch, raw, mmap=False):
    # a new file each time: rewriting a file that an earlier (memory-mapped) model maps can SIGBUS
    path = scratch / f"fuzzed{next(_serial)}.npz"
    path.write_bytes(raw)
    try:
        with memory_mapped(mmap):
            return ObjectModel.load(path)
    finally:
        path.unlink()


@FUZZ
@given(st.data())
def test_load_truncated(scratch, model_files, data):
    model, raw, _ = model_files
    kind = data.draw(st.sampled_from(sorted(raw)))
    cut = data.draw(st.integers(0, len(raw[kind]) - 1))
    loaded = outcome("load_truncated", _load_bytes, scratch, raw[kind][:cut], mmap=data.draw(st.booleans()))
    assert loaded is None, f"a {kind} model file cut at {cut} of {len(raw[kind])} bytes loaded"


@FUZZ
@given(st.data())
def test_load_bit_flipped(scratch, model_files, data):
    model, raw, _ = model_files
    kind = data.draw(st.sampled_from(sorted(raw)))
    buf = bytearray(raw[kind])
    headers = _header_offsets(raw[kind])
    positions = st.integers(0, len(buf) - 1) | st.sampled_from(headers)
    for pos, bit in data.draw(st.lists(st.tuples(positions, st.integers(0, 7)), min_size=1, max_size=8)):
        buf[pos] ^= 1 << bit
    loaded = outcome("load_bit_flipped", _load_bytes, scratch, bytes(buf), mmap=data.draw(st.booleans()))
    if loaded is not None:
        _same_model(model, loaded)


@FUZZ
@given(st.binary(max_size=2000) | st.binary(max_size=2000).map(lambda b: b"PK\x03\x04" + b), st.booleans())
def test_load_random_bytes(scratch, raw, mmap):
    outcome("load_random_bytes", _load_bytes, scratch, raw, mmap=mmap)


array_values = hnp.arrays(
    dtype=st.sampled_from([np.int64, np.int32, np.float64, np.float32, np.bool_, np.dtype("<U3")]),
    shape=hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4),
)


@FUZZ
@given(st.data())
def test_load_altered_arrays(scratch, model_files, data):
    """A well-formed .npz whose arrays were dropped, replaced, retyped or cut, after saving
    (the content hash is stale) or by the writer (the hash is recomputed)."""
    _, _, arrays = model_files
    changed = dict(arrays)
    for _ in range(data.draw(st.integers(1, 3))):
        key = data.draw(st.sampled_from(sorted(changed)))
        action = data.draw(st.sampled_from(["drop", "replace", "retype", "cut", "add"]))
        if action == "drop":
            del changed[key]
        elif action == "replace":
            changed[key] = data.draw(array_values)
        elif action == "retype":
            dtype = data.draw(st.sampled_from([np.int8, np.float16, np.bool_, "<U2"]))
            with warnings.catch_warnings(), np.errstate(all="ignore"):
                warnings.simplefilter("ignore")
                try:
                    changed[key] = changed[key].astype(dtype)
                except (TypeError, ValueError):  # e.g. "exact" as int8: not a model file problem
                    pass
        elif action == "cut" and changed[key].ndim:
            changed[key] = changed[key][:data.draw(st.integers(0, max(0, len(changed[key]) - 1)))]
        elif action == "add":
            changed[data.draw(st.text("abc_", min_size=1, max_size=6))] = data.draw(array_values)
    if data.draw(st.booleans()) and hasattr(model_module, "content_hash"):
        changed.pop("content_hash", None)
        changed["content_hash"] = np.array(model_module.content_hash(changed))
    buf = pyio.BytesIO()
    np.savez(buf, **changed)
    outcome("load_altered_arrays", _load_bytes, scratch, buf.getvalue(), mmap=data.draw(st.booleans()))


header_shapes = st.lists(st.integers(0, 64) | st.integers(-3, 2 ** 62) | st.sampled_from([10 ** 13, 2 ** 63, 10 ** 30]),
                         max_size=3).map(tuple)
header_dtypes = st.sampled_from(["<f8", "<f4", "<f2", "<i8", "<i4", "|i1", "|b1", "<U3", "|S0", "|V7", "|O", ">f8"])


def _npy_bytes(a, header=None):
    """The .npy bytes of array a, with its header dict replaced by ``header`` (data unchanged)."""
    buf = pyio.BytesIO()
    if header is None:
        np.lib.format.write_array(buf, a, allow_pickle=False)
    else:
        np.lib.format.write_array_header_1_0(buf, header)
        buf.write(np.ascontiguousarray(a).tobytes())
    return buf.getvalue()


@FUZZ
@given(st.data())
def test_load_rewritten_headers(scratch, model_files, data):
    """A zip with valid CRCs whose .npy headers declare other shapes, dtypes or orders than their
    data holds, whose data is cut or padded, or whose member lost its .npy suffix (a hand-made
    or buggy file: huge declared arrays must not reach an allocation)."""
    model, _, arrays = model_files
    members = {f"{k}.npy": _npy_bytes(a) for k, a in arrays.items()}
    for _ in range(data.draw(st.integers(1, 3))):
        key = data.draw(st.sampled_from(sorted(arrays)))
        a = arrays[key]
        header = {"descr": data.draw(st.just(np.lib.format.dtype_to_descr(a.dtype)) | header_dtypes),
                  "fortran_order": data.draw(st.booleans()), "shape": data.draw(st.just(a.shape) | header_shapes)}
        raw = _npy_bytes(a, header)
        edit = data.draw(st.sampled_from(["keep", "cut", "pad", "rename"]))
        if edit == "cut":
            raw = raw[:data.draw(st.integers(0, len(raw)))]
        elif edit == "pad":
            raw += data.draw(st.binary(min_size=1, max_size=64))
        members.pop(f"{key}.npy", None)
        members[key if edit == "rename" else f"{key}.npy"] = raw  # np.load gives a member without .npy as bytes
    buf = pyio.BytesIO()
    method = data.draw(st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]))
    with zipfile.ZipFile(buf, "w", method) as zf:
        for name, raw in members.items():
            zf.writestr(name, raw)
    loaded = outcome("load_rewritten_headers", _load_bytes, scratch, buf.getvalue(), mmap=data.draw(st.booleans()))
    if loaded is not None:
        _same_model(model, loaded)


def test_fuzz_model_file_is_readable(model_files):
    """The files fuzzed above are valid to start with."""
    model, raw, _ = model_files
    assert zipfile.is_zipfile(pyio.BytesIO(raw["plain"])) and zipfile.is_zipfile(pyio.BytesIO(raw["compressed"]))
    assert model.num_facets == 20
