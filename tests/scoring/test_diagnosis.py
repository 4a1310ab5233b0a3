"""The diagnosis of an empty or poor answer: each cause provoked for real (a mesh in
millimetres, a finger lifted off the object, an inside-out mesh, reversed contact normals, a
wrong normal among five fingers, noise stated far too small), named in ``result.diagnosis``
and in the hint, and its suggestion checked by localizing again with it against the grasp's
true facets."""

import json

import jsonschema
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from contactpose import Contacts, ObjectModel, localize
from contactpose import diagnosis as diagnosis_module
from contactpose.diagnosis import diagnose
from contactpose.geometry.metrics import rotation_error_deg, translation_error
from contactpose.io.modelfile import content_hash, read_npz, write_replacing
from contactpose.io.output import load_schema
from contactpose.progress import Deadline
from contactpose.sim import grasps as simulate
from contactpose.sim import objects
from contactpose.types import CAUSES

NOISE = dict(position_noise=0.0005, normal_noise_deg=1.0)
#: Statuses of an answer that fits with its pose found, however sure (three fingers of the
#: 53-facet banana pin it to 0.9° and 4 % of the diameter, one sigma: not surely strictly right).
SURE_OR_NOT = ("ok", "ambiguous", "underdetermined")


def _grasp(model, seed, n=4):
    return simulate.grasp(model, np.random.default_rng(seed), n=n, **NOISE)


def _valid(result):
    """The result's JSON validates against the shipped schema; its diagnosis as written."""
    data = json.loads(json.dumps(result.to_dict()))
    jsonschema.Draft202012Validator(load_schema("result")).validate(data)
    return data["diagnosis"]


@pytest.fixture(scope="module")
def inside_out(tmp_path_factory):
    """The rock with every face's winding reversed, built (it warns), saved and loaded."""
    rock = objects.load("rock")
    with pytest.warns(UserWarning, match="facet normals point inward"):
        model = ObjectModel.from_mesh(trimesh.Trimesh(rock.vertices, rock.faces[:, ::-1], process=False))
    path = tmp_path_factory.mktemp("inside_out") / "rock_inverted.npz"
    model.save(path)
    return path


def test_a_good_grasp_is_not_diagnosed(banana_model, monkeypatch):
    """An ok answer runs no test: no trial localize, no diagnose time, no diagnosis."""
    def refuse(*args, **kwargs):
        raise AssertionError("a good grasp must not be diagnosed")

    monkeypatch.setattr(diagnosis_module._Trials, "run", refuse)
    r = localize(banana_model, _grasp(banana_model, 0).contacts, **NOISE)
    assert r.status == "ok" and r.diagnosis is None and "diagnose" not in r.timing
    assert _valid(r) is None


def test_contacts_in_metres_on_a_mesh_in_millimetres(banana_mesh, banana_model):
    mm = ObjectModel.from_mesh(trimesh.Trimesh(banana_mesh.vertices * 1000.0, banana_mesh.faces, process=False))
    g = _grasp(banana_model, 0)
    r = localize(mm, g.contacts)  # the default noise: 0.25 % of the diameter, in millimetres
    d = r.diagnosis
    assert r.status == "no_hypothesis" and d.cause == "units" and d.scale == pytest.approx(1000.0)
    assert "metres for a mesh in millimetres" in r.hint and d.message in r.hint and d.tested == ("units",)
    assert "1/1," in d.message  # the contacts span about 1/1000 of the model, and it says so
    again = localize(mm, Contacts(g.contacts.points * d.scale, finger_normals=g.contacts.finger_normals))
    assert again.status == "ok" and again.best.facets.tolist() == g.facets.tolist()
    assert _valid(r)["scale"] == pytest.approx(1000.0)


def test_diagnose_false_skips_the_tests(banana_mesh, banana_model, monkeypatch):
    """The same empty answer with diagnose=False: no trial localize, no diagnosis, the plain hint."""
    def refuse(*args, **kwargs):
        raise AssertionError("diagnose=False must not test causes")

    mm = ObjectModel.from_mesh(trimesh.Trimesh(banana_mesh.vertices * 1000.0, banana_mesh.faces, process=False))
    contacts = _grasp(banana_model, 0).contacts
    monkeypatch.setattr(diagnosis_module._Trials, "run", refuse)
    r = localize(mm, contacts, diagnose=False)
    assert r.status == "no_hypothesis" and r.diagnosis is None and "diagnose" not in r.timing
    assert "metres for a mesh in millimetres" not in r.hint and _valid(r) is None


def test_one_finger_lifted_off_the_object(banana_model):
    g = _grasp(banana_model, 0)
    points = g.contacts.points.copy()
    points[2] -= 0.03 * g.contacts.finger_normals[2]  # 3 cm out along the outward normal
    off = Contacts(points, finger_normals=g.contacts.finger_normals)
    r = localize(banana_model, off, **NOISE)
    d = r.diagnosis
    assert r.status in ("no_hypothesis", "poor_fit") and d.cause == "finger_off"
    assert (d.finger, d.max_outliers) == (2, 1) and "finger 2 is off the object" in r.hint
    assert "noise too small" not in r.hint  # the generic guess is replaced by the cause found
    again = localize(banana_model, off, max_outliers=d.max_outliers, **NOISE)
    assert again.status in SURE_OR_NOT and again.best.outliers.tolist() == [2]
    assert np.array_equal(np.delete(again.best.facets, 2), np.delete(g.facets, 2))


def test_a_subset_of_fingers_fits(rock_model):
    """Five fingers on the rock, one normal read 30° off: the other four fit, and they name it."""
    for seed in range(2):
        g = _grasp(rock_model, seed, n=5)
        normals = g.contacts.finger_normals.copy()
        normals[3] = Rotation.from_rotvec([np.radians(30.0), 0.0, 0.0]).apply(normals[3])
        bad = Contacts(g.contacts.points, finger_normals=normals)
        r = localize(rock_model, bad, **NOISE)
        d = r.diagnosis
        assert r.status == "poor_fit" and d.cause == "finger_off" and d.finger == 3, (seed, r.hint)
        assert d.tested == ("model_normals_inward", "contact_normals_flipped", "finger_off")
        again = localize(rock_model, bad, max_outliers=d.max_outliers, **NOISE)
        assert again.status == "ok" and again.best.outliers.tolist() == [3]
        assert rotation_error_deg(again.best.pose, g.pose) < 2.0  # the truth, placed by the other four
        assert translation_error(again.best.pose, g.pose) < 0.02 * rock_model.diameter


def test_an_inside_out_model_is_recorded_and_reported(inside_out, rock_model):
    """The build warned; the model file keeps the finding, and localize on the loaded model
    names it; the model rebuilt with fix_normals finds the true facets."""
    model = ObjectModel.load(inside_out)
    assert model.winding == "inward" and rock_model.winding == "outward"
    g = _grasp(rock_model, 1)
    r = localize(model, g.contacts, **NOISE)
    assert r.status == "no_hypothesis" and r.diagnosis.cause == "model_normals_inward"
    assert "facet normals point inward (found when it was built)" in r.hint and "--fix-normals" in r.hint
    rock = objects.load("rock")
    fixed = ObjectModel.from_mesh(trimesh.Trimesh(rock.vertices, rock.faces[:, ::-1], process=False),
                                  fix_normals=True)
    again = localize(fixed, g.contacts, **NOISE)
    assert fixed.winding == "outward" and again.status in SURE_OR_NOT
    assert again.best.facets.tolist() == g.facets.tolist()


def test_a_model_file_written_before_the_record_loads_as_not_recorded(inside_out, rock_model, tmp_path):
    """A file without the 'winding' array (written before it was kept) loads, winding None;
    the diagnosis then goes by the contacts, which press into the object as a grasp's do."""
    data = dict(read_npz(str(inside_out)))
    data.pop("winding"), data.pop("content_hash")
    data["content_hash"] = np.array(content_hash(data))
    old = tmp_path / "old.npz"
    write_replacing(str(old), data)
    model = ObjectModel.load(old)
    assert model.winding is None
    r = localize(model, _grasp(rock_model, 1).contacts, **NOISE)
    assert r.diagnosis.cause == "model_normals_inward" and "not recorded" in r.diagnosis.message


def test_contact_normals_given_the_wrong_way(rock_model):
    g = _grasp(rock_model, 2)
    flipped = Contacts(g.contacts.points, finger_normals=-g.contacts.finger_normals)
    r = localize(rock_model, flipped, **NOISE)
    assert r.status == "no_hypothesis" and r.diagnosis.cause == "contact_normals_flipped"
    assert "finger_normal points into the object" in r.hint
    again = localize(rock_model, Contacts(g.contacts.points, object_normals=flipped.finger_normals), **NOISE)
    assert again.status == "ok" and again.best.facets.tolist() == g.facets.tolist()


@pytest.mark.parametrize("seed,stated,status", [(0, (0.00005, 0.1), "no_hypothesis"),
                                                (5, (0.0002, 0.3), "poor_fit")])
def test_noise_stated_far_too_small(banana_model, seed, stated, status):
    """Noise of 0.5 mm and 1°, stated 10x (or 2.5x) smaller: the diagnosis gives a noise at
    which localize fits, larger than stated and at most MAX_NOISE_FACTOR times it."""
    g = _grasp(banana_model, seed)
    r = localize(banana_model, g.contacts, position_noise=stated[0], normal_noise_deg=stated[1])
    d = r.diagnosis
    assert r.status == status and d.cause == "noise_too_small", r.hint
    assert stated[0] < d.position_noise <= diagnosis_module.MAX_NOISE_FACTOR * stated[0] * 1.05
    assert stated[1] < d.normal_noise_deg <= diagnosis_module.MAX_NOISE_FACTOR * stated[1] * 1.05
    assert f"--position-noise {d.position_noise:.2g}" in r.hint
    again = localize(banana_model, g.contacts, position_noise=d.position_noise, normal_noise_deg=d.normal_noise_deg)
    assert again.status == "ok" and again.best.facets.tolist() == g.facets.tolist()
    written = _valid(r)
    assert (written["position_noise"], written["normal_noise_deg"]) == (d.position_noise, d.normal_noise_deg)


def test_two_contacts_prove_nothing(banana_model):
    """Two contacts with reversed normals: reversed back they fit only a pose family
    (underdetermined), which proves nothing, so no cause is claimed; the hint keeps its
    reasons and says what was tested."""
    g = _grasp(banana_model, 2, n=2)
    flipped = Contacts(g.contacts.points, finger_normals=-g.contacts.finger_normals)
    assert localize(banana_model, g.contacts, **NOISE).status == "underdetermined"
    r = localize(banana_model, flipped, **NOISE)
    d = r.diagnosis
    assert r.status == "no_hypothesis" and d.cause == "unexplained"
    assert d.tested == ("model_normals_inward", "contact_normals_flipped", "noise_too_small")
    assert r.hint.endswith("; " + d.message) and "none of the causes tested holds" in d.message


def test_the_diagnosis_keeps_to_the_time_left(banana_model):
    """With no time left, no test runs and the diagnosis says where it stopped."""
    g = _grasp(banana_model, 0)
    flipped = Contacts(g.contacts.points, finger_normals=-g.contacts.finger_normals)
    r = localize(banana_model, flipped, **NOISE)
    spent = Deadline(1e-9)
    while not spent.passed:
        pass
    hint, d = diagnose(banana_model, flipped, r.tolerance, r.status, r.hint, r.hypotheses.arrays, deadline=spent)
    assert d.cause == "unexplained" and d.tested == () and "time limit" in d.message and d.message in hint


def test_the_paper_method_is_not_diagnosed(rock_model):
    g = _grasp(rock_model, 2)
    r = localize(rock_model, Contacts(g.contacts.points, finger_normals=-g.contacts.finger_normals),
                 method="paper", **NOISE)
    assert r.status in ("no_hypothesis", "poor_fit") and r.diagnosis is None and "diagnose" not in r.timing


def test_causes_are_declared_once_and_in_the_schema():
    schema = load_schema("result")["$defs"]["diagnosis"]["properties"]
    assert tuple(schema["cause"]["enum"]) == CAUSES
    assert set(schema["tested"]["items"]["enum"]) == set(CAUSES) - {"unexplained"}
