"""The 3D page of an answer (contactpose.view, Result.to_html, ``--html``): what the written
page holds, read back from its HTML and checked against the model and the answer with numpy;
that it opens offline; and that headless Chromium draws it without an error."""

import base64
import html
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import NORMAL_NOISE_DEG, POSITION_NOISE

import contactpose as cp
from contactpose import view
from contactpose.cli import main
from contactpose.errors import ContactPoseError
from contactpose.io import jsonfiles
from contactpose.sim import grasps as simulate

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "banana_contacts.json"
NOISE = dict(position_noise=POSITION_NOISE, normal_noise_deg=NORMAL_NOISE_DEG)


# ---------------------------------------------------------- the page, read back ---

def _array(value):
    """A trace attribute as numpy: plotly writes arrays as {"dtype", "bdata"[, "shape"]}."""
    if isinstance(value, dict) and "bdata" in value:
        arr = np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(value["dtype"]))
        return arr.reshape([int(s) for s in str(value["shape"]).split(",")]) if "shape" in value else arr
    return np.asarray(value, dtype=float)


def read_page(path):
    """The data and layout that the page hands to Plotly.newPlot."""
    text = Path(path).read_text(encoding="utf-8")
    decoder, blank = json.JSONDecoder(), re.compile(r"\s*")
    at = text.index(",", text.index("Plotly.newPlot(")) + 1  # past the graph's id
    data, at = decoder.raw_decode(text, blank.match(text, at).end())
    layout, _ = decoder.raw_decode(text, blank.match(text, text.index(",", at) + 1).end())
    return data, layout


def xyz(trace):
    """A trace's points, (m, 3), NaN rows (line breaks) kept."""
    return np.stack([_array(trace[k]) for k in "xyz"], axis=1)


def named(data, prefix):
    return [t for t in data if t.get("name", "").startswith(prefix)]


def posed(model, T):
    """The model's vertices under T, computed here: R v + t."""
    return np.einsum("ij,vj->vi", T[:3, :3], model.vertices) + T[:3, 3]


def assert_draws(mesh, model, T):
    """The Mesh3d trace draws the model's triangles (F, 3, 3) where T puts them (single
    precision: within a micrometre)."""
    drawn = xyz(mesh)[np.stack([_array(mesh[k]).astype(np.int64) for k in "ijk"], axis=1)]
    np.testing.assert_allclose(drawn, posed(model, T)[model.faces], rtol=0, atol=1e-6)


def bbox_diagonal(vertices):
    return np.linalg.norm(np.ptp(vertices, axis=0))


@pytest.fixture(scope="module")
def example(banana_model):
    contacts = jsonfiles.read_contacts(EXAMPLE)
    return banana_model, contacts, cp.localize(banana_model, contacts)


@pytest.fixture(scope="module")
def ambiguous(banana_model):
    """Three noisy contacts that leave the banana several placements (7 pose classes)."""
    g = simulate.grasp(banana_model, np.random.default_rng(3), n=3, **NOISE)
    result = cp.localize(banana_model, g.contacts, position_noise=POSITION_NOISE)
    assert len(result.classes) >= 3 and len(result.placements) >= 3
    return banana_model, g.contacts, result


# --------------------------------------------------------------- what it draws ---

def test_the_mesh_is_the_model_at_the_best_pose(example, tmp_path):
    model, contacts, result = example
    data, _ = read_page(result.to_html(tmp_path / "v.html"))
    [mesh] = named(data, "best placement")
    assert mesh["type"] == "mesh3d"
    assert_draws(mesh, model, result.best.pose)


def test_a_triangle_soup_is_drawn_with_each_vertex_once(example):
    """An STL file loads as a soup, three vertices of its own per face (the YCB meshes): the
    page draws each vertex once, the same triangles."""
    model, contacts, result = example
    soup = model.vertices[model.faces].reshape(-1, 3)
    fig = view.localization_figure(soup, np.arange(len(soup)).reshape(-1, 3), contacts.points,
                                   contacts.finger_normals, pose=result.best.pose)
    mesh = json.loads(fig.to_json())["data"][0]
    assert len(_array(mesh["x"])) == len(np.unique(model.faces))
    assert_draws(mesh, model, result.best.pose)


def test_the_contacts_and_their_finger_normals(example, tmp_path):
    model, contacts, result = example
    data, _ = read_page(result.to_html(tmp_path / "v.html"))
    [points] = named(data, "contacts")
    assert points["name"] == f"contacts ({contacts.n})"
    np.testing.assert_allclose(xyz(points), contacts.points, atol=1e-12)
    shafts = xyz(named(data, "finger normals")[0]).reshape(contacts.n, 3, 3)  # tail, tip, break
    assert np.isnan(shafts[:, 2]).all()
    np.testing.assert_allclose(shafts[:, 1], contacts.points, atol=1e-12)
    along = shafts[:, 1] - shafts[:, 0]
    length = np.linalg.norm(along, axis=1)
    np.testing.assert_allclose(along / length[:, None], contacts.finger_normals, atol=1e-9)  # into the object
    assert np.all((0.05 <= length / bbox_diagonal(model.vertices)) & (length / bbox_diagonal(model.vertices) <= 0.1))


def test_fingertips_rest_on_the_contacts_outside_the_object(example, tmp_path):
    model, contacts, result = example
    r = 0.01
    data, _ = read_page(result.to_html(tmp_path / "v.html", finger_radius=r))
    [spheres] = named(data, "fingertips")
    balls = xyz(spheres).reshape(contacts.n, -1, 3)
    centres = contacts.points + r * contacts.object_normals  # the outward side, r from the contact
    np.testing.assert_allclose(np.linalg.norm(balls - centres[:, None], axis=2), r, rtol=0, atol=1e-6)
    assert not named(read_page(result.to_html(tmp_path / "w.html"))[0], "fingertips")


def test_the_other_placements_are_the_weighed_placements(ambiguous, tmp_path):
    model, contacts, result = ambiguous
    data, _ = read_page(result.to_html(tmp_path / "v.html"))
    others = named(data, "placement ")
    assert result.placements
    best_class = next(c for c in result.placements if 0 in c.members)
    rest = [c for c in result.placements if c is not best_class]
    assert len(others) == min(len(rest), view.MAX_OTHERS)
    [best] = named(data, "best placement")
    assert best["name"].endswith(f"p = {best_class.probability:.3g})")
    for trace, c in zip(others, rest):
        assert float(re.search(r"p = (\S+)$", trace["name"]).group(1)) == pytest.approx(c.probability, rel=5e-3)
        assert trace["opacity"] < 1
        assert_draws(trace, model, c.pose)
    shown = [t.get("visible", True) is True for t in others]
    assert shown == [i < view.VISIBLE_OTHERS for i in range(len(others))]  # the rest: in the legend, hidden


def test_free_directions_of_an_underdetermined_answer(tmp_path):
    """Three contacts on a box's top and bottom faces leave the in-plane translations and the
    turn about the normal free: each is drawn along the best hypothesis's own direction."""
    model = cp.ObjectModel.from_mesh(cp.objects.load("box"))
    lo, hi = model.vertices.min(axis=0), model.vertices.max(axis=0)
    T = simulate.paper_pose()
    points = np.array([[0.2 * hi[0], 0.1 * hi[1], hi[2]], [0.1 * lo[0], 0.3 * lo[1], lo[2]],
                       [0.5 * hi[0], 0.4 * lo[1], hi[2]]])
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    contacts = cp.Contacts(points @ T[:3, :3].T + T[:3, 3], object_normals=normals @ T[:3, :3].T)
    result = cp.localize(model, contacts)
    best = result.best
    assert best.underdetermined and len(best.free_translation) == 2 and best.free_rotation is not None
    data, layout = read_page(result.to_html(tmp_path / "v.html"))
    assert "underdetermined" in layout["title"]["text"]
    shafts = xyz(named(data, "free translations (2)")[0]).reshape(-1, 3, 3)
    drawn = shafts[:, 1] - shafts[:, 0]
    drawn /= np.linalg.norm(drawn, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(drawn @ best.free_translation.T).max(axis=1), 1.0, atol=1e-9)
    axis = xyz(named(data, "free rotation")[0])[:2]
    along = (axis[1] - axis[0]) / np.linalg.norm(axis[1] - axis[0])
    assert abs(along @ best.free_rotation) == pytest.approx(1.0, abs=1e-9)


def test_the_title_names_status_facets_and_the_hint_in_two_lines(example, tmp_path):
    model, contacts, _ = example
    points = contacts.points.copy()
    points[2] -= 0.03 * contacts.finger_normals[2]  # finger 2 off the object: a long diagnosis
    result = cp.localize(model, cp.Contacts(points, finger_normals=contacts.finger_normals))
    assert result.status == "poor_fit" and len(result.hint) > 2 * view.TITLE_CHARS
    _, layout = read_page(result.to_html(tmp_path / "v.html"))
    head, *hint = [html.unescape(re.sub("<[^>]+>", "", line)) for line in layout["title"]["text"].split("<br>")]
    assert head.startswith(f"status poor_fit: 1 hypothesis, best facets {result.best.facets.tolist()}")
    assert len(hint) == 2 and all(len(line) <= view.TITLE_CHARS for line in hint)
    assert hint[1].endswith("…") and result.hint.startswith(" ".join(hint)[:-1])


def test_the_page_needs_no_network(example, tmp_path):
    _, _, result = example
    text = Path(result.to_html(tmp_path / "v.html")).read_text(encoding="utf-8")
    assert not re.search(r"<script[^>]*\ssrc=", text) and not re.search(r"<link[^>]*\shref=\S*http", text)
    assert "Plotly.newPlot(" in text and len(text) > 3_000_000  # plotly.js itself is inside


def test_a_session_result_carries_what_its_page_needs(banana_model, tmp_path):
    contacts = jsonfiles.read_contacts(EXAMPLE)
    session = cp.TouchSession(banana_model)
    first = session.add(cp.Contacts(contacts.points[:1], finger_normals=contacts.finger_normals[:1]))
    data, _ = read_page(first.to_html(tmp_path / "one.html"))  # no placement yet: the contact only
    assert [t["type"] for t in named(data, "contacts")] == ["scatter3d"] and not named(data, "best placement")
    result = session.add(cp.Contacts(contacts.points[1:], finger_normals=contacts.finger_normals[1:]))
    data, _ = read_page(result.to_html(tmp_path / "all.html"))
    np.testing.assert_allclose(xyz(named(data, "contacts")[0]), contacts.points, atol=1e-12)
    assert_draws(named(data, "best placement")[0], banana_model, result.best.pose)


def test_a_held_session_page_shows_every_touch_carried_to_the_tracked_pose(banana_model, tmp_path):
    seq, _ = simulate.touch_sequence(banana_model, np.random.default_rng(3), 2, **NOISE)
    session = cp.TouchSession(banana_model, position_noise=POSITION_NOISE)
    for contacts, motion, _ in jsonfiles.parse_sequence(seq):
        result = session.add(contacts, hand_motion=motion)
    track = session.tracks.best
    data, _ = read_page(result.to_html(tmp_path / "held.html"))
    T = track.pose
    assert_draws(named(data, "best placement")[0], banana_model, T)
    every = np.concatenate([(T @ np.linalg.inv(track.poses[k]) @ np.c_[c.points, np.ones(c.n)].T).T[:, :3]
                            for k, c, _ in track.touches])  # each touch moved from its own smoothed pose
    np.testing.assert_allclose(xyz(named(data, "contacts")[0]), every, atol=1e-9)


# ------------------------------------------------------------------ bad input ---

def test_bad_input_names_the_value(example, tmp_path):
    model, contacts, result = example
    bare = cp.localize(model, contacts)
    bare.model = bare.contacts = None
    with pytest.raises(ContactPoseError, match="needs the model and the contacts"):
        bare.to_html(tmp_path / "v.html")
    three = cp.Contacts(contacts.points[:3], finger_normals=contacts.finger_normals[:3])
    with pytest.raises(ContactPoseError, match="contacts has 3 contacts, the answer's hypotheses 4"):
        result.to_html(tmp_path / "v.html", contacts=three)
    with pytest.raises(ContactPoseError, match="finger_radius"):
        result.to_html(tmp_path / "v.html", finger_radius=-1.0)
    with pytest.raises(ContactPoseError, match="folder .* does not exist"):
        result.to_html(tmp_path / "missing" / "v.html")
    with pytest.raises(ContactPoseError, match="it is a folder"):
        result.to_html(tmp_path)
    with pytest.raises(ContactPoseError, match="faces must index the 29 vertices"):
        view.localization_figure(model.vertices, model.faces + 1, contacts.points, contacts.finger_normals)
    with pytest.raises(ContactPoseError, match="pose must be a rigid transform"):
        view.localization_figure(model.vertices, model.faces, contacts.points, contacts.finger_normals,
                                 pose=2 * np.eye(4))
    with pytest.raises(ContactPoseError, match="finger normals must be unit vectors, row 0"):
        view.localization_figure(model.vertices, model.faces, contacts.points, 2 * contacts.finger_normals)


# ----------------------------------------------------------------------- CLI ---

def test_localize_html_writes_the_page(banana_model, tmp_path, capsys):
    page = tmp_path / "v.html"
    assert main(["localize", "banana", "--contacts", str(EXAMPLE), "--html", str(page), "--finger-radius", "0.01",
                 "-o", str(tmp_path / "out.json")]) == 0
    pose = np.array(json.loads((tmp_path / "out.json").read_text())["best"]["pose"])
    data, _ = read_page(page)
    assert_draws(named(data, "best placement")[0], banana_model, pose)
    assert named(data, "fingertips (radius 0.01)")


@pytest.mark.parametrize("command", ["localize", "track"])
def test_html_to_a_bad_path_exits_2_with_one_line(tmp_path, capsys, command):
    given = ["--contacts", str(EXAMPLE)] if command == "localize" else ["--sequence", str(tmp_path / "seq.json")]
    code = main([command, "banana", *given, "--html", str(tmp_path / "no" / "v.html")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("contactpose: error: cannot write the page") and "no/v.html" in err


def test_track_html_steps_through_the_touches(banana_model, tmp_path, capsys):
    seq, _ = simulate.touch_sequence(banana_model, np.random.default_rng(3), 3, **NOISE)
    (tmp_path / "seq.json").write_text(json.dumps(seq))
    page = tmp_path / "t.html"
    assert main(["track", "banana", "--sequence", str(tmp_path / "seq.json"), "--position-noise", "0.0005",
                 "-o", str(tmp_path / "out.json"), "--html", str(page), "--finger-radius", "0.008"]) == 0
    steps = json.loads((tmp_path / "out.json").read_text())["steps"]
    data, layout = read_page(page)
    [slider] = layout["sliders"]
    assert len(slider["steps"]) == len(steps) == 4 and slider["active"] == 3
    touches = [len(s["contacts"]) for s in seq["steps"]]
    for k, (step, row) in enumerate(zip(slider["steps"], steps)):
        shown = [t for t, on in zip(data, step["args"][0]["visible"]) if on]
        [mesh] = named(shown, "tracked pose")
        assert_draws(mesh, banana_model, np.array(row["pose"]))
        [truth] = named(shown, "true pose")
        assert_draws(truth, banana_model, np.array(seq["steps"][k]["true_pose"]))
        [latest] = named(shown, "contacts of this touch")
        assert latest["name"] == f"contacts of this touch ({touches[k]})"
        earlier = named(shown, "contacts of earlier touches")
        assert len(xyz(earlier[0]) if earlier else []) == sum(touches[:k])
        assert f"step {k}:" in step["args"][1]["title.text"]
    assert [t.get("visible") for t in data] == slider["steps"][-1]["args"][0]["visible"]


# ------------------------------------------------------------------- browser ---

@pytest.fixture(scope="module")
def chromium():
    """(contactpose.harness.pages, a launched headless Chromium), or a skip saying why not."""
    from contactpose.harness import pages

    if shutil.which(pages.CHROMIUM) is None:
        pytest.skip(f"no Chromium at {pages.CHROMIUM} (apt-get install chromium)")
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    manager = pages.chromium()
    try:
        browser = manager.__enter__()
    except Exception as exc:  # missing system libraries, a sandbox that refuses, ...
        pytest.skip(f"Chromium does not start: {str(exc).splitlines()[0]}")
    yield pages, browser
    manager.__exit__(None, None, None)


def test_chromium_draws_the_page_offline_without_errors(example, chromium, tmp_path):
    from matplotlib.image import imread

    pages, browser = chromium
    _, _, result = example
    fetched = []
    png, errors = pages.shoot(browser, result.to_html(tmp_path / "v.html", finger_radius=0.01), tmp_path / "v.png",
                              on_request=fetched.append)
    assert errors == []
    assert [u for u in fetched if not u.startswith(("file:", "data:", "blob:"))] == []
    rgb = imread(io.BytesIO(png))[..., :3]
    plot = rgb[int(0.15 * len(rgb)):, int(0.25 * rgb.shape[1]):]  # below the title, right of the legend
    r, g, b = plot[..., 0], plot[..., 1], plot[..., 2]
    yellow = (r > 0.55) & (g > 0.45) & (b < 0.35) & (r - b > 0.3)  # the best placement, lit or shaded
    assert yellow.sum() > 5000, f"the mesh is not drawn: {yellow.sum()} yellow pixels"
    assert len(np.unique((plot * 255).astype(np.uint8).reshape(-1, 3), axis=0)) > 200
