"""``python -m warp_vision``: lists every command and runs one as ``python -m warp_vision.COMMAND`` would."""

import subprocess
import sys
from pathlib import Path

import pytest

import warp_vision
from warp_vision.__main__ import COMMANDS, main

PACKAGE = Path(warp_vision.__file__).parent


def test_every_command_of_the_package_is_listed_and_each_listed_one_exists():
    runnable = {p.parent.name for p in PACKAGE.glob("*/__main__.py")}
    assert runnable == set(COMMANDS)


def test_no_command_prints_the_list(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    assert all(f"  {name}" in out for name in COMMANDS), out


def test_a_mistyped_command_is_refused_with_the_nearest(capsys):
    assert main(["trian", "--preset", "smoke"]) == 2
    err = capsys.readouterr().err
    assert "error: 'trian' is not a command (did you mean 'train'?): expected one of train, sim" in err, err


@pytest.mark.parametrize("command", ["scene", "data"])
def test_a_command_runs_as_its_own_module_does(command):
    def run(*args):
        return subprocess.run([sys.executable, "-m", *args, "--help"], capture_output=True, text=True, timeout=120)

    via_index, direct = run("warp_vision", command), run(f"warp_vision.{command}")
    assert via_index.returncode == direct.returncode == 0, via_index.stderr
    assert via_index.stdout == direct.stdout and f"python -m warp_vision.{command}" in direct.stdout


def test_the_exit_code_is_the_commands(tmp_path, capsys):
    assert main(["train", "evaluate", str(tmp_path / "nothing")]) == 2
    assert "no best.pt" in capsys.readouterr().err


def test_version_names_the_package_and_its_commit(capsys, monkeypatch):
    from warp_vision import __version__, provenance

    monkeypatch.setattr(provenance, "commit", lambda: {"commit": "0123456789abcdef" * 2, "dirty": True})
    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"warp_vision {__version__} (commit 0123456789ab, with local changes)\n"
    monkeypatch.setattr(provenance, "commit", lambda: None)
    assert main(["--version"]) == 0 and capsys.readouterr().out == f"warp_vision {__version__}\n"


def every_parser():
    """Every command line's parser of the package, subcommands included, by its command."""
    import argparse
    import importlib

    import warp_vision.train.cli as T

    roots = [("train", T._train_parser()), ("train evaluate", T._eval_parser())]
    roots += [(f"train {name}", T._task_parser(name)) for name in T.TASKS]
    roots += [(name, importlib.import_module(f"warp_vision.{name}.cli").parser()) for name in ("sim", "data")]
    roots += [(name, importlib.import_module(f"warp_vision.{name}.cli")._parser()) for name in ("bench", "scene")]

    def walk(p, path):
        yield path, p
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sub in a.choices.items():
                    yield from walk(sub, f"{path} {name}")

    for path, root in roots:
        yield from walk(root, path)


def test_every_option_with_a_default_says_it_in_its_help():
    """``bench linet --help`` said "timed repeats per measurement (median reported)" and "JSON output path",
    leaving the user to guess 10 and bench_results/linet.json; ``sim demo`` did not say --seed's or
    --duration's. Every option that has a value when not given now states it."""
    import argparse

    silent, seen = [], 0
    for path, p in every_parser():
        for a in p._actions:
            flag_only = isinstance(a, (argparse._StoreTrueAction, argparse._StoreConstAction, argparse._HelpAction))
            if not a.option_strings or flag_only or a.help == argparse.SUPPRESS or a.default in (None, [], False):
                continue
            seen += 1
            if "default" not in (a.help or ""):
                silent.append(f"{path} {a.option_strings[-1]} (default {a.default!r})")
    assert seen > 40 and not silent, silent
