"""The README, the project's front door: short, and true. Its Python example and its command
print what it shows (times aside), `make demo` prints the lines it shows, every `make` target
it names exists, every link resolves, the contracts users rely on stay named, and every
headline figure is found in the file it links to.

The helpers here (snippets, blocks, masking, running the CLI) serve tests/test_docs.py too."""

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from contactpose import cli

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TEXT = README.read_text()
#: The README's hard limit; it aims at about 150 lines, the rest lives in docs/.
MAX_LINES = 160


def snippets(text, language):
    """The code blocks of a language, in order."""
    return re.findall(rf"^```{language}\n(.*?)^```", text, flags=re.S | re.M)


def block_after(text, lead):
    """The plain ``` block that follows ``lead`` in text, as lines."""
    found = re.search(re.escape(lead) + r".*?^```\n(.*?)^```", text, flags=re.S | re.M)
    assert found, lead
    return found.group(1).rstrip("\n").splitlines()


def masked(line):
    """A printed line with what varies by run or machine left out: times, the demo picture's
    folder, the sign of a zero and round-off below 1e-6 (written as e-07 and smaller)."""
    line = re.sub(r"[\d.]+ ms\b", "<ms>", line)
    line = re.sub(r"-(0\.0+)(?!\d)", r" \1", line)
    line = re.sub(r"\b\d\.\d+e-(0[7-9]|[1-9]\d)\b", "<tiny>", line)
    return re.sub(r"^picture: .*banana_demo\.png$", "picture: <dir>/banana_demo.png", line)


def run_cli(argv):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = cli.main(argv)
    return code, out.getvalue().splitlines()


def run_snippet(code, namespace, capsys, name):
    """Run code in namespace; its printed lines."""
    capsys.readouterr()
    exec(compile(code, name, "exec"), namespace)
    return capsys.readouterr().out.splitlines()


def demo_lines_match(shown, tmp_path):
    """`contactpose demo` (what `make demo` runs) prints the lines shown, times aside."""
    code, out = run_cli(["demo", "--out", str(tmp_path)])
    assert code == 0
    assert [masked(line) for line in out] == [masked(line) for line in shown]
    png = tmp_path / "banana_demo.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000


# ------------------------------------------------------------------------ the README ---

def test_the_readme_is_short():
    assert len(TEXT.splitlines()) <= MAX_LINES


def test_the_python_example_prints_what_the_readme_shows(tmp_path, monkeypatch, capsys):
    (code,) = snippets(TEXT, "python")
    assert "points, normals =" in code and "cp.localize(" in code
    monkeypatch.chdir(tmp_path)
    out = run_snippet(code, {"__name__": "readme"}, capsys, "README.md")
    shown = block_after(TEXT, "It prints (the time varies):")
    assert [masked(line) for line in out] == [masked(line) for line in shown]


def test_make_demo_prints_what_the_readme_shows(tmp_path):
    demo_lines_match(block_after(TEXT, "with both methods. It prints:"), tmp_path)


def test_the_command_line_example_prints_what_the_readme_shows(monkeypatch):
    shown = block_after(TEXT, "## Command line")
    command = shown[0]
    assert command.startswith("$ .venv/bin/contactpose ")
    monkeypatch.chdir(ROOT)  # the example's file is named relative to the repository
    code, out = run_cli(shlex.split(command)[2:])
    assert code == 0 and [masked(line) for line in out] == [masked(line) for line in shown[1:]]


def test_every_make_target_it_names_exists():
    targets = set(re.findall(r"^([\w-]+):", (ROOT / "Makefile").read_text(), flags=re.M))
    named = set(re.findall(r"`make ([\w-]+)", TEXT)) | set(re.findall(r"^make ([\w-]+)", TEXT, flags=re.M))
    assert {"demo", "test", "docs"} <= named and named <= targets, named - targets


def test_it_names_the_contracts_users_rely_on():
    for contract in ("ObjectModel.from_mesh", "cp.Contacts(", "cp.PosePrior(", "cp.localize(", "`.status`", "`.best`",
                     ".hypotheses[i]", "`.facets`", "`.pose`", "`.covariance`", "`.sample_covariance`",
                     "exits with code 2", "make demo", "make test"):
        assert contract in TEXT, contract


def links(text):
    return re.findall(r"\]\(([^)\s]+)\)", text)


def test_every_link_resolves():
    local = [t for t in links(TEXT) if not re.match(r"[a-z]+:", t)]
    assert any(t.startswith("docs/") for t in local)
    missing = [t for t in local if not (ROOT / t.split("#")[0]).exists()]
    assert missing == []


NUMBER = re.compile(r"\d[\d,]*(?:\.\d+)?")


def test_every_figure_is_in_the_file_it_links_to():
    """Each row of the figures table: every number of its figure appears in its source file."""
    table = re.search(r"## Figures\n\n((?:\|.*\n)+)", TEXT).group(1)
    rows = [r for r in table.splitlines() if "---" not in r][1:]
    assert len(rows) >= 5
    for row in rows:
        _, figure, source = [c.strip() for c in row.strip("|").split("|")]
        paths = [t for t in links(source) if t.startswith(("results/", "research/"))]
        assert paths, row
        text = " ".join((ROOT / p).read_text() for p in paths)
        for number in NUMBER.findall(figure):
            assert re.search(rf"(?<![\d.]){re.escape(number)}(?![\d])", text), (number, paths)


@pytest.mark.parametrize("line, seen", [
    ("  1.000000 -0.000000 -0.099320  2.045e-09  time: 606.30 ms", "  1.000000  0.000000 -0.099320  <tiny>  time: <ms>"),
    ("chi2: 1.2e-06 cost: 30.1", "chi2: 1.2e-06 cost: 30.1"),
    ("picture: /tmp/x/banana_demo.png", "picture: <dir>/banana_demo.png")])
def test_masking_leaves_out_only_what_varies(line, seen):
    assert masked(line) == seen
