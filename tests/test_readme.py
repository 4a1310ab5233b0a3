"""Every Python and JSON snippet of the README runs: the examples a newcomer copies work."""

import json
import re
from pathlib import Path

import pytest

from contactpose import cli
from contactpose.io import jsonfiles
from contactpose.io.output import load_schema

README = Path(__file__).resolve().parents[1] / "README.md"
EXAMPLE = README.parent / "examples" / "banana_contacts.json"


def snippets(language):
    return re.findall(rf"```{language}\n(.*?)```", README.read_text(), flags=re.S)


@pytest.mark.parametrize("code", snippets("python"), ids=lambda c: c.splitlines()[0][:40])
def test_python_snippet_runs(code, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    if "OUT.json" in code:  # a snippet that reads what `contactpose localize -o OUT.json` wrote
        assert cli.main(["localize", "banana", "--contacts", str(EXAMPLE), "-o", "OUT.json"]) == 0
    exec(compile(code, "README.md", "exec"), {"__name__": "readme"})


def test_the_use_example_defines_what_it_uses():
    code = snippets("python")[0]
    assert "points, normals =" in code and "cp.localize(" in code


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
