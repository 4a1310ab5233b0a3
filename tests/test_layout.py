"""The package's shape: what ``import contactpose`` loads, and the names the README promises.

The layer order itself is checked by ``lint-imports`` (contracts in pyproject.toml), which
``make test`` runs before the tests.
"""

import importlib
import json
import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
#: Never loaded by ``import contactpose``: the harness, the CLI and heavy optional libraries.
NOT_AT_IMPORT = ("contactpose.cli", "contactpose.harness", "contactpose.peers", "matplotlib", "dask", "distributed",
                 "experiments")


def test_import_loads_no_harness_cli_or_plotting():
    script = ("import json, sys, contactpose\n"
              "mods = {m: getattr(sys.modules[m], '__file__', None) for m in list(sys.modules)}\n"
              "uses_argparse = [m for m in mods if m.startswith('contactpose')\n"
              "                 and 'argparse' in vars(sys.modules[m])]\n"
              "print(json.dumps({'modules': sorted(mods), 'argparse': uses_argparse}))\n")
    out = json.loads(subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout)
    loaded = [m for m in out["modules"] if m.split(".")[0] in ("contactpose", "matplotlib", "dask", "distributed",
                                                                 "experiments")]
    bad = [m for m in loaded if any(m == p or m.startswith(p + ".") for p in NOT_AT_IMPORT)]
    assert bad == [], f"import contactpose loaded {bad}"
    assert out["argparse"] == [], f"modules of the core that use argparse: {out['argparse']}"


def readme_names():
    """Every dotted name of the package the README mentions: cp.X.Y and contactpose.X.Y."""
    text = README.read_text()
    names = set(re.findall(r"\bcp\.([A-Za-z_][\w.]*\w)", text))
    names |= set(re.findall(r"\bcontactpose\.([a-z_][\w.]*\w)", text))
    return sorted(n for n in names if not n.endswith((".py", ".npz", ".json")))


def resolve(dotted):
    """The object at contactpose.<dotted>, importing submodules as needed."""
    obj, path = importlib.import_module("contactpose"), "contactpose"
    for part in dotted.split("."):
        path += "." + part
        try:
            obj = getattr(obj, part)
        except AttributeError:
            obj = importlib.import_module(path)
    return obj


def test_every_name_in_the_readme_exists():
    names = readme_names()
    assert {"ObjectModel.from_mesh", "Contacts", "PosePrior", "localize", "objects.load"} <= set(names)
    missing = []
    for name in names:
        try:
            resolve(name)
        except (ImportError, AttributeError):
            missing.append(name)
    assert missing == [], f"README names that do not exist: {missing}"


PACKAGE = Path(__file__).resolve().parents[1] / "contactpose"


def test_every_subpackage_declares_its_public_names():
    """Each subpackage's __init__ states __all__, and every name in it exists."""
    for init in sorted(PACKAGE.glob("*/__init__.py")):
        name = f"contactpose.{init.parent.name}"
        module = importlib.import_module(name)
        assert isinstance(getattr(module, "__all__", None), list), f"{name} declares no __all__"
        for public in module.__all__:
            resolve(f"{init.parent.name}.{public}")


def test_experiments_import_no_private_name():
    """The experiments use the library's public names only: none with a leading underscore."""
    import ast

    private = []
    for script in sorted((PACKAGE.parent / "experiments").glob("*.py")):
        for node in ast.walk(ast.parse(script.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("contactpose"):
                private += [f"{script.name}: {node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
    assert private == []


def test_no_root_module_belongs_to_the_harness():
    """Sweeps, benches, demos, figures and the peers live in their packages, not at the root."""
    roots = {p.stem for p in PACKAGE.glob("*.py")}
    assert not roots & {"sweep", "bench", "demo", "viz", "baselines"}, roots
