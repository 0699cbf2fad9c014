"""The foveation job end to end: data synthesis, the smoke preset, resume, corruption, NaN, torchrun."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from warp_vision.data.foveation import FoveationDataConfig, sample_params, synthesize
from warp_vision.data.store import ChunkedStore
from warp_vision.frames import gaze_directions
from warp_vision.train import config as C
from warp_vision.train import foveation, harness, workers
from warp_vision.train.cli import main as train_main
from warp_vision.train.config import resolve


@pytest.fixture(scope="module")
def smoke_data(tmp_path_factory):
    d = tmp_path_factory.mktemp("data")
    cfg = resolve("smoke", {"data_dir": str(d)})
    synthesize(d, cfg.data_config(), progress=False, log=lambda *a: None)
    return d


def smoke(tmp_path, data, **kw):
    return resolve("smoke", {"out": str(tmp_path / "run"), "data_dir": str(data), **kw})


def test_targets_point_the_axis_at_the_ball():
    cfg = FoveationDataConfig(samples=10, generator=7)
    for i in range(10):
        p = sample_params(cfg, i)
        T = p["eye_pose"]
        u = T[:3, :3].T @ (p["ball"] - T[:3, 3])
        u /= np.linalg.norm(u)
        g = gaze_directions(torch.tensor(p["target"][None], dtype=torch.float64))[0].numpy()
        assert np.allclose(u, g, atol=1e-6)
        assert np.degrees(np.arccos(u[2])) <= cfg.max_field_deg + 1e-6
        assert 0.3 <= p["meta"][0] <= 5.0
    assert not np.allclose(sample_params(cfg, 0)["target"], sample_params(cfg, 1)["target"])
    assert np.array_equal(sample_params(cfg, 3)["target"], sample_params(cfg, 3)["target"])


def test_hidden_balls_are_redrawn():
    """A ball behind a wall of the room is hidden; the same sample's ball in the open is visible; samples
    draw balls at least MIN_APPARENT_DIAMETER_DEG across, and a redraw draws another."""
    from warp_vision.data import foveation as F

    cfg = FoveationDataConfig(samples=8, generator=7)
    scene = F.make_scene(cfg.seed)
    p = sample_params(cfg, 0)
    F._place(scene, [p])
    assert F.ball_visible(scene, p, 0)
    eye = p["eye_pose"][:3, 3]
    wall = dict(p, ball=np.array([eye[0], F.ROOM_SIZE[1] / 2 + 1.0, eye[2]]))  # 1 m beyond the north wall
    F._place(scene, [wall])
    assert not F.ball_visible(scene, wall, 0)
    for i in range(40):
        q = sample_params(cfg, i)
        assert 2 * np.degrees(np.arcsin(q["radius"] / q["meta"][0])) >= F.MIN_APPARENT_DIAMETER_DEG - 1e-9
    assert not np.array_equal(sample_params(cfg, 0, attempt=1)["ball"], p["ball"])


def test_the_panel_partly_hides_the_ball():
    """With a panel in every sample, the panel covers part of the ball (not none, not all) in most samples:
    it faces the eye and its edge runs past the ball."""
    from warp_vision.data import foveation as F

    cfg = FoveationDataConfig(samples=16, occluded_fraction=1.0, generator=7)
    scene = F.make_scene(cfg.seed)
    ps = [sample_params(cfg, i) for i in range(16)]
    F._place(scene, ps)
    frac = np.array([F.ball_sight_fraction(scene, p, k, rings=(0.3, 0.6, 0.9), per_ring=12) for k, p in enumerate(ps)])
    partly = (frac > 0.05) & (frac < 0.95)
    assert partly.mean() >= 0.5, frac
    assert 0.2 < frac.mean() < 0.9, frac
    # and without the panel the same balls are in full view (furniture aside)
    F._place(scene, [dict(p, meta=np.array([*p["meta"][:2], 0.0], np.float32)) for p in ps])
    clear = np.array([F.ball_sight_fraction(scene, p, k, rings=(0.3, 0.6, 0.9), per_ring=12) for k, p in enumerate(ps)])
    assert np.median(clear) == 1.0 and clear.mean() > frac.mean() + 0.2


def test_smoke_preset_end_to_end(tmp_path, smoke_data, capsys):
    summary = foveation.run(smoke(tmp_path, smoke_data), progress=False)
    run = tmp_path / "run"
    for name in ("config.json", "latest.pt", "best.pt", "metrics.jsonl", "summary.json",
                 "figures/loss_curves.png", "figures/predicted_vs_true.png", "figures/retina_images.png"):
        assert (run / name).exists(), name
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2, 3]
    assert all(np.isfinite(r["train_mse"]) and np.isfinite(r["val_mse"]) for r in rows)
    ck = torch.load(run / "best.pt", weights_only=True)
    assert {"model", "optimizer", "epoch", "norm", "config"} <= set(ck)
    assert summary["epochs"] == 3 and np.isfinite(summary["test_median_deg"])
    saved = json.loads((run / "summary.json").read_text())
    assert saved["software"]["warp_vision"] and saved["software"]["torch"]  # what code gave these numbers
    assert json.loads((run / "config.json").read_text())["preset"] == "smoke"
    assert train_main(["evaluate", str(run)]) == 0
    assert "angular error median" in capsys.readouterr().out
    assert summary["peak_rss_mib"] > 0 and summary["model_state_mib"] > 0
    assert summary["train_precision"] == "float32"  # a liNet: precision auto leaves it in float32
    # a second run into the same directory is refused, not appended to the first's metrics
    with pytest.raises(ValueError, match="already holds a run"):
        foveation.run(smoke(tmp_path, smoke_data), progress=False, log=lambda *a: None)
    foveation.run(smoke(tmp_path, smoke_data, epochs=1), progress=False, log=lambda *a: None, overwrite=True)
    assert len((run / "metrics.jsonl").read_text().splitlines()) == 1


def test_the_batch_bar_redraws_at_tqdm_pace_not_at_every_batch(tmp_path, smoke_data, capsys):
    # the loss shown beside the bar redrew it at every batch, whatever tqdm's mininterval: a line per batch
    # in a log (the pupil net's quick run wrote 81 KB of bars; 11 KB now)
    cfg = smoke(tmp_path, smoke_data)
    foveation.run(cfg, progress=True, log=lambda *a: None)
    err = capsys.readouterr().err
    batches_per_epoch = int(re.search(r"epoch 1/3: +0%\|[^|]*\| 0/(\d+)", err).group(1))
    assert cfg.epochs == 3 and batches_per_epoch >= 8
    assert err.count("loss=") < cfg.epochs * batches_per_epoch / 2, err


def test_resume_equals_an_uninterrupted_run(tmp_path, smoke_data):
    full = foveation.run(smoke(tmp_path / "a", smoke_data), progress=False, log=lambda *a: None)
    cfg_b = smoke(tmp_path / "b", smoke_data)
    assert foveation.run(cfg_b, progress=False, log=lambda *a: None, stop_after_epoch=1) == {"interrupted": True}
    assert torch.load(tmp_path / "b/run/latest.pt", weights_only=True)["epoch"] == 0
    resumed = foveation.run(resume=str(tmp_path / "b/run"), progress=False, log=lambda *a: None)
    a = torch.load(tmp_path / "a/run/latest.pt", weights_only=True)
    b = torch.load(tmp_path / "b/run/latest.pt", weights_only=True)
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert [h["train_mse"] for h in a["history"]] == [h["train_mse"] for h in b["history"]]
    assert resumed["test_mse"] == full["test_mse"]


def test_nan_loss_stops_with_the_last_good_checkpoint(tmp_path, smoke_data, monkeypatch):
    real = foveation.net_input
    calls = {"n": 0}

    def poisoned(onv, norm, device, dtype=torch.float32):
        calls["n"] += 1
        x = real(onv, norm, device, dtype)
        return x * float("nan") if calls["n"] > 12 else x  # epoch 1 has 8 steps + 1 validation batch

    monkeypatch.setattr(foveation, "net_input", poisoned)
    with pytest.raises(harness.NonFiniteLoss, match="latest.pt"):
        foveation.run(smoke(tmp_path, smoke_data), progress=False, log=lambda *a: None)
    ck = torch.load(tmp_path / "run/latest.pt", weights_only=True)
    assert ck["epoch"] == 0 and all(torch.isfinite(v).all() for v in ck["model"].values() if v.is_floating_point())


def test_shards_build_one_dataset(tmp_path):
    cfg = FoveationDataConfig(samples=24, photoreceptors=60, samples_per_receptor=1, chunk_size=4, max_field_deg=15.0)
    one = synthesize(tmp_path / "one", cfg, progress=False, log=lambda *a: None).load()
    for i in range(3):
        synthesize(tmp_path / "three", cfg, shard=(i, 3), progress=False, log=lambda *a: None)
    three = ChunkedStore.open(tmp_path / "three")
    assert three.complete
    got = three.load()
    for k in one:
        assert np.array_equal(one[k], got[k]), k


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="model"):
        resolve("smoke", {"model": "transformer"})
    with pytest.raises(ValueError, match="val_fraction"):
        resolve("smoke", {"val_fraction": 0.95})
    with pytest.raises(ValueError, match="head"):
        resolve("smoke", {"model": "fc", "head": "softargmax"})
    with pytest.raises(ValueError, match="loss"):
        resolve("smoke", {"loss": "l1"})
    assert resolve("smoke", {"model": "fc"}).head_kind() == "linear"
    assert resolve("smoke", {}).head_kind() == "softargmax"
    assert train_main(["--preset", "smoke", "--batch", "0", "--out", "/nonexistent/x"]) == 2


@pytest.mark.parametrize("argv, said", [
    # each was refused by the net's builder only after the dataset was rendered (at the default preset
    # `--generator 7 --model linet --layers 8` began by synthesising 6,112 ONVs; here smoke-sized)
    (["--preset", "smoke", "--layers", "5"], "layers: expected every layer to keep N_h"),
    (["--preset", "smoke", "--model", "fc", "--layers", "4", "--receptive-field", "10"], "expected R_4 <= N_3 = 9"),
    (["--preset", "smoke", "--model", "conv", "--layers", "4"], "layers: layer 4 would have no sites"),
    (["--preset", "smoke", "--model", "conv", "--reduction", "1"], "reduction: the conv net's stride"),
    (["faces", "--preset", "smoke", "--layers", "9"], "--receptive-field: expected R_9 <= N_8 = 4"),
    (["limb", "--preset", "smoke", "--model", "linet", "--layers", "5"], "layers: expected every layer to keep N_h"),
    # v7 placed no ball at all on a retina this small: a RuntimeError after the run was claimed
    (["--preset", "smoke", "--photoreceptors", "3", "--layers", "1", "--receptive-field", "2"],
     "photoreceptors: 3 are too few for balls out to max_field_deg=45"),
    (["--preset", "smoke", "--photoreceptors", "60", "--layers", "2"], "from 18.5 deg out"),
])
def test_a_net_or_retina_too_small_for_its_settings_is_refused_before_any_data_is_rendered(
    argv, said, tmp_path, capsys
):
    assert train_main([*argv, "--out", str(tmp_path / "run"), "--data-dir", str(tmp_path / "data")]) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1, err
    assert not list(tmp_path.iterdir())


def test_a_warm_start_that_cannot_load_is_refused_before_any_data_is_rendered(tmp_path, capsys):
    """--init was read only once the dataset was synthesised: at the default preset, after minutes."""
    import json

    for name, cfg in (("arm", {"task": "arm", "side": "left"}), ("cnn16", {"model": "cnn", "channels": 16})):
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.json").write_text(json.dumps(cfg))
        (tmp_path / name / "best.pt").write_bytes(b"weights")
    for init, extra, said in ((tmp_path / "none", [], "no such checkpoint (--init takes a foveation run directory"),
                              (tmp_path / "arm", [], "is an arm run; --init takes a foveation run"),
                              (tmp_path / "cnn16" / "best.pt", [], "--model cnn there, linet here"),
                              (tmp_path / "cnn16", ["--model", "cnn", "--channels", "8"],
                               "--channels 16 there, 8 here")):
        argv = ["--preset", "smoke", *extra, "--init", str(init), "--out", str(tmp_path / "run"), "--data-dir",
                str(tmp_path / "d")]
        assert train_main(argv) == 2, argv
        err = capsys.readouterr().err
        assert said in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arm", "cnn16"]


def test_the_field_check_passes_where_every_direction_admits_a_ball():
    FoveationDataConfig(photoreceptors=60, max_field_deg=15.0).validate()
    FoveationDataConfig(photoreceptors=400).validate()  # the smoke preset's retina, to 45 deg


def test_a_run_of_another_task_is_refused_by_resume_compare_and_the_foveation_evaluations(tmp_path, capsys):
    """Each command reads the task a run directory's config.json names and says in one line what it expected
    (it was a TypeError or KeyError from deep inside before); nothing is trained or written."""
    import json

    arm = tmp_path / "arm"
    arm.mkdir()
    (arm / "config.json").write_text(json.dumps({"task": "arm", "side": "left", "out": str(arm)}))
    (arm / "metrics.jsonl").write_text(json.dumps({"epoch": 1, "train_loss": 1.0, "val_loss": 1.0}) + "\n")
    fov = tmp_path / "fov"
    fov.mkdir()
    # foveation: the config names no task
    (fov / "config.json").write_text(json.dumps({"model": "cnn", "out": str(fov)}))
    capsys.readouterr()
    for argv, said in ((["--resume", str(arm)], f"an arm run, not a foveation run; resume it with "
                                                 f"python -m warp_vision.train arm --resume {arm}"),
                       (["limb", "--resume", str(fov)], "a foveation run, not a limb run; resume it with "
                                                        f"python -m warp_vision.train --resume {fov}"),
                       (["compare", str(arm), "--out", str(tmp_path / "c.png")], "is an arm run; compare plots"),
                       (["evaluate", str(arm), "--conditions"], "an arm run; --conditions measures foveation runs"),
                       (["evaluate", str(fov), str(arm), "--conditions"], "an arm run; --conditions"),  # before fov's
                       (["evaluate", str(fov), str(arm), "--misses"], "is an arm run"),
                       (["evaluate", str(arm), "--views", "2"], "is an arm run")):
        assert train_main(argv) == 2, argv
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err, (argv, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arm", "fov"] and not (arm / "best.pt").exists()


def test_a_file_given_as_the_run_or_the_data_directory_is_refused_before_anything_is_written(tmp_path, capsys):
    f = tmp_path / "notes.txt"
    f.write_text("not a directory")
    for task in ([], ["oculomotor"], ["pupil"]):
        for argv, flag in ((["--out", str(f)], "--out"),
                           (["--out", str(tmp_path / "run"), "--data-dir", str(f)], "--data-dir")):
            assert train_main([*task, "--preset", "smoke", *argv]) == 2
            assert f"{flag} names a file, not a directory" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_face_and_limb_runs_offer_only_the_models_they_train():
    """Face recognition trains a liNet or its fc twin, limb vision also the cnn and range nets: each config
    refuses the other models and its command's --model offers only its own; foveation offers the conv net."""
    import argparse

    from warp_vision.train.config import FACE_PRESETS, FaceTrainConfig, add_arguments
    from warp_vision.train.config_body import LIMB_PRESETS, LimbTrainConfig

    for cls, presets, own, other in ((FaceTrainConfig, FACE_PRESETS, ["linet", "fc"], "cnn"),
                                     (LimbTrainConfig, LIMB_PRESETS, ["linet", "fc", "cnn", "range"], "conv")):
        with pytest.raises(ValueError, match=re.escape(f"model: expected one of {own}")):
            resolve("smoke", {"model": other}, cls, presets)
        assert resolve("smoke", {"model": "fc"}, cls, presets).model == "fc"
        p = argparse.ArgumentParser()
        add_arguments(p, cls, presets)
        assert next(a for a in p._actions if "--model" in a.option_strings).choices == own
    fov = argparse.ArgumentParser()
    add_arguments(fov)
    assert next(a for a in fov._actions if "--model" in a.option_strings).choices == ["linet", "fc", "conv", "cnn"]
    with pytest.raises(ValueError, match=re.escape("model: expected one of ['linet', 'fc', 'conv', 'cnn']")):
        resolve("smoke", {"model": "range"})


def _task_configs():
    from warp_vision.train import config, config_body, config_intraocular

    return [(config.FaceTrainConfig, config.FACE_PRESETS),
            (config_body.OculomotorTrainConfig, config_body.OCULOMOTOR_PRESETS),
            (config_body.ArmTrainConfig, config_body.ARM_PRESETS),
            (config_body.LimbTrainConfig, config_body.LIMB_PRESETS),
            (config_intraocular.PupilTrainConfig, config_intraocular.PUPIL_PRESETS),
            (config_intraocular.LensTrainConfig, config_intraocular.LENS_PRESETS)]


@pytest.mark.parametrize("task", ["foveation", "faces", "oculomotor", "arm", "limb", "pupil", "lens"])
def test_each_training_command_groups_its_flags_by_what_they_set(task):
    """--help listed some 40 flags in one block; now under the config's sections, every flag in one of them."""
    from warp_vision.train.cli import _task_parser, _train_parser

    p = _train_parser() if task == "foveation" else _task_parser(task)
    titles = [g.title for g in p._action_groups]
    assert titles[-4:] == ["the run", "the dataset", "the model", "optimisation"] or (
        task in ("limb", "pupil",
                 "lens") and titles[-4] == "the run" and titles[-3].startswith("the dataset (")), titles
    placed = {g.title: {o for a in g._group_actions for o in a.option_strings} for g in p._action_groups}
    assert {"--preset", "--out", "--device", "--resume", "--overwrite", "--workers", "--debug"} <= placed["the run"]
    assert "--batch" in placed["optimisation"] and "--lr" in placed["optimisation"]
    assert any("--photoreceptors" in v or "--gazes" in v or "--postures" in v for k, v in placed.items()
               if k.startswith("the dataset"))
    assert placed[p._optionals.title] == {"-h", "--help"}  # every other flag sits in a section
    help_text = p.format_help()
    assert "\nthe run:\n" in help_text and "\noptimisation:\n" in help_text


@pytest.mark.parametrize("cls, presets", _task_configs(), ids=lambda x: getattr(x, "__name__", ""))
def test_every_task_config_shares_the_checks_and_the_default_out(cls, presets):
    """Each task's config refuses another task's name, fractions that leave no training data (a test
    fraction of 0 too: only foveation may skip its test split) and a non-finite number; an empty --out
    becomes runs/<task>/<eye or side>."""
    cfg = resolve("smoke", {}, cls, presets)
    task = cls.task
    assert cfg.out == ("runs/faces" if task == "faces" else f"runs/{task}/left")
    side = "side" if hasattr(cfg, "side") else "eye"
    if task != "faces":
        assert resolve("smoke", {side: "right"}, cls, presets).out == f"runs/{task}/right"
    assert resolve("smoke", {"out": "elsewhere"}, cls, presets).out == "elsewhere"
    with pytest.raises(ValueError, match="task: expected"):
        resolve("smoke", {"task": "foveation"}, cls, presets)
    # each named as what it is: "fractions that leave some training data" was said of a validation fraction of 0 too
    for bad, says in (({"val_fraction": 0.0}, r"val_fraction: expected a fraction in \(0, 1\), got 0.0"),
                      ({"test_fraction": 0.0}, r"test_fraction: expected a fraction in \(0, 1\), got 0.0"),
                      ({"val_fraction": 0.5, "test_fraction": 0.5},
                       r"val_fraction and test_fraction: 0.5 \+ 0.5 leave no training data; expected a sum < 1")):
        with pytest.raises(ValueError, match=says):
            resolve("smoke", bad, cls, presets)
    with pytest.raises(ValueError, match="lr"):
        resolve("smoke", {"lr": float("nan")}, cls, presets)
    assert resolve("smoke", {"test_fraction": 0.0}).test_fraction == 0.0  # foveation's test split may be empty
    with pytest.raises(ValueError, match=r"test_fraction: expected a fraction in \[0, 1\), got -0.1"):
        resolve("smoke", {"test_fraction": -0.1})


def test_presets_pick_the_scene_generator_and_model_and_the_help_says_so():
    """quick and default train the retina CNN on v9, paper the paper's liNet on v9, smoke a small v7 liNet;
    --help gives the default preset's value and the others' where they differ."""
    from warp_vision.errors import preset_defaults
    from warp_vision.train.config import PRESETS

    picks = {p: (resolve(p, {}).generator, resolve(p, {}).model) for p in PRESETS}
    assert picks == {"smoke": (7, "linet"), "quick": (9, "cnn"), "default": (9, "cnn"), "paper": (9, "linet")}
    assert resolve("paper", {}).samples_per_receptor == 8 and resolve("default", {"generator": 7}).generator == 7
    assert preset_defaults(PRESETS, "generator", 7) == "default: 9; --preset smoke: 7"
    assert preset_defaults({"default": {}, "smoke": {}}, "batch", 64) == "default: 64"


def test_evaluate_offers_the_checkpoints_the_reader_knows():
    """evaluate's --checkpoint choices are spelled out in the CLI (it parses without importing torch); they
    must stay the names nn/trained reads, so neither side can gain a name the other refuses."""
    from warp_vision.nn.trained import CHECKPOINTS
    from warp_vision.train.cli import _eval_parser

    action = next(a for a in _eval_parser()._actions if "--checkpoint" in a.option_strings)
    assert tuple(action.choices) == CHECKPOINTS and action.default == CHECKPOINTS[0]


def test_learning_rate_schedule(tmp_path, smoke_data):
    cfg = resolve("default", {"epochs": 11})
    lrs = [cfg.epoch_lr(e) for e in range(11)]
    assert lrs[0] == cfg.lr and abs(lrs[-1] - cfg.lr / 20) < 1e-12 and abs(lrs[5] - cfg.lr * 0.525) < 1e-12
    assert all(a > b for a, b in zip(lrs, lrs[1:]))
    assert resolve("default", {"lr_schedule": "constant"}).epoch_lr(7) == cfg.lr
    with pytest.raises(ValueError, match="lr_schedule"):
        resolve("default", {"lr_schedule": "step"})
    foveation.run(smoke(tmp_path, smoke_data), progress=False, log=lambda *a: None)  # the optimiser follows it
    rows = [json.loads(x) for x in (tmp_path / "run/metrics.jsonl").read_text().splitlines()]
    sm = resolve("smoke", {})
    assert [r["lr"] for r in rows] == [sm.epoch_lr(e) for e in range(3)]
    ck = torch.load(tmp_path / "run/latest.pt", weights_only=True)
    assert ck["optimizer"]["param_groups"][0]["lr"] == sm.epoch_lr(2)


def test_plateau_schedule_lowers_the_rate_when_validation_stalls(tmp_path, smoke_data, monkeypatch):
    # one stalled epoch lowers the rate here, and the rate is high for 128 ONVs, so the run stalls at
    # least once whatever the data (with the default 3 epochs whether it stalls depends on the generator)
    monkeypatch.setattr(harness, "PLATEAU_EPOCHS", 1)
    cfg = smoke(tmp_path, smoke_data, lr_schedule="plateau", epochs=8, patience=8, lr=1e-1)
    foveation.run(cfg, progress=False, log=lambda *a: None)
    rows = [json.loads(x) for x in (tmp_path / "run/metrics.jsonl").read_text().splitlines()]
    lr, best, bad = cfg.lr, float("inf"), 0
    for r in rows:  # the rule, replayed from the validation losses
        assert r["lr"] == pytest.approx(lr)
        best, bad = (r["val_loss"], 0) if r["val_loss"] < best else (best, bad + 1)
        if bad and bad % harness.PLATEAU_EPOCHS == 0:
            lr *= harness.PLATEAU_FACTOR
    assert len(rows) == 8 or bad >= cfg.patience
    assert any(r["lr"] < cfg.lr for r in rows)  # the rule was exercised


@pytest.mark.parametrize("model,head,loss", [("linet", "linear", "mse"), ("fc", "auto", "huber")])
def test_other_read_outs_train(tmp_path, smoke_data, model, head, loss):
    """The paper's linear read-out and MSE loss, and the FC baseline, train and evaluate too."""
    summary = foveation.run(smoke(tmp_path, smoke_data, model=model, head=head, loss=loss, epochs=2), progress=False,
                       log=lambda *a: None)
    assert summary["head"] == "linear" and summary["model"] == model and summary["loss"] == loss
    rows = [json.loads(x) for x in (tmp_path / "run/metrics.jsonl").read_text().splitlines()]
    if loss == "mse":  # the training loss is the MSE itself
        assert all(r["val_loss"] == pytest.approx(r["val_mse"]) for r in rows)
    else:  # Huber is at most half the squared error
        assert all(r["val_loss"] <= 0.5 * r["val_mse"] + 1e-9 for r in rows)
    assert np.isfinite(summary["test_median_deg"])
    assert foveation.evaluate_run(str(tmp_path / "run"),
                                  log=lambda *a: None)["median_deg"] == pytest.approx(summary["test_median_deg"])


def test_workers_synthesise_the_same_dataset_in_several_processes(tmp_path, smoke_data, capsys):
    lines = []
    foveation.run(smoke(tmp_path, tmp_path / "data", epochs=1), progress=False, log=lines.append, workers=2)
    assert any("synthesis in 2 processes" in line for line in lines), lines
    got, want = ChunkedStore.open(tmp_path / "data"), ChunkedStore.open(smoke_data)
    assert got.complete
    # shard 1 of 2 (the odd chunks) was the spawned helper's: every chunk equals one process's rendering
    for k, v in want.load().items():
        assert np.array_equal(v, got.load()[k]), k
    # a complete dataset starts no helper
    lines.clear()
    foveation.run(smoke(tmp_path / "again", tmp_path / "data", epochs=1), progress=False, log=lines.append, workers=2)
    assert not any("processes" in line for line in lines)
    assert workers.auto_workers("cuda:0", 50_000) == 1 and workers.auto_workers("cpu", 160) == 1
    with pytest.raises(ValueError, match="workers"):
        foveation.run(smoke(tmp_path / "bad", smoke_data), progress=False, workers=0)
    with pytest.raises(SystemExit):
        train_main(["--preset", "smoke", "--workers", "0"])
    assert "positive integer or 'auto'" in capsys.readouterr().err
    # a task that renders in one process: --workers N was dropped without a word
    assert train_main(["faces", "--preset", "smoke", "--workers", "2", "--out", str(tmp_path / "faces")]) == 2
    assert "a faces run renders its dataset in one process" in capsys.readouterr().err
    assert not (tmp_path / "faces").exists()


def test_evaluate_renders_a_dataset_gone_from_its_cache_again(tmp_path, smoke_data):
    """Datasets are a cache (runs/datasets/...): deleted to free the disk, evaluate said only "not a ChunkedStore"."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(smoke_data, data)
    foveation.run(smoke(tmp_path, data, epochs=1), progress=False, log=lambda *a: None)
    before = foveation.evaluate_run(str(tmp_path / "run"), log=lambda *a: None)
    shutil.rmtree(data)
    lines = []
    after = foveation.evaluate_run(str(tmp_path / "run"), log=lines.append, progress=False)
    assert lines[0] == f"the run's dataset {data} is gone: rendering it again (the same samples as in training)"
    assert after["mse"] == before["mse"] and after["median_deg"] == before["median_deg"]
    for f in sorted(smoke_data.glob("chunk_*.npy")):
        assert (data / f.name).read_bytes() == f.read_bytes(), f.name


def test_the_mse_is_split_into_missed_balls_and_the_rest(tmp_path, smoke_data, capsys):
    se = torch.tensor([0.001, 0.003, 2.0, 0.002])
    err = torch.tensor([0.5, 1.5, 30.0, 4.9])
    parts = foveation.mse_parts(se, err)
    assert parts["over_5deg"] == 0.25
    assert parts["mse_share_off"] == pytest.approx(2.0 / 2.006)
    assert parts["mse_within_5deg"] == pytest.approx(0.002)
    assert np.isnan(foveation.mse_parts(torch.zeros(0), torch.zeros(0))["over_5deg"])
    # every ball missed: the rest is empty, said in words (it printed "the rest's MSE nan")
    line = foveation.FoveationTask.eval_line(None, "run", "test", 4, {"mse": 2.0, "median_deg": 30.0, "p90_deg": 40.0,
                                                                    **foveation.mse_parts(se, err + 10.0)})
    assert line.endswith("the rest's MSE none: every one is off") and "nan" not in line, line
    foveation.run(smoke(tmp_path, smoke_data, epochs=1), progress=False, log=lambda *a: None)
    assert train_main(["evaluate", str(tmp_path / "run")]) == 0
    assert "deg off (another object found) hold" in capsys.readouterr().out
    row = json.loads((tmp_path / "run/metrics.jsonl").read_text().splitlines()[0])
    assert 0 <= row["val_over_5deg"] <= 1


def test_the_misses_are_broken_down_by_eccentricity_size_and_scene(tmp_path, smoke_data, capsys):
    """Designed samples: each row counts its samples, the share off and its share of all the misses; the
    CLI prints the table for a foveation run's split and refuses --misses with --conditions."""
    from warp_vision.data.foveation import META_V9

    deg = np.radians
    target = np.array([[0.0, 0.0], [deg(35), 0.0], [0.0, deg(-15)], [deg(45), 0.0]])  # eccentricities 0, 35, 15, 45
    err = np.array([1.0, 12.0, 6.0, 0.5])  # the second and third are off
    meta = np.zeros((4, len(META_V9)), np.float32)
    meta[:, 0] = 2.0                                            # 2 m away
    meta[:, 1] = 2.0 * np.sin(deg(np.array([0.5, 3.0, 3.0, 9.0])))  # apparent radii 0.5, 3, 3, 9 deg
    meta[1, META_V9.index("arm")] = meta[2, META_V9.index("arm")] = 1
    meta[0, META_V9.index("decoy")] = 1
    rows = {(r["group"], r["bin"]): r for r in foveation.miss_breakdown(err, target, meta, META_V9)}
    assert rows[("eccentricity (deg)", "0-10")] == {"group": "eccentricity (deg)", "bin": "0-10", "n": 1, "off": 0.0,
                                                    "of_misses": 0.0}
    assert rows[("eccentricity (deg)", "30-40")]["off"] == 1.0
    assert rows[("eccentricity (deg)", "30-40")]["of_misses"] == 0.5
    assert rows[("eccentricity (deg)", ">= 40")]["n"] == 1 and ("eccentricity (deg)", "20-30") not in rows
    assert rows[("apparent radius (deg)", "2-4")]["n"] == 2
    assert rows[("apparent radius (deg)", "2-4")]["of_misses"] == 1.0
    assert rows[("apparent radius (deg)", "8-11")]["off"] == 0.0
    assert rows[("arm", "yes")]["off"] == 1.0 and rows[("arm", "no")]["off"] == 0.0
    assert rows[("decoy", "yes")]["n"] == 1 and rows[("decoy", "no")]["off"] == pytest.approx(2 / 3)
    assert ("distance_m", "yes") not in rows and ("brightness", "yes") not in rows
    # v7's meta has three columns: occluded is its only flag
    assert {r["group"] for r in foveation.miss_breakdown(err, target, meta[:, :3], META_V9[:3])} == {
        "eccentricity (deg)", "apparent radius (deg)", "occluded"}
    foveation.run(smoke(tmp_path, smoke_data, epochs=1), progress=False, log=lambda *a: None)
    capsys.readouterr()
    assert train_main(["evaluate", str(tmp_path / "run"), "--misses"]) == 0
    out = capsys.readouterr().out
    assert "where the balls more than 5 deg off lie" in out and "| occluded | yes |" in out
    assert (tmp_path / "run/figures/misses_test.png").exists()
    with pytest.raises(SystemExit):
        train_main(["evaluate", str(tmp_path / "run"), "--misses", "--conditions"])


def test_the_misses_are_broken_down_by_the_balls_signal_and_where_the_estimates_land():
    """With ball_signal's measures: rows per band of photoreceptors on the ball and of its contrast (NaN,
    no ring seen, counts as 0), and per class of what the estimate lands on."""
    from warp_vision.data.foveation import META_V9

    target = np.zeros((4, 2))
    err = np.array([30.0, 0.5, 12.0, 1.0])  # the first and third are off
    meta = np.zeros((4, len(META_V9)), np.float32)
    meta[:, 0], meta[:, 1] = 2.0, 0.1
    signal = {"receptors": np.array([3, 50, 12, 400]), "contrast": np.array([0.03, 0.5, np.nan, 20.0]),
              "landed_on": np.array(["furniture: box", "ball", "decoy: plate", "ball"], dtype=object)}
    rows = {(r["group"], r["bin"]): r for r in foveation.miss_breakdown(err, target, meta, META_V9, signal=signal)}
    assert rows[("photoreceptors on the ball", "0-5")] == {"group": "photoreceptors on the ball", "bin": "0-5", "n": 1,
                                                           "off": 1.0, "of_misses": 0.5}
    assert rows[("photoreceptors on the ball",
                 "10-20")]["off"] == 1.0 and rows[("photoreceptors on the ball", ">= 320")]["off"] == 0.0
    assert rows[("ball's contrast", "0-0.05")]["n"] == 2 and rows[("ball's contrast", "0-0.05")]["of_misses"] == 1.0
    assert rows[("ball's contrast", ">= 10")]["off"] == 0.0
    assert rows[("estimate lands on", "ball")] == {"group": "estimate lands on", "bin": "ball", "n": 2, "off": 0.0,
                                                   "of_misses": 0.0}
    assert rows[("estimate lands on", "decoy: plate")]["off"] == 1.0 and ("estimate lands on", "arm") not in rows
    assert rows[("estimate lands on",
                 "furniture: box")]["of_misses"] == 0.5 and ("estimate lands on", "furniture: cylinder") not in rows
    assert all("chance" not in r for r in rows.values())
    chance = np.array(["wall, floor or ceiling", "wall, floor or ceiling", "decoy: plate", "furniture: box"],
                      dtype=object)
    rows = {(r["group"], r["bin"]): r for r in foveation.miss_breakdown(err, target, meta, META_V9,
                                                                         signal={**signal, "chance_landed_on": chance})}
    assert rows[("estimate lands on",
                 "decoy: plate")]["chance"] == 0.25 and rows[("estimate lands on", "ball")]["chance"] == 0.0
    assert "| 50.0% (chance 25.0%) |" in foveation.miss_table([rows[("estimate lands on", "decoy: plate")]])
    assert "chance" not in rows[("ball's contrast", ">= 10")]
    assert "chance" not in foveation.miss_table([rows[("ball's contrast", ">= 10")]])
    b = foveation.barely_seen(err, signal)  # the first (3 photoreceptors) and third (NaN contrast) are barely seen
    assert b == {"share": 0.5, "off": 1.0, "of_misses": 1.0, "others_off": 0.0}
    assert foveation.barely_seen(err,
                                 {**signal, "receptors": np.full(4, 99), "contrast": np.ones(4)})["others_off"] == 0.5
    without = {r["group"] for r in foveation.miss_breakdown(err, target, meta, META_V9)}
    assert "photoreceptors on the ball" not in without and "estimate lands on" not in without


@pytest.mark.parametrize("argv, says", [
    (["--samples", "10"], "--samples: the ONVs of each held-out set of --conditions"),  # was ignored without a word
    (["--conditions", "--split", "val"], "--split val: of a run's own split; --conditions measures held-out sets"),
    (["--signal"], "--signal: a part of --misses"),
])
def test_evaluate_refuses_a_flag_its_evaluation_would_not_read(argv, says, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        train_main(["evaluate", str(tmp_path / "run"), *argv])
    assert e.value.code == 2 and says in capsys.readouterr().err


def test_evaluate_signal_renders_the_split_again_for_v8_and_v9_runs(tmp_path, smoke_data, capsys):
    """--signal: a v9 run's misses by the balls' signal; refused without --misses and for a v7 run."""
    cfg = smoke(tmp_path, tmp_path / "data9", generator=9, samples=48, epochs=1)
    foveation.run(cfg, progress=False, log=lambda *a: None)
    capsys.readouterr()
    assert train_main(["evaluate", str(tmp_path / "run"), "--misses", "--signal", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "| photoreceptors on the ball |" in out and "| estimate lands on |" in out and "barely seen" in out
    assert "(chance " in out  # what the estimates land on, beside what a direction drawn like the targets would
    assert (tmp_path / "run/figures/misses_test.png").stat().st_size > 10_000
    with pytest.raises(SystemExit):
        train_main(["evaluate", str(tmp_path / "run"), "--signal"])
    foveation.run(smoke(tmp_path / "v7", smoke_data, epochs=1), progress=False, log=lambda *a: None)
    assert train_main(["evaluate", str(tmp_path / "v7/run"), "--misses", "--signal"]) == 2
    assert "v8 and v9 runs only" in capsys.readouterr().err
    with pytest.raises(ValueError, match="misses=True"):
        foveation.evaluate_run(str(tmp_path / "run"), signal=True)


def test_a_failing_synthesis_helper_is_an_error(tmp_path, monkeypatch):
    import dataclasses

    good = resolve("smoke", {"data_dir": str(tmp_path / "data")})
    task = foveation.FoveationTask(dataclasses.replace(good, samples_per_receptor=0), log=lambda *a: None)
    # the spawned helper renders with the task's (invalid) config and fails; this process's shard is a no-op
    monkeypatch.setattr(foveation.FoveationTask, "render", lambda self, shard, progress: None)
    with pytest.raises(RuntimeError, match="synthesis helper"):
        workers.render_in_processes(task, 2, progress=False)


def test_torchrun_two_processes(tmp_path, smoke_data):
    env = dict(os.environ, WARP_VISION_THREADS="1", OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2", "--master-port", "29517",
           "-m", "warp_vision.train", "--preset", "smoke", "--out", str(tmp_path / "ddp"), "--data-dir",
           str(smoke_data), "--no-progress"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    summary = json.loads((tmp_path / "ddp/summary.json").read_text())
    assert summary["epochs"] == 3 and np.isfinite(summary["test_mse"])
    rows = (tmp_path / "ddp/metrics.jsonl").read_text().splitlines()
    assert len(rows) == 3  # rank 0 alone writes


def test_no_rank_is_dealt_an_empty_batch(tmp_path):
    """Under torchrun an epoch's last batch of fewer samples than ranks left a rank none, and its loss was NaN
    (`torchrun --nproc-per-node 2 -m warp_vision.train faces --preset smoke`: 33 training samples in batches of
    8, the last of one: "epoch 1, step 4: the loss is nan")."""
    from warp_vision.train.harness import Dist, Task, _train_epoch

    dealt = []

    class Recorder(Task):
        def batch_loss(self, net, idx, norm, device):
            dealt.append(len(idx))
            loss = net(torch.ones(len(idx), 2)).square().mean()
            return loss, {"loss": float(loss.detach())}

    task = Recorder(resolve("smoke", {"batch": 8}), log=lambda *a: None)
    net = torch.nn.Linear(2, 1)
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    for world, n, expected in [(2, 33, {0: [4, 4, 4, 4], 1: [4, 4, 4, 4]}),  # the last batch's one sample: left out
                               (2, 35, {0: [4, 4, 4, 4, 2], 1: [4, 4, 4, 4, 1]}),
                               (1, 33, {0: [8, 8, 8, 8, 1]})]:  # one process: every sample, as before
        for rank in range(world):
            dd = Dist("cpu")
            dd.world, dd.rank = world, rank  # the dealing alone (no process group: all_mean is this rank's)
            dealt.clear()
            metrics = _train_epoch(task, net, net, opt, np.arange(n), 0, {}, "cpu", dd, False, tmp_path)
            assert dealt == expected[rank] and np.isfinite(metrics["loss"]), (world, n, rank, dealt)


def test_a_batch_smaller_than_the_ranks_is_refused_before_any_work(tmp_path, monkeypatch):
    # `torchrun --nproc-per-node 2 -m warp_vision.train --preset smoke --batch 1` dealt rank 1 an empty batch:
    # "epoch 1, step 0: the loss is nan"
    monkeypatch.setenv("WORLD_SIZE", "2")  # (refused before the process group would be made)
    with pytest.raises(ValueError, match="batch: expected at least one sample for each of the 2 ranks under "
                                         "torchrun, got 1"):
        foveation.run(smoke(tmp_path, tmp_path / "data", batch=1), progress=False, log=lambda *a: None)
    assert not (tmp_path / "data").exists() and not (tmp_path / "run" / "config.json").exists()


def test_a_run_too_small_for_a_test_split_names_the_split_it_evaluates(tmp_path, capsys):
    # 3 ONVs: 2 to train, 1 to validate, none to test; the validation sample was reported as "(test, 1 ONVs)"
    said = []
    summary = foveation.run(smoke(tmp_path, tmp_path / "data", samples=3), progress=False, log=said.append)
    assert summary["evaluated_split"] == "val"
    assert (
        f"{tmp_path / 'run'} (val, 1 ONVs): " in said[-1] and "(no test split: the summary's test_* are" in said[-1]
    ), said[-1]
    assert train_main(["evaluate", str(tmp_path / "run")]) == 0
    out = capsys.readouterr().out
    assert (
        "no test split (--test-fraction 0, or too few samples)" in out and f"{tmp_path / 'run'} (val, 1 ONVs): " in out
    ), out


def test_fewer_than_two_to_train_is_refused():
    # `--samples 3 --val-fraction 0.5` left one sample to train: its targets' spread was 0, the loss NaN at step 0
    # ("try a lower --lr")
    from warp_vision.train.harness import splits

    tr, va, te = splits(3, 0, 0.1, 0.1)
    assert (len(tr), len(va), len(te)) == (2, 1, 0) and sorted([*tr, *va, *te]) == [0, 1, 2]
    with pytest.raises(ValueError,
                       match="samples: 3 leave 1 to train after 2 to validate and 0 to test: expected at least 2"):
        splits(3, 0, 0.5, 0.0)
    with pytest.raises(ValueError, match="leave 0 to train after 1 to validate and 2 to test"):
        splits(3, 0, 0.1, 0.1, min_test=2)


def test_compare_figure(tmp_path, smoke_data):
    foveation.run(smoke(tmp_path, smoke_data, epochs=2), progress=False, log=lambda *a: None)
    fig = tmp_path / "cmp.png"
    assert train_main(["compare", str(tmp_path / "run"), "--out", str(fig)]) == 0
    assert fig.stat().st_size > 1000
    assert train_main(["compare", str(tmp_path / "nope"), "--out", str(fig)]) == 2
    assert train_main(["compare", str(tmp_path / "run"), str(tmp_path / "run"), "--out", str(fig)]) == 2  # twice


def test_compare_labels_every_run_by_its_directory_and_titles_the_figure(tmp_path, monkeypatch):
    """Runs of one model and retina size still get a curve each, named by their directories."""
    import json

    from warp_vision.train import figures

    for d in ("a/plain", "b/plain", "copies"):
        (tmp_path / d).mkdir(parents=True)
        (tmp_path / d / "config.json").write_text(json.dumps({"model": "cnn", "photoreceptors": 14400}))
        (tmp_path / d / "metrics.jsonl").write_text(json.dumps({"epoch": 1, "train_mse": 0.5, "val_mse": 0.6}) + "\n")
    seen = {}
    real = figures.plot_curves
    monkeypatch.setattr(figures, "plot_curves", lambda h,
                        title: seen.update(labels=list(h), title=title) or real(h, title))
    runs = [str(tmp_path / d) for d in ("a/plain", "b/plain", "copies")]
    assert train_main(["compare", *runs, "--out", str(tmp_path / "c.png"), "--title", "with and without"]) == 0
    assert seen == {"labels": [f"{runs[0]} (cnn, P=14,400)", f"{runs[1]} (cnn, P=14,400)", "copies (cnn, P=14,400)"],
                    "title": "with and without"}


def test_compare_writes_the_format_its_suffix_names(tmp_path, capsys):
    # it wrote a PNG whatever the suffix: curves.pdf was a PNG
    import json

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.json").write_text(json.dumps({"model": "cnn"}))
    (tmp_path / "run" / "metrics.jsonl").write_text(json.dumps({"epoch": 1, "train_mse": 0.5, "val_mse": 0.6}) + "\n")
    for name, magic in (("c.pdf", b"%PDF"), ("c.svg", b"<?xml"), ("c", b"\x89PNG"), ("c.PNG", b"\x89PNG")):
        assert train_main(["compare", str(tmp_path / "run"), "--out", str(tmp_path / name)]) == 0
        assert (tmp_path / name).read_bytes().startswith(magic), name
    assert train_main(["compare", str(tmp_path / "run"), "--out", str(tmp_path / "c.xyz")]) == 2
    assert ".xyz is not a figure format matplotlib writes; expected one of" in capsys.readouterr().err
    assert not (tmp_path / "c.xyz").exists()


def test_the_liNet_reads_the_stores_float16_onvs_and_float32_stays_available(tmp_path, smoke_data, monkeypatch):
    """By default a liNet is fed the store's float16 ONVs (standardised in its first layer: no float32
    copy of a batch); --onv-dtype float32 keeps the old path. Both train to similar errors."""
    from warp_vision.kernels.linet import op
    from warp_vision.nn.trained import load_net

    seen = []
    real = op.locally_connected
    monkeypatch.setattr(op, "locally_connected", lambda x, *a, **k: seen.append(x.dtype) or real(x, *a, **k))
    import warp_vision.nn.linet as nl

    monkeypatch.setattr(nl, "locally_connected", op.locally_connected)
    half = foveation.run(smoke(tmp_path / "h", smoke_data), progress=False, log=lambda *a: None)
    assert seen and seen[0] == torch.float16
    seen.clear()
    full = foveation.run(smoke(tmp_path / "f", smoke_data, onv_dtype="float32"), progress=False, log=lambda *a: None)
    assert seen[0] == torch.float32
    net, ck = load_net(tmp_path / "h" / "run")
    assert ck["net"]["onv_dtype"] == "float16" and net.backbone.layers[0].folds_input
    assert float(net.backbone.layers[0].input_std) == pytest.approx(float(ck["norm"]["input_std"]))
    assert abs(half["test_median_deg"] - full["test_median_deg"]) < 0.5, (half, full)
    with pytest.raises(ValueError, match="onv_dtype: the fc baseline reads float32"):
        smoke(tmp_path, smoke_data, model="fc", head="linear", onv_dtype="float16")


def test_miss_agreement_tells_shared_misses_from_independent_ones():
    """Designed estimates: nets A and B miss the same two balls (one on the same wrong thing, one apart);
    C misses another one; the oracle takes the best net per ball."""
    target = np.zeros((5, 2))
    far, other = [0.5, 0.0], [-0.5, 0.0]  # about 29 degrees off, on either side
    a = np.array([far, far, [0, 0], [0, 0], [0, 0]])
    b = np.array([far, other, [0, 0], [0.001, 0], [0, 0]])
    c = np.array([[0, 0], [0, 0], far, [0, 0], [0, 0]])
    r = foveation.miss_agreement(["a", "b", "c"], [a, b, c], target)
    assert r["off"] == [0.4, 0.4, 0.2] and r["n"] == 5
    ab, ac, bc = r["pairs"]
    assert (ab["a"], ab["b"]) == ("a", "b")
    assert (
        ab["both"] == 0.4
        and ab["shared"] == 1.0
        and ab["same_wrong"] == 0.2
        and ab["independent"] == pytest.approx(0.16)
    )
    assert ac["both"] == 0.0 and ac["shared"] == 0.0 and bc["same_wrong"] == 0.0
    assert r["best_of"] == 0.0  # C finds the first two, A the third
    assert foveation.miss_agreement(["a", "b"], [a, b], target)["best_of"] == 0.4
    table = foveation.agreement_table(r)
    assert (
        "| a | b | 40.0% | 40.0% | 40.0% | 16.0% | 100% | 20.0% |" in table and "oracle): 0.0% of the 5 balls" in table
    )
    with pytest.raises(ValueError, match="two or more"):
        foveation.miss_agreement(["a"], [a], target)
    with pytest.raises(ValueError, match="shaped like"):
        foveation.miss_agreement(["a", "b"], [a, b[:4]], target)


def test_evaluate_agreement_needs_runs_on_one_split(tmp_path, smoke_data, capsys):
    """A run given twice agrees with itself entirely; runs on different datasets are refused."""
    foveation.run(smoke(tmp_path, smoke_data, epochs=1), progress=False, log=lambda *a: None)
    capsys.readouterr()
    run = str(tmp_path / "run")
    assert train_main(["evaluate", run, run, "--agreement", "--split", "val"]) == 0
    out = capsys.readouterr().out
    assert "| net A | net B |" in out and "an oracle" in out
    r = foveation.evaluate_agreement([run, run], "val", log=lambda *a: None)
    assert r["pairs"][0]["both"] == r["off"][0] == r["best_of"] and r["pairs"][0]["same_wrong"] == r["off"][0]
    other = tmp_path / "other"
    foveation.run(smoke(other, tmp_path / "data_other", data_seed=1, epochs=1), progress=False, log=lambda *a: None)
    assert train_main(["evaluate", run, str(other / "run"), "--agreement"]) == 2
    assert "does not share" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train_main(["evaluate", run, "--agreement"])


@pytest.mark.parametrize("argv, refused", [
    (["--model", "cnn", "--receptive-field", "30"],
     "--receptive-field: the cnn net does not read it (the linet and fc nets do)"),
    (["--model", "linet", "--views", "8"], "--views: the linet net does not read it (the cnn net does)"),
    (["--preset", "smoke", "--channels", "32"], "--channels: the linet net does not read it"),  # smoke's model: linet
    (["--model", "conv", "--receptive-field", "9"], "--receptive-field: the conv net does not read it"),
    (["limb", "--model", "range", "--layers", "4"], "--layers: the range net does not read it"),
    (["--model", "fc", "--receptive-field", "30"], None),  # the fc twin copies the liNet of these sizes
    (["--model", "cnn", "--channels", "8", "--views", "1"], None),
    (["--preset", "smoke", "--model", "cnn"], None),  # smoke's own layers and receptive field: not given, not refused
])
def test_a_net_setting_the_model_does_not_read_is_refused(argv, refused):
    """They were dropped without a word: --model cnn --receptive-field 30 trained the cnn as if it were not there."""
    from warp_vision.train.cli import parse_training

    make = parse_training(argv)[3]
    if refused is None:
        make()
    else:
        with pytest.raises(ValueError, match=re.escape(refused)):
            make()


@pytest.mark.parametrize("kind", ["foveation", "faces"])
def test_the_data_command_builds_the_dataset_a_training_preset_reads(kind):
    """``python -m warp_vision.data foveation`` built v7's glowing-ball dataset of 4,000 ONVs and ``data faces``
    the paper's poses, whatever the run it was meant for (the default run trains on v9's 12,000, faces on
    4-degree poses): its dataset was refused by ``train --data-dir``. Now ``--preset`` (default: default) and
    the same flags give the training run's dataset."""
    from warp_vision.data.cli import config_of, parser
    from warp_vision.train.cli import parse_training

    task = [] if kind == "foveation" else [kind]
    presets = C.PRESETS if kind == "foveation" else C.FACE_PRESETS
    for preset in presets:
        built = config_of(kind, parser().parse_args([kind, "--preset", preset]))
        assert built == parse_training([*task, "--preset", preset])[3]().data_config(), preset
    assert config_of(kind, parser().parse_args([kind])) == parse_training(task)[3]().data_config()
    flags = (["--samples", "20000", "--generator",
              "8"] if kind == "foveation" else ["--identities", "7"]) + ["--eye", "right"]
    built = config_of(kind, parser().parse_args([kind, *flags, "--seed", "3"]))
    assert built == parse_training([*task, *flags, "--data-seed", "3"])[3]().data_config()


@pytest.mark.parametrize("kind", ["foveation", "faces"])
def test_the_data_commands_help_reads_by_section_and_names_each_fields_values(kind, capsys):
    """``data foveation --help`` was one block of 20 flags, and --eye, --rooms and --condition named no values
    (--condition pointed at a module's constant); a value outside them was refused only by the config."""
    from warp_vision.data.cli import parser

    with pytest.raises(SystemExit):
        parser().parse_args([kind, "--help"])
    shown = capsys.readouterr().out
    shown = shown[shown.index("\noptions:"):]  # (past the usage lines, which name every flag)
    dataset, built = shown.index("the dataset:"), shown.index("where and how it is built:")
    assert (
        dataset < shown.index("--eye {left,right}") < shown.index("--chunk-size") < built < shown.index("--shard SHARD")
    )
    if kind == "foveation":
        assert (
            "--condition {mixed,glow_dim,white,matte,distractor,arm,decoy}" in shown and "--generator {7,8,9}" in shown
        )
    else:
        assert built < shown.index("--identities-cache")
    with pytest.raises(SystemExit):
        parser().parse_args([kind, "--eye", "middle"])
    assert capsys.readouterr().err == (f"error: --eye: expected one of left, right, got 'middle' (python -m "
                                       f"warp_vision.data {kind} --help says more)\n")


def test_the_data_command_writes_where_the_training_run_looks(tmp_path, monkeypatch, capsys):
    """Its default --out is the run's dataset cache, so the run finds the dataset without --data-dir."""
    from warp_vision.data.cli import main as data_main
    from warp_vision.train.foveation import FoveationTask

    monkeypatch.chdir(tmp_path)
    assert data_main(["foveation", "--preset", "smoke", "--samples", "24", "--shard", "0/2"]) == 0
    assert "synthesis:" in capsys.readouterr().err  # its progress bar
    assert data_main(["foveation", "--preset", "smoke", "--samples", "24", "--shard", "1/2", "--no-progress"]) == 0
    cfg = resolve("smoke", {"samples": 24})
    FoveationTask.resolve_paths(cfg)
    assert ChunkedStore.open(cfg.data_dir).complete
    said = capsys.readouterr()
    assert f"{Path(cfg.data_dir).relative_to(tmp_path)}: shard 1/2 done; dataset complete" in said.out
    assert "synthesis:" not in said.err  # --no-progress, as train's and sim's
