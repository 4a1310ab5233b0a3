"""The docs site (mkdocs.yml, docs/): it builds strictly, it has an API page for every public
subpackage and a section for every subcommand (both derived from the package, so a new one
without its page fails), and the snippets of its pages run and print what they show.

Snippet convention: every ```python block of a page under docs/ runs, the page's blocks in
order in one namespace, in a temporary directory that holds `examples/` (the repository's).
A block whose fence follows the line

    <!-- not run: REASON -->

is shown but not run (the test is skipped with REASON: a Dask cluster, a file of the
user's); one that follows

    <!-- needs: contactpose.some.name -->

runs when that name exists and is skipped while it does not. ```json blocks are parsed as the
input they show (CONTACTS, PRIOR, SEQ) or checked against the output schema's keys.
"""

import argparse
import importlib
import importlib.util
import json
import logging
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from test_readme import ROOT, block_after, demo_lines_match, masked, run_cli, run_snippet, snippets

from contactpose import Contacts, cli
from contactpose.cli import build_parser
from contactpose.io import jsonfiles
from contactpose.io.output import load_schema

DOCS = ROOT / "docs"
PACKAGE = ROOT / "contactpose"
EXAMPLE = ROOT / "examples" / "banana_contacts.json"
PAGES = sorted(p for p in DOCS.rglob("*.md"))

def load_hooks():
    """docs/hooks.py, the build's generated parts, as a module."""
    spec = importlib.util.spec_from_file_location("docs_hooks", DOCS / "hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


hooks = load_hooks()

#: "about X" in a page: within this share of X.
ABOUT = 0.3


def page_text(path):
    return path.read_text(encoding="utf-8")


def public_subpackages():
    return sorted(init.parent.name for init in PACKAGE.glob("*/__init__.py"))


# -------------------------------------------------------------------------- the build ---

@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """`mkdocs build --strict` (what `make docs` runs) into a temporary folder."""
    out = tmp_path_factory.mktemp("site")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                          capture_output=True, text=True, env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return out


def html(site, uri):
    path = site / uri / "index.html"
    assert path.exists(), uri
    return path.read_text(encoding="utf-8")


def nav_pages():
    return set(re.findall(r"(?:^|\s)([\w/.-]+\.md)\s*$", (ROOT / "mkdocs.yml").read_text(), flags=re.M))


def test_every_public_subpackage_has_an_api_page(site):
    """docs/api/NAME.md for each contactpose/NAME/__init__.py, in the nav, built, every name of
    its __all__ documented there."""
    for name in public_subpackages():
        page = DOCS / "api" / f"{name}.md"
        assert page.exists(), f"contactpose.{name} has no API page: add docs/api/{name}.md and its nav entry"
        assert re.search(rf"^::: contactpose\.{name}\s*$", page_text(page), flags=re.M), page
        assert f"api/{name}.md" in nav_pages(), f"api/{name}.md is not in mkdocs.yml's nav"
        built = html(site, f"api/{name}")
        for public in importlib.import_module(f"contactpose.{name}").__all__:
            assert re.search(rf'id="contactpose\.{name}\.(?:[\w.]+\.)?{public}"', built), f"contactpose.{name}.{public}"


def test_the_package_and_its_top_level_modules_are_documented(site):
    built = html(site, "api/contactpose")
    for public in importlib.import_module("contactpose").__all__:
        assert f'id="contactpose.{public}' in built or f"<code>contactpose.{public}</code>" in built.replace(
            "contactpose.sim.", "contactpose."), public
    core = html(site, "api/core")
    for module in hooks.top_level_modules():
        assert f'id="{module}.' in core, module


def test_every_subcommand_has_its_section(site):
    page = html(site, "reference/cli")
    commands = hooks.subcommands()
    assert {"localize", "build-model", "track", "demo"} <= {name for name, _ in commands}
    for name, _ in commands:
        assert f'id="contactpose-{name}"' in page, name
        assert f"usage: contactpose {name} " in page, name


def test_every_schema_research_note_and_result_is_in_the_site(site):
    page = html(site, "reference/json")
    for schema in (PACKAGE / "data").glob("*.schema.json"):
        assert schema.name in page
    for note in (ROOT / "research").glob("*.md"):
        html(site, f"research/{note.stem}")
    for uri, path in hooks.mirrored():
        if uri.endswith(".md"):
            html(site, uri.removesuffix(".md").removesuffix("README").rstrip("/"))
        else:
            assert (site / uri).read_bytes() == path.read_bytes()


def test_a_broken_link_between_pages_fails_the_build():
    from mkdocs.config import load_config

    config = load_config(str(ROOT / "mkdocs.yml"))
    assert config.strict
    assert config.validation.links.not_found == logging.WARNING  # a warning, which --strict makes an error
    assert config.validation.links.anchors == logging.WARNING
    assert config.validation.nav.omitted_files == logging.WARNING


def test_links_of_a_mirrored_page_to_files_outside_the_site_become_code():
    class Files:
        def get_file_from_path(self, path):
            return object() if path == "research/errata.md" else None

    text = "[errata](errata.md), [the script](../experiments/x.py), ![fig](../results/a.png), [web](https://x.org)"
    assert hooks.unlinked_outside(text, "research/note.md", Files()) == (
        "[errata](errata.md), the script (`../experiments/x.py`), `../results/a.png`, [web](https://x.org)")


def test_a_page_links_a_research_note_or_result_by_its_repository_path():
    text = "[e](../../research/errata.md#x), ![f](../../results/demo/banana_demo.png), [p](statuses.md)"
    assert hooks.repository_links(text, "concepts/noise.md") == (
        "[e](../research/errata.md#x), ![f](../results/demo/banana_demo.png), [p](statuses.md)")


def test_the_sources_links_resolve_in_the_repository():
    """Read as they are (on a code host), the pages of docs/ link files that exist."""
    broken = []
    for page in PAGES:
        for target in re.findall(r"\]\(([^)\s]+)\)", page_text(page)):
            path = target.split("#")[0]
            if path and not re.match(r"[a-z]+:", target) and not (page.parent / path).exists():
                broken.append((page.relative_to(DOCS).as_posix(), target))
    assert broken == []


# ------------------------------------------------------------------------ the snippets ---

MARK = re.compile(r"<!-- (not run|needs): (.+?) -->\n```python\n", flags=re.S)


def page_blocks(text):
    """(code, skip reason or None) of every python block of a page, in order."""
    marks = {m.end(): (m.group(1), m.group(2).strip()) for m in MARK.finditer(text)}
    out = []
    for m in re.finditer(r"^```python\n(.*?)^```", text, flags=re.S | re.M):
        kind, what = marks.get(m.start() + len("```python\n"), (None, None))
        reason = None
        if kind == "not run":
            reason = what
        elif kind == "needs" and not name_exists(what):
            reason = f"{what} does not exist yet"
        out.append((m.group(1), reason))
    return out


def name_exists(dotted):
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        try:
            for part in parts[i:]:
                obj = getattr(obj, part)
        except AttributeError:
            return False
        return True
    return False


def check_getting_started(out, text):
    """The Use example prints the lines the page shows (times aside)."""
    shown = block_after(text, "It prints (the time varies")
    assert [masked(line) for line in out] == [masked(line) for line in shown]


def check_touch_session(out, text):
    """The comments of its two prints: "ok [...] True" and "about 0.9° / 1 mm"."""
    code = next(c for c, _ in page_blocks(text) if "TouchSession(" in c)
    same, error = re.findall(r"^print\(.*\)\s+# (.+)$", code, flags=re.M)
    assert re.fullmatch(re.escape(same).replace(r"\[\.\.\.\]", r"\[[\d, ]+\]"), out[0]), (same, out[0])
    want_deg, want_mm = map(float, re.fullmatch(r"about ([\d.]+)° / ([\d.]+) mm", error).groups())
    got = re.fullmatch(r"ok: \d+ track\(s\); error ([\d.]+)° / ([\d.]+) mm", out[1])
    assert got, out[1]
    deg, mm = map(float, got.groups())
    assert abs(deg - want_deg) <= ABOUT * want_deg and abs(mm - want_mm) <= ABOUT * want_mm, out[1]


#: Pages whose printed lines are checked, and the check.
PROMISES = {"getting-started.md": check_getting_started, "concepts/sessions.md": check_touch_session}
RUN_PAGES = [p for p in PAGES if page_blocks(page_text(p))]
#: Pages with at least one block that runs.
RUNNABLE_PAGES = [p for p in RUN_PAGES if any(reason is None for _, reason in page_blocks(page_text(p)))]


def test_the_checked_pages_have_their_snippets():
    assert set(PROMISES) <= {p.relative_to(DOCS).as_posix() for p in RUN_PAGES}


@pytest.mark.parametrize("page", RUNNABLE_PAGES, ids=lambda p: p.relative_to(DOCS).as_posix())
def test_the_python_snippets_of_a_page_run(page, tmp_path, monkeypatch, capsys):
    text = page_text(page)
    blocks = page_blocks(text)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    if "OUT.json" in text:  # a snippet that reads what `contactpose localize -o OUT.json` wrote
        assert cli.main(["localize", "banana", "--contacts", str(EXAMPLE), "-o", "OUT.json"]) == 0
    namespace = {"__name__": "docs"}
    out = []
    for code, reason in blocks:
        if reason is None:
            out += run_snippet(code, namespace, capsys, str(page))
    uri = page.relative_to(DOCS).as_posix()
    if uri in PROMISES:
        PROMISES[uri](out, text)


NOT_RUN = [(p, reason) for p in RUN_PAGES for _, reason in page_blocks(page_text(p)) if reason]


@pytest.mark.parametrize("page, reason", NOT_RUN, ids=lambda x: x.relative_to(DOCS).as_posix() if isinstance(x, Path) else "")
def test_a_block_not_run(page, reason):
    """Listed so that a run's summary names each block the tests leave out, and why."""
    pytest.skip(f"{page.relative_to(DOCS)}: {reason}")


def test_the_snippet_markers_are_read():
    text = "<!-- not run: a cluster -->\n```python\nx = 1\n```\n\n```python\ny = 2\n```\n" \
           "<!-- needs: contactpose.no_such_name -->\n```python\nz = 3\n```\n"
    assert page_blocks(text) == [("x = 1\n", "a cluster"), ("y = 2\n", None),
                                 ("z = 3\n", "contactpose.no_such_name does not exist yet")]


JSON_BLOCKS = [(p, t) for p in PAGES for t in snippets(page_text(p), "json")]


@pytest.mark.parametrize("page, text", JSON_BLOCKS, ids=lambda x: x.name if isinstance(x, Path) else x.split('"')[1])
def test_json_snippet_parses(page, text):
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


# --------------------------------------------------------------- what the commands print ---

def test_make_demo_prints_what_getting_started_shows(tmp_path):
    demo_lines_match(block_after(page_text(DOCS / "getting-started.md"), "with both methods. It prints"), tmp_path)


def test_the_localize_example_prints_what_the_cli_page_shows(tmp_path):
    """examples/banana_contacts.json with finger 2 lifted 3 cm along its outward normal; every
    line but the times as shown."""
    shown = block_after(page_text(DOCS / "reference" / "cli.md"), "banana (along its outward normal):")
    assert shown[0] == "$ contactpose localize banana --contacts lifted.json"
    c = jsonfiles.read_contacts(EXAMPLE)
    points = c.points.copy()
    points[2] -= 0.03 * c.finger_normals[2]
    path = tmp_path / "lifted.json"
    jsonfiles.write_json(path, Contacts(points, finger_normals=c.finger_normals).to_dict())
    code, out = run_cli(["localize", "banana", "--contacts", str(path)])
    assert code == 0 and [masked(line) for line in out] == [masked(line) for line in shown[1:]]
    assert cli.main(["localize", "banana", "--contacts", str(path), "--strict"]) == 3


def options_of(parser):
    return {s for action in parser._actions for s in action.option_strings}


def test_the_cli_synopsis_names_only_what_the_parsers_take():
    """The hand-written synopsis at the top of the CLI page: every subcommand and option exists."""
    lines = block_after(page_text(DOCS / "reference" / "cli.md"), "# Command line")
    parsers = dict(hooks.subcommands())
    top = build_parser()
    current = None
    for line in lines:
        plain = line.split("#")[0].replace("--[no-]", "--")
        words = shlex.split(plain.replace("[", " ").replace("]", " ").replace("|", " "))
        if words and words[0] == "contactpose":
            current = parsers.get(words[1]) if len(words) > 1 and not words[1].startswith("-") else top
            assert current is not None, line
        for word in words:
            if word.startswith("--") and not word.endswith("..."):  # --scan-...: a family
                name = word.split("=")[0]
                assert name in options_of(current) | options_of(top), (name, line)


def test_hooks_render_every_subcommand_help():
    text = hooks.cli_reference()
    for name, parser in hooks.subcommands():
        assert f"## contactpose {name}" in text
        assert isinstance(parser, argparse.ArgumentParser)


