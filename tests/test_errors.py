"""Bad input gives a ContactPoseError (or a warning) that names the value and the expectation.

One test per case of the issue's list: meshes, contacts files, prior files, model files,
resource limits, and the CLI's contract (exit code 2, exactly one stderr line, no traceback).
Cases where the library falls short are written anyway and marked
``xfail(strict=True)`` with the reason, so they turn red the day they are fixed.
"""

import json
import os
import re
import subprocess
import sys
import warnings
import zipfile
from collections import namedtuple

import numpy as np
import pytest
import trimesh

import contactpose as cp
from contactpose import cli
from contactpose.contacts import Contacts
from contactpose.errors import ContactPoseError, ContactsError, MeshError, ModelFileError, PriorError, ResourceError
from contactpose.io import jsonfiles as io
from contactpose.io import modelfile as model_module
from contactpose.io.modelfile import FORMAT_VERSION
from contactpose.model.object_model import ObjectModel
from contactpose.sim import objects
from contactpose.types import PosePrior

#: Small bins keep the model files of these tests a few kB.
SMALL_BINS = (4, 4, 4)
GOOD_CONTACTS = [
    {"point": [0.0, 0.0, 0.02], "finger_normal": [0.0, 0.0, -1.0]},
    {"point": [0.0, 0.0, -0.02], "finger_normal": [0.0, 0.0, 1.0]},
    {"point": [0.05, 0.0, 0.0], "finger_normal": [-1.0, 0.0, 0.0]},
]
GOOD_PRIOR = {"pose": np.eye(4).tolist(), "sigma_rot_deg": 10.0, "sigma_trans": 0.01}


# --------------------------------------------------------------------- helpers

def raises(kind, *fragments):
    """pytest.raises(kind) that also checks each fragment occurs in the message."""
    return _Raises(kind, fragments)


class _Raises:
    def __init__(self, kind, fragments):
        self.kind, self.fragments, self.ctx = kind, fragments, pytest.raises(kind)

    def __enter__(self):
        self.info = self.ctx.__enter__()
        return self.info

    def __exit__(self, *exc):
        out = self.ctx.__exit__(*exc)
        if not out:  # another exception type: let it propagate unchanged
            return out
        message = str(self.info.value)
        for fragment in self.fragments:
            assert fragment in message, f"{fragment!r} not in message {message!r}"
        return out


def write_obj(path, vertices, faces, header=""):
    """A plain OBJ (1-based faces) in the given face order."""
    lines = [header] if header else []
    lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def write_json(path, data):
    path.write_text(json.dumps(data))
    return str(path)


def contacts_doc(*contacts):
    return {"contacts": [dict(c) for c in (contacts or GOOD_CONTACTS)]}


def recorded(fn, *args, **kwargs):
    """(result, [warning messages]) of fn(*args, **kwargs)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = fn(*args, **kwargs)
    return result, [str(w.message) for w in caught]


@pytest.fixture(scope="module")
def box_mesh():
    return objects.load("box")


@pytest.fixture(scope="module")
def box_small(box_mesh):
    """The box with small bins: a model file of a few kB."""
    return ObjectModel.from_mesh(box_mesh, bins=SMALL_BINS)


@pytest.fixture(scope="module")
def box_file(box_small, tmp_path_factory):
    return box_small.save(tmp_path_factory.mktemp("model") / "box.npz")


@pytest.fixture(scope="module")
def box_arrays(box_file):
    with np.load(box_file) as npz:
        return {k: npz[k] for k in npz.files}


def rewrite(tmp_path, arrays, resign=False, **changes):
    """A copy of a model file's arrays with some replaced (None: dropped), saved to tmp_path.

    resign : store a content hash of the changed arrays (a file written that way, not
    damaged afterwards), else keep the original hash (a file changed after saving).
    """
    data = {k: v for k, v in {**arrays, **changes}.items() if v is not None}
    if resign and hasattr(model_module, "content_hash"):
        data.pop("content_hash", None)
        data["content_hash"] = np.array(model_module.content_hash(data))
    path = tmp_path / "changed.npz"
    np.savez(path, **data)
    return str(path)


# ---------------------------------------------------------------------- meshes

def test_missing_mesh_file(tmp_path):
    path = str(tmp_path / "nope.stl")
    with raises(MeshError, path, "does not exist"):
        ObjectModel.from_mesh(path)


def test_mesh_path_is_a_directory(tmp_path):
    path = tmp_path / "folder.stl"
    path.mkdir()
    with raises(MeshError, str(path), "not a file"):
        ObjectModel.from_mesh(str(path))


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads files without read permission")
def test_mesh_file_without_read_permission(tmp_path, box_mesh):
    path = tmp_path / "locked.stl"
    box_mesh.export(path)
    path.chmod(0)
    with raises(MeshError, str(path)):
        ObjectModel.from_mesh(str(path))


@pytest.mark.parametrize("ext", ["ply", "off", "glb"])
def test_text_file_with_mesh_extension_names_the_file(tmp_path, ext):
    path = tmp_path / f"notes.{ext}"
    path.write_text("these are my notes, not a mesh\n")
    with raises(MeshError, "cannot read", str(path), "as a mesh"):
        ObjectModel.from_mesh(str(path))


@pytest.mark.parametrize("ext,content", [("stl", b"these are my notes, not a mesh\n"),
                                         ("stl", bytes(range(256)) * 2), ("obj", b"hello\n")])
def test_non_mesh_file_is_a_mesh_error(tmp_path, ext, content):
    """trimesh reads text or random bytes as an STL/OBJ with no faces: still a MeshError."""
    path = tmp_path / f"junk.{ext}"
    path.write_bytes(content)
    with raises(MeshError, "faces", "(0, 3)"):
        ObjectModel.from_mesh(str(path))


@pytest.mark.parametrize("ext", ["stl", "obj"])
def test_non_mesh_stl_or_obj_names_the_file(tmp_path, ext):
    path = tmp_path / f"notes.{ext}"
    path.write_text("these are my notes, not a mesh\n")
    with raises(MeshError, f"cannot read {str(path)!r} as a mesh", "no faces"):
        ObjectModel.from_mesh(str(path))


def test_unsupported_mesh_format(tmp_path):
    path = tmp_path / "mesh.xyz123"
    path.write_text("v 0 0 0\n")
    with raises(MeshError, str(path), "not supported"):
        ObjectModel.from_mesh(str(path))


def test_empty_mesh():
    with raises(MeshError, "m >= 1", "(0, 3)"):
        ObjectModel.from_mesh(trimesh.Trimesh())


def test_mesh_file_with_vertices_but_no_faces(tmp_path):
    path = write_obj(tmp_path / "points.obj", np.eye(3), [])
    with raises(MeshError, "m >= 1", "(0, 3)"):
        ObjectModel.from_mesh(path)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_vertex(box_mesh, bad):
    v = box_mesh.vertices.copy()
    v[3, 1] = bad
    with raises(MeshError, "1 non-finite vertices", "index 3"):
        ObjectModel.from_mesh(trimesh.Trimesh(v, box_mesh.faces, process=False))


def test_non_finite_vertex_in_file(tmp_path, box_mesh):
    v = box_mesh.vertices.copy()
    v[5, 0] = np.nan
    with raises(MeshError, "non-finite", "index 5"):
        ObjectModel.from_mesh(write_obj(tmp_path / "nan.obj", v, box_mesh.faces))


@pytest.mark.parametrize("face", [[0, 1, 5], [0, 1, -1]])
def test_face_index_out_of_range(face):
    mesh = trimesh.Trimesh(np.eye(3), [[0, 1, 2], face], process=False)
    with raises(MeshError, "face indices must lie in [0, 2]", str(max(face) if max(face) > 2 else min(face))):
        ObjectModel.from_mesh(mesh)


def test_face_index_out_of_range_in_ply(tmp_path):
    path = tmp_path / "oob.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 7\n")
    with raises(MeshError, "face indices must lie in [0, 2]", "7"):
        ObjectModel.from_mesh(str(path))


@pytest.mark.parametrize("ext,text", [
    ("obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n"),
    ("off", "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 7\n"),
])
def test_face_index_out_of_range_in_obj_off(tmp_path, ext, text):
    """trimesh itself rejects these; the error still names the file and says 'cannot read'."""
    path = tmp_path / f"oob.{ext}"
    path.write_text(text)
    with raises(MeshError, "cannot read", str(path)):
        ObjectModel.from_mesh(str(path))


def test_all_facets_degenerate():
    collinear = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], [[0, 1, 2], [1, 2, 3]], process=False)
    with raises(MeshError, "all 2 facets are degenerate"):
        ObjectModel.from_mesh(collinear)


def test_all_vertices_coincide():
    with raises(MeshError, "zero extent"):
        ObjectModel.from_mesh(trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False))


def test_some_facets_degenerate_warns_and_keeps_indices(box_mesh):
    v = np.concatenate([box_mesh.vertices, [[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0]]])
    k = len(box_mesh.vertices)
    faces = np.concatenate([box_mesh.faces[:10], [[k, k + 1, k + 2]], box_mesh.faces[10:]])
    model, messages = recorded(ObjectModel.from_mesh, trimesh.Trimesh(v, faces, process=False))
    assert any("1 degenerate facets excluded" in m and ": 10" in m for m in messages), messages
    assert model.num_facets == len(faces) and not model.planes.valid[10] and model.planes.valid.sum() == len(faces) - 1


def _flip(faces, rows):
    out = faces.copy()
    out[rows] = out[rows][:, ::-1]
    return out


def test_inconsistent_winding_warns(box_mesh):
    mesh = trimesh.Trimesh(box_mesh.vertices, _flip(box_mesh.faces, slice(0, 5)), process=False)
    _, messages = recorded(ObjectModel.from_mesh, mesh)
    assert any("winding is inconsistent" in m and "--fix-normals" in m for m in messages), messages


def test_fix_normals_repairs_inconsistent_winding(box_mesh):
    good = ObjectModel.from_mesh(box_mesh)
    mesh = trimesh.Trimesh(box_mesh.vertices, _flip(box_mesh.faces, slice(0, 5)), process=False)
    model, messages = recorded(ObjectModel.from_mesh, mesh, fix_normals=True)
    assert not any("winding" in m or "inward" in m for m in messages), messages
    np.testing.assert_allclose(model.planes.normals, good.planes.normals, atol=1e-12)
    assert np.array_equal(np.sort(model.faces, axis=1), np.sort(box_mesh.faces, axis=1))  # face order kept


def test_inverted_closed_mesh_warns(box_mesh):
    mesh = trimesh.Trimesh(box_mesh.vertices, box_mesh.faces[:, ::-1], process=False)
    _, messages = recorded(ObjectModel.from_mesh, mesh)
    assert any("point inward" in m and "--fix-normals" in m for m in messages), messages


def test_fix_normals_repairs_inverted_closed_mesh(box_mesh):
    good = ObjectModel.from_mesh(box_mesh)
    mesh = trimesh.Trimesh(box_mesh.vertices, box_mesh.faces[:, ::-1], process=False)
    model, messages = recorded(ObjectModel.from_mesh, mesh, fix_normals=True)
    assert not any("inward" in m for m in messages), messages
    np.testing.assert_allclose(model.planes.normals, good.planes.normals, atol=1e-12)


def test_cli_fix_normals_repairs_winding(tmp_path, box_mesh, capsys):
    path = write_obj(tmp_path / "flipped.obj", box_mesh.vertices, _flip(box_mesh.faces, [0, 7, 20]))
    out = str(tmp_path / "m.npz")
    assert cli.main(["build-model", path, "-o", out, "--bins", "4", "4", "4"]) == 0
    assert "warning: face winding is inconsistent" in capsys.readouterr().err
    assert cli.main(["build-model", path, "-o", out, "--bins", "4", "4", "4", "--fix-normals"]) == 0
    assert "warning" not in capsys.readouterr().err


@pytest.mark.parametrize("material", [
    "",                                        # the .mtl file itself is missing
    "newmtl skin\nKd 0.8 0.7 0.2\nmap_Kd missing_texture.png\n",  # the .mtl names a missing image
])
def test_obj_with_missing_texture_loads(tmp_path, box_mesh, material):
    if material:
        (tmp_path / "skin.mtl").write_text(material)
    path = tmp_path / "textured.obj"
    write_obj(path, box_mesh.vertices, box_mesh.faces, header="mtllib skin.mtl\nusemtl skin")
    text = path.read_text().replace("\nf ", "\nvt 0 0\nf ", 1)  # one texture coordinate too
    path.write_text(text)
    model, _ = recorded(ObjectModel.from_mesh, str(path), bins=SMALL_BINS)
    assert model.num_facets == len(box_mesh.faces)
    np.testing.assert_allclose(model.vertices[model.faces], box_mesh.vertices[box_mesh.faces])


# ------------------------------------------------------------- contacts files

def test_contacts_file_missing(tmp_path):
    path = str(tmp_path / "none.json")
    with raises(ContactsError, path, "does not exist"):
        io.read_contacts(path)


def test_contacts_file_is_a_directory(tmp_path):
    with raises(ContactsError, "cannot read", str(tmp_path)):
        io.read_contacts(tmp_path)


@pytest.mark.parametrize("text", ["", "{", '{"contacts": [}', "{'contacts': []}", '{"contacts": [1,]}'])
def test_contacts_invalid_json(tmp_path, text):
    path = tmp_path / "c.json"
    path.write_text(text)
    with raises(ContactsError, str(path), "is not valid JSON", "line 1"):
        io.read_contacts(path)


def test_contacts_not_utf8(tmp_path):
    path = tmp_path / "c.json"
    path.write_bytes(b'\xff\xfe{"contacts": []}')
    with raises(ContactsError, str(path), "not UTF-8"):
        io.read_contacts(path)


def test_contacts_integer_beyond_digit_limit(tmp_path):
    path = tmp_path / "c.json"
    path.write_text('{"contacts": [{"point": [' + "9" * 5000 + ", 0, 0]}]}")
    with raises(ContactsError, str(path), "digits"):
        io.read_contacts(path)


def test_contacts_nested_too_deeply(tmp_path):
    path = tmp_path / "c.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    with raises(ContactsError, str(path), "nested too deeply"):
        io.read_contacts(path)


@pytest.mark.parametrize("data", [None, [], [1, 2], {"contact": []}, {"contacts": {"point": [0, 0, 0]}}])
def test_contacts_top_level_shape(data):
    with raises(ContactsError, 'must be an object {"contacts": [...]}', "got " + json.dumps(data)[:20]):
        io.parse_contacts(data)


def test_contacts_missing_point():
    with raises(ContactsError, "contact 1", '"point"', "finger_normal"):
        io.parse_contacts(contacts_doc(GOOD_CONTACTS[0], {"finger_normal": [0, 0, 1]}))


def test_contacts_entry_not_an_object():
    with raises(ContactsError, "contact 0 must be an object", "[0, 0, 0]"):
        io.parse_contacts({"contacts": [[0, 0, 0], GOOD_CONTACTS[1]]})


@pytest.mark.parametrize("field,value", [
    ("point", [0.0, 0.0]), ("point", [[0.0, 0.0, 0.0]]), ("point", [0, 0, 0, 0]), ("point", ["0", 0, 0]),
    ("point", [True, 0, 0]), ("point", "0 0 0"), ("point", None), ("finger_normal", [0, 1]),
    ("finger_normal", {"x": 1}),
])
def test_contacts_wrong_shape_or_type(field, value):
    bad = dict(GOOD_CONTACTS[1], **{field: value})
    with raises(ContactsError, f"contact 1 {field} must be a list of 3 numbers", "got " + json.dumps(value)[:10]):
        io.parse_contacts(contacts_doc(GOOD_CONTACTS[0], bad))


def test_contacts_coordinate_too_large_for_float():
    bad = dict(GOOD_CONTACTS[0], point=[10 ** 400, 0, 0])
    with raises(ContactsError, "contact 0 point", "representable as a float"):
        io.parse_contacts(contacts_doc(bad, GOOD_CONTACTS[1]))


@pytest.mark.parametrize("kind", ["both", "neither"])
def test_contacts_both_or_neither_normal(kind):
    c = {"point": [0.0, 0.0, 0.0]}
    if kind == "both":
        c.update(finger_normal=[0, 0, 1], object_normal=[0, 0, -1])
    want = "['finger_normal', 'object_normal']" if kind == "both" else "neither"
    with raises(ContactsError, 'contact 0 needs exactly one of "finger_normal" or "object_normal"', want):
        io.parse_contacts(contacts_doc(c, GOOD_CONTACTS[1]))


def test_contacts_mixed_normal_kinds():
    other = {"point": [0.0, 0.0, -0.02], "object_normal": [0.0, 0.0, -1.0]}
    with raises(ContactsError, "same kind of normal", "both kinds"):
        io.parse_contacts(contacts_doc(GOOD_CONTACTS[0], other))


def test_contacts_both_normals_in_the_constructor():
    with raises(ContactsError, "exactly one of finger_normals or object_normals"):
        Contacts(np.zeros((2, 3)), finger_normals=np.eye(3)[:2], object_normals=np.eye(3)[:2])


@pytest.mark.parametrize("points,normals,want", [
    (np.zeros((3, 2)), np.zeros((3, 2)), "points must have shape (n, 3), got shape (3, 2)"),
    (np.eye(3), np.eye(3)[:2], "finger_normals must have shape (3, 3), got shape (2, 3)"),
    ([[0, 0, "a"], [1, 0, 0]], np.eye(3)[:2], "points must be numbers of shape (n, 3)"),
])
def test_contacts_constructor_shapes(points, normals, want):
    with raises(ContactsError, want):
        Contacts(points, finger_normals=normals)


def test_zero_normal():
    bad = dict(GOOD_CONTACTS[1], finger_normal=[0.0, 0.0, 0.0])
    with raises(ContactsError, "finger_normals row 1 is a zero vector", "needs a direction"):
        io.parse_contacts(contacts_doc(GOOD_CONTACTS[0], bad))


@pytest.mark.parametrize("field,value,want", [
    ("finger_normal", [0.0, float("nan"), 1.0], "finger_normals has a NaN or inf entry in row 1: [0.0, nan, 1.0]"),
    ("point", [0.0, float("inf"), 1.0], "points has a NaN or inf entry in row 1: [0.0, inf, 1.0]"),
    ("point", [1e999, 0.0, 0.0], "points has a NaN or inf entry in row 1: [inf, 0.0, 0.0]"),
])
def test_nan_or_inf_in_contacts(field, value, want):
    bad = dict(GOOD_CONTACTS[1], **{field: value})
    with raises(ContactsError, want, "every entry must be a finite number"):
        io.parse_contacts(contacts_doc(GOOD_CONTACTS[0], bad))


def test_nan_in_contacts_file(tmp_path):
    """Python's json reads the non-standard NaN literal; the contact check still rejects it."""
    path = tmp_path / "c.json"
    path.write_text('{"contacts": [{"point": [NaN, 0, 0], "finger_normal": [0, 0, 1]},'
                    ' {"point": [1, 0, 0], "finger_normal": [0, 0, 1]}]}')
    with raises(ContactsError, "points has a NaN or inf entry in row 0"):
        io.read_contacts(path)


def test_non_unit_normal_is_normalised_with_a_warning():
    bad = dict(GOOD_CONTACTS[1], finger_normal=[0.0, 0.0, 2.0])
    contacts, messages = recorded(io.parse_contacts, contacts_doc(GOOD_CONTACTS[0], bad))
    assert any("1 non-unit normals normalised" in m and "2.0" in m for m in messages), messages
    np.testing.assert_allclose(contacts.finger_normals[1], [0.0, 0.0, 1.0])


def test_normal_whose_length_overflows():
    """[1e308, 1e308, 0] has no float length: rejected, not silently turned into [0, 0, 0]."""
    bad = dict(GOOD_CONTACTS[1], finger_normal=[1e308, 1e308, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy overflow warning either
        with raises(ContactsError, "finger_normals row 1", "too long to normalise", "1e+308"):
            io.parse_contacts(contacts_doc(GOOD_CONTACTS[0], bad))


@pytest.mark.parametrize("contacts,want", [([], "lists no contacts; need at least 2"),
                                           (GOOD_CONTACTS[:1], "need at least 2 contacts, got 1")])
def test_fewer_than_two_contacts(contacts, want):
    with raises(ContactsError, want):
        io.parse_contacts({"contacts": contacts})


def test_duplicate_contacts():
    with raises(ContactsError, "contacts 0 and 2 are at the same point", "[0.0, 0.0, 0.02]"):
        io.parse_contacts(contacts_doc(GOOD_CONTACTS[0], GOOD_CONTACTS[1], GOOD_CONTACTS[0]))


def test_far_apart_contacts_are_not_called_duplicates():
    a = dict(GOOD_CONTACTS[0], point=[0.0, 1e308, 0.0])
    b = dict(GOOD_CONTACTS[1], point=[0.0, -1e308, 0.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no numpy overflow warning either
        with raises(ContactsError, "contacts 0 and 1 are too far apart", "check the units") as info:
            io.parse_contacts(contacts_doc(a, b))
    assert "same point" not in str(info.value)


def test_contacts_in_millimetres_are_an_error_naming_the_units(box_small):
    # the contacts of a 0.12 m box given in millimetres
    mm = Contacts(np.array([c["point"] for c in GOOD_CONTACTS]) * 1000,
                  finger_normals=[c["finger_normal"] for c in GOOD_CONTACTS])
    with raises(ContactsError, "contacts span 53.85 but the model is 0.1233 across", "millimetres vs metres?"):
        cp.localize(box_small, mm, position_noise=0.0005)


def test_contact_spread_a_little_larger_than_object_warns_about_units(box_small):
    wide = Contacts(np.array([c["point"] for c in GOOD_CONTACTS]) * 4,
                    finger_normals=[c["finger_normal"] for c in GOOD_CONTACTS])
    result, messages = recorded(cp.localize, box_small, wide, position_noise=0.0005)
    assert any("contacts span 0.2154 but the model is 0.1233 across" in m and "same units?" in m
               for m in messages), messages
    assert result.status == "no_hypothesis" and "same units?" in result.hint


# ----------------------------------------------------------------- prior files

@pytest.mark.parametrize("pose,want", [
    (2 * np.eye(4), "prior pose is not rigid: |RᵀR - I| = 3"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "det R = -1"),
    (np.array([[1, 0.1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "not rigid"),
    (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row must be [0, 0, 0, 1], got [0.0, 0.0, 1.0, 1.0]"),
])
def test_prior_pose_not_rigid(pose, want):
    with raises(PriorError, want):
        io.parse_prior(dict(GOOD_PRIOR, pose=pose.tolist()))


@pytest.mark.parametrize("pose,want", [
    (np.eye(3).tolist(), "prior pose must be a 4x4 matrix"), ([[1, 0, 0, 0]] * 3 + [[0, 0, 0]], "4x4 matrix"),
    ([["1", "0", "0", "0"]] * 4, "prior pose must hold only numbers"), (None, "got null"),
    ([[float("nan")] * 4] * 4, "finite 4x4 matrix"),
])
def test_prior_pose_wrong_shape_or_type(pose, want):
    with raises(PriorError, want):
        io.parse_prior(dict(GOOD_PRIOR, pose=pose))


@pytest.mark.parametrize("key,value", [("sigma_rot_deg", -1.0), ("sigma_trans", -0.01), ("sigma_trans", 0.0),
                                       ("sigma_rot_deg", float("nan"))])
def test_prior_negative_or_zero_sigma(key, value):
    with raises(PriorError, f"prior {key} must be a positive number, got {value!r}"):
        io.parse_prior(dict(GOOD_PRIOR, **{key: value}))


@pytest.mark.parametrize("value,want", [(None, "got null"), ("10", 'got "10"'), (True, "got true"),
                                        (10 ** 400, "representable as a float")])
def test_prior_sigma_not_a_number(value, want):
    with raises(PriorError, "prior sigma_rot_deg must be a number", want):
        io.parse_prior(dict(GOOD_PRIOR, sigma_rot_deg=value))


@pytest.mark.parametrize("cov,want", [(-np.eye(6), "positive definite"), (np.eye(5), "6x6 matrix"),
                                      (np.triu(np.ones((6, 6))), "symmetric (6, 6)")])
def test_prior_bad_covariance(cov, want):
    with raises(PriorError, "prior covariance", want):
        io.parse_prior({"pose": GOOD_PRIOR["pose"], "covariance": cov.tolist()})


def test_prior_with_both_sigmas_and_covariance():
    with raises(PriorError, "both", "covariance", "sigma_rot_deg"):
        io.parse_prior(dict(GOOD_PRIOR, covariance=np.eye(6).tolist()))


def test_prior_file_invalid_json(tmp_path):
    path = tmp_path / "p.json"
    path.write_text('{"pose": [[1, 0, 0, 0]')
    with raises(PriorError, str(path), "not valid JSON"):
        io.read_prior(path)


def test_prior_file_missing_pose(tmp_path):
    with raises(PriorError, 'must be an object with "pose"', "sigma_rot_deg"):
        io.read_prior(write_json(tmp_path / "p.json", {"sigma_rot_deg": 1.0, "sigma_trans": 0.1}))


def test_prior_constructor_names_the_defect():
    with raises(PriorError, "prior sigma_trans must be a positive number, got -1"):
        PosePrior(np.eye(4), sigma_rot_deg=1.0, sigma_trans=-1)


# ----------------------------------------------------------------- model files

def test_model_file_missing(tmp_path):
    path = str(tmp_path / "none.npz")
    with raises(ModelFileError, path, "does not exist"):
        ObjectModel.load(path)


@pytest.mark.parametrize("fraction", [0.0, 0.001, 0.25, 0.5, 0.9, 0.999])
def test_model_file_truncated(tmp_path, box_file, fraction):
    raw = open(box_file, "rb").read()
    path = tmp_path / "cut.npz"
    path.write_bytes(raw[:int(fraction * len(raw))])
    with raises(ModelFileError, str(path), "truncated, corrupt or not a .npz model"):
        ObjectModel.load(path)


def _member_data_offset(path, name):
    """Byte offset of the stored data of zip member ``name`` (uncompressed)."""
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(name)
    with open(path, "rb") as fh:
        fh.seek(info.header_offset + 26)
        n_name, n_extra = np.frombuffer(fh.read(4), "<u2")
    return info.header_offset + 30 + int(n_name) + int(n_extra)


@pytest.mark.parametrize("member", ["vertices.npy", "features_dmax.npy", "table_offsets.npy", "format_version.npy"])
def test_model_file_corrupted_bytes(tmp_path, box_file, member):
    """A flipped bit inside any stored array is caught (the zip CRC-32 of the member)."""
    raw = bytearray(open(box_file, "rb").read())
    raw[_member_data_offset(box_file, member) + 130] ^= 0x10  # past the 128-byte .npy header
    path = tmp_path / "flipped.npz"
    path.write_bytes(bytes(raw))
    with raises(ModelFileError, str(path), "CRC-32", member):
        ObjectModel.load(path)


def test_model_file_not_a_zip(tmp_path):
    path = tmp_path / "model.npz"
    path.write_text("not a model")
    with raises(ModelFileError, str(path), "not a .npz model"):
        ObjectModel.load(path)


def test_model_file_with_pickled_objects(tmp_path):
    path = tmp_path / "pickle.npz"
    np.savez(path, format_version=np.array([{"a": 1}], dtype=object))
    with raises(ModelFileError, str(path), "allow_pickle=False"):
        ObjectModel.load(path)


@pytest.mark.parametrize("compressed", [False, True])
def test_model_file_corrupted_compression_field(tmp_path, box_arrays, compressed):
    """zipfile raises NotImplementedError for an unknown compression method: still a ModelFileError."""
    path = tmp_path / "model.npz"
    (np.savez_compressed if compressed else np.savez)(path, **box_arrays)
    raw = bytearray(path.read_bytes())
    # zipfile trusts the central directory: compression method of its first entry 0 -> 1 (or 8 -> 9)
    raw[raw.index(b"PK\x01\x02") + 10] ^= 0x01
    path.write_bytes(bytes(raw))
    with raises(ModelFileError, str(path), "compression method"):
        ObjectModel.load(path)


def test_model_file_wrong_format_version(tmp_path, box_arrays):
    path = rewrite(tmp_path, box_arrays, format_version=np.array(FORMAT_VERSION + 1))
    with raises(ModelFileError, f"format version {FORMAT_VERSION + 1}", f"reads version {FORMAT_VERSION}",
                "build-model"):
        ObjectModel.load(path)


def test_model_file_of_the_old_writer_says_rebuild(tmp_path, box_arrays):
    """Files of format version 1 (written before load checked every array) are refused."""
    path = rewrite(tmp_path, box_arrays, format_version=np.array(1))
    with raises(ModelFileError, str(path), "format version 1", f"reads version {FORMAT_VERSION}", "rebuild it", "build-model"):
        ObjectModel.load(path)


@pytest.mark.parametrize("value", [None, np.array("x"), np.zeros((2, 2)), np.array(np.inf)])
def test_model_file_unreadable_format_version(tmp_path, box_arrays, value):
    with raises(ModelFileError, "no readable format version", "not a contactpose model"):
        ObjectModel.load(rewrite(tmp_path, box_arrays, format_version=value))


@pytest.mark.parametrize("key,change", [
    ("vertices", lambda a: a + 1e-9), ("features_dmax", lambda a: a[:5]), ("features_k", lambda a: a + 1000),
    ("table_offsets", lambda a: a[::-1]), ("diameter", lambda a: a * 2), ("features_dmax", lambda a: None),
])
def test_model_file_tampered_arrays(tmp_path, box_arrays, key, change):
    """Any array changed or dropped after saving: the content hash no longer matches."""
    path = rewrite(tmp_path, box_arrays, **{key: change(box_arrays[key])})
    with raises(ModelFileError, str(path), "is corrupt", "content hash"):
        ObjectModel.load(path)


@pytest.mark.parametrize("key,value", [("diameter", np.array("x")), ("table_bins", np.array(["a", "b", "c"])),
                                       ("table_bins", np.array(3)), ("patches_tol_deg", np.array("x")),
                                       ("faces", np.array([["a", "b", "c"]]))])
def test_model_file_resigned_scalar_of_wrong_type(tmp_path, box_arrays, key, value):
    """A valid content hash over a mistyped array (a buggy writer): the array and its expected form are named."""
    path = rewrite(tmp_path, box_arrays, resign=True, **{key: value})
    shape = {"diameter": "()", "table_bins": "(3,)", "patches_tol_deg": "()", "faces": "(m, 3)"}[key]
    with raises(ModelFileError, f"model file {path!r} is corrupt", f"array {key!r} must hold", f"of shape {shape}",
                f"got {value.dtype} of shape {value.shape}"):
        ObjectModel.load(path)


@pytest.mark.parametrize("change,want", [
    ("dmax_short", "'features_dmax' must hold finite floats of shape (P,) with P = 1176 as in 'features_k'"),
    ("k_out_of_range", "'features_k' must lie in [0, 47], got range [1000, 1047]"),
    ("dmax_missing", "lacks the array 'features_dmax'"),
    ("valid_float", "'valid' must hold booleans of shape (m,) with m = 48"),
    ("offsets_falling", "'table_offsets' must rise from 0 to 1176"),
    ("patch_k_out_of_range", "'pfeatures_k' must lie in [0, 5]"),
    ("labels_out_of_range", "'patches_labels' must lie in [-1, 5]"),
    ("float16", "'features_alpha' must hold finite floats"),
    ("nan_dmax", "'features_dmax' must hold finite floats"),
    ("zero_widths", "'table_widths' must be positive"),
    ("patch_table_without_patches", "a patch table ('ptable_...') but no patches"),
])
def test_model_file_resigned_inconsistent_arrays(tmp_path, box_arrays, change, want):
    a = box_arrays
    changes = {"dmax_short": {"features_dmax": a["features_dmax"][:5]},
               "k_out_of_range": {"features_k": a["features_k"] + 1000},
               "dmax_missing": {"features_dmax": None},
               "valid_float": {"valid": np.zeros(3)},
               "offsets_falling": {"table_offsets": a["table_offsets"][::-1]},
               "patch_k_out_of_range": {"pfeatures_k": a["pfeatures_k"] + 6},
               "labels_out_of_range": {"patches_labels": a["patches_labels"] + 100},
               "float16": {"features_alpha": a["features_alpha"].astype(np.float16)},
               "nan_dmax": {"features_dmax": np.where(np.arange(len(a["features_dmax"])) == 3, np.nan,
                                                      a["features_dmax"]).astype(np.float32)},
               "zero_widths": {"table_widths": np.zeros(3)},
               "patch_table_without_patches": {k: None for k in a if k.startswith("patches_")}}[change]
    path = rewrite(tmp_path, a, resign=True, **changes)
    with raises(ModelFileError, f"model file {path!r} is corrupt or not a model", want):
        ObjectModel.load(path)


def test_model_file_lacks_an_array(tmp_path, box_arrays):
    with raises(ModelFileError, "lacks the array 'vertices'", "corrupt or not a model"):
        ObjectModel.load(rewrite(tmp_path, box_arrays, resign=True, vertices=None))


def test_model_file_mesh_does_not_match_its_hash(tmp_path, box_arrays):
    path = rewrite(tmp_path, box_arrays, resign=True, vertices=box_arrays["vertices"] + 1e-9)
    with raises(ModelFileError, "corrupt", "does not match its stored hash"):
        ObjectModel.load(path)


def test_large_model_file_not_a_zip(tmp_path, monkeypatch):
    monkeypatch.setattr(model_module, "MMAP_MIN_BYTES", 0)  # treat every file as large
    path = tmp_path / "model.npz"
    path.write_text("not a model")
    with raises(ModelFileError, str(path), "not a zip file", "not a .npz model"):
        ObjectModel.load(path)



def _npz_with_header(path, arrays, name, shape, compressed):
    """arrays as an .npz whose member ``name`` declares ``shape`` in its .npy header; its data
    bytes are unchanged and the zip CRCs are valid (a hand-made or buggy file, not a damaged one)."""
    import io as pyio

    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED) as zf:
        for key, a in arrays.items():
            buf = pyio.BytesIO()
            if key == name:
                header = {"descr": np.lib.format.dtype_to_descr(a.dtype), "fortran_order": False, "shape": shape}
                np.lib.format.write_array_header_1_0(buf, header)
                buf.write(np.ascontiguousarray(a).tobytes())
            else:
                np.lib.format.write_array(buf, a, allow_pickle=False)
            zf.writestr(f"{key}.npy", buf.getvalue())
    return str(path)


@pytest.mark.parametrize("compressed", [False, True])
@pytest.mark.parametrize("mmap", [False, True])
def test_model_file_header_declares_a_huge_array(tmp_path, box_arrays, monkeypatch, compressed, mmap):
    """A header that declares 240 TB is refused from the header alone (no MemoryError, no allocation)."""
    if mmap:
        monkeypatch.setattr(model_module, "MMAP_MIN_BYTES", 0)
    path = _npz_with_header(tmp_path / "huge.npz", box_arrays, "vertices", (10 ** 13, 3), compressed)
    held = box_arrays["vertices"].nbytes
    with raises(ModelFileError, f"cannot read model file {path!r}",
                "member 'vertices.npy' declares an array of shape (10000000000000, 3) and dtype <f8",
                f"but holds {held:,} bytes of data", "corrupt or not a .npz model"):
        ObjectModel.load(path)


def test_model_file_header_declares_a_smaller_array(tmp_path, box_arrays):
    """A header that declares fewer bytes than its member holds is refused too (not read as a prefix)."""
    path = _npz_with_header(tmp_path / "short.npz", box_arrays, "features_dmax", (5,), False)
    with raises(ModelFileError, "member 'features_dmax.npy' declares an array of shape (5,)",
                f"holds {box_arrays['features_dmax'].nbytes:,} bytes"):
        ObjectModel.load(path)



def test_model_file_member_that_is_not_an_array(tmp_path, box_arrays):
    """np.load returns a member without the .npy suffix as raw bytes: refused by name."""
    path = tmp_path / "raw.npz"
    with zipfile.ZipFile(path, "w") as zf:
        for key, a in box_arrays.items():
            with zf.open(f"{key}.npy" if key != "content_hash" else key, "w") as fh:
                np.lib.format.write_array(fh, a, allow_pickle=False)
    with raises(ModelFileError, str(path), "member 'content_hash' is not a .npy array", "not a .npz model"):
        ObjectModel.load(path)

def test_model_file_larger_than_the_available_memory(box_file, monkeypatch):
    _tiny_memory(monkeypatch, available=1024)
    with raises(ResourceError, f"model file {str(box_file)!r} holds", "GiB of arrays", "GiB of memory is available"):
        ObjectModel.load(box_file)


def test_memory_error_while_reading_a_model_file(box_file, monkeypatch):
    def out_of_memory(*args, **kwargs):
        raise MemoryError("Unable to allocate 3 GiB")

    monkeypatch.setattr(model_module.np, "load", out_of_memory)
    with raises(ResourceError, f"not enough memory to read model file {str(box_file)!r}"):
        ObjectModel.load(box_file)

def test_saving_over_a_memory_mapped_model_does_not_crash_its_reader(tmp_path):
    script = (
        "import sys, trimesh; from contactpose import model; from contactpose.io import modelfile; from contactpose.sim import objects\n"
        "modelfile.MMAP_MIN_BYTES = 0\n"
        "path = sys.argv[1]\n"
        "model.ObjectModel.from_mesh(objects.load('box'), bins=(4, 4, 4)).save(path)\n"
        "loaded = model.ObjectModel.load(path)\n"
        "tetra = trimesh.Trimesh([[0, 0, 0], [.05, 0, 0], [0, .05, 0], [0, 0, .05]],\n"
        "                        [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], process=False)\n"
        "model.ObjectModel.from_mesh(tetra, bins=(1, 1, 1)).save(path)  # a much smaller file, same path\n"
        "print(float(loaded.features.dmax.sum()), float(loaded.table.offsets.sum()))\n")
    proc = subprocess.run([sys.executable, "-c", script, str(tmp_path / "m.npz")], capture_output=True, timeout=300)
    assert proc.returncode == 0, f"reader died with code {proc.returncode}: {proc.stderr.decode()[-300:]}"


def test_saving_to_an_unwritable_path(tmp_path, box_small):
    path = tmp_path / "no_such_folder" / "m.npz"
    with raises(ModelFileError, f"cannot write model file {str(path)!r}", "No such file or directory"):
        box_small.save(path)


def test_saving_replaces_the_file_and_leaves_no_temporary(tmp_path, box_small):
    path = tmp_path / "m.npz"
    path.write_bytes(b"an older file")
    old_inode = path.stat().st_ino
    box_small.save(path)
    assert ObjectModel.load(path).num_facets == 48
    assert path.stat().st_ino != old_inode and os.listdir(tmp_path) == ["m.npz"]


def test_model_file_built_for_another_mesh(box_file):
    with raises(ModelFileError, str(box_file), "was built for another mesh", "rebuild"):
        ObjectModel.load(box_file, mesh=objects.load("rock"))


def test_model_file_for_the_same_mesh_loads(box_file, box_mesh):
    assert ObjectModel.load(box_file, mesh=box_mesh, bins=SMALL_BINS, bounds="exact").num_facets == 48


def test_model_file_other_bins(box_file):
    with raises(ModelFileError, str(box_file), f"built with bins={SMALL_BINS}", "bins=(16, 16, 16) was asked for"):
        ObjectModel.load(box_file, bins=(16, 16, 16))


def test_model_file_other_bounds(box_file):
    with raises(ModelFileError, str(box_file), "built with bounds='exact'", "bounds='paper' was asked for"):
        ObjectModel.load(box_file, bounds="paper")


@pytest.mark.parametrize("bins", [(0, 4, 4), (4, 4), (4.5, 4, 4), (1, 1, 10 ** 6)])
def test_bad_bins_asked(box_file, bins):
    with raises(ContactPoseError, "bins must be three integers in [1, 4096]", repr(bins)):
        ObjectModel.load(box_file, bins=bins)


# ------------------------------------------------------------- resource limits

def _tiny_memory(monkeypatch, available=1 << 20):
    import psutil

    memory = namedtuple("svmem", "total available percent used free")
    monkeypatch.setattr(psutil, "virtual_memory",
                        lambda: memory(available, available, 99.0, 0, available))


def test_table_predicted_to_exceed_memory(monkeypatch):
    _tiny_memory(monkeypatch)
    with raises(ResourceError, "the pair table for 320 facets", "needs about", "GiB is available", "decimate"):
        ObjectModel.from_mesh(objects.load("rock"))


def test_memory_check_passes_with_enough_memory(monkeypatch):
    _tiny_memory(monkeypatch, available=1 << 40)
    assert ObjectModel.from_mesh(objects.load("box"), bins=SMALL_BINS).num_facets == 48



@pytest.fixture(scope="module")
def box_span_file(box_mesh, tmp_path_factory):
    """The box (diameter 0.123) built for a hand span of 3 cm, saved."""
    model = ObjectModel.from_mesh(box_mesh, bins=SMALL_BINS, max_span=0.03)
    return model.save(tmp_path_factory.mktemp("span") / "box_span.npz")


def test_query_beyond_max_span(box_span_file):
    """GOOD_CONTACTS 0 and 1 are 4 cm apart: a 3 cm span-bounded table cannot answer them."""
    model = ObjectModel.load(box_span_file)
    assert model.max_span == 0.03
    with raises(ResourceError, "contacts 0 and 1 are 0.04 apart", "beyond the model's max_span 0.03",
                "rebuild the model with a larger --max-span"):
        cp.localize(model, io.parse_contacts(contacts_doc()), position_noise=0.0005)


def test_query_within_max_span_is_answered(box_span_file):
    model = ObjectModel.load(box_span_file)
    near = contacts_doc({"point": [0.0, 0.0, 0.02], "finger_normal": [0.0, 0.0, -1.0]},
                        {"point": [0.01, 0.0, 0.02], "finger_normal": [0.0, 0.0, -1.0]})
    result, _ = recorded(cp.localize, model, io.parse_contacts(near), position_noise=0.0005)
    assert result.status in ("ok", "underdetermined", "ambiguous") and len(result.hypotheses.arrays.cost) > 0


@pytest.mark.parametrize("span", [-0.1, 0.0, float("nan"), float("inf"), "a"])
def test_bad_max_span(box_mesh, span):
    with raises(MeshError, "max_span must be a positive length in the mesh's units", f"got {span!r}"):
        ObjectModel.from_mesh(box_mesh, bins=SMALL_BINS, max_span=span)


def test_cli_query_beyond_max_span_exits_2(tmp_path, box_span_file, capsys):
    good = write_json(tmp_path / "good.json", contacts_doc())
    assert cli.main(["localize", box_span_file, "--contacts", good]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("contactpose: error: contacts 0 and 1 are 0.04 apart") and "max_span 0.03" in err, err

# ------------------------------------------------------------------------ CLI

def _cli_cases(tmp, box_file, box_arrays):
    """(name, argv, message fragment) for a representative subset of bad input."""
    stl = tmp / "notes.stl"
    stl.write_text("these are my notes\n")
    v = objects.load("box").vertices.copy()
    v[2, 2] = np.nan
    nan_obj = write_obj(tmp / "nan.obj", v, objects.load("box").faces)
    bad_json = tmp / "bad.json"
    bad_json.write_text("{")
    one = write_json(tmp / "one.json", {"contacts": GOOD_CONTACTS[:1]})
    both = write_json(tmp / "both.json", contacts_doc(dict(GOOD_CONTACTS[0], object_normal=[0, 0, 1]),
                                                      GOOD_CONTACTS[1]))
    good = write_json(tmp / "good.json", contacts_doc())
    skew = write_json(tmp / "skew.json", dict(GOOD_PRIOR, pose=(2 * np.eye(4)).tolist()))
    negative = write_json(tmp / "neg.json", dict(GOOD_PRIOR, sigma_trans=-1.0))
    cut = tmp / "cut.npz"
    cut.write_bytes(open(box_file, "rb").read()[:500])
    old = rewrite(tmp, box_arrays, format_version=np.array(FORMAT_VERSION + 1))
    return [
        ("missing mesh", ["build-model", str(tmp / "none.stl"), "-o", str(tmp / "o.npz")], "does not exist"),
        ("text .stl", ["build-model", str(stl), "-o", str(tmp / "o.npz")], "faces"),
        ("NaN vertex", ["build-model", nan_obj, "-o", str(tmp / "o.npz")], "non-finite"),
        ("bad bins", ["build-model", "box", "--bins", "0", "4", "4", "-o", str(tmp / "o.npz")], "bins must be"),
        ("invalid JSON", ["localize", box_file, "--contacts", str(bad_json)], "not valid JSON"),
        ("missing contacts", ["localize", box_file, "--contacts", str(tmp / "none.json")], "does not exist"),
        ("one contact", ["localize", box_file, "--contacts", one], "need at least 2 contacts"),
        ("both normals", ["localize", box_file, "--contacts", both], "exactly one of"),
        ("non-rigid prior", ["localize", box_file, "--contacts", good, "--prior", skew], "not rigid"),
        ("negative sigma", ["localize", box_file, "--contacts", good, "--prior", negative], "positive number"),
        ("truncated model", ["localize", str(cut), "--contacts", good], "truncated"),
        ("model version", ["localize", old, "--contacts", good], "format version"),
        ("bad noise", ["localize", box_file, "--contacts", good, "--position-noise", "-1"], "positive number"),
    ]


def test_cli_bad_input_exits_2_with_one_line(tmp_path, box_file, box_arrays, capsys):
    for name, argv, fragment in _cli_cases(tmp_path, box_file, box_arrays):
        code = cli.main(argv)
        out, err = capsys.readouterr()
        lines = err.splitlines()
        assert code == 2, (name, code, err)
        assert len(lines) == 1 and lines[0].startswith("contactpose: error: "), (name, err)
        assert fragment in lines[0] and "Traceback" not in err, (name, err)
        assert out == "", (name, out)


def test_cli_resource_limit_exits_2(tmp_path, capsys, monkeypatch):
    _tiny_memory(monkeypatch)
    assert cli.main(["build-model", "rock", "-o", str(tmp_path / "rock.npz")]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "needs about" in err and "Traceback" not in err


def test_cli_debug_reraises(tmp_path, capsys):
    with pytest.raises(MeshError):
        cli.main(["--debug", "build-model", str(tmp_path / "none.stl")])


def test_cli_units_warning_is_one_line(tmp_path, box_file, capsys):
    far = write_json(tmp_path / "far.json", {"contacts": [
        {"point": [0, 0, 0], "finger_normal": [0, 0, 1]}, {"point": [1, 0, 0], "finger_normal": [0, 0, 1]}]})
    assert cli.main(["localize", box_file, "--contacts", far]) == 0
    out, err = capsys.readouterr()
    assert re.fullmatch(r"contactpose: warning: contacts span 1 but the model is .* same units\?\n", err), err
    assert "status: no_hypothesis (contacts span 1 but" in out and "same units?" in out


@pytest.mark.parametrize("argv,code", [(["localize", "{box}", "--contacts", "{far}"], 0),
                                       (["build-model", "{tmp}/none.stl"], 2),
                                       (["--debug", "build-model", "{tmp}/none.stl"], None)])
def test_cli_restores_showwarning(tmp_path, box_file, capsys, argv, code):
    """main() prints warnings as one line only while it runs: library users keep their own."""
    far = write_json(tmp_path / "far.json", {"contacts": [
        {"point": [0, 0, 0], "finger_normal": [0, 0, 1]}, {"point": [1, 0, 0], "finger_normal": [0, 0, 1]}]})
    argv = [a.format(box=box_file, far=far, tmp=tmp_path) for a in argv]
    before = warnings.showwarning
    if code is None:
        with pytest.raises(MeshError):
            cli.main(argv)
    else:
        assert cli.main(argv) == code
    assert warnings.showwarning is before
    if code == 0:
        assert "contactpose: warning: contacts span 1" in capsys.readouterr().err


def test_non_manifold_edges_are_named_when_building():
    """A closed tetrahedron with a fin on one edge: that edge is used by three facets."""
    v = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05], [0.03, 0.03, -0.04]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [0, 1, 4]])
    with pytest.warns(UserWarning, match=r"mesh has 1 non-manifold edges \(each shared by more than two facets\)"):
        ObjectModel.from_mesh(trimesh.Trimesh(v, f, process=False))
