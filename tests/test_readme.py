"""Every Python and JSON snippet of the README runs, and prints what the README promises:
the examples a newcomer copies work and say what the text says they say."""

import contextlib
import io
import json
import re
from pathlib import Path

import pytest

from contactpose import Contacts, cli
from contactpose.io import jsonfiles
from contactpose.io.output import load_schema

README = Path(__file__).resolve().parents[1] / "README.md"
TEXT = README.read_text()
EXAMPLE = README.parent / "examples" / "banana_contacts.json"
#: "about X" in the README: within this share of X.
ABOUT = 0.3


def snippets(language):
    return re.findall(rf"```{language}\n(.*?)```", TEXT, flags=re.S)


def block_after(lead):
    """The plain ``` block that follows the README text ``lead``, as lines."""
    found = re.search(re.escape(lead) + r".*?```\n(.*?)```", TEXT, flags=re.S)
    assert found, lead
    return found.group(1).rstrip("\n").splitlines()


def masked(line):
    """A printed line with its times (and the demo picture's folder) left out: they vary by run."""
    line = re.sub(r"[\d.]+ ms\b", "<ms>", line)
    return re.sub(r"^picture: .*banana_demo\.png$", "picture: <dir>/banana_demo.png", line)


def run_cli(argv):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = cli.main(argv)
    return code, out.getvalue().splitlines()


# ------------------------------------------------- what the snippets print ---

def check_use_example(out, code):
    """print(model) and print(result) give one line each, the model's the README's own example."""
    model_line = re.search(r"`(ObjectModel\(53 facets[^`]*)`", TEXT).group(1)
    assert out[0] == model_line
    assert re.fullmatch(r"Result\(status='ok', 1 hypothesis \(best facets \[[\d, ]+\], chi2 [\d.]+\), "
                        r"1 pose class, method='fast', [\d.]+ ms\)", out[1]), out[1]
    assert out[2].startswith("ok [")


def check_touch_session(out, code):
    """The comments of its two prints: "ok [...] True" and "about 0.9° / 1 mm"."""
    same, error = re.findall(r"^print\(.*\)\s+# (.+)$", code, flags=re.M)
    assert re.fullmatch(re.escape(same).replace(r"\[\.\.\.\]", r"\[[\d, ]+\]"), out[0]), (same, out[0])
    want_deg, want_mm = map(float, re.fullmatch(r"about ([\d.]+)° / ([\d.]+) mm", error).groups())
    got = re.fullmatch(r"ok: \d+ track\(s\); error ([\d.]+)° / ([\d.]+) mm", out[1])
    assert got, out[1]
    deg, mm = map(float, got.groups())
    assert abs(deg - want_deg) <= ABOUT * want_deg and abs(mm - want_mm) <= ABOUT * want_mm, out[1]


#: (text that marks the snippet, its check of the printed lines).
PROMISES = [("model = cp.ObjectModel.from_mesh(cp.objects.load(\"banana\"))  # or", check_use_example),
            ("session = cp.TouchSession(model, **noise)", check_touch_session)]


@pytest.mark.parametrize("code", snippets("python"), ids=lambda c: c.splitlines()[0][:40])
def test_python_snippet_runs(code, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    if "OUT.json" in code:  # a snippet that reads what `contactpose localize -o OUT.json` wrote
        assert cli.main(["localize", "banana", "--contacts", str(EXAMPLE), "-o", "OUT.json"]) == 0
    capsys.readouterr()
    exec(compile(code, "README.md", "exec"), {"__name__": "readme"})
    out = capsys.readouterr().out.splitlines()
    for marker, check in PROMISES:
        if marker in code:
            check(out, code)


def test_every_promise_has_its_snippet():
    for marker, _ in PROMISES:
        assert sum(marker in code for code in snippets("python")) == 1, marker


def test_the_use_example_defines_what_it_uses():
    code = snippets("python")[0]
    assert "points, normals =" in code and "cp.localize(" in code


# ----------------------------------------------- what the commands print ---

def test_make_demo_prints_what_the_readme_shows(tmp_path):
    """`contactpose demo` (what `make demo` runs): the README's lines but for the times, and the picture."""
    code, out = run_cli(["demo", "--out", str(tmp_path)])
    assert code == 0
    assert [masked(line) for line in out] == [masked(line) for line in block_after("It prints, for example:")]
    png = tmp_path / "banana_demo.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000


def test_the_localize_example_prints_what_the_readme_shows(tmp_path):
    """The Command line section's example: examples/banana_contacts.json with finger 2 lifted
    3 cm along its outward normal; every line but the times as shown."""
    shown = block_after("banana (along its outward normal):")
    assert shown[0] == "$ contactpose localize banana --contacts lifted.json"
    c = jsonfiles.read_contacts(EXAMPLE)
    points = c.points.copy()
    points[2] -= 0.03 * c.finger_normals[2]
    path = tmp_path / "lifted.json"
    jsonfiles.write_json(path, Contacts(points, finger_normals=c.finger_normals).to_dict())
    code, out = run_cli(["localize", "banana", "--contacts", str(path)])
    assert code == 0 and [masked(line) for line in out] == [masked(line) for line in shown[1:]]
    assert cli.main(["localize", "banana", "--contacts", str(path), "--strict"]) == 3


@pytest.mark.parametrize("text", snippets("json"), ids=lambda t: t.split('"')[1])
def test_json_snippet_parses(text):
    data = json.loads(text)
    if "schema_version" in data:  # a sketch of the output (with "..." parts): the schema's keys
        schema = load_schema("result")
        assert set(schema["required"]) <= set(data) <= set(schema["properties"])
        assert data["schema_version"] == schema["properties"]["schema_version"]["const"]
    elif "contacts" in data:
        assert jsonfiles.parse_contacts(data).n == len(data["contacts"])
    elif "steps" in data:
        assert len(jsonfiles.parse_sequence(data)) == len(data["steps"])
    else:
        assert jsonfiles.parse_prior(data).pose.shape == (4, 4)
