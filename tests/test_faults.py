"""Fault drills on smoke-sized runs: each ends in a bit-identical result or in one line that names the
file and what is wrong, never in silent wrong numbers or a traceback.

The drills: SIGKILL at random points of synthesis and of training, then resume; a flipped byte in a chunk,
in a checkpoint and in a manifest; a truncated, emptied or clipped checkpoint; a read-only output; a full
disk (a real 1 MiB tmpfs where this machine lets root mount one, and ENOSPC injected at the write call
everywhere); a missing device; a non-finite option; a run moved to another working directory.
"""

from __future__ import annotations

import argparse
import errno
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from warp_vision.data.foveation import synthesize
from warp_vision.data.store import CorruptChunkError
from warp_vision.train import foveation
from warp_vision.train.cli import main as train_main
from warp_vision.train.config import resolve

QUIET = dict(progress=False, log=lambda *a: None)


def copy_run(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "run"
    shutil.copytree(src, dst)
    return dst


def cli(argv, capsys, cwd: Path | None = None) -> tuple[int, str]:
    """(exit code, stderr) of ``python -m warp_vision.train ARGV`` run in this process."""
    old = os.getcwd()
    if cwd is not None:
        os.chdir(cwd)
    try:
        code = train_main([*argv, "--no-progress"] if argv and argv[0] not in ("evaluate", "compare") else argv)
    finally:
        os.chdir(old)
    return code, capsys.readouterr().err


def one_line_naming(err: str, name: str) -> bool:
    lines = [x for x in err.strip().splitlines() if x.strip()]
    return len(lines) == 1 and lines[0].startswith("error:") and name in lines[0] and "Traceback" not in err


def flip_bit_in_tensor(path: Path, key_path: list, bit: int = 20) -> None:
    """Flip one bit of the stored bytes of a tensor of the checkpoint at ``path`` (in the file itself:
    the tensor's bytes are found in the zip and changed in place)."""
    ck = torch.load(path, weights_only=True)
    t = ck
    for k in key_path:
        t = t[k]
    raw = t.detach().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes()
    blob = bytearray(path.read_bytes())
    at = blob.find(raw)  # (a buffer copied into the model may hold the same bytes: the first is flipped)
    assert at >= 0, "the tensor's bytes are not in the file"
    blob[at + bit // 8] ^= 1 << (bit % 8)
    path.write_bytes(bytes(blob))


# --------------------------------------------------------------------------------------------------
# 1. checkpoints that prove their integrity


@pytest.mark.parametrize("where", [["norm", "target_mean"], ["model", "head.weight"]])
def test_a_flipped_bit_in_best_pt_is_caught_by_evaluate(where, finished, tmp_path, capsys):
    run = copy_run(finished, tmp_path)
    flip_bit_in_tensor(run / "best.pt", where)
    code, err = cli(["evaluate", str(run)], capsys)
    assert code != 0 and one_line_naming(err, "best.pt") and "checksum" in err, err


def test_a_flipped_bit_in_latest_pt_falls_back_on_resume(finished, tmp_path, capsys):
    run = copy_run(finished, tmp_path)
    flip_bit_in_tensor(run / "latest.pt", ["model", "head.weight"])
    code = train_main(["--resume", str(run), "--epochs", "4", "--no-progress"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "latest.pt" in out.out and "previous.pt" in out.out  # says what it did
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2, 3, 4]  # the damaged epoch 3 was trained again, no row twice


def test_a_resumed_run_takes_no_epoch_cap_under_what_it_has_trained(finished, tmp_path, capsys):
    # --epochs 2 after 3 epochs became the run's saved cap (config.json: 2 epochs, its summary 3)
    run = copy_run(finished, tmp_path)
    config = (run / "config.json").read_bytes()
    code, err = cli(["--resume", str(run), "--epochs", "2"], capsys)
    assert code == 2 and "--epochs 2: " in err and "has trained 3 epochs; expected 3 (end it now) or more" in err, err
    assert (run / "config.json").read_bytes() == config
    # a finished run resumed as it stands says why nothing is trained (it said only "max epochs")
    assert train_main(["--resume", str(run), "--no-progress"]) == 0
    assert "no epochs left to train (its cap is 3): its best checkpoint is evaluated again; --epochs N with N > 3" \
        in capsys.readouterr().out


def test_a_run_that_early_stopping_ended_trains_further_only_under_a_higher_cap(data, tmp_path, capsys):
    run = tmp_path / "run"
    first = foveation.run(resolve("smoke", {"out": str(run), "data_dir": str(data), "patience": 1, "epochs": 8}),
                          **QUIET)
    done = first["epochs"]
    assert first["stopped"].startswith("early stop") and done < 8, first  # (the drill needs a run that ended early)
    rows = (run / "metrics.jsonl").read_text()
    # resumed as it stands: nothing trained (it trained on to the cap of 8, without a word), its summary the same
    assert train_main(["--resume", str(run), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert f"early stopping ended it after epoch {done} (no better validation loss for 1 epochs)" in out, out
    assert f"--epochs N with N > {done} trains it further, its patience counted afresh" in out, out
    assert (run / "metrics.jsonl").read_text() == rows
    again = json.loads((run / "summary.json").read_text())
    assert again["stopped"] == first["stopped"] and again["epochs"] == done and again["test_mse"] == first["test_mse"]
    # under a higher cap: trained on, its patience counted afresh
    assert train_main(["--resume", str(run), "--epochs", str(done + 2), "--no-progress"]) == 0
    assert f"early stopping ended it; training on to epoch {done + 2}, its patience (1 epochs) counted afresh" \
        in capsys.readouterr().out
    epochs = [json.loads(x)["epoch"] for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert epochs[: done + 1] == list(range(1, done + 2))


@pytest.mark.parametrize("damage", ["half", "empty", "clip100"])
def test_a_damaged_latest_pt_gives_one_line_before_any_work(damage, finished, tmp_path, capsys, monkeypatch):
    def load(*a, **k):
        raise AssertionError("the dataset was loaded before the checkpoint was checked")

    monkeypatch.setattr(foveation.FoveationTask, "load", load)
    run = copy_run(finished, tmp_path)
    for name in ("latest.pt", "previous.pt", "best.pt"):  # nothing to fall back on
        p = run / name
        if not p.exists():
            continue
        raw = p.read_bytes()
        p.write_bytes({"half": raw[: len(raw) // 2], "empty": b"", "clip100": raw[:-100]}[damage])
    code, err = cli(["--resume", str(run), "--epochs", "4"], capsys)
    assert code != 0 and one_line_naming(err, "latest.pt"), err


@pytest.mark.parametrize("argv, named", [
    (["--lr", "0.1"], "--lr does not apply"),  # it carried on at the run's own rate without a word
    (["--preset", "quick", "--batch", "8"], "--batch, --preset do not apply"),
    (["--overwrite"], "--overwrite does not apply"),
    (["--out", "elsewhere"], "--out does not apply"),
])
def test_settings_given_with_resume_are_refused(argv, named, finished, tmp_path, capsys):
    run = copy_run(finished, tmp_path)
    before = {f.name: f.read_bytes() for f in run.iterdir() if f.is_file()}
    code, err = cli(["--resume", str(run), *argv, "--epochs", "4"], capsys)
    assert code == 2 and one_line_naming(err, f"--resume {run}") and named in err, err
    assert {f.name: f.read_bytes() for f in run.iterdir() if f.is_file()} == before
    assert not (tmp_path / "elsewhere").exists()


def test_load_net_verifies_the_checkpoint(finished, tmp_path):
    from warp_vision.nn.trained import load_net

    run = copy_run(finished, tmp_path)
    load_net(run)
    flip_bit_in_tensor(run / "best.pt", ["model", "head.weight"])
    with pytest.raises(ValueError, match="best.pt.*checksum"):
        load_net(run)


def test_a_file_that_is_no_checkpoint_is_named_as_such(finished, tmp_path):
    # torch's words for either advised "re-running torch.load with weights_only set to False"
    from warp_vision.nn.trained import read_checkpoint

    text, foreign, cut = tmp_path / "notes.pt", tmp_path / "foreign.pt", tmp_path / "cut.pt"
    text.write_text("not a checkpoint\n")
    torch.save({"model": argparse.Namespace(lr=0.1)}, foreign)  # an object a weights-only load refuses
    cut.write_bytes((finished / "best.pt").read_bytes()[:-100])
    for path in (text, cut):
        with pytest.raises(ValueError,
                           match=r"not a readable checkpoint: not a whole zip archive as torch.save writes"):
            read_checkpoint(path)
    with pytest.raises(ValueError, match=r"foreign.pt: not a checkpoint of this package: it holds objects that a "
                                         r"weights-only load refuses") as e:
        read_checkpoint(foreign)
    assert "weights_only" not in str(e.value)


def test_identical_runs_give_identical_checkpoints(data, tmp_path):
    digests = []
    for k in range(2):
        out = tmp_path / f"r{k}"
        foveation.run(resolve("smoke", {"out": str(out), "data_dir": str(data), "epochs": 2}), **QUIET)
        digests.append([hashlib.sha256((out / n).read_bytes()).hexdigest() for n in ("latest.pt", "best.pt")])
    assert digests[0] == digests[1]


# --------------------------------------------------------------------------------------------------
# 2. run directories that do not depend on the working directory


def test_resume_and_evaluate_from_another_directory(data, tmp_path, capsys):
    run = tmp_path / "run"
    cfg = resolve("smoke", {"out": str(run), "data_dir": ""})  # the default, cached dataset location
    old = os.getcwd()
    os.chdir(tmp_path)
    try:
        shutil.copytree(data, tmp_path / "runs" / "datasets" / f"foveation-{cfg.data_config().key()}")
        foveation.run(cfg, **QUIET, stop_after_epoch=1)
    finally:
        os.chdir(old)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    code, err = cli(["--resume", str(run), "--epochs", "2"], capsys, cwd=elsewhere)
    assert code == 0, err
    assert list(elsewhere.iterdir()) == []  # nothing rendered or written outside the run and its dataset
    code, err = cli(["evaluate", str(run)], capsys, cwd=elsewhere)
    assert code == 0, err


# --------------------------------------------------------------------------------------------------
# 4, 8. preflight before any expensive work


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_cuda_on_a_cpu_machine_fails_before_any_work(tmp_path, capsys):
    out = tmp_path / "run"
    code, err = cli(["--preset", "smoke", "--out", str(out), "--data-dir", str(tmp_path / "d"), "--device", "cuda"],
                    capsys)
    assert code != 0 and one_line_naming(err, "cuda"), err
    assert not out.exists() and not (tmp_path / "d").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_the_data_command_checks_the_device_first(tmp_path, capsys):
    from warp_vision.data.cli import main as data_main

    code = data_main(["foveation", "--samples", "8", "--photoreceptors", "100", "--out", str(tmp_path / "d"),
                      "--device", "cuda"])
    err = capsys.readouterr()
    assert code != 0 and "cuda" in (err.err + err.out) and not (tmp_path / "d").exists()


@pytest.mark.parametrize("flag,value", [("--lr", "inf"), ("--lr", "nan"), ("--val-fraction", "nan"),
                                        ("--max-field-deg", "inf")])
def test_non_finite_options_are_refused_by_name(flag, value, tmp_path, capsys):
    code, err = cli(["--preset", "smoke", "--out", str(tmp_path / "run"), "--data-dir", str(tmp_path / "d"), flag,
                     value], capsys)
    assert code == 2 and one_line_naming(err, flag + ":"), err
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("command, argv, says", [
    ("train", ["--preset", "smoke", "--out", "OUT", "--batch", "0"], "--batch: expected a positive integer, got 0"),
    ("train", ["--preset", "smoke", "--out", "OUT", "--lr", "-1e-3"], "--lr: expected > 0, got -0.001"),
    ("train", ["faces", "--preset", "smoke", "--out", "OUT", "--lr", "-1"], "--lr: expected > 0, got -1.0"),
    ("train", ["limb", "--out", "OUT", "--epochs", "0"], "--epochs: expected a positive integer, got 0"),
    ("train", ["evaluate", "RUN", "--conditions", "--samples", "3"],
     "--samples: expected at least 10 per condition, got 3"),
    ("data", ["foveation", "--out", "OUT", "--samples", "0"], "--samples: expected a positive integer, got 0"),
    ("data", ["faces", "--out", "OUT", "--shard", "3/2"],
     "--shard: the index I in I/N must satisfy 0 <= I < N, got 3/2"),
    ("data", ["foveation", "--out", "OUT", "--shard=a/2"],
     "--shard: expected 'I/N' with integers 0 <= I < N, got 'a/2'"),
    ("data", ["foveation", "--out", "OUT", "--shard", "-1/2"],
     "--shard: expected 'I/N' with integers 0 <= I < N, got '-1/2'"),
    ("scene", ["demo", "--device", "gpu", "--out", "OUT"], "--device: expected cpu, cuda or cuda:N, got 'gpu'"),
    ("sim", ["intercept", "--perception-error-cm", "-1e1", "--out", "OUT"],
     "--perception-error-cm: expected distances of 0-500 cm with --shots, got [-10.0]"),
])
def test_a_refused_setting_is_named_as_the_option_typed(command, argv, says, finished, tmp_path, capsys):
    # the configs' checks name their fields ("batch: expected ..."): the command line names the option
    import importlib

    main = importlib.import_module(f"warp_vision.{command}.cli").main
    argv = [{"OUT": str(tmp_path / "out"), "RUN": str(finished)}.get(a, a) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == f"error: {says}\n", err


def test_a_directory_of_runs_is_refused_naming_the_runs_in_it(finished, tmp_path, capsys):
    # `sim` writes an eye's nets as runs/quick/pupil/left and .../right: `evaluate runs/quick/pupil` said
    # "no best.pt: is this a training run directory?", which did not say where the runs were
    for eye in ("right", "left"):
        shutil.copytree(finished, tmp_path / "pupil" / eye)
    (tmp_path / "pupil" / "figures").mkdir()  # a directory that is not a run is not named
    for argv, name in [(["evaluate", str(tmp_path / "pupil")], "best.pt"),
                       (["compare", str(tmp_path / "pupil"), "--out", str(tmp_path / "c.png")], "metrics.jsonl")]:
        code, err = cli(argv, capsys)
        assert code == 2 and err == (f"error: {tmp_path / 'pupil'}: holds the runs left, right, not a run's {name}: "
                                     f"name one, e.g. {tmp_path / 'pupil' / 'left'}\n"), err
    code, err = cli(["evaluate", str(tmp_path / "pupil" / "figures")], capsys)  # no run below: as before
    assert code == 2 and err == (f"error: {tmp_path / 'pupil' / 'figures' / 'best.pt'}: no best.pt: is this a training "
                                 "run directory?\n"), err


def test_a_resumed_runs_bad_setting_is_named_in_its_config_json(finished, tmp_path, capsys):
    # "--resume RUN" named "lr" as if typed (and after the change, as "--lr"); the value is the file's
    run = copy_run(finished, tmp_path)
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "lr": -1.0}))
    code, err = cli(["--resume", str(run)], capsys)
    assert code == 2 and err == f"error: {run / 'config.json'}: lr: expected > 0, got -1.0\n", err
    code, err = cli(["--resume", str(finished), "--epochs", "0"], capsys)  # what was typed: the option
    assert code == 2 and err == "error: --epochs: expected a positive integer, got 0\n", err


def test_a_value_that_begins_with_a_minus_and_a_digit_goes_to_its_option():
    # argparse took "-1e-3" for an option ("argument --lr: expected one argument"); joined, it is --lr's value
    from warp_vision.errors import ArgumentParser

    p = ArgumentParser(prog="p")
    p.add_argument("--lr", type=float)
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--sizes", type=float, nargs="+")
    p.add_argument("rest", nargs="*")
    assert p.parse_args(["--lr", "-1e-3"]).lr == -1e-3
    assert p.parse_args(["--lr", "-.5e1"]).lr == -5.0
    # a list option takes a number in exponent form as argparse takes '-1' ('--perception-error-cm -1e1' said
    # "unrecognized arguments: -1e1"), and an option of no value leaves it to the positionals, as it does '-1'
    assert p.parse_args(["--sizes", "-1e-3", "2", "-.5E+1"]).sizes == [-1e-3, 2.0, -5.0]
    assert p.parse_args(["--quiet", "-1e-3"]).rest == ["-1e-3"]
    with pytest.raises(SystemExit):  # what is no number stays an option, unknown here
        p.parse_args(["--sizes", "-1x"])
    assert p.parse_args(["--", "--lr", "-1e-3"]).rest == ["--lr", "-1e-3"]  # after "--": positional, as typed


@pytest.mark.parametrize("command, argv", [
    # `data faces --samples 10` was taken as --samples-per-receptor 10 and rendered all 45,000 face ONVs.
    # Each abbreviation here, were it matched, would make a value the command refuses at once (code 2
    # returned, not argparse's SystemExit), so the test fails fast without the change
    ("data", ["foveation", "--out", "OUT", "--samp", "0"]),
    ("train", ["--preset", "smoke", "--out", "OUT", "--samp", "0"]),
    ("train", ["evaluate", "OUT", "--cond"]),
    ("sim", ["demo", "--see", "-1"]),
    ("bench", ["linet", "--photo", "0"]),
    ("scene", ["demo", "--photo", "0", "--out", "OUT"]),
])
def test_an_abbreviated_option_is_refused_not_matched_to_a_longer_one(command, argv, tmp_path, capsys):
    import importlib

    main = importlib.import_module(f"warp_vision.{command}.cli").main
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in argv]
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2 and "unrecognized arguments" in capsys.readouterr().err


@pytest.mark.parametrize("argv, says", [
    (["evalute", "runs/foveation"], "'evalute' is not a task or command (did you mean 'evaluate'?): expected one of "
                                    "faces, oculomotor, arm, limb, pupil, lens, verify, evaluate, compare"),
    (["occulomotor", "--eye", "left"], "(did you mean 'oculomotor'?)"),
    (["runs/foveation"], "'runs/foveation' is not a task or command: expected"),
])
def test_a_mistyped_task_is_named_with_the_nearest(argv, says, tmp_path, capsys):
    # it was "unrecognized arguments: evalute runs/foveation" from the foveation task's parser
    from warp_vision.train.cli import main

    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2 and says in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # nothing rendered, trained or written


@pytest.mark.parametrize("command, argv, says", [
    # each was argparse's: "the following arguments are required: cmd" (the parser's field), "argument command:
    # invalid choice: 'experiment' (choose from ...)", "unrecognized arguments: --photoreceptor 100"
    ("scene", [], "expected a command: one of demo (python -m warp_vision.scene COMMAND --help says more)"),
    ("sim", [], "expected a command: one of demo, experiments, intraocular, oculomotor, intercept, search"),
    ("sim", ["experiment"], "'experiment' is not a command (did you mean 'experiments'?): expected one of demo, "),
    ("bench", ["lnet"], "'lnet' is not a command (did you mean 'linet'?)"),
    ("data", ["fovea"], "'fovea' is not a command (did you mean 'foveation'?): expected one of foveation, faces"),
    ("scene", ["demo", "--photoreceptor", "100"], "unrecognized arguments: --photoreceptor 100 (did you mean "
                                                   "--photoreceptors?)"),
    ("sim", ["demo", "--shots", "5"], "unrecognized arguments: --shots 5 (--shots is an option of intercept)"),
    ("data", ["faces", "--samples", "10"], "(--samples is an option of foveation)"),
    # train's tasks, evaluate and compare are separate parsers, not subcommands: a flag of another was unnamed
    ("train", ["faces", "--preset", "smoke", "--samples", "5"], "unrecognized arguments: --samples 5 (--samples is "
                                                                "an option of the foveation task, limb, pupil, lens, "
                                                                "verify and evaluate)"),
    ("train", ["--preset", "smoke", "--conditions"],
     "unrecognized arguments: --conditions (--conditions is an option of evaluate)"),
    ("train", ["compare", "r", "--out", "c.png", "--split", "val"], "(--split is an option of evaluate)"),
    ("train", ["evaluate", "r", "--lr", "0.1"], "(--lr is an option of the foveation task, faces, oculomotor, arm, "
                                                "limb, pupil, lens and verify)"),
    # a flag near another task's (not its own) was unnamed
    ("train", ["oculomotor", "--photoreceptor", "5"], "unrecognized arguments: --photoreceptor 5 (did you mean "
                                                      "--photoreceptors, an option of the foveation task, faces, limb, "
                                                      "pupil, lens and verify?)"),
    ("sim", ["demo", "--shot", "5"], "(did you mean --shots, an option of intercept?)"),
    # a command's option given before the command: "unrecognized arguments: --quick (--quick is an option of
    # experiments, ...)", as if demo lacked it; "'quick' is not a command", its value taken for the command
    ("sim", ["--quick", "demo", "--gif"],
     "error: --quick goes after the command: python -m warp_vision.sim demo --gif --quick\n"),
    ("data", ["--preset", "quick", "foveation"], "error: --preset goes after the command: python -m warp_vision.data "
                                                 "foveation --preset quick\n"),
    ("sim", ["--shots", "3", "demo"], "error: --shots is an option of intercept, given after the command: "
                                      "python -m warp_vision.sim COMMAND --shots 3\n"),
    ("bench", ["--repeats", "3"],
     "error: --repeats is an option of linet, raytrace, readout and cnn, given after the command"),
    ("train", ["--preset", "smoke", "faces"],
     "unrecognized arguments: faces (faces is a command: name it first, before the options)"),
    ("bench", ["linet", "--batchs=3"], "unrecognized arguments: --batchs=3 (did you mean --batch?)"),
    ("train", ["limb", "--epoch", "3"], "unrecognized arguments: --epoch 3 (did you mean --epochs?)"),
    ("scene", ["demo", "--bogus"], "error: unrecognized arguments: --bogus (python -m warp_vision.scene demo --help "
                                   "says more)\n"),  # nothing near: no guess
])
def test_a_missing_or_mistyped_command_or_flag_is_named_with_the_nearest(command, argv, says, capsys):
    import importlib

    with pytest.raises(SystemExit) as e:
        importlib.import_module(f"warp_vision.{command}.cli").main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and says in err, err


def test_the_eye_demo_names_the_one_bad_count(tmp_path, capsys):
    from warp_vision.scene.cli import main

    # was "--photoreceptors and --samples: expected positive integers", whichever of the two it was
    assert main(["demo", "--samples", "0", "--out", str(tmp_path / "demo")]) == 2
    assert "error: --samples: expected a positive integer, got 0" in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()
    # was "pupil_diameter_mm: expected 1 to 9 mm", the eye's parameter, and the --out directory made, empty
    assert main(["demo", "--pupil", "0.5", "--out", str(tmp_path / "demo")]) == 2
    assert "error: --pupil: expected 1 to 9 mm, got 0.5" in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()


def test_a_generator_is_given_as_the_docs_name_it_and_a_bad_count_by_its_name(capsys):
    from warp_vision.data.cli import config_of, parser
    from warp_vision.data.foveation import FoveationDataConfig
    from warp_vision.sim.limb import LimbDataConfig
    from warp_vision.train.cli import parse_training

    for text in ("v8", "V8", "8"):  # "v8" was "argument --generator: invalid int value: 'v8'"
        assert parse_training(["--generator", text])[3]().generator == 8
        assert config_of("foveation", parser().parse_args(["foveation", "--generator", text])).generator == 8
    with pytest.raises(SystemExit):
        parse_training(["--generator", "eight"])
    assert "expected a generator version, one of 7, 8, 9 (or v7 ...), got 'eight'" in capsys.readouterr().err
    # each named all four counts whichever it was: "samples, photoreceptors, samples_per_receptor and chunk_size
    # must be positive"
    for cls in (FoveationDataConfig, LimbDataConfig):
        with pytest.raises(ValueError, match=r"^chunk_size: expected a positive integer, got 0$"):
            cls(chunk_size=0).validate()


def test_a_failed_allocation_is_one_line_and_other_runtime_errors_still_raise(capsys):
    from warp_vision.errors import guarded

    def oom():
        torch.empty(1 << 62, dtype=torch.uint8)  # 4 EiB: the CPU allocator refuses it at once

    assert guarded(oom) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: out of memory") and err.count("\n") == 1, err

    def memory_error():
        raise MemoryError()

    assert guarded(memory_error) == 2 and "out of memory" in capsys.readouterr().err

    def bug():
        raise RuntimeError("a shape mismatch")

    with pytest.raises(RuntimeError, match="shape mismatch"):
        guarded(bug)
    with pytest.raises(RuntimeError):
        guarded(oom, debug=True)


@pytest.mark.parametrize("command", [
    ["train", "--preset", "smoke", "--data-seed", "-1"], ["train", "--preset", "smoke", "--seed", "-1"],
    ["train", "faces", "--preset", "smoke", "--identity-seed", "-1"],
    ["train", "pupil", "--preset", "smoke", "--seed", "-1"],
    ["train", "limb", "--preset", "smoke", "--data-seed", "-1"], ["data", "foveation", "--seed", "-1"],
    ["data", "faces", "--identity-seed", "-1"], ["train", "--preset", "smoke", "--seed", "2147483648"],
    ["data", "foveation", "--seed", "1180591620717411303424"],
])
def test_a_seed_out_of_range_is_refused_by_name_before_anything_is_written(command, tmp_path, capsys):
    import importlib

    main = importlib.import_module(f"warp_vision.{command[0]}.cli").main
    flag = command[-2]  # (named as the option typed)
    assert main([*command[1:], "--out", str(tmp_path / "out")] + (["--data-dir", str(tmp_path / "d")]
                                                                    if command[0] == "train" else [])) == 2
    assert f"{flag}: expected a seed 0..2,147,483,647, got {command[-1]}" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------------------------------
# 7, 9. writers that fail cleanly


def test_out_naming_a_file_is_one_line(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    code, err = cli(["--preset", "smoke", "--out", str(f), "--data-dir", str(tmp_path / "d")], capsys)
    assert code != 0 and one_line_naming(err, str(f)), err
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("command, flags, says", [
    ([], ["--samples", "200"], "first difference: config['samples']"),
    # a foveation dataset given to a pupil run: it used to name the first differing setting and advise
    # deleting the directory "to rebuild the dataset", the foveation run's dataset
    (["pupil", "--eye", "left"], [], "holds another kind of dataset: its samples hold onv, target, meta;"),
])
def test_a_data_dir_of_other_settings_is_refused_before_the_run_is_claimed(
        command, flags, says, tmp_path, capsys, data):
    # it used to be found by the store after the preflight had printed "(already there)" and the run
    # directory had been claimed with its config.json
    manifest = (data / "manifest.json").read_bytes()
    code, err = cli([*command, "--preset", "smoke", *flags, "--out", str(tmp_path / "run"), "--data-dir", str(data)],
                    capsys)
    assert code == 2 and one_line_naming(err, str(data / "manifest.json")) and says in err, err
    assert ("delete" in err) == (not command), err
    assert not (tmp_path / "run").exists()
    assert (data / "manifest.json").read_bytes() == manifest


@pytest.mark.parametrize("command, argv", [
    # each wrote its output only at the end: a bench after its minutes of timing, the simulation after
    # training the nets it lacks, the eye demo after rendering; a plot after reading every run
    ("bench", ["linet", "--photoreceptors", "200", "--repeats", "1", "--out", "FILE/linet.json"]),
    ("bench", ["raytrace", "--photoreceptors", "50", "--samples", "1", "--repeats", "1", "--out", "DIR"]),
    ("sim", ["experiments", "--out", "FILE/sim"]),
    ("sim", ["intraocular", "--out", "FILE"]),
    ("scene", ["demo", "--photoreceptors", "100", "--samples", "1", "--out", "FILE/demo"]),
    ("data", ["foveation", "--samples", "8", "--out", "FILE"]),
    ("train", ["compare", "RUN", "--out", "DIR"]),
])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(command, argv, tmp_path, monkeypatch, capsys,
                                                                      finished):
    import importlib

    import warp_vision.sim.provision as provision

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(provision, "provide", lambda *_a, **_k: pytest.fail("nets were trained first"))
    (tmp_path / "FILE").write_text("x")
    (tmp_path / "DIR").mkdir()
    argv = [str(finished) if a == "RUN" else a for a in argv]
    main = importlib.import_module(f"warp_vision.{command}.cli").main
    assert main(argv) == 2
    out = capsys.readouterr()
    err = out.err.strip()
    assert err.count("\n") == 0 and "--out" in err, err
    assert ("is a file, not a directory" in err or "names a file, not a directory" in err
            or "names a directory, not a file" in err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["DIR", "FILE"] and not list((tmp_path / "DIR").iterdir())
    assert "ONV:" not in out.out and "linet layer" not in out.out  # nothing was rendered or timed


def test_an_output_under_a_directory_we_cannot_write_is_refused_by_name(tmp_path, monkeypatch):
    from warp_vision.fileio import require_output

    monkeypatch.setattr(os, "access", lambda *_a, **_k: False)  # (root writes through a 0o555 mode)
    with pytest.raises(PermissionError, match=f"--out: {tmp_path}: Permission denied"):
        require_output(tmp_path / "a" / "b", "--out")
    require_output(tmp_path, "--data-dir", writable=False)  # a complete dataset may be read in place
    monkeypatch.undo()
    require_output(tmp_path / "new" / "deeper", "--out")  # can be made: left to the writer
    assert not (tmp_path / "new").exists()
    with pytest.raises(ValueError, match="kind"):
        require_output(tmp_path, kind="folder")


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_an_output_where_nothing_can_be_made_is_refused_whatever_the_mode_says(tmp_path):
    """/proc lets root pass os.access's write check, yet no directory can be made there: it was let through,
    and a sim demo trained its nets for minutes before it failed to write. The probe leaves nothing behind."""
    from warp_vision.fileio import require_output

    with pytest.raises(OSError, match="--out: /proc"):
        require_output("/proc/warp_vision_out/run", "--out")
    require_output(tmp_path / "new", "--out")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_a_dataset_directory_where_nothing_can_be_made_is_refused_before_the_run_is_claimed(data, tmp_path, capsys):
    # it was "No space left for the dataset: about 378 KiB needed, 0 KiB free", after --out was claimed
    code, err = cli(["--preset", "smoke", "--data-dir", "/proc/warp_vision_data", "--out", str(tmp_path / "run")],
                    capsys)
    assert code == 2 and "--data-dir: /proc: nothing can be made there" in err, err
    assert not (tmp_path / "run").exists()
    # the data command's was "/proc/warp_vision_data: No such file or directory", from its first mkdir
    from warp_vision.data.cli import main as data_main

    assert data_main(["foveation", "--preset", "smoke", "--out", "/proc/warp_vision_data"]) == 2
    assert "--out: /proc: nothing can be made there" in capsys.readouterr().err


def _enospc_after(monkeypatch, name: str):
    """Make writes of files called ``name`` (their temporaries) fail with ENOSPC."""
    import warp_vision.fileio as fio

    real = fio.temporary_path

    def full(final):
        p = real(final)
        if Path(final).name == name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(p))
        return p

    monkeypatch.setattr(fio, "temporary_path", full)


def test_the_data_command_refuses_a_dataset_the_disk_cannot_hold_before_rendering(tmp_path, capsys, monkeypatch):
    # it rendered until the first chunk's write failed ("chunk_000000.onv.npy: No space left on device";
    # measured on a 600 KiB tmpfs with --samples 1000), where a training run's preflight refuses at once
    import warp_vision.data.foveation as F
    import warp_vision.resources as R
    from warp_vision.data.cli import main as data_main

    monkeypatch.setattr(R, "free_disk_bytes", lambda path: 500_000)
    monkeypatch.setattr(F, "render_samples", lambda *a, **k: pytest.fail("rendered"))
    out = tmp_path / "d"
    assert data_main(["foveation", "--preset", "smoke", "--samples", "1000", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert one_line_naming(err, str(out)) and "No space left for the dataset's missing chunks: about 2 MiB needed, " \
                                               "488 KiB free" in err, err
    assert not list(out.glob("chunk_*"))


def test_a_training_run_refuses_a_dataset_the_disk_cannot_hold_before_rendering(tmp_path, capsys, monkeypatch):
    import warp_vision.data.foveation as F
    import warp_vision.resources as R

    monkeypatch.setattr(R, "free_disk_bytes", lambda path: 500_000)
    monkeypatch.setattr(F, "render_samples", lambda *a, **k: pytest.fail("rendered"))
    data = tmp_path / "d"
    code, err = cli(["--preset", "smoke", "--samples", "1000", "--out", str(tmp_path / "run"), "--data-dir", str(data)],
                    capsys)
    assert (
        code == 2 and "error: " + str(data) + ": No space left for the dataset: about 2 MiB needed, 488 KiB free" in err
    ), err
    assert not data.exists()


@pytest.mark.parametrize("flag", ["--conditions", "--misses"])
def test_evaluating_a_read_only_run_is_refused_before_any_work(flag, finished, tmp_path, capsys, monkeypatch):
    # --conditions rendered the held-out sets and evaluated every one, then failed to write conditions.json
    # (its table unprinted); --misses printed its table and failed on the figure (measured on a read-only mount)
    import warp_vision.data.foveation as F
    import warp_vision.fileio as fio

    run = copy_run(finished, tmp_path)
    real = fio.probe_writable

    def read_only(d):
        if Path(d).resolve().is_relative_to(run.resolve()):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(d))
        return real(d)

    monkeypatch.setattr(fio, "probe_writable", read_only)
    monkeypatch.setattr(F, "render_samples", lambda *a, **k: pytest.fail("rendered"))
    before = sorted(p.name for p in run.rglob("*"))
    code, err = cli(["evaluate", str(run), flag, *(["--samples", "10"] if flag == "--conditions" else [])], capsys)
    assert code == 2 and one_line_naming(err, f"{run}: evaluate {flag} writes its results into the run directory, "
                                              f"and nothing can be written there (Read-only file system)"), err
    assert sorted(p.name for p in run.rglob("*")) == before


def test_a_full_disk_while_checkpointing_leaves_a_consistent_run(data, tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    foveation.run(resolve("smoke", {"out": str(run), "data_dir": str(data)}), **QUIET, stop_after_epoch=1)
    _enospc_after(monkeypatch, "latest.pt")
    code, err = cli(["--resume", str(run)], capsys)
    assert code != 0 and one_line_naming(err, "latest.pt") and "No space left" in err, err
    assert not [p for p in run.iterdir() if ".tmp" in p.name]
    monkeypatch.undo()
    assert train_main(["--resume", str(run), "--no-progress"]) == 0
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2, 3]


def test_a_row_lost_between_checkpoint_and_metrics_is_restored(data, tmp_path):
    """Killed after latest.pt was written but before its metrics row was appended: the resumed run
    restores the row from the checkpoint's history; none is repeated or skipped."""
    run = tmp_path / "run"
    foveation.run(resolve("smoke", {"out": str(run), "data_dir": str(data)}), **QUIET, stop_after_epoch=2)
    m = run / "metrics.jsonl"
    m.write_text("".join(x + "\n" for x in m.read_text().splitlines()[:1]))
    assert train_main(["--resume", str(run), "--no-progress"]) == 0
    rows = [json.loads(x) for x in m.read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2, 3]


def _mount_tmpfs(path: Path, size: str) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    return r.returncode == 0


def _can_mount() -> bool:
    import tempfile

    d = Path(tempfile.mkdtemp())
    ok = _mount_tmpfs(d, "64k")
    if ok:
        subprocess.run(["umount", str(d)])
    return ok


REAL_FS = _can_mount()


@pytest.mark.skipif(not REAL_FS,
                    reason="this machine does not let the tests mount a tmpfs; the injected ENOSPC drill covers it")
def test_a_really_full_disk_while_synthesising(tmp_path, capsys):
    d = tmp_path / "small"
    assert _mount_tmpfs(d, "128k")
    try:
        code, err = cli(["--preset", "smoke", "--out", str(tmp_path / "run"), "--data-dir", str(d / "data")], capsys)
        assert code != 0 and "error:" in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1 and ("space" in err), err
        assert not [p for p in (d / "data").rglob("*") if ".tmp" in p.name]
    finally:
        subprocess.run(["umount", str(d)])


@pytest.mark.skipif(not REAL_FS,
                    reason="this machine does not let the tests mount a tmpfs; the injected EROFS drill covers it")
def test_a_read_only_output(data, tmp_path, capsys):
    d = tmp_path / "ro"
    assert _mount_tmpfs(d, "4m")
    try:
        subprocess.run(["mount", "-o", "remount,ro", str(d)], check=True)
        code, err = cli(["--preset", "smoke", "--out", str(d / "run"), "--data-dir", str(data)], capsys)
        assert code != 0 and one_line_naming(err, str(d / "run")) and "Read-only" in err, err
    finally:
        subprocess.run(["umount", str(d)])


@pytest.mark.skipif(not REAL_FS, reason="this machine does not let the tests mount a tmpfs")
def test_a_whole_dataset_on_a_read_only_disk_trains(data, tmp_path, capsys):
    """Only a dataset still to be rendered needs a directory it can be written to: a whole one is read where it lies."""
    d = tmp_path / "ro"
    assert _mount_tmpfs(d, "4m")
    try:
        shutil.copytree(data, d / "data")
        subprocess.run(["mount", "-o", "remount,ro", str(d)], check=True)
        code, err = cli(["--preset", "smoke", "--data-dir", str(d / "data"), "--epochs", "1", "--out",
                         str(tmp_path / "run")],
                        capsys)
        assert code == 0, err
        code, err = cli(["--preset", "smoke", "--samples", "200", "--data-dir", str(d / "other"), "--out",
                         str(tmp_path / "run2")], capsys)
        assert code == 2 and "--data-dir" in err and "Read-only" in err and not (tmp_path / "run2").exists(), err
    finally:
        subprocess.run(["umount", str(d)])


def test_a_read_only_partial_dataset_fails_before_rendering(data, tmp_path, capsys, monkeypatch):
    """A dataset with a missing chunk in a directory that refuses writes: the error comes before the
    chunk is rendered (EROFS injected at the write probe)."""
    import warp_vision.fileio as fio

    d = tmp_path / "data"
    shutil.copytree(data, d)
    victim = sorted(d.glob("chunk_*.json"))[-1]
    victim.unlink()
    rendered = []
    import warp_vision.data.foveation as F

    real_render = F.render_samples
    monkeypatch.setattr(F, "render_samples", lambda *a, **k: rendered.append(1) or real_render(*a, **k))
    real = fio.temporary_path

    def ro(final):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(real(final)))

    monkeypatch.setattr(fio, "temporary_path", ro)
    code, err = cli(["--preset", "smoke", "--out", str(tmp_path / "run"), "--data-dir", str(d)], capsys)
    assert code != 0 and "Read-only" in err and len(err.strip().splitlines()) == 1, err
    assert rendered == []


# --------------------------------------------------------------------------------------------------
# drills: SIGKILL and flipped bytes in data


def _kill_and_resume(argv: list[str], out_files: list[Path], tmp_path: Path, seed: int) -> None:
    """Run ``argv`` in a subprocess, SIGKILL it at a random moment, run it again to the end."""
    rng = np.random.default_rng(seed)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen([sys.executable, "-m", "warp_vision.train", *argv, "--no-progress"], cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    marker = "synthesising" if out_files[0].name == "synth" else "parameters"  # the phase to kill in
    t0 = time.time()
    for line in p.stdout:  # wait until the phase begins, then a random moment within it
        if marker in line or time.time() - t0 > 120:
            break
    time.sleep(float(rng.uniform(0.0, 1.5 if marker == "synthesising" else 0.4)))
    p.send_signal(signal.SIGKILL)
    p.wait()


def test_sigterm_during_training_says_where_the_run_stands_and_resume_finishes_it(data, finished, tmp_path):
    """SIGTERM (kill, a scheduler's preemption) ended the run without a word (exit -15); now it stops as
    Ctrl-C does: its line, exit 143, and --resume carries on to the same bytes."""
    run = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-m", "warp_vision.train", "--preset", "smoke", "--out", str(run),
                          "--data-dir", str(data), "--epochs", "3", "--no-progress"],
                         env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True)
    lines = []
    for line in p.stdout:  # stop it at the first epoch's end (its checkpoint is written by then)
        lines.append(line)
        if line.startswith("epoch   1"):
            p.send_signal(signal.SIGTERM)
            break
    lines += p.stdout.readlines()
    code = p.wait()
    assert code == 143, lines
    assert any(x.startswith(f"interrupted: {run / 'latest.pt'}") for x in lines), lines
    assert not any("stopped (SIGTERM)" in x for x in lines), lines  # its own line says it all
    assert train_main(["--resume", str(run), "--no-progress"]) == 0
    for name in ("latest.pt", "best.pt"):
        assert (run / name).read_bytes() == (finished / name).read_bytes(), name


def test_sigkill_during_synthesis_then_resume_is_bit_identical(data, tmp_path):
    d = tmp_path / "synth"
    cfg = resolve("smoke", {"data_dir": str(d)})
    argv = ["--preset", "smoke", "--out", str(tmp_path / "run"), "--data-dir", str(d)]
    _kill_and_resume(argv, [d], tmp_path, seed=1)
    synthesize(d, cfg.data_config(), progress=False, log=lambda *a: None)
    for f in sorted(data.glob("chunk_*.npy")):
        assert (d / f.name).read_bytes() == f.read_bytes(), f.name
    assert not [p for p in d.iterdir() if ".tmp" in p.name]


def test_sigkill_during_training_then_resume_is_bit_identical(data, finished, tmp_path):
    run = tmp_path / "run"
    argv = ["--preset", "smoke", "--out", str(run), "--data-dir", str(data), "--epochs", "3"]
    _kill_and_resume(argv, [run], tmp_path, seed=2)
    # killed before the first epoch ended, --resume starts it again
    assert train_main(["--resume", str(run), "--no-progress"]) == 0
    for name in ("latest.pt", "best.pt"):
        assert (run / name).read_bytes() == (finished / name).read_bytes(), name
    rows = [json.loads(x)["epoch"] for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert rows == [1, 2, 3]


def test_an_interrupted_and_resumed_run_writes_the_same_bytes(data, finished, tmp_path):
    run = tmp_path / "run"
    foveation.run(resolve("smoke", {"out": str(run), "data_dir": str(data)}), **QUIET, stop_after_epoch=1)
    foveation.run(resume=str(run), **QUIET)
    for name in ("latest.pt", "previous.pt", "best.pt"):
        assert (run / name).read_bytes() == (finished / name).read_bytes(), name


def test_a_file_lock_is_one_process_at_a_time_and_absent_flock_counts_as_taken(tmp_path, monkeypatch):
    import builtins

    from warp_vision.fileio import FileLock

    a, b = FileLock(tmp_path / "x.lock"), FileLock(tmp_path / "x.lock")  # two opens: as two processes
    assert a.acquire() and a.acquire()  # (again: still held)
    assert not b.acquire() and b.holder == str(os.getpid()) and b.fd is None
    a.release()
    assert b.acquire(block=True)
    b.release()
    real = builtins.__import__
    monkeypatch.setattr(builtins, "__import__", lambda name, *r, **k: (_ for _ in ()).throw(ImportError(name))
                        if name == "fcntl" else real(name, *r, **k))
    assert FileLock(tmp_path / "y.lock").acquire()  # a platform without flock runs unlocked


def test_a_run_directory_another_process_trains_is_refused_and_freed_when_it_ends(data, finished, tmp_path, capsys):
    """Two processes training one run directory interleaved its checkpoints and metrics rows, and
    --overwrite deleted them under the other: now the second is refused, naming the first."""
    run = copy_run(finished, tmp_path)
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from pathlib import Path; "
                               "from warp_vision.train.rundir import hold_run_dir; hold_run_dir(Path(sys.argv[1])); "
                               "print('held', flush=True); time.sleep(300)", str(run)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = {f.name: f.read_bytes() for f in run.iterdir() if f.is_file()}
        for argv in (["--resume", str(run), "--epochs", "4"],
                     ["--preset", "smoke", "--out", str(run), "--data-dir", str(data), "--overwrite"]):
            code, err = cli(argv, capsys)
            assert code == 2 and one_line_naming(err, str(run)) and f"process {holder.pid}" in err, err
            assert {f.name: f.read_bytes() for f in run.iterdir() if f.is_file()} == before
    finally:
        holder.kill()  # (SIGKILL: the kernel lets go of the lock)
        holder.wait()
    assert cli(["--resume", str(run), "--epochs", "4"], capsys)[0] == 0
    # this process let go of it at the end: another can take it
    out = subprocess.run([sys.executable, "-c", "import sys; from pathlib import Path; "
                          "from warp_vision.train.rundir import hold_run_dir; hold_run_dir(Path(sys.argv[1]))",
                          str(run)],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    # and a refused new run (the directory holds one) lets go of it too
    assert cli(["--preset", "smoke", "--out", str(run), "--data-dir", str(data)], capsys)[0] == 2
    from warp_vision.train import rundir

    assert not rundir._held


def test_a_run_waits_for_another_process_rendering_its_dataset_and_renders_nothing(data, tmp_path):
    """Two runs of one missing dataset started at once (a sweep) both rendered it, and one could fail
    reading a chunk the other was rewriting ("record missing"): now the second waits, then uses it."""
    d = tmp_path / "data"
    cfg = resolve("smoke", {"out": str(tmp_path / "run"), "data_dir": str(d)})
    other = subprocess.Popen([sys.executable, "-c", "import sys, time; from pathlib import Path\n"
                              "from warp_vision.data.foveation import synthesize; from warp_vision.fileio import "
                              "FileLock\nfrom warp_vision.train.config import resolve\n"
                              "d = Path(sys.argv[1]); d.mkdir(); FileLock(d / '.render.lock').acquire(); print('held', "
                              "flush=True)\ntime.sleep(2); synthesize(d, resolve('smoke', {}).data_config(), "
                              "progress=False, log=print)",
                              str(d)], stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "held"
        said = []
        foveation.run(cfg, progress=False, log=said.append)
    finally:
        other.wait()
    assert other.returncode == 0
    assert any(f"waiting for process {other.pid}" in x for x in said), said
    assert not any(x.startswith("synthesised") for x in said), said
    for f in sorted(data.glob("chunk_*.npy")):
        assert (d / f.name).read_bytes() == f.read_bytes(), f.name


_HOLD_A_CONDITION_SET = """import sys, time, dataclasses
from pathlib import Path
from warp_vision.data.foveation import synthesize
from warp_vision.fileio import FileLock
from warp_vision.nn.trained import read_checkpoint
from warp_vision.train.conditions import condition_config
from warp_vision.train.foveation import FoveationTask
from warp_vision.train.rundir import dataset_dir, run_config
run = Path(sys.argv[1])
cfg = run_config(FoveationTask, run, read_checkpoint(run / "best.pt"))
dcfg = condition_config(cfg.data_config(), "glow_dim", 10)
d = dataset_dir(dataclasses.replace(cfg, data_dir=""), "foveation", dcfg)  # (as evaluate --conditions names it)
d.mkdir(parents=True)
FileLock(d / ".render.lock").acquire()
print("held", flush=True)
time.sleep(2)
synthesize(d, dcfg, progress=False, log=print)
"""


def test_evaluate_conditions_waits_for_another_process_rendering_a_held_out_set(finished, tmp_path, monkeypatch):
    """Two evaluations of runs of one dataset (two seeds, say) started at once each rendered the held-out
    condition sets: now the second waits for the first's, then reads it."""
    from warp_vision.train.conditions import evaluate_conditions

    run = copy_run(finished, tmp_path)
    monkeypatch.chdir(tmp_path)  # the held-out sets are cached under ./runs/datasets
    other = subprocess.Popen([sys.executable, "-c", _HOLD_A_CONDITION_SET, str(run)], stdout=subprocess.PIPE,
                             text=True, cwd=tmp_path)
    try:
        assert other.stdout.readline().strip() == "held"
        said = []
        res = evaluate_conditions([str(run)], 10, conditions=["glow_dim"], progress=False, log=said.append)
    finally:
        other.wait()
    assert other.returncode == 0
    assert any(f"waiting for process {other.pid}, which is rendering the dataset" in x for x in said), said
    assert not any(x.startswith(("synthesising", "synthesised")) for x in said), said
    assert res[str(run)]["glow_dim"]["n"] == 10


def test_ctrl_c_before_the_first_epoch_says_so_and_resume_starts_the_run_again(data, finished, tmp_path, monkeypatch):
    """It said nothing, and --resume then refused the run: "no checkpoint to resume from"."""
    from warp_vision.train import harness

    def ctrl_c(*_a, **_k):
        raise KeyboardInterrupt

    run, lines = tmp_path / "run", []
    monkeypatch.setattr(harness, "render_in_processes", ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        foveation.run(resolve("smoke", {"out": str(run), "data_dir": str(data)}), progress=False, log=lines.append)
    assert lines[-1] == (f"interrupted before any epoch finished (the dataset's chunks written so far are kept); "
                         f"--resume {run} starts it again"), lines
    monkeypatch.undo()
    lines.clear()
    foveation.run(resume=str(run), progress=False, log=lines.append)
    assert lines[0] == f"no epoch of {run} finished: training it from the start, as its config.json says"
    for name in ("latest.pt", "best.pt"):
        assert (run / name).read_bytes() == (finished / name).read_bytes(), name
    (run / "latest.pt").unlink()  # a run with files but no checkpoint that reads is still refused
    (run / "previous.pt").unlink()
    (run / "best.pt").write_bytes(b"damaged")
    with pytest.raises(ValueError, match="no checkpoint to resume from"):
        foveation.run(resume=str(run), **QUIET)


def test_ctrl_c_during_data_synthesis_says_the_same_command_carries_on(tmp_path, monkeypatch, capsys):
    import warp_vision.data.cli as data_cli

    def ctrl_c(*_a, **_k):
        raise KeyboardInterrupt

    monkeypatch.setattr(data_cli, "synthesize", ctrl_c)
    assert data_cli.main(["foveation", "--samples", "8", "--photoreceptors", "400", "--out",
                          str(tmp_path / "d")]) == 130
    assert capsys.readouterr().err == ("interrupted: the chunks written are kept; the same command carries on from "
                                       "them\n")


class _SlowRender:
    """A task whose shard takes a minute, for the helper-process drill (``cfg``: a directory to mark)."""

    def __init__(self, cfg, log=print):
        self.cfg = cfg

    def render(self, shard, progress):
        (Path(self.cfg) / "started").write_text("")
        time.sleep(60)


def test_a_synthesis_helper_leaves_ctrl_c_to_its_parent_and_unwinds_when_stopped(tmp_path):
    """Ctrl-C reaches every process of the command: each helper printed a KeyboardInterrupt traceback, and
    one stopped by its parent left the resource tracker warning of leaked semaphores."""
    import multiprocessing as mp

    from warp_vision.train.workers import _render_shard

    p = mp.get_context("spawn").Process(target=_render_shard, args=(_SlowRender, str(tmp_path), (1, 2), 1), daemon=True)
    p.start()
    t0 = time.time()
    while not (tmp_path / "started").exists() and time.time() - t0 < 60:
        time.sleep(0.1)
    os.kill(p.pid, signal.SIGINT)
    p.join(1.0)
    assert p.is_alive()  # ignored: the parent stops its helpers
    p.terminate()
    p.join(30)
    assert p.exitcode == 128 + signal.SIGTERM  # sys.exit from the handler: unwound, not killed (exit code -15)


def _running(pid: int) -> bool:
    """Whether process ``pid`` still runs (a zombie no init has reaped yet has ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_a_synthesis_helper_ends_when_its_parent_is_killed_outright(tmp_path):
    """A helper ignores Ctrl-C, its parent's to handle; with the parent gone (SIGKILL), it must not render on
    for minutes as an orphan."""
    script = tmp_path / "parent.py"
    script.write_text(
        "import multiprocessing as mp, sys, time\n"
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
        "from test_faults import _SlowRender\n"
        "from warp_vision.train.workers import _render_shard\n"
        "if __name__ == '__main__':\n"
        f"    p = mp.get_context('spawn').Process(target=_render_shard, args=(_SlowRender, {str(tmp_path)!r}, (1, 2), "
        "1))\n    p.start()\n"
        "    print(p.pid, flush=True)\n"
        "    time.sleep(120)\n")
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    helper = int(parent.stdout.readline())
    t0 = time.time()
    while not (tmp_path / "started").exists() and time.time() - t0 < 60:
        time.sleep(0.1)
    parent.kill()
    parent.wait()
    t0 = time.time()
    while _running(helper) and time.time() - t0 < 15:
        time.sleep(0.2)
    assert not _running(helper), "the helper outlived its parent"


def test_a_flipped_byte_in_a_chunk_names_the_file(data, tmp_path, capsys):
    d = tmp_path / "data"
    shutil.copytree(data, d)
    victim = sorted(d.glob("chunk_*.onv.npy"))[0]
    raw = bytearray(victim.read_bytes())
    raw[-7] ^= 0xFF
    victim.write_bytes(bytes(raw))
    code, err = cli(["--preset", "smoke", "--out", str(tmp_path / "run"), "--data-dir", str(d)], capsys)
    assert code != 0 and one_line_naming(err, victim.name), err
    with pytest.raises(CorruptChunkError, match=victim.name):  # the API's own exception (a ValueError)
        foveation.run(resolve("smoke", {"out": str(tmp_path / "run2"), "data_dir": str(d)}), **QUIET)


def test_a_flipped_byte_in_the_manifest_names_the_file(data, tmp_path, capsys):
    d = tmp_path / "data"
    shutil.copytree(data, d)
    m = d / "manifest.json"
    raw = bytearray(m.read_bytes())
    raw[len(raw) // 2] ^= 0x01
    m.write_bytes(bytes(raw))
    code, err = cli(["--preset", "smoke", "--out", str(tmp_path / "run"), "--data-dir", str(d)], capsys)
    assert code != 0 and one_line_naming(err, "manifest.json"), err


# --------------------------------------------------------------------------------------------------
# 6, 10. sizes bounded by memory, and the smaller faults


def _tiny_scene():
    from warp_vision.frames import translation
    from warp_vision.scene import Material, Scene

    sc = Scene(ambient=(0.1, 0.1, 0.1))
    sc.add_sphere("ball", 0.1, (0, 0, 0), Material((1, 1, 1)), subdivisions=1)
    sc.set_transform("ball", translation([0.0, 1.0, 0.0]))
    sc.add_light((0.0, 0.0, 2.0))
    return sc


def _eye_and_pose():
    from warp_vision.eye.optics import NavarroEye
    from warp_vision.eye.retina import Retina
    from warp_vision.frames import eye_look_at

    return Retina.log_polar(50), NavarroEye(), eye_look_at([0.0, -0.5, 0.0], [0.0, 1.0, 0.0])


def test_render_onv_refuses_rays_that_cannot_fit_before_allocating():
    from warp_vision.kernels.render import render_onv

    retina, eye, pose = _eye_and_pose()
    with pytest.raises(
        ValueError, match=r"render_onv \(B=1, P=50, S=1,000,000,000\) needs about .* GiB.*lower samples_per_receptor"
    ):
        render_onv(_tiny_scene(), retina, eye, pose[None], samples_per_receptor=10**9)


def test_a_retina_that_cannot_fit_is_refused_at_once():
    from warp_vision.eye.retina import Retina

    with pytest.raises(ValueError, match=r"P=1,000,000,000 photoreceptors needs about .* GiB.*lower P, the "
                                         r"photoreceptors \(--photoreceptors\)"):
        Retina.log_polar(10**9)


def test_render_onv_of_no_poses_is_empty():
    from warp_vision.kernels.render import render_onv

    retina, eye, _ = _eye_and_pose()
    onv = render_onv(_tiny_scene(), retina, eye, np.zeros((0, 4, 4)), samples_per_receptor=1)
    assert onv.shape == (0, 150)


def test_a_pose_with_a_wrong_bottom_row_is_refused():
    from warp_vision.kernels.render import render_onv

    retina, eye, pose = _eye_and_pose()
    bad = pose.copy()
    bad[3] = [0.0, 0.0, 0.5, 1.0]
    with pytest.raises(ValueError, match=r"bottom row \[0, 0, 0, 1\]"):
        render_onv(_tiny_scene(), retina, eye, bad[None], samples_per_receptor=1)


@pytest.mark.parametrize("kw", [dict(accommodation_D=None), dict(pupil_diameter_mm=[4.0]),
                                dict(lens_semi_diameter_mm=float("nan"))])
def test_navarro_eye_names_a_bad_argument(kw):
    from warp_vision.eye.optics import NavarroEye

    with pytest.raises(ValueError, match=next(iter(kw))):
        NavarroEye(**kw)


@pytest.mark.parametrize("kw", [dict(pupil_mm=float("nan")), dict(accommodation_D=float("inf"))])
def test_set_intraocular_refuses_non_finite_commands(kw):
    from warp_vision.body import Body, BodyConfig

    body = Body(BodyConfig(arms=False))
    with pytest.raises(ValueError, match=next(iter(kw))):
        body.set_intraocular("left", **kw)


@pytest.mark.parametrize("value", ["abc", "-1", "0", "nan", "inf", "8 GB"])
def test_a_bad_memory_cap_in_the_environment_is_refused_by_name(value, monkeypatch):
    """WARP_VISION_MEMORY_LIMIT=abc said only "could not convert string to float: 'abc'", nan "cannot
    convert float NaN to integer", inf raised an OverflowError with a traceback, and 0 or -1 went through
    as caps that refuse everything."""
    from warp_vision.resources import available_memory_bytes, require_memory

    monkeypatch.setenv("WARP_VISION_MEMORY_LIMIT", value)
    with pytest.raises(ValueError, match=f"WARP_VISION_MEMORY_LIMIT: expected a number of bytes >= 1 .*got '{value}'"):
        available_memory_bytes()
    monkeypatch.setenv("WARP_VISION_MEMORY_LIMIT", "1e3")
    assert available_memory_bytes() == 1000
    require_memory(1000, "a dataset", "--samples")
    with pytest.raises(ValueError,
                       match="a dataset needs about 2 KiB, more than the 1 KiB of memory available; lower --samples"):
        require_memory(2000, "a dataset", "--samples")


def test_a_kernel_cache_that_cannot_be_made_is_refused_by_name(tmp_path):
    """WARP_VISION_KERNEL_CACHE naming a file: the error named Warp's subdirectory ("FILE/1.19.0: Not a
    directory"), not the variable."""
    (tmp_path / "FILE").write_text("x")
    env = dict(os.environ, WARP_VISION_KERNEL_CACHE=str(tmp_path / "FILE"))
    r = subprocess.run([sys.executable, "-m", "warp_vision.scene", "demo", "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert "WARP_VISION_KERNEL_CACHE" in r.stderr and str(tmp_path / "FILE") in r.stderr, r.stderr


#: config.json damage -> what the error says, and which readers refuse it: --resume, evaluate (it reads config.json
#: to check that the checkpoint belongs to its run) and the simulation (it reads the task and the eye)
_CONFIG_DAMAGE = [
    (lambda c: "{garbage", "does not read as JSON", "resume evaluate sim"),
    (lambda c: "[1, 2]", "a JSON list, where a run writes an object of settings", "resume evaluate sim"),
    (lambda c: json.dumps({**c, "task": 5}), "task 5 is not a task's name", "resume evaluate sim"),
    (lambda c: json.dumps({**c, "lr": "fast"}), "'lr' is 'fast'; expected a float", "resume evaluate"),
    (lambda c: json.dumps({**c, "epochs": 2.5}), "'epochs' is 2.5; expected an int", "resume evaluate"),
    (lambda c: json.dumps({**c, "out": 7}), "'out' is 7; expected a str", "resume evaluate"),
    (lambda c: json.dumps({**c, "bogus": 1}), "'bogus': not a setting of this run's task", "resume evaluate"),
]


@pytest.mark.parametrize("damage, says, refused_by", _CONFIG_DAMAGE)
def test_a_damaged_config_json_is_named_in_one_line(damage, says, refused_by, finished, tmp_path, capsys):
    """A config.json cut short or edited by hand gave a bare JSON error ("Expecting property name ..."), or a
    TypeError's or AttributeError's traceback, in --resume, evaluate and the simulation."""
    from warp_vision.sim.provision import NetSpec

    run = copy_run(finished, tmp_path)
    path = run / "config.json"
    path.write_text(damage(json.loads(path.read_text())))
    for reader, argv in (("resume", ["--resume", str(run), "--epochs", "4"]), ("evaluate", ["evaluate", str(run)])):
        code, err = cli(argv, capsys)
        if reader in refused_by:
            assert code == 2 and one_line_naming(err, str(path)) and says in err, err
        else:
            assert code == 0, err
    if "sim" in refused_by:
        with pytest.raises(ValueError, match=re.escape(says)):
            NetSpec("foveation", "left", str(run), "default").mismatch()


@pytest.mark.parametrize("line, says", [("{broken", "line 4 is not a metrics row (Expecting"),
                                        ('{"epoch": 4}', "line 4 is not a metrics row: no train_mse, val_mse")])
def test_compare_names_a_damaged_metrics_line(line, says, finished, tmp_path, capsys):
    """A metrics.jsonl line that is not a row gave compare a bare JSON error, or a KeyError's traceback."""
    run = copy_run(finished, tmp_path)
    with open(run / "metrics.jsonl", "a") as f:
        f.write(line + "\n")
    code, err = cli(["compare", str(run), "--out", str(tmp_path / "c.png")], capsys)
    assert code == 2 and one_line_naming(err, str(run / "metrics.jsonl")) and says in err, err
    assert not (tmp_path / "c.png").exists()
    (run / "config.json").unlink()  # (a run without its config.json is still drawn)
    (run / "metrics.jsonl").write_text("".join(x + "\n" for x in (run / "metrics.jsonl").read_text().splitlines()[:3]))
    assert cli(["compare", str(run), "--out", str(tmp_path / "c.png")], capsys)[0] == 0
    assert (tmp_path / "c.png").stat().st_size > 0


@pytest.mark.parametrize("command, says", [
    (["oculomotor", "--max-gaze-deg", "0"], r"--max-gaze-deg: expected degrees in (0, 45], got 0.0"),
    (["--max-field-deg", "0"], r"--max-field-deg: expected degrees in (0, 80], got 0.0"),
    (["lens", "--defocus-range-D", "0"], r"--defocus-range-D: expected dioptres in (0, 5], got 0.0"),
])
def test_an_open_bound_is_said_to_be_open(command, says, tmp_path, capsys):
    # "expected 0 to 45 degrees, got 0.0" refused the 0 it named as allowed
    code, err = cli([*command, "--preset", "smoke", "--out", str(tmp_path / "run")], capsys)
    assert code == 2 and says in err, err


def test_an_interrupted_command_says_so_unless_it_said_where_it_stopped(capsys):
    # Ctrl-C in evaluate or a sim ended it without a word (exit 130; SIGTERM 143)
    from warp_vision.errors import Terminated, guarded, told

    def stop(e):
        def job():
            raise e
        return job

    assert guarded(stop(KeyboardInterrupt())) == 130 and capsys.readouterr().err == "interrupted (Ctrl-C)\n"
    assert guarded(stop(Terminated("signal 15"))) == 143 and capsys.readouterr().err == "stopped (SIGTERM)\n"
    assert guarded(stop(told(KeyboardInterrupt()))) == 130 and capsys.readouterr().err == ""
    assert guarded(stop(told(Terminated("signal 15")))) == 143 and capsys.readouterr().err == ""
