"""Active face recognition (the paper's Section VI.B): train the two-headed liNet on face ONVs.

``python -m warp_vision.train faces [--preset smoke|default|paper] [--flag value ...]``

The run directory has the foveation run's layout (``config.json``, ``latest.pt``, ``best.pt``,
``metrics.jsonl``, ``summary.json``, ``figures/``), and ``--resume``, Ctrl-C, NaN checks and
``torchrun`` behave the same. As in the paper:

- The loss is cross-entropy(identity) + ``loss_lambda`` x MSE(pose standardised with the training set's
  mean and std), with lambda 6 and Adam (1e-3, betas 0.9/0.999), on a 70/10/20 split.
- ``best.pt`` is written only at an epoch that attains both the best validation regression loss and
  the best validation accuracy so far (ties count).
- The run stops early after ``patience`` (30) epochs in which neither metric reaches a new best.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from warp_vision.train.config import FaceTrainConfig, asdict
from warp_vision.train.loop import (
    NonFiniteLoss,
    _Dist,
    _Interrupt,
    load_best,
    open_run,
    input_stats,
    net_input,
    peak_rss_mib,
    pick_device,
    record_epoch,
)


def dataset_dir(cfg: FaceTrainConfig) -> Path:
    return Path(cfg.data_dir) if cfg.data_dir else Path("runs/datasets") / f"faces-{cfg.data_config().key()}"


def splits(n: int, cfg: FaceTrainConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(train, val, test) sample indices: a fixed permutation of the dataset (seeded by data_seed)."""
    perm = np.random.default_rng([cfg.data_seed, 7919]).permutation(n)
    n_test = max(1, int(round(n * cfg.test_fraction)))
    n_val = max(1, int(round(n * cfg.val_fraction)))
    return perm[n_test + n_val :], perm[n_test : n_test + n_val], perm[:n_test]


def load_data(cfg: FaceTrainConfig, dd, progress: bool, log):
    from warp_vision.data.faces import synthesize
    from warp_vision.data.store import ChunkedStore
    from warp_vision.eye.retina import Retina

    ddir = dataset_dir(cfg)
    synthesize(ddir, cfg.data_config(), shard=(dd.rank, dd.world), progress=progress and dd.rank == 0, log=log,
               identities_path=cfg.identities_cache or None)
    dd.barrier()
    data = ChunkedStore.open(ddir).load(["onv", "identity", "pose"])
    return (torch.from_numpy(data["onv"]), torch.from_numpy(data["identity"]), torch.from_numpy(data["pose"]),
            Retina.load(ddir / "retina.npz"), ddir)


def build_model(cfg: FaceTrainConfig, retina, device: str):
    from warp_vision.nn.connectivity import onv_positions
    from warp_vision.nn.heads import afr_net

    return afr_net(onv_positions(retina.domain_xy), cfg.identities, cfg.layers, cfg.receptive_field, cfg.reduction,
                   cfg.seed, cfg.model).to(device)


def evaluate_model(model, onv16, ident, pose, idx, norm, device, lam: float, batch: int = 256) -> dict:
    """Losses, accuracy and pose errors of ``model`` on samples ``idx``, and its predictions."""
    model.eval()
    logits, z = [], []
    with torch.no_grad():
        for s in range(0, len(idx), batch):
            i = torch.as_tensor(idx[s : s + batch])
            a, b = model(net_input(onv16[i], norm, device))
            logits.append(a.cpu())
            z.append(b.cpu())
    model.train()
    i = torch.as_tensor(idx)
    logits, z = torch.cat(logits), torch.cat(z)
    zt = (pose[i] - norm["pose_mean"]) / norm["pose_std"]
    ce = float(F.cross_entropy(logits, ident[i]))
    mse = float(F.mse_loss(z, zt))
    pred_pose = z * norm["pose_std"] + norm["pose_mean"]
    err = (pred_pose - pose[i]).abs()
    pred_id = logits.argmax(1)
    return {
        "ce": ce,
        "mse": mse,
        "loss": ce + lam * mse,
        "accuracy": float((pred_id == ident[i]).float().mean()),
        "pose_mae_deg": float(err.mean()),
        "yaw_mae_deg": float(err[:, 0].mean()),
        "pitch_mae_deg": float(err[:, 1].mean()),
        "pred_identity": pred_id,
        "pred_pose": pred_pose,
    }


def _shuffled_labels(ident, pose, tr, seed: int):
    """Copies of the labels whose training entries are permuted among the training ONVs (val/test keep theirs)."""
    ident, pose = ident.clone(), pose.clone()
    src = torch.as_tensor(np.random.default_rng([seed, 104729]).permutation(tr))
    t = torch.as_tensor(tr)
    ident[t], pose[t] = ident[src], pose[src]
    return ident, pose


def run(cfg: FaceTrainConfig | None = None, resume: str | None = None, progress: bool = True, log=print,
        stop_after_epoch: int | None = None, overwrite: bool = False, epochs: int | None = None) -> dict:
    """Train (or resume) an AFR run; returns the summary (also written to summary.json). ``epochs``
    gives a resumed run a new epoch cap (the epochs already done: end it now, evaluated)."""
    from tqdm import tqdm

    cfg, out = open_run(FaceTrainConfig, cfg, resume, overwrite, epochs)
    device = pick_device(cfg.device)
    dd = _Dist(device)
    say = log if dd.rank == 0 else (lambda *a, **k: None)
    if dd.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(asdict(cfg), indent=2))
    t_start = time.perf_counter()
    onv16, ident, pose, retina, ddir = load_data(cfg, dd, progress, say)
    t_data = time.perf_counter() - t_start
    tr, va, te = splits(len(ident), cfg)
    scale = float(onv16[torch.as_tensor(tr[: min(len(tr), 2000)])].float().mean().clamp_min(1e-12))
    in_mean, in_std = input_stats(onv16, tr, scale)
    t = torch.as_tensor(tr)
    norm = {"input_scale": scale, "input_mean": in_mean, "input_std": in_std,
            "pose_mean": pose[t].mean(0), "pose_std": pose[t].std(0).clamp_min(1e-6)}
    model = build_model(cfg, retina, device)
    model.set_pose_norm(norm["pose_mean"], norm["pose_std"])
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, betas=(0.9, 0.999))
    start_epoch, history, best_mse, best_acc, bad, best_epoch = 0, [], math.inf, -math.inf, 0, None
    if resume:
        ck = torch.load(out / "latest.pt", weights_only=True, map_location=device)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start_epoch, history, bad = ck["epoch"] + 1, ck["history"], ck["bad_epochs"]
        best_mse, best_acc, best_epoch = ck["best_mse"], ck["best_acc"], ck["best_epoch"]
        norm = {k: (v.cpu() if torch.is_tensor(v) else v) for k, v in ck["norm"].items()}
        say(f"resuming {out} after epoch {ck['epoch']}")
    net = torch.nn.parallel.DistributedDataParallel(model) if dd.on else model
    n_params = sum(p.numel() for p in model.parameters())
    say(f"AFR {cfg.model}: {n_params:,} parameters, layers {getattr(model.backbone, 'layer_sizes', '?')}; "
        f"{cfg.identities} identities, {len(tr):,} train / {len(va):,} val / {len(te):,} test ONVs; device {device}"
        f"{'; TRAINING LABELS SHUFFLED (sanity check)' if cfg.shuffle_labels else ''}")
    lab_id, lab_pose = _shuffled_labels(ident, pose, tr, cfg.seed) if cfg.shuffle_labels else (ident, pose)
    z_all = (lab_pose - norm["pose_mean"]) / norm["pose_std"]

    def checkpoint(epoch):
        return {"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch, "history": history,
                "best_mse": best_mse, "best_acc": best_acc, "best_epoch": best_epoch, "bad_epochs": bad,
                "norm": norm, "config": asdict(cfg)}

    stopped = "max epochs"
    try:
        for epoch in range(start_epoch, cfg.epochs):
            t0 = time.perf_counter()
            perm = np.random.default_rng([cfg.seed, epoch]).permutation(tr)
            sums = np.zeros(3)
            count = 0
            bar = tqdm(range(0, len(perm), cfg.batch), desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="batch",
                       disable=not progress or dd.rank != 0, dynamic_ncols=True, leave=False)
            for s in bar:
                idx = torch.as_tensor(perm[s : s + cfg.batch])[dd.rank :: dd.world]
                logits, z = net(net_input(onv16[idx], norm, device))
                ce = F.cross_entropy(logits, lab_id[idx].to(device))
                mse = F.mse_loss(z, z_all[idx].to(device))
                loss = ce + cfg.loss_lambda * mse
                if not torch.isfinite(loss):
                    raise NonFiniteLoss(f"epoch {epoch + 1}, step {s // cfg.batch}: the loss is {loss.item()}; stopping. "
                                        f"The last good checkpoint ({out / 'latest.pt'}) is untouched; try a lower --lr.")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                n = len(idx)
                sums += n * np.array([ce.item(), mse.item(), (logits.detach().argmax(1).cpu() == lab_id[idx]).float().mean().item()])
                count += n
                bar.set_postfix(ce=f"{sums[0] / count:.3f}", mse=f"{sums[1] / count:.3f}")
            tr_ce, tr_mse, tr_acc = (float(dd.all_mean(float(x) / max(count, 1))) for x in sums)
            ev = evaluate_model(model, onv16, ident, pose, va, norm, device, cfg.loss_lambda)
            new_mse, new_acc = ev["mse"] <= best_mse, ev["accuracy"] >= best_acc
            improved = (ev["mse"] < best_mse) or (ev["accuracy"] > best_acc)
            best_mse, best_acc = min(best_mse, ev["mse"]), max(best_acc, ev["accuracy"])
            save_best = new_mse and new_acc
            if save_best:
                best_epoch = epoch
            bad = 0 if improved else bad + 1
            row = {"epoch": epoch + 1, "train_ce": tr_ce, "train_mse": tr_mse, "train_accuracy": tr_acc,
                   "val_ce": ev["ce"], "val_mse": ev["mse"], "val_accuracy": ev["accuracy"],
                   "val_pose_mae_deg": ev["pose_mae_deg"], "saved_best": save_best, "seconds": time.perf_counter() - t0}
            history.append(row)
            if dd.rank == 0:
                record_epoch(out, row, checkpoint(epoch), save_best)
                say(f"epoch {epoch + 1:3d}: train CE {tr_ce:.3f} MSE {tr_mse:.4f} acc {tr_acc:.3f} | val CE {ev['ce']:.3f} "
                    f"MSE {ev['mse']:.4f} acc {ev['accuracy']:.3f} pose MAE {ev['pose_mae_deg']:.2f} deg "
                    f"({row['seconds']:.1f} s){'  *' if save_best else ''}")
            if stop_after_epoch is not None and epoch + 1 >= stop_after_epoch:
                raise _Interrupt()
            if bad >= cfg.patience:
                stopped = f"early stop: neither validation metric improved for {cfg.patience} epochs"
                break
    except (KeyboardInterrupt, _Interrupt):
        say(f"interrupted: {out / 'latest.pt'} holds the last finished epoch; continue with --resume {out}")
        if stop_after_epoch is None:
            raise
        return {"interrupted": True}
    say(stopped)
    summary = {}
    if dd.rank == 0:
        best = torch.load(out / "best.pt", weights_only=True, map_location=device)
        model.load_state_dict(best["model"])
        test = evaluate_model(model, onv16, ident, pose, te, norm, device, cfg.loss_lambda)
        from warp_vision.data.faces import FaceIdentities

        nn_mm = FaceIdentities.load(ddir / "identities.npz").nearest_neighbour_mm()
        summary = {
            "task": "faces",
            "model": cfg.model,
            "shuffle_labels": cfg.shuffle_labels,
            "parameters": n_params,
            "identities": cfg.identities,
            "onvs": len(ident),
            "epochs": len(history),
            "stopped": stopped,
            "best_epoch": int(best["epoch"]) + 1,
            "test_accuracy": test["accuracy"],
            "chance_accuracy": 1.0 / cfg.identities,
            "test_pose_mae_deg": test["pose_mae_deg"],
            "test_yaw_mae_deg": test["yaw_mae_deg"],
            "test_pitch_mae_deg": test["pitch_mae_deg"],
            "test_ce": test["ce"],
            "test_mse": test["mse"],
            "identity_nearest_neighbour_mm": {"min": float(nn_mm.min()), "median": float(np.median(nn_mm))},
            "seconds_data": t_data,
            "seconds_total": time.perf_counter() - t_start,
            "seconds_per_epoch": float(np.median([h["seconds"] for h in history])) if history else None,
            "peak_rss_mib": peak_rss_mib(),
            "dataset": str(ddir),
        }
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        from warp_vision.train.figures import write_face_figures

        write_face_figures(out, history, retina, onv16, ident, pose, te, test, cfg)
        say(f"test: accuracy {100 * test['accuracy']:.2f}% (chance {100 / cfg.identities:.1f}%), pose MAE "
            f"{test['pose_mae_deg']:.2f} deg (yaw {test['yaw_mae_deg']:.2f}, pitch {test['pitch_mae_deg']:.2f}); "
            f"figures in {out / 'figures'}")
    dd.barrier()
    return summary


def evaluate_run(run_dir: str, split: str = "test", log=print) -> dict:
    """Re-evaluate an AFR run's best checkpoint on one of its splits; prints accuracy and pose error."""
    from warp_vision.data.store import ChunkedStore
    from warp_vision.eye.retina import Retina

    ck, cfg = load_best(run_dir, FaceTrainConfig)
    ddir = dataset_dir(cfg)
    data = ChunkedStore.open(ddir).load(["onv", "identity", "pose"])
    onv16, ident, pose = (torch.from_numpy(data[k]) for k in ("onv", "identity", "pose"))
    tr, va, te = splits(len(ident), cfg)
    idx = {"test": te, "val": va, "train": tr}[split]
    device = pick_device(cfg.device)
    model = build_model(cfg, Retina.load(ddir / "retina.npz"), device)
    model.load_state_dict(ck["model"])
    ev = evaluate_model(model, onv16, ident, pose, idx, ck["norm"], device, cfg.loss_lambda)
    log(f"{run_dir} ({split}, {len(idx):,} ONVs): identity accuracy {100 * ev['accuracy']:.2f}%; pose mean absolute "
        f"error {ev['pose_mae_deg']:.3f} deg (yaw {ev['yaw_mae_deg']:.3f}, pitch {ev['pitch_mae_deg']:.3f})")
    return {k: v for k, v in ev.items() if not torch.is_tensor(v)}
