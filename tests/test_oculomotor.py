"""The oculomotor task on the training harness: data the body solves for itself, a net trained on it, and
its accuracy measured on the body."""

import json

import numpy as np
import pytest
import torch

from warp_vision.body import Body, BodyConfig
from warp_vision.nn.trained import build_net, load_net, run_identity, seal
from warp_vision.sim.oculomotor import (
    HOLDING_VERSION,
    HoldingDataConfig,
    evaluate_on_body,
    load_oculomotor,
    transition_pairs,
)
from warp_vision.train import oculomotor
from warp_vision.train.config import resolve
from warp_vision.train.config_body import OCULOMOTOR_PRESETS, OculomotorTrainConfig
from warp_vision.train.rundir import run_config, save_checkpoint


def cfg_for(tmp_path, **kw):
    return resolve("default", {"out": str(tmp_path / "left"), "data_dir": str(tmp_path / "data"), "gazes": 400,
                               "transitions": 20_000, "epochs": 15, "seed": 3, "body_checks": 20, **kw},
                   OculomotorTrainConfig, OCULOMOTOR_PRESETS)


def test_transition_pairs_mix_saccades_corrections_and_holds():
    rng = np.random.default_rng(0)
    gaze = np.radians(rng.uniform(-30, 30, size=(500, 2)))
    idx = np.arange(400)
    i, j = transition_pairs(idx, 5000, rng, gaze)
    assert set(i) <= set(idx) and set(j) <= set(idx)
    step = np.degrees(np.linalg.norm(gaze[j] - gaze[i], axis=1))
    assert 0.07 < np.mean(step == 0) < 0.3  # a tenth stay put (plus near moves that drew the same gaze)
    assert 0.2 < np.mean((step > 0) & (step <= 3.0)) < 0.45  # most of the 36% small corrections
    assert np.mean(step > 3.0) > 0.4  # the rest saccades


def test_holding_config_is_validated_and_keyed():
    assert HoldingDataConfig().key() != HoldingDataConfig(eye="right").key()
    for bad in (dict(eye="middle"), dict(gazes=1), dict(max_gaze_deg=90)):
        try:
            HoldingDataConfig(**bad).validate()
        except ValueError:
            continue
        raise AssertionError(f"accepted {bad}")


def test_oculomotor_net_learns_the_inverse(tmp_path):
    """A small oculomotor net trained on the body's own holding activations, through the harness, drives
    the eye near the gaze asked for on held-out transitions, also when it is applied to its own output step
    after step; the same net untrained does not. The simulation loads it without the training code."""
    summary = oculomotor.run(cfg_for(tmp_path), progress=False, log=lambda *a: None)
    run = tmp_path / "left"
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 15 and rows[-1]["train_loss"] < rows[0]["train_loss"]
    assert summary["test_activation_rmse"] < 0.05 and summary["gaze_error_deg_median"] < 3.0, summary
    assert summary["pursuit_chain_error_deg_median"] < 5.0, summary  # 30 steps of 0.5 deg: a 15 deg path
    net, ck = load_net(run)
    task = oculomotor.OculomotorTask(run_config(oculomotor.OculomotorTask, run, ck), log=lambda *a: None)
    task.load((0, 1), progress=False, synthesize=False)
    task.splits()
    body = Body(BodyConfig(arms=False))
    ev = evaluate_on_body(net, body, "left", task.gaze_np, task.act_np, task.test_gazes, n=20)
    assert ev["gaze_error_deg_median"] == summary["gaze_error_deg_median"]  # the same checks as the run's
    untrained = build_net(ck["net"]).eval()
    bad = evaluate_on_body(untrained, body, "left", task.gaze_np, task.act_np, task.test_gazes, n=20)
    assert bad["gaze_error_deg_median"] > 2 * ev["gaze_error_deg_median"], (bad, ev)
    # the left eye's run given as the right eye's is refused
    (tmp_path / "right").symlink_to(run)
    with pytest.raises(ValueError, match="belongs to the left eye's oculomotor run .* not to the right eye's"):
        load_oculomotor(tmp_path)
    # the simulation's loader finds both eyes' runs under one root (the right one: the same weights, as its run)
    (tmp_path / "right").unlink()
    right = tmp_path / "right"
    right.mkdir()
    config = {**json.loads((run / "config.json").read_text()), "eye": "right", "out": str(right)}
    (right / "config.json").write_text(json.dumps(config))
    mirrored = {k: v for k, v in ck.items() if k != "integrity"}
    mirrored["config"] = {**ck["config"], "eye": "right"}
    mirrored["binding"] = {**ck["binding"], **run_identity("oculomotor", config)}
    save_checkpoint(mirrored, right / "best.pt")
    nets = load_oculomotor(tmp_path)
    x = (torch.zeros(1, 2), torch.full((1, 6), 0.2))
    assert torch.equal(nets["left"](*x), net(*x))
    # a net of an older eye plant's holding data is refused, naming the command that retrains it
    assert ck["data"]["generator_version"] == HOLDING_VERSION
    ck["data"]["generator_version"] = HOLDING_VERSION - 1
    torch.save(seal({k: v for k, v in ck.items() if k != "integrity"}), run / "best.pt")
    with pytest.raises(ValueError, match="retrain it: python -m warp_vision.train oculomotor --eye left"):
        load_oculomotor(tmp_path)
