"""Fault drills: a checkpoint belongs to its run. A checkpoint copied into another run's directory (the other
eye's, another seed's), a run whose config.json names another dataset, and a warm start from the other eye's
net are each refused in one line naming what the checkpoint belongs to and what was expected, by every reader:
evaluate, --resume, --init, nn.trained.load_net, the simulation's provisioning check and Foveator."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from warp_vision.data.foveation import synthesize
from warp_vision.data.store import ChunkedStore
from warp_vision.nn.trained import binding, load_net, read_checkpoint, run_identity
from warp_vision.train import foveation
from warp_vision.train.cli import main as train_main
from warp_vision.train.config import resolve
from warp_vision.train.rundir import save_checkpoint

QUIET = dict(progress=False, log=lambda *a: None)
#: the right eye's retina needs more photoreceptors than the smoke preset's 400 for its field
RIGHT = {"eye": "right", "photoreceptors": 600}


def _run(tmp_path_factory, name: str, **settings) -> Path:
    data = tmp_path_factory.mktemp(f"data_{name}")
    cfg = resolve("smoke", {"data_dir": str(data), **settings})
    synthesize(data, cfg.data_config(), progress=False, log=lambda *a: None)
    out = tmp_path_factory.mktemp(name) / "run"
    foveation.run(resolve("smoke", {"out": str(out), "data_dir": str(data), **settings}), **QUIET)
    return out


@pytest.fixture(scope="module")
def left(finished):
    return finished


@pytest.fixture(scope="module")
def right(tmp_path_factory):
    return _run(tmp_path_factory, "right", **RIGHT)


@pytest.fixture(scope="module")
def left_seed1(tmp_path_factory, data):
    out = tmp_path_factory.mktemp("seed1") / "run"
    foveation.run(resolve("smoke", {"out": str(out), "data_dir": str(data), "seed": 1}), **QUIET)
    return out


def _copy(src: Path, tmp_path: Path, name: str = "run") -> Path:
    dst = tmp_path / name
    shutil.copytree(src, dst)
    return dst


def _cli(argv, capsys) -> tuple[int, str]:
    code = train_main(argv)
    return code, capsys.readouterr().err


def _one_line(err: str, *names: str) -> str:
    lines = [x for x in err.strip().splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    for n in names:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def test_every_checkpoint_records_what_it_belongs_to(left):
    ck = read_checkpoint(left / "best.pt")
    b = ck["binding"]
    config = json.loads((left / "config.json").read_text())
    assert b["task"] == "foveation" and b["eye"] == "left"
    assert b["run"] == run_identity("foveation", config)["run"]
    assert b["dataset"] == ChunkedStore.open(config["data_dir"]).content_digest()
    assert len(b["data_config"]) == 16


def test_the_other_eyes_best_pt_is_refused_by_every_reader(left, right, tmp_path, capsys):
    from warp_vision.sim.loop import Foveator
    from warp_vision.sim.provision import NetSpec

    run = _copy(right, tmp_path)
    shutil.copy(left / "best.pt", run / "best.pt")
    code, err = _cli(["evaluate", str(run)], capsys)
    assert code == 2
    _one_line(err, "best.pt belongs to the left eye's foveation run", "the right eye's",
              "eye 'left' there, 'right' here")
    why = NetSpec("foveation", "right", str(run), "quick").mismatch()
    assert why and "left eye's" in why
    with pytest.raises(ValueError, match="belongs to the left eye's"):
        Foveator(str(run), eye="right")
    with pytest.raises(ValueError, match="belongs to the left eye's"):
        load_net(run)
    # the run's own checkpoint passes them all
    assert NetSpec("foveation", "right", str(right), "quick").mismatch() is None
    Foveator(str(right), eye="right")
    assert "right eye's" in NetSpec("foveation", "left", str(right), "quick").mismatch()


def test_a_checkpoint_written_before_bindings_is_checked_by_its_config(left, right, tmp_path, capsys):
    run = _copy(right, tmp_path)
    ck = read_checkpoint(left / "best.pt")
    del ck["binding"]
    del ck["integrity"]
    save_checkpoint(ck, run / "best.pt")
    assert binding(read_checkpoint(run / "best.pt"))["eye"] == "left"
    code, err = _cli(["evaluate", str(run)], capsys)
    assert code == 2
    _one_line(err, "belongs to the left eye's foveation run")


def test_the_other_eyes_latest_pt_is_never_resumed(left, right, tmp_path, capsys):
    run = _copy(right, tmp_path)
    shutil.copy(left / "latest.pt", run / "latest.pt")
    before = (run / "latest.pt").read_bytes()
    code, err = _cli(["--resume", str(run), "--epochs", "4", "--no-progress"], capsys)
    assert code == 2
    _one_line(err, "latest.pt belongs to the left eye's foveation run", f"the run in {run}")
    assert (run / "latest.pt").read_bytes() == before


def test_another_seeds_best_pt_is_refused_naming_the_seed(left, left_seed1, tmp_path, capsys):
    run = _copy(left, tmp_path)
    shutil.copy(left_seed1 / "best.pt", run / "best.pt")
    code, err = _cli(["evaluate", str(run)], capsys)
    assert code == 2
    _one_line(err, "seed 1 there, 0 here")


def test_a_data_dir_holding_other_samples_of_the_same_settings_is_refused(left, tmp_path, capsys):
    run = _copy(left, tmp_path)
    config = json.loads((run / "config.json").read_text())
    same = tmp_path / "same"
    shutil.copytree(config["data_dir"], same)
    # the same settings, and a store of the same shape, but one chunk's ONVs are others
    other = tmp_path / "other"
    shutil.copytree(config["data_dir"], other)
    m = ChunkedStore.open(other).manifest
    store = ChunkedStore.create_or_resume(other, m["config"], m["total"], m["chunk_size"],
                                          {k: (tuple(s), d) for k, (s, d) in ChunkedStore.open(other).fields.items()})
    arrays = store.load_chunk(0)
    arrays["onv"] = np.ascontiguousarray(arrays["onv"][::-1])
    store.write_chunk(0, arrays)

    (run / "config.json").write_text(json.dumps({**config, "data_dir": str(other)}))
    code, err = _cli(["evaluate", str(run)], capsys)
    assert code == 2
    _one_line(err, str(other), "holds other samples", "than")

    (run / "config.json").write_text(json.dumps({**config, "data_dir": str(same)}))
    code, err = _cli(["evaluate", str(run)], capsys)
    assert code == 0, err


def test_a_resumed_run_whose_dataset_holds_other_samples_is_refused(left, tmp_path, capsys):
    run = _copy(left, tmp_path)
    config = json.loads((run / "config.json").read_text())
    other = tmp_path / "other"
    shutil.copytree(config["data_dir"], other)
    store = ChunkedStore.open(other)
    w = ChunkedStore.create_or_resume(other, store.config, store.total, store.chunk_size, store.fields)
    arrays = w.load_chunk(0)
    arrays["target"] = arrays["target"] + np.float32(0.01)
    w.write_chunk(0, arrays)
    (run / "config.json").write_text(json.dumps({**config, "data_dir": str(other)}))
    code, err = _cli(["--resume", str(run), "--epochs", "4", "--no-progress"], capsys)
    assert code == 2
    _one_line(err, "holds other samples")
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 3


def test_init_from_the_other_eyes_linet_is_refused_before_any_data(left, tmp_path, capsys):
    data = tmp_path / "data"
    code, err = _cli(["--preset", "smoke", "--eye", "right", "--photoreceptors", "600", "--init", str(left),
                      "--data-dir", str(data), "--out", str(tmp_path / "out"), "--no-progress"], capsys)
    assert code == 2
    _one_line(err, "--init", "left eye's", "across eyes is refused", "--model cnn or conv")
    assert not (tmp_path / "out").exists() and not data.exists()


def test_init_from_the_other_eyes_cnn_is_allowed_and_says_so(left, tmp_path, capsys):
    """A net whose weights are shared across the retina carries over to the other eye: allowed, in a line."""
    src = tmp_path / "cnn_left"
    src.mkdir()
    config = {**json.loads((left / "config.json").read_text()), "model": "cnn", "out": str(src)}
    (src / "config.json").write_text(json.dumps(config))
    ck = read_checkpoint(left / "best.pt")
    del ck["integrity"]
    ck["config"] = {k: v for k, v in config.items() if k not in ("out", "data_dir")}
    ck["binding"] = {**ck["binding"], **run_identity("foveation", config)}
    save_checkpoint(ck, src / "best.pt")
    cfg = resolve("smoke", {"eye": "right", "photoreceptors": 600, "model": "cnn", "init": str(src),
                            "out": str(tmp_path / "out")})
    foveation.FoveationTask.check_new_run(cfg)
    out = capsys.readouterr().out
    assert "starting the right eye's net from the left eye's foveation run" in out and "carry over" in out
