"""Build-time parts of the docs site (a mkdocs hook: ``hooks:`` in mkdocs.yml, no plugin).

* The command-line reference: ``<!-- cli-reference -->`` in a page becomes one section per
  subcommand, each the ``--help`` of the parser that ``contactpose.cli.build_parser`` builds,
  so the page cannot drift from the parsers.
* The JSON formats: ``<!-- json-schemas -->`` becomes one section per schema of
  ``contactpose/data/*.schema.json``: its title, description and a table of its keys.
* The API reference: on a page under ``api/``, ``<!-- api-modules -->`` becomes a ``:::`` block
  for every top-level module of the package that declares ``__all__`` and has no block on the
  page yet; after each ``::: contactpose.X`` block come blocks for the names of ``X.__all__``
  that griffe's static view does not show as members: submodules listed in ``__all__`` and
  functions that share their module's name (``contactpose.localize``, the function, is also
  the name of its module).
* ``<!-- view-screenshots -->`` becomes the 3D view's screenshots of ``results/demo/`` that
  are committed (a sentence saying so while there are none).
* ``<!-- research-notes -->`` and ``<!-- results-pages -->`` become lists of links to those
  pages, by title.
* The research notes (``research/*.md``) and the committed results (``results/``: its
  Markdown summaries and PNG figures) are added to the site as files of their own, at the
  same paths (``research/errata.md``, ``results/bench/bench_stages.png``), without copies in
  ``docs/``; their pages join the navigation's "Research" and "Benchmarks" sections. A link in
  them to a file that is not part of the site becomes plain code text, so that the strict
  build fails only on broken links between pages; their lists are laid out for the site's
  Markdown parser (nested by 4 spaces, a blank line before).
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import importlib
import inspect
import json
import logging
import os
import posixpath
import re
import sys
from pathlib import Path

from mkdocs.structure.files import File

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
RESEARCH = ROOT / "research"
RESULTS = ROOT / "results"
SCHEMAS = ROOT / "contactpose" / "data"
CLI_MARKER = "<!-- cli-reference -->"
JSON_MARKER = "<!-- json-schemas -->"
API_MARKER = "<!-- api-modules -->"
RESEARCH_MARKER = "<!-- research-notes -->"
RESULTS_MARKER = "<!-- results-pages -->"
VIEW_MARKER = "<!-- view-screenshots -->"
#: Screenshots of the 3D view (results/demo/), with their captions, shown once committed.
VIEW_SHOTS = {
    "view_banana.png": "`contactpose localize banana --contacts examples/banana_contacts.json --html PAGE`",
    "view_ycb.png": "The YCB banana touched by four fingertips of 8 mm, localized with `--finger-radius`: "
                    "the other placements that fit, with their probabilities, and the fingertips",
}
PACKAGE = ROOT / "contactpose"
#: Width of the rendered --help text (argparse reads $COLUMNS).
HELP_COLUMNS = "100"
#: Navigation sections the mirrored pages join, and the first page of each.
RESEARCH_NAV, RESULTS_NAV = "Research", "Benchmarks"
#: The errata and the design decisions first, then the notes by name.
RESEARCH_FIRST = ("errata.md", "design.md")


# ------------------------------------------------------------------ the docstrings ---

class TwoSpaceContinuation(logging.Filter):
    """The library's numpy-style sections indent a description by 2 spaces under its item,
    which griffe parses as meant but calls confusing; that one remark is dropped, every other
    docstring warning still fails the strict build."""

    def filter(self, record):
        return "Confusing indentation for continuation line" not in record.getMessage()


def on_startup(command, dirty):
    logging.getLogger("mkdocs.plugins.griffe").addFilter(TwoSpaceContinuation())


# ------------------------------------------------------------------ mirrored files ---

def research_notes():
    first = [RESEARCH / n for n in RESEARCH_FIRST if (RESEARCH / n).exists()]
    return first + sorted(p for p in RESEARCH.glob("*.md") if p not in first)


def result_files(suffix):
    """Committed result files with this suffix (scratch and resume folders left out)."""
    skip = {"_scratch", "resume", "resume_chsel"}
    return sorted(p for p in RESULTS.rglob(f"*{suffix}") if not skip & set(p.relative_to(RESULTS).parts))


def mirrored():
    """(site path, file on disk) of every file the site takes from outside docs/."""
    out = [(f"research/{p.name}", p) for p in research_notes()]
    for suffix in (".md", ".png"):
        out += [(f"results/{p.relative_to(RESULTS).as_posix()}", p) for p in result_files(suffix)]
    return out


def page_title(path):
    found = re.search(r"^#\s+(.+)$", path.read_text(encoding="utf-8"), flags=re.M)
    return found.group(1).strip() if found else path.stem


def results_title(uri, path):
    """A results page's title: its folder's own heading."""
    folder = posixpath.dirname(uri)[len("results/"):]
    return "All results" if not folder else f"{folder}: {page_title(path)}"


def short_title(title):
    """A navigation title: a heading up to its colon."""
    return title.split(":", 1)[0].strip()


def results_nav_title(uri):
    """The folder under results/, and the file's name unless it is the folder's summary."""
    stem = posixpath.splitext(uri[len("results/"):])[0]
    if stem == "README":
        return "All results"
    return posixpath.dirname(stem) if posixpath.basename(stem) == "summary" else stem


def on_config(config):
    """Append the mirrored pages to their navigation sections (present in mkdocs.yml)."""
    results = [{results_nav_title(uri): uri} for uri, _ in mirrored() if uri.startswith("results/") and uri.endswith(".md")]
    sections = {RESEARCH_NAV: [{short_title(page_title(p)): f"research/{p.name}"} for p in research_notes()],
                RESULTS_NAV: [{"Results": results}]}
    for entry in config["nav"] or []:
        if isinstance(entry, dict):
            for name, children in entry.items():
                if name in sections and isinstance(children, list):
                    children.extend(sections[name])
    return config


def on_files(files, config):
    for uri, path in mirrored():
        if files.get_file_from_path(uri) is None:
            files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files


# --------------------------------------------------------------------- the markers ---

def on_page_markdown(markdown, page, config, files):
    if CLI_MARKER in markdown:
        markdown = markdown.replace(CLI_MARKER, cli_reference())
    if JSON_MARKER in markdown:
        markdown = markdown.replace(JSON_MARKER, json_reference())
    if RESEARCH_MARKER in markdown or RESULTS_MARKER in markdown:
        here = posixpath.dirname(page.file.src_uri)
        notes = [(f"research/{p.name}", page_title(p)) for p in research_notes()]
        results = [(uri, results_title(uri, p)) for uri, p in mirrored() if uri.startswith("results/") and uri.endswith(".md")]
        markdown = markdown.replace(RESEARCH_MARKER, link_list(notes, here))
        markdown = markdown.replace(RESULTS_MARKER, link_list(results, here))
    if VIEW_MARKER in markdown:
        markdown = markdown.replace(VIEW_MARKER, view_screenshots(page.file.src_uri))
    uri = page.file.src_uri
    if uri.startswith("api/"):
        markdown = api_blocks(markdown)
    if uri.startswith(("research/", "results/")) and page.file.generated_by is not None:
        markdown = site_lists(unlinked_outside(markdown, uri, files))
    elif page.file.generated_by is None:
        markdown = repository_links(markdown, uri)
    return markdown


def repository_links(markdown, uri):
    """A page of docs/ links a research note or a result by its path in the repository
    (``../../research/errata.md`` from ``docs/concepts/``), so that the link works where the
    sources are read as they are; in the site it becomes the link to that file's copy."""
    site_paths = {path.resolve(): site_uri for site_uri, path in mirrored()}
    here = posixpath.dirname(uri)

    def replace(match):
        bang, text, target = match.groups()
        path, _, anchor = target.partition("#")
        if re.match(r"[a-z]+:", target) or not path:
            return match.group(0)
        site_uri = site_paths.get((DOCS / here / path).resolve())
        if site_uri is None:
            return match.group(0)
        new = posixpath.relpath(site_uri, here or ".") + (f"#{anchor}" if anchor else "")
        return f"{bang}[{text}]({new})"
    return LINK.sub(replace, markdown)


ITEM = re.compile(r"^(\s*)(?:[*-]|\d+\.) ")


def site_lists(markdown):
    """The repository's Markdown nests lists by 2 spaces and starts a list right below a
    paragraph, as code hosts allow; the site's parser wants 4 spaces and a blank line before.
    Outside code fences, a line indented by 2 or 3 spaces is indented by 2 more, and a blank
    line goes before a list that follows a paragraph's line."""
    out, fenced, in_list = [], False, False
    for line in markdown.split("\n"):
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced:
            item = ITEM.match(line)
            if not line.strip():
                in_list = False
            elif item and not item.group(1):
                if out and out[-1].strip() and not in_list and not out[-1].lstrip().startswith("|"):
                    out.append("")
                in_list = True
            elif not (out and out[-1].strip()):
                in_list = False
            if re.match(r" {2,3}\S", line):
                line = "  " + line
        out.append(line)
    return "\n".join(out)


def view_screenshots(uri):
    here = posixpath.dirname(uri) or "."
    shots = [(name, caption) for name, caption in VIEW_SHOTS.items() if (RESULTS / "demo" / name).exists()]
    if not shots:
        return "Screenshots of the view will be shown here once they are committed with the results.\n"
    return "\n".join(f"![The 3D view]({posixpath.relpath(f'results/demo/{name}', here)})\n\n*{caption}* "
                     f"(`results/demo/{name}`, made by `python -m contactpose.harness.pages`).\n"
                     for name, caption in shots)


def link_list(pages, here):
    return "\n".join(f"* [{title}]({posixpath.relpath(uri, here or '.')})" for uri, title in pages) + "\n"


LINK = re.compile(r"(!?)\[([^\]]*)\]\(([^)\s]+)\)")


def unlinked_outside(markdown, uri, files):
    """Links of a mirrored page to files the site does not hold, as code text."""
    def replace(match):
        bang, text, target = match.groups()
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            return match.group(0)
        path = posixpath.normpath(posixpath.join(posixpath.dirname(uri), target.split("#")[0]))
        if files.get_file_from_path(path) is not None:
            return match.group(0)
        return f"{text} (`{target}`)" if text and not bang else f"`{target}`"
    return LINK.sub(replace, markdown)


@contextlib.contextmanager
def _columns(width):
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = width
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def subcommands(parser=None):
    """(name, parser) of every subcommand of the contactpose parser, in its order."""
    if parser is None:
        from contactpose.cli import build_parser

        parser = build_parser()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices.items())
    return []


def cli_reference():
    from contactpose.cli import build_parser

    with _columns(HELP_COLUMNS):
        parser = build_parser()
        parts = ["## contactpose", "", "```text", parser.format_help().rstrip(), "```", ""]
        for name, sub in subcommands(parser):
            parts += [f"## contactpose {name}", "", "```text", sub.format_help().rstrip(), "```", ""]
    return "\n".join(parts)


# ------------------------------------------------------------------------ the API ---

#: A ``:::`` line of the package without an options block below it.
BLOCK = re.compile(r"^::: (contactpose[\w.]*)[ \t]*$(?!\n[ \t]+\S)", flags=re.M)


def declares_all(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return any(isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets)
               for node in tree.body)


def top_level_modules():
    """The package's top-level modules (not subpackages) that declare __all__."""
    return [f"contactpose.{p.stem}" for p in sorted(PACKAGE.glob("*.py"))
            if not p.stem.startswith("_") and declares_all(p)]


def hidden_exports(name):
    """Blocks for the names of name.__all__ that griffe does not show as its members."""
    module = importlib.import_module(name)
    out = []
    for public in getattr(module, "__all__", []):
        obj = getattr(module, public, None)
        if obj is None:  # a submodule that __init__ lists but does not import
            obj = importlib.import_module(f"{name}.{public}")
        sub = sys.modules.get(f"{name}.{public}")
        if inspect.ismodule(obj):
            if obj.__name__ == f"{name}.{public}":
                out.append(f"::: {obj.__name__}\n    options:\n      show_root_heading: true\n")
            else:  # a module of another subpackage, exported under a short name
                out.append(f"`{name}.{public}` is the module [`{obj.__name__}`][{obj.__name__}].\n")
        elif inspect.ismodule(sub) and sub is not obj and getattr(obj, "__module__", None):
            out.append(f"::: {obj.__module__}.{public}\n    options:\n      show_root_heading: true\n")
    return out


def api_blocks(markdown):
    if API_MARKER in markdown:
        present = set(BLOCK.findall(markdown))
        blocks = [f"## `{m}`\n\n::: {m}\n" for m in top_level_modules() if m not in present]
        markdown = markdown.replace(API_MARKER, "\n".join(blocks))

    def extend(match):
        extras = hidden_exports(match.group(1))
        return match.group(0) + ("\n\n" + "\n".join(extras) if extras else "")
    return BLOCK.sub(extend, markdown)


# ------------------------------------------------------------------- JSON schemas ---

def schema_type(spec):
    if "const" in spec:
        return f"`{json.dumps(spec['const'])}`"
    if "enum" in spec:
        return " / ".join(f"`{json.dumps(v)}`" for v in spec["enum"])
    if "$ref" in spec:
        name = spec["$ref"].rsplit("/", 1)[-1]
        return f"`{name}` (below)"
    for key in ("anyOf", "oneOf"):
        if key in spec:
            return " or ".join(schema_type(s) for s in spec[key])
    kind = spec.get("type", "")
    kind = " or ".join(kind) if isinstance(kind, list) else kind
    if kind == "array" and isinstance(spec.get("items"), dict) and spec["items"]:
        return f"array of {schema_type(spec['items'])}"
    return kind or "any"


def cell(text):
    return str(text).replace("|", "\\|").replace("\n", " ")


def key_table(spec):
    props = spec.get("properties", {})
    if not props:
        return []
    required = set(spec.get("required", []))
    rows = ["| key | type | required | meaning |", "|---|---|---|---|"]
    for key, sub in props.items():
        rows.append(f"| `{key}` | {cell(schema_type(sub))} | {'yes' if key in required else ''} "
                    f"| {cell(sub.get('description', ''))} |")
    return rows + [""]


def json_reference():
    parts = []
    for path in sorted(SCHEMAS.glob("*.schema.json")):
        schema = json.loads(path.read_text(encoding="utf-8"))
        name = path.name.removesuffix(".schema.json")
        parts += [f"### Schema `{name}`", "",
                  f"`contactpose/data/{path.name}`, `load_schema(\"{name}\")`: {schema.get('title', '')}.", "",
                  cell(schema.get("description", "")), ""]
        parts += key_table(schema)
        for def_name, sub in schema.get("$defs", {}).items():
            table = key_table(sub)
            if table:
                parts += [f"`{def_name}`: {cell(sub.get('description', schema_type(sub)))}", ""] + table
        parts += [f'??? note "The whole schema: {path.name}"', "", "    ```json"]
        parts += ["    " + line for line in json.dumps(schema, indent=1, ensure_ascii=False).splitlines()]
        parts += ["    ```", ""]
    return "\n".join(parts)
