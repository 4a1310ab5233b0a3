"""Command-line conventions: --version, --debug anywhere, help with defaults, a closed
stdout, warnings for options given in vain, and the exit codes."""

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import contactpose
from contactpose.cli import build_parser, main
from contactpose.cli import common as cli_common
from contactpose.errors import ContactsError
from contactpose.localize import localize
from contactpose.model.object_model import ObjectModel
from contactpose.sim import objects

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = str(ROOT / "examples" / "banana_contacts.json")
#: Options whose default the library applies: the parser's is None, the help states the real one.
LIBRARY_DEFAULTS = {("localize", "--robust"): localize.__kwdefaults__["robust"],
                    ("localize", "--position-noise"): "0.0025 x the object's diameter",
                    ("localize", "--solver"): "closed-form with --method fast",
                    ("build-model", "--bounds"): ObjectModel.from_mesh.__kwdefaults__["bounds"],
                    ("build-model", "--bins"): "32 32 64"}


@pytest.fixture(scope="module")
def banana_npz(tmp_path_factory):
    path = tmp_path_factory.mktemp("conventions") / "banana.npz"
    ObjectModel.from_mesh(objects.load("banana")).save(path)
    return str(path)


def subparsers(parser):
    """{name: parser} of every subcommand."""
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


def options(parser):
    """The parser's arguments other than -h."""
    return [a for a in parser._actions if not isinstance(a, argparse._HelpAction)]


def run_cli(*argv, **kwargs):
    """``python -m contactpose ARGV`` in a subprocess that imports this checkout."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-m", "contactpose", *argv], env=env, stderr=subprocess.PIPE,
                            text=True, **kwargs)


def test_version_prints_the_package_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out == f"contactpose {contactpose.__version__}\n" == "contactpose 0.1.0\n"


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_before_or_after_the_command_shows_the_exception(tmp_path, capsys, where):
    argv = ["localize", "banana", "--contacts", str(tmp_path / "missing.json")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("contactpose: error: ") and len(err.splitlines()) == 1 and "Traceback" not in err
    with pytest.raises(ContactsError, match="does not exist"):
        main(["--debug", *argv] if where == "before" else [*argv, "--debug"])


@pytest.mark.parametrize("before,after,debug", [([], [], False), (["--debug"], [], True), ([], ["--debug"], True)])
def test_debug_value_is_kept_from_either_position(before, after, debug):
    argv = [*before, "localize", "banana", "--contacts", "c.json", *after]
    assert build_parser().parse_args(argv).debug is debug


def test_every_option_has_help_and_help_shows_defaults():
    parser = build_parser()
    assert "scan" in subparsers(parser), "Open3D is installed here: scan must be registered"
    for name, sub in [("contactpose", parser), *subparsers(parser).items()]:
        assert issubclass(sub.formatter_class, argparse.ArgumentDefaultsHelpFormatter), name
        formatter = sub.formatter_class(sub.prog)
        text = re.sub(r"\s+", " ", sub.format_help())
        for action in options(sub):
            if isinstance(action, argparse._SubParsersAction):
                assert all(choice.help for choice in action._choices_actions), name
                continue
            flag = action.option_strings[-1] if action.option_strings else action.dest
            assert action.help and action.help is not argparse.SUPPRESS, (name, flag)
            shown = formatter._get_help_string(action)
            if action.default not in (None, False, argparse.SUPPRESS):
                assert "(default: " in shown, (name, flag, shown)
            if (name, flag) in LIBRARY_DEFAULTS:
                stated = re.search(r"\(default: [^)]*" + re.escape(str(LIBRARY_DEFAULTS[name, flag])), shown)
                assert action.default is None and stated, (name, flag, shown)
        assert "--debug" in text, name


def test_top_level_help_lists_the_exit_codes():
    text = re.sub(r"\s+", " ", build_parser().format_help())
    for code in (0, 1, 2, 3, 130, 141):
        assert re.search(rf"\b{code} \w", text), code


@pytest.mark.parametrize("closed", ["before the first line", "after the first line"])
def test_closed_stdout_ends_quietly(closed):
    argv = ["localize", "banana", "--contacts", EXAMPLE]
    if closed == "before the first line":  # deterministic: every write fails
        read, write = os.pipe()
        os.close(read)
        proc = run_cli(*argv, stdout=write)
        os.close(write)
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == cli_common.EXIT_CLOSED_PIPE, err
    else:  # like `| head -1`: whether the rest was written before the close is up to timing
        proc = run_cli(*argv, stdout=subprocess.PIPE)
        assert proc.stdout.readline().startswith("status: ")
        proc.stdout.close()
        err = proc.stderr.read()
        assert proc.wait(timeout=300) in (0, cli_common.EXIT_CLOSED_PIPE)
    assert "Traceback" not in err and "BrokenPipeError" not in err and "Exception ignored" not in err, err


def in_vain_cases(tmp, npz):
    """(argv, the warning lines expected on stderr)."""
    loc = ["localize", "banana", "--contacts", EXAMPLE]
    out = str(tmp / "r.json")
    return [
        (loc, []),
        (loc + ["--seed", "3"], ["--seed has no effect without --samples"]),
        (loc + ["--seed", "3", "--samples", "20"], []),
        (loc + ["--robust", "huber"], ["--robust has no effect without --solver factor-graph or --samples"]),
        (loc + ["--robust", "cauchy", "--solver", "factor-graph"], []),
        (loc + ["--top", "2"], ["--top has no effect without -o (the printed result shows the best hypothesis only)"]),
        (loc + ["--top", "2", "-o", out], []),
        (loc + ["--method", "paper", "--prior", str(ROOT / "examples" / "banana_prior.json")], []),
        (loc + ["--surface"], []),
        (loc + ["--surface", "--solver", "factor-graph"],
         ["--surface has no effect with --method paper or --solver lm|factor-graph (closed form only)"]),
        (["localize", npz, "--contacts", EXAMPLE, "--fix-normals"],
         [f"--fix-normals has no effect with a model file ({npz}): it applies when building from a mesh"]),
        (["build-model", "banana", "-o", str(tmp / "b.npz"), "--save-mesh", str(tmp / "m.ply")],
         ["--save-mesh has no effect without a point cloud (banana is not a point cloud file)"]),
    ]


def test_options_given_in_vain_warn_one_line_each(tmp_path, capsys, banana_npz):
    for argv, expected in in_vain_cases(tmp_path, banana_npz):
        assert main(argv) == 0, argv
        err = capsys.readouterr().err
        warned = [line for line in err.splitlines() if "has no effect" in line]
        assert warned == [f"contactpose: warning: {w}" for w in expected], (argv, err)


def test_scan_options_in_vain_warn(recwarn):
    pytest.importorskip("open3d")
    from contactpose.cli import scan

    parser = build_parser()
    args = parser.parse_args(["build-model", "cloud.npy", "--scan-bpa-radii", "0.01", "--scan-outlier-neighbors", "9"])
    scan.warn_scan_options_in_vain(args, scan.options_from_args(args))
    args = parser.parse_args(["scan", "cloud.npy", "-o", "m.ply", "--method", "bpa", "--depth", "7"])
    scan.warn_scan_options_in_vain(args, scan.options_from_args(args))
    assert [str(w.message) for w in recwarn] == [
        "--scan-bpa-radii has no effect without --scan-method bpa",
        "--scan-outlier-neighbors has no effect without --scan-outlier-std above 0",
        "--depth has no effect with --method bpa (Poisson only)"]


def test_strict_exits_3_when_no_hypothesis_fits(tmp_path, capsys):
    far = tmp_path / "far.json"  # contacts 0.5 m apart on the 0.18 m banana (10x would be an error)
    far.write_text(json.dumps({"contacts": [{"point": [0, 0, 0], "finger_normal": [0, 0, 1]},
                                            {"point": [0.5, 0, 0], "finger_normal": [0, 0, -1]},
                                            {"point": [0, 0.5, 0], "finger_normal": [1, 0, 0]}]}))
    argv = ["localize", "banana", "--contacts", str(far)]
    assert main(argv) == 0
    assert main(argv + ["--strict"]) == cli_common.EXIT_NO_HYPOTHESIS == 3
    assert capsys.readouterr().out.count("status: no_hypothesis") == 2
    assert main(["localize", "banana", "--contacts", EXAMPLE, "--strict"]) == 0


def test_internal_error_is_one_line_with_exit_1(capsys, monkeypatch):
    from contactpose.cli import localize as cli_localize

    def broken(*args, **kwargs):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(cli_localize, "localize", broken)
    argv = ["localize", "banana", "--contacts", EXAMPLE]
    assert main(argv) == cli_common.EXIT_INTERNAL == 1
    err = capsys.readouterr().err
    assert err.splitlines() == ["contactpose: internal error: ZeroDivisionError: division by zero "
                                "(rerun with --debug for the traceback)"]
    with pytest.raises(ZeroDivisionError):
        main(argv + ["--debug"])


def test_build_model_refuses_a_model_file(capsys, banana_npz):
    assert main(["build-model", banana_npz, "--fix-normals"]) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [f"contactpose: error: {banana_npz} is a model file already; build-model takes a "
                                "mesh, a point cloud or a built-in object name"]


def test_usage_error_exits_2(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["localize", "banana"])
    assert exit_.value.code == cli_common.EXIT_BAD_INPUT
    assert "--contacts" in capsys.readouterr().err
