"""How well limb vision sees: its errors against the truth, for training summaries, the interception's
frames and the held-out ONVs (the data and the perceptions themselves: :mod:`warp_vision.sim.limb`)."""

from __future__ import annotations

import numpy as np
import torch

from warp_vision.data.store import ChunkedStore, IncompleteStoreError, MissingStoreError
from warp_vision.frames import gaze_direction
from warp_vision.sim.limb import NEAR_M, LimbDataConfig, Poser, ball_in_eye

#: m: the distance bins of the summary
BINS_M = (0.0, 0.2, 0.4, 0.6, 1.0, 2.0, 4.0)
#: m: the ranging summary's bins of the eye-ball distance
RANGE_BINS_M = (0.0, 0.5, 1.0, 2.0, 4.0)


def discrepancy_errors(pred: np.ndarray, true: np.ndarray) -> dict:
    """Errors of predicted discrepancies [N, 6] (m) against the true ones: per arm-sample pair, |pred -
    true| and the true distance |true|. The near metrics (``near_*``) take the pairs within
    :data:`NEAR_M`; ``by_distance`` the median error per bin of :data:`BINS_M`."""
    p, t = np.asarray(pred, float).reshape(-1, 3), np.asarray(true, float).reshape(-1, 3)
    err = np.linalg.norm(p - t, axis=1)
    dist = np.linalg.norm(t, axis=1)
    near = dist < NEAR_M
    nan = float("nan")
    out = {"near_pairs": int(near.sum()),
           "near_median_cm": float(np.median(err[near]) * 100) if near.any() else nan,
           "near_p90_cm": float(np.percentile(err[near], 90) * 100) if near.any() else nan,
           "near_median_relative": float(np.median(err[near] / dist[near])) if near.any() else nan,
           "all_median_cm": float(np.median(err) * 100) if len(err) else nan,
           "all_median_relative": float(np.median(err / np.maximum(dist, 1e-6))) if len(err) else nan}
    out["by_distance"] = {f"{lo:g}-{hi:g} m": {"pairs": int(((dist >= lo) & (dist < hi)).sum()),
                                               "median_cm": float(np.median(err[(dist >= lo) & (dist < hi)]) * 100)
                                               if ((dist >= lo) & (dist < hi)).any() else None}
                          for lo, hi in zip(BINS_M, BINS_M[1:])}
    return out


def range_errors(pred_log: np.ndarray, true_log: np.ndarray, hand_m: np.ndarray) -> dict:
    """Errors of predicted eye-ball distances (log m, [N]) against the true ones: relative (pred / true -
    1) and absolute (cm), overall, by :data:`RANGE_BINS_M`, and for the balls within :data:`NEAR_M` of a
    hand (``hand_m`` [N]: the nearer hand's distance to the ball, m): the discrepancy's error along the
    line of sight."""
    p, t = np.asarray(pred_log, float).ravel(), np.asarray(true_log, float).ravel()
    rel = np.exp(p - t) - 1.0
    cm = np.abs(np.exp(p) - np.exp(t)) * 100
    dist, near = np.exp(t), np.asarray(hand_m, float).ravel() < NEAR_M
    nan = float("nan")

    def stats(m):
        return {"n": int(m.sum()), "median_relative": float(np.median(np.abs(rel[m]))) if m.any() else nan,
                "p90_relative": float(np.percentile(np.abs(rel[m]), 90)) if m.any() else nan,
                "bias_relative": float(np.median(rel[m])) if m.any() else nan,
                "median_cm": float(np.median(cm[m])) if m.any() else nan}

    every = np.ones(len(t), bool)
    out = {"depth_" + k: v for k, v in stats(every).items()}
    out["near_hand"] = stats(near)
    out["by_distance"] = {f"{lo:g}-{hi:g} m": stats((dist >= lo) & (dist < hi)) for lo,
                          hi in zip(RANGE_BINS_M, RANGE_BINS_M[1:])}
    return out


def frame_errors(log, shot, until: float) -> list:
    """Per visual frame of one shot before ``until`` s (its first contact): (true ball-hand distance m,
    |estimated - true ball| m, |estimated - true| ball-hand distance m), against the shot's ballistic path;
    ``log``: a :class:`BallisticPerception`'s log entries of that shot."""
    from warp_vision.sim.intercept import ballistic_path

    out = []
    for t, p, _per_eye, hand in log:
        if t >= until:
            continue
        ball = ballistic_path(shot.muzzle, shot.launch_velocity, [t])[0]
        true = float(np.linalg.norm(ball - hand))
        out.append((true, float(np.linalg.norm(p - ball)), abs(float(np.linalg.norm(p - hand)) - true)))
    return out


def frame_error_summary(rows: list, near_m: float = NEAR_M) -> dict:
    """Medians and 90th percentiles (cm) of :func:`frame_errors` rows: all frames, and the frames whose
    ball is within ``near_m`` of the hand (the limb vision goal's range)."""
    a = np.asarray(rows, float).reshape(-1, 3)

    def part(m):
        if not m.any():
            return {"frames": 0, "median_cm": None, "p90_cm": None, "median_relative": None}
        return {"frames": int(m.sum()), "median_cm": float(np.median(a[m, 1]) * 100),
                "p90_cm": float(np.percentile(a[m, 1], 90) * 100),
                "median_relative": float(np.median(a[m, 1] / np.maximum(a[m, 0], 1e-6)))}

    return {"all": part(np.ones(len(a), bool)), "near": part(a[:, 0] < near_m), "near_m": near_m}


def heldout_limb_vision_errors(limb_run: str, foveation, progress: bool = False) -> dict:
    """The limb vision of the loop on the held-out ONVs of ``limb_run`` (a ranging run of ``python -m
    warp_vision.train limb``): for each held-out sample whose ball ``foveation`` (the eye's
    :class:`warp_vision.sim.loop.Foveator`) sees within the ranging gate, the ball where the foveation
    net's direction and the ranging net's distance put it, minus each hand at its true place
    (proprioception), against the true discrepancies: :func:`discrepancy_errors`
    (cm, near = balls within :data:`NEAR_M` of the hand), and the share of samples seen within the gate."""
    import json as _json
    from pathlib import Path

    from tqdm import tqdm

    from warp_vision.nn.retina_cnn import RANGE_GATE_DEG
    from warp_vision.nn.trained import load_net, predict_targets

    net, ck = load_net(limb_run)
    if ck["net"].get("model") != "range":
        raise ValueError(f"{limb_run}: expected a ranging limb vision run (--model range), got "
                         f"{ck['net'].get('model')!r}")
    summary = _json.loads((Path(limb_run) / "summary.json").read_text())
    again = f"python -m warp_vision.train evaluate {limb_run}"  # (renders the run's datasets where they are not whole)
    try:
        store = ChunkedStore.open(summary["heldout_dataset"])
        d = store.load(["onv", "target"])
    except MissingStoreError as e:
        raise ValueError(f"{e.root}: the held-out dataset of {limb_run} is gone; {again} renders it again") from None
    except IncompleteStoreError as e:
        raise e.finished_by(again) from None
    cfg = LimbDataConfig.from_manifest(store.manifest["config"])
    onv = torch.from_numpy(d["onv"])
    direction = foveation(onv)  # [N, 2] yaw, pitch
    u = np.stack([gaze_direction(*a) for a in direction])
    seen = np.degrees(np.arccos(np.clip(u[:, 2], -1.0, 1.0))) <= RANGE_GATE_DEG
    idx = np.flatnonzero(seen)
    dist = np.exp(predict_targets(net, onv[torch.as_tensor(idx)], ck["norm"], "cpu").numpy()[:, 0])
    poser = Poser()
    true_ball = np.stack([ball_in_eye(cfg, int(i), poser)
                          for i in tqdm(idx, desc="held-out balls", disable=not progress)])
    est_ball = dist[:, None] * u[idx]
    target = d["target"][idx].astype(np.float64)  # ball - hand, each arm, eye frame
    pred = target + np.tile(est_ball - true_ball, 2)  # the hands at their true places
    return {"samples": int(len(onv)), "seen_within_gate": int(len(idx)), **discrepancy_errors(pred, target),
            "ball_median_cm": float(np.median(np.linalg.norm(est_ball - true_ball, axis=1)) * 100)}
