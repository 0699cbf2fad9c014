"""What the commands say when something is wrong: one line that names the file, the setting, the option or
the variable and what to do, said before any work where it can be, never a default filled in silently.

The drills: a saved config that lacks a setting; a dataset missing a chunk, or holding another dataset's;
counts too small for the splits; a bad environment variable; a command line argparse refuses.
"""

from __future__ import annotations

import importlib
import json
import shutil
from pathlib import Path

import pytest

from warp_vision.__main__ import main as index_main
from warp_vision.data.foveation import synthesize
from warp_vision.train.cli import main as train_main
from warp_vision.train.config import resolve

QUIET = dict(progress=False, log=lambda *a: None)


def copy_of(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def one_error_line(err: str) -> str:
    """The one line of ``err``, checked to be an ``error:`` line and alone."""
    assert err.count("\n") == 1 and err.startswith("error: ") and "usage:" not in err, err
    return err[len("error: "):-1]


# --------------------------------------------------------------------------------------------------
# a saved config that lacks a setting


@pytest.mark.parametrize("drop, named", [(["samples"], "the setting 'samples' is missing"),
                                         (["samples", "lr"], "the settings 'samples', 'lr' are missing")])
def test_a_config_json_without_a_setting_is_refused_by_name_and_left_as_it_is(drop, named, finished, tmp_path, capsys):
    run = copy_of(finished, tmp_path / "run")
    path = run / "config.json"
    path.write_text(json.dumps({k: v for k, v in json.loads(path.read_text()).items() if k not in drop}))
    text = path.read_text()
    assert train_main(["--resume", str(run), "--epochs", "4", "--no-progress"]) == 2
    out = capsys.readouterr()
    assert one_error_line(out.err) == (f"{path}: {named} (edited by hand, or cut short?); a default would not be "
                                       f"the run's own, so none is put in")
    assert path.read_text() == text and out.out == ""  # (nothing rewritten, no dataset looked at)


def test_a_setting_added_since_a_run_was_saved_takes_its_legacy_value(finished):
    from warp_vision.nn.trained import read_checkpoint
    from warp_vision.train.config import TrainConfig
    from warp_vision.train.foveation import FoveationTask
    from warp_vision.train.rundir import config_from_saved, run_config

    saved = json.loads((finished / "config.json").read_text())
    old = {k: v for k, v in saved.items() if k not in TrainConfig.LEGACY_DEFAULTS}
    cfg = config_from_saved(TrainConfig, old, finished / "config.json")
    assert {k: getattr(cfg, k) for k in TrainConfig.LEGACY_DEFAULTS} == TrainConfig.LEGACY_DEFAULTS
    # a checkpoint's config carries no paths, and a run may have lost its config.json: the paths are not refused
    ck = read_checkpoint(finished / "best.pt")
    assert run_config(FoveationTask, finished / "nowhere", ck, finished / "best.pt").samples == saved["samples"]
    # a checkpoint without a setting is named, not the config.json that holds only the paths
    ck["config"] = {k: v for k, v in ck["config"].items() if k != "samples"}
    with pytest.raises(ValueError, match=f"^{finished / 'best.pt'}: the setting 'samples' is missing"):
        run_config(FoveationTask, finished, ck, finished / "best.pt")


# --------------------------------------------------------------------------------------------------
# a dataset missing a chunk, or holding another dataset's


@pytest.fixture(scope="module")
def other(tmp_path_factory):
    """Another dataset of the smoke run's sizes (another seed, another dataset id)."""
    d = tmp_path_factory.mktemp("other")
    synthesize(d, resolve("smoke", {"data_dir": str(d), "data_seed": 1}).data_config(), **QUIET)
    return d


def run_on(finished: Path, data: Path, tmp_path: Path) -> Path:
    """A copy of the run ``finished`` whose config.json names ``data`` as its dataset."""
    run = copy_of(finished, tmp_path / "run")
    path = run / "config.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "data_dir": str(data)}))
    return run


def test_evaluate_renders_a_chunk_gone_from_the_runs_dataset_again(finished, data, tmp_path, capsys):
    d = copy_of(data, tmp_path / "data")
    (d / "chunk_000000.onv.npy").unlink()
    assert train_main(["evaluate", str(finished)]) == 0
    intact = capsys.readouterr().out.splitlines()[-1]
    assert train_main(["evaluate", str(run_on(finished, d, tmp_path)), "--no-progress"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == (f"the run's dataset {d} lacks 1 of its 1 chunks: rendering them again (the same samples as in "
                      f"training)")
    assert out[-1].split(": ", 1)[1] == intact.split(": ", 1)[1]  # the same numbers: the same bytes


def test_a_training_run_names_the_command_that_finishes_its_dataset(data, tmp_path, capsys, monkeypatch):
    from warp_vision.train.foveation import FoveationTask

    d = copy_of(data, tmp_path / "data")
    (d / "chunk_000000.onv.npy").unlink()
    out = tmp_path / "run"
    argv = ["--preset", "smoke", "--out", str(out), "--data-dir", str(d), "--workers", "1", "--no-progress"]
    with monkeypatch.context() as m:  # a writer that stopped (another rank's, say): the chunk stays missing
        m.setattr(FoveationTask, "render", lambda self, shard, progress: None)
        assert train_main(argv) == 2
    assert one_error_line(capsys.readouterr().err) == (
        f"{d}: dataset incomplete: 1 of 1 chunks missing (chunks 0); python -m warp_vision.train --resume {out} "
        f"renders them")
    assert train_main(["--resume", str(out), "--no-progress"]) == 0  # and it does
    assert (out / "summary.json").exists()


def test_a_chunk_of_another_dataset_is_named_not_counted_missing(data, other, tmp_path):
    from warp_vision.data.store import ChunkedStore, ForeignChunkError

    d = copy_of(data, tmp_path / "data")
    for f in other.glob("chunk_000000.*"):
        shutil.copy(f, d / f.name)
    ours, theirs = ChunkedStore.open(d).dataset_id, ChunkedStore.open(other).dataset_id
    says = (f"{d / 'chunk_000000.json'}: chunk 0 belongs to another dataset: its record's dataset_id is {theirs!r}, "
            f"this dataset's (manifest.json) {ours!r} (copied in from another dataset's directory?); remove its files "
            f"({d / 'chunk_000000.*'}) to have it rendered again")
    store = ChunkedStore.open(d)
    for read in (store.missing_chunks, store.load, lambda: store.complete):
        with pytest.raises(ForeignChunkError) as e:
            read()
        assert str(e.value) == says


def test_a_chunk_of_another_dataset_is_refused_by_training_and_evaluate_in_one_line(finished, data, other, tmp_path,
                                                                                    capsys):
    d = copy_of(data, tmp_path / "data")
    for f in other.glob("chunk_000000.*"):
        shutil.copy(f, d / f.name)
    out = tmp_path / "new"
    assert train_main(["--preset", "smoke", "--out", str(out), "--data-dir", str(d), "--no-progress"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert line.startswith(f"{d / 'chunk_000000.json'}: chunk 0 belongs to another dataset"), line
    assert not out.exists()  # refused before the run directory is claimed
    assert train_main(["evaluate", str(run_on(finished, d, tmp_path))]) == 2
    assert one_error_line(capsys.readouterr().err) == line


# --------------------------------------------------------------------------------------------------
# counts too small for the splits: refused before the dataset is rendered or anything written


def test_too_few_samples_for_the_splits_are_refused_before_anything_is_written(tmp_path, capsys):
    argv = ["--preset", "smoke", "--samples", "1", "--out", str(tmp_path / "run"), "--data-dir", str(tmp_path / "data"),
            "--no-progress"]
    assert train_main(argv) == 2
    out = capsys.readouterr()
    assert one_error_line(out.err) == ("--samples: 1 leave 0 to train after 1 to validate and 0 to test: expected at "
                                       "least 2 (more samples, or a smaller --val-fraction or --test-fraction)")
    assert out.out == "" and not list(tmp_path.iterdir())


@pytest.mark.parametrize("task, overrides, says", [
    ("oculomotor", {"gazes": 4}, "gazes: 4 leave 1 to train after 1 to validate and 2 to test"),
    ("arm", {"postures": 8, "val_fraction": 0.5, "test_fraction": 0.4},
     "postures: 8 leave 1 to train after 4 to validate"),
    ("limb", {"samples": 4}, "samples: 4 leave 1 to train after 1 to validate and 2 to test"),
    ("pupil", {"samples": 4}, "samples: 4 leave 1 to train after 1 to validate and 2 to test"),
    ("lens", {"samples": 3}, "samples: 3 leave 0 to train after 1 to validate and 2 to test"),
    ("faces", {"identities": 2, "val_fraction": 0.5, "test_fraction": 0.47},
     "identities: 32 samples (2 identities x 16 poses) leave 1 to train after 16 to validate and 15 to test: expected "
     "at least 2 (more identities, or a smaller --val-fraction or --test-fraction)"),
])
def test_every_tasks_config_refuses_counts_too_small_for_its_splits(task, overrides, says):
    from warp_vision.train.cli import TASKS

    _, cls, presets, _ = TASKS[task]
    with pytest.raises(ValueError) as e:
        resolve("smoke", overrides, cls, presets)
    assert str(e.value).startswith(says), e.value


# --------------------------------------------------------------------------------------------------
# parse errors: one line, as the typed checks give


@pytest.mark.parametrize("command, argv, says", [
    # argparse's own: a type refusing its value, an invalid choice, a missing value or argument, an unknown flag
    ("train", ["--preset", "smoke", "--workers", "0"],
     "--workers: expected a positive integer or 'auto', got '0' (python -m warp_vision.train --help says more)"),
    ("train", ["evaluate", "RUN", "--checkpoint", "previous"],
     "--checkpoint: expected one of best, latest, got 'previous' (python -m warp_vision.train evaluate --help says "
     "more)"),
    ("train", ["evaluate"],
     "the following arguments are required: RUN_DIR (python -m warp_vision.train evaluate --help says more)"),
    ("train", ["compare", "r", "--out"],
     "--out: expected one argument (python -m warp_vision.train compare --help says more)"),
    ("train", ["oculomotor", "--lr", "fast"], "--lr: expected a number, got 'fast' (python -m warp_vision.train "
                                              "oculomotor --help says more)"),
    ("train", ["faces", "--eye", "middle"], "--eye: expected one of left, right, got 'middle' (python -m "
                                            "warp_vision.train faces --help says more)"),
    ("data", ["foveation", "--samples", "abc"],
     "--samples: expected an integer, got 'abc' (python -m warp_vision.data foveation --help says more)"),
    ("sim", ["demo", "--bogus"], "unrecognized arguments: --bogus (python -m warp_vision.sim demo --help says more)"),
    ("sim", ["intraocular", "--cards", "0"],
     "--cards: expected an integer 1..100 cards, got 0 (python -m warp_vision.sim intraocular --help says more)"),
    ("bench", ["linet", "--repeats", "x"],
     "--repeats: expected an integer, got 'x' (python -m warp_vision.bench linet --help says more)"),
    ("scene", ["demo", "--samples", "1.5"],
     "--samples: expected an integer, got '1.5' (python -m warp_vision.scene demo --help says more)"),
    # ours, as before, on a line of their own
    ("sim", ["experiment"], "'experiment' is not a command (did you mean 'experiments'?): expected one of demo, "
                            "experiments, intraocular, oculomotor, intercept, search (python -m warp_vision.sim --help "
                            "says more)"),
    ("scene", [], "expected a command: one of demo (python -m warp_vision.scene COMMAND --help says more)"),
    ("sim", ["--quick", "demo"], "--quick goes after the command: python -m warp_vision.sim demo --quick"),
])
def test_every_parse_error_is_one_error_line_with_exit_code_2(command, argv, says, capsys):
    main = importlib.import_module(f"warp_vision.{command}.cli").main
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert one_error_line(capsys.readouterr().err) == says


def test_a_mistyped_command_of_the_index_is_one_error_line(capsys):
    assert index_main(["trian"]) == 2
    assert one_error_line(capsys.readouterr().err) == (
        "'trian' is not a command (did you mean 'train'?): expected one of train, sim, data, bench, scene "
        "(python -m warp_vision --help says more)")


# --------------------------------------------------------------------------------------------------
# the environment, checked when a command starts


@pytest.mark.parametrize("variable, value, says", [
    ("WARP_VISION_THREADS", "0", "WARP_VISION_THREADS: expected a whole number of threads >= 1 (4, say), got '0'"),
    ("WARP_VISION_THREADS", "abc", "WARP_VISION_THREADS: expected a whole number of threads >= 1 (4, say), got 'abc'"),
    ("WARP_VISION_MEMORY_LIMIT", "8 GB",
     "WARP_VISION_MEMORY_LIMIT: expected a number of bytes >= 1 (8e9, say), got '8 GB'"),
    ("WORLD_SIZE", "0", "WORLD_SIZE: expected a whole number >= 1 (torchrun sets it), got '0'"),
    ("RANK", "first", "RANK: expected a whole number >= 0 (torchrun sets it), got 'first'"),
])
@pytest.mark.parametrize("command, argv", [
    ("train", ["--preset", "smoke", "--out", "OUT/run", "--data-dir", "OUT/data", "--no-progress"]),
    ("data", ["foveation", "--preset", "smoke", "--out", "OUT/data"]),
    ("scene", ["demo", "--photoreceptors", "100", "--out", "OUT/demo"]),
])
def test_a_bad_environment_variable_is_one_line_before_any_work(variable, value, says, command, argv, tmp_path,
                                                                 monkeypatch, capsys):
    main = importlib.import_module(f"warp_vision.{command}.cli").main
    monkeypatch.setenv(variable, value)
    assert main([a.replace("OUT", str(tmp_path)) for a in argv]) == 2
    out = capsys.readouterr()
    assert one_error_line(out.err) == says and out.out == ""  # (no bar, no "dataset: ..." line)
    assert not list(tmp_path.iterdir())  # nothing made


def test_a_kernel_cache_where_a_file_is_is_refused_before_the_job_runs(tmp_path, monkeypatch, capsys):
    from warp_vision.errors import guarded

    (tmp_path / "FILE").write_text("x")
    monkeypatch.setenv("WARP_VISION_KERNEL_CACHE", str(tmp_path / "FILE" / "kernels"))
    ran = []
    assert guarded(lambda: ran.append(1)) == 2 and not ran
    assert "WARP_VISION_KERNEL_CACHE" in one_error_line(capsys.readouterr().err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["FILE"]
