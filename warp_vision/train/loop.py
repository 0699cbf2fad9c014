"""The foveation training run: data, model, epochs, checkpoints, metrics, early stopping, DDP.

A run directory holds ``config.json``, ``latest.pt`` and ``best.pt`` (atomic writes; plain tensors and
numbers, so ``torch.load(path, weights_only=True)`` reads them), ``metrics.jsonl`` (one line per
epoch), ``summary.json`` and ``figures/``. Everything random derives from the config's seeds (the
epoch's shuffle from (seed, epoch)), so ``--resume`` continues a stopped run exactly.

Under ``torchrun --nproc-per-node N`` the same code trains with DistributedDataParallel (gloo on CPU,
nccl on CUDA): the ranks build disjoint shards of the dataset, then each takes 1/N of every batch;
only rank 0 writes files.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from warp_vision.train.config import TrainConfig, asdict


class NonFiniteLoss(RuntimeError):
    """The loss became NaN or infinite; the last good checkpoint is left as it was."""


class _Interrupt(Exception):
    """Raised by the test hook ``stop_after_epoch`` to simulate Ctrl-C at an epoch boundary."""


# --------------------------------------------------------------------------------------------------
# small utilities


def save_atomic(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def directions(yaw_pitch: torch.Tensor) -> torch.Tensor:
    """[N, 2] (yaw, pitch) radians -> unit gaze directions [N, 3] in the eye frame."""
    y, p = yaw_pitch[:, 0], yaw_pitch[:, 1]
    return torch.stack([torch.cos(p) * torch.sin(y), torch.sin(p), torch.cos(p) * torch.cos(y)], dim=1)


def angular_error_deg(pred: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """Angle (degrees) between the gaze directions of predicted and true (yaw, pitch) [N, 2]."""
    c = (directions(pred.double()) * directions(true.double())).sum(1).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(c)).float()


def net_input(onv: torch.Tensor, norm: dict, device) -> torch.Tensor:
    """What the net sees: a compressive (log) photoreceptor response, log(1 + irradiance / scale) with the
    scale the training set's mean irradiance (it keeps dim scenes and a lamp's hot spot in one range),
    standardised with the training set's mean and std over all inputs. One mean and std for every input
    keeps "brighter" meaning the same everywhere on the retina; standardising each input on its own
    (tried) turns a rarely lit peripheral photoreceptor's noise into large values, and the brightest
    standardised input then lies on the ball in 72% of the samples against 98% for the log response."""
    x = torch.log1p(onv.to(device=device, dtype=torch.float32) / norm["input_scale"])
    return (x - norm["input_mean"].to(device)) / norm["input_std"].to(device)


def input_stats(onv16: torch.Tensor, idx, scale: float, limit: int = 2000) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and std (0-d tensors) of log(1 + onv / scale) over all inputs of (at most ``limit`` of) the
    samples ``idx``."""
    x = torch.log1p(onv16[torch.as_tensor(idx[:limit])].float() / scale)
    return x.mean(), x.std().clamp_min(1e-6)


def peak_rss_mib() -> float:
    """This process's peak resident memory (MiB) so far: dataset, model, activations and all."""
    import resource
    import sys

    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 1024


def open_run(cls, cfg, resume: str | None, overwrite: bool, epochs: int | None = None):
    """(validated config, output directory) of the run to resume (its config.json read as ``cls``) or
    of the new run ``cfg`` (refusing an --out that holds a run unless ``overwrite``).

    ``epochs`` (resume only) changes the resumed run's epoch cap: more to extend it, or the epochs
    already done to end it now (the best checkpoint is then evaluated and the figures written).
    """
    if resume:
        out = Path(resume)
        if not (out / "latest.pt").exists():
            raise FileNotFoundError(f"--resume {resume}: no latest.pt there to resume from")
        cfg = cls(**json.loads((out / "config.json").read_text()))
        if epochs is not None:
            cfg.epochs = epochs
    elif epochs is not None:
        raise ValueError("epochs: only a resumed run takes a new epoch cap; set it in the config otherwise")
    elif cfg is None:
        raise ValueError("run: give a config or a run directory to resume")
    else:
        out = Path(cfg.out)
        claim_out_dir(out, overwrite)
    cfg.validate()
    return cfg, out


def load_best(run_dir: str, cls):
    """(best.pt's contents, its config as ``cls``) of a finished run directory."""
    out = Path(run_dir)
    if not (out / "best.pt").exists():
        raise FileNotFoundError(f"{run_dir}: no best.pt (is this a training run directory?)")
    ck = torch.load(out / "best.pt", weights_only=True)
    return ck, cls(**ck["config"])


def record_epoch(out: Path, row: dict, checkpoint: dict, best: bool) -> None:
    """Append the epoch's metrics row and write latest.pt (and best.pt when ``best``), atomically."""
    with open(out / "metrics.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")
    save_atomic(checkpoint, out / "latest.pt")
    if best:
        save_atomic(checkpoint, out / "best.pt")


def claim_out_dir(out: Path, overwrite: bool) -> None:
    """Refuse to start a new run in a directory that holds one (its metrics or checkpoints), unless
    ``overwrite``: then delete them (rank 0)."""
    old = [out / n for n in ("metrics.jsonl", "latest.pt", "best.pt", "summary.json")]
    if any(f.exists() for f in old):
        if not overwrite:
            raise ValueError(f"--out {out} already holds a run; continue it with --resume {out}, "
                             f"choose another --out, or pass --overwrite to replace it")
        if int(os.environ.get("RANK", "0")) == 0:
            for f in old:
                f.unlink(missing_ok=True)


def pick_device(name: str) -> str:
    if name == "auto":
        from warp_vision.kernels.launch import available_devices

        return "cuda:0" if "cuda:0" in available_devices() else "cpu"
    if name == "cuda":
        return "cuda:0"
    return name


def dataset_dir(cfg: TrainConfig) -> Path:
    return Path(cfg.data_dir) if cfg.data_dir else Path("runs/datasets") / f"foveation-{cfg.data_config().key()}"


def splits(n: int, cfg: TrainConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(train, val, test) sample indices: a fixed permutation of the dataset (seeded by data_seed)."""
    perm = np.random.default_rng([cfg.data_seed, 7919]).permutation(n)
    n_test = int(round(n * cfg.test_fraction))
    n_val = max(1, int(round(n * cfg.val_fraction)))
    return perm[n_test + n_val :], perm[n_test : n_test + n_val], perm[:n_test]


class _Dist:
    def __init__(self, device: str):
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        self.on = self.world > 1
        if self.on and not dist.is_initialized():
            dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")

    def barrier(self):
        if self.on:
            dist.barrier()

    def all_mean(self, x: float) -> float:
        if not self.on:
            return x
        t = torch.tensor([x], dtype=torch.float64)
        dist.all_reduce(t)
        return float(t.item()) / self.world


# --------------------------------------------------------------------------------------------------
# the run


def load_data(cfg: TrainConfig, dd: _Dist, progress: bool, log):
    from warp_vision.data.foveation import synthesize
    from warp_vision.data.store import ChunkedStore
    from warp_vision.eye.retina import Retina

    ddir = dataset_dir(cfg)
    synthesize(ddir, cfg.data_config(), shard=(dd.rank, dd.world), progress=progress and dd.rank == 0, log=log)
    dd.barrier()
    store = ChunkedStore.open(ddir)
    data = store.load(["onv", "target"])
    return torch.from_numpy(data["onv"]), torch.from_numpy(data["target"]), Retina.load(ddir / "retina.npz"), ddir


def train_loss(kind: str, pred: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """The training loss on standardised targets: "mse" (the paper's) or "huber" (quadratic within
    HUBER_DELTA of the target, linear beyond: a few balls too small or too hidden to localise do not
    dominate the gradient and the choice of the best epoch)."""
    if kind == "mse":
        return torch.nn.functional.mse_loss(pred, y)
    return torch.nn.functional.huber_loss(pred, y, delta=HUBER_DELTA)


#: lr_schedule "plateau": the rate is multiplied by PLATEAU_FACTOR after every PLATEAU_EPOCHS epochs
#: without a better validation loss.
PLATEAU_EPOCHS = 3
PLATEAU_FACTOR = 0.3
#: Huber loss threshold in standardised target units (the targets' std is about 20 degrees, so ~2 degrees).
HUBER_DELTA = 0.1


def evaluate_model(model, onv16, target, idx, norm, device, batch: int = 256, loss: str = "mse") -> dict:
    """Standardised MSE, the training ``loss`` and angular errors (deg) of ``model`` on samples ``idx``;
    also the predictions."""
    model.eval()
    preds = []
    with torch.no_grad():
        for s in range(0, len(idx), batch):
            i = torch.as_tensor(idx[s : s + batch])
            x = net_input(onv16[i], norm, device)
            preds.append(model(x).cpu())
    model.train()
    z = torch.cat(preds) if preds else torch.zeros(0, 2)
    zt = (target[torch.as_tensor(idx)] - norm["target_mean"]) / norm["target_std"]
    pred = z * norm["target_std"] + norm["target_mean"]
    err = angular_error_deg(pred, target[torch.as_tensor(idx)])
    return {
        "mse": float(((z - zt) ** 2).mean()) if len(idx) else float("nan"),
        "loss": float(train_loss(loss, z, zt)) if len(idx) else float("nan"),
        "median_deg": float(err.median()) if len(idx) else float("nan"),
        "p90_deg": float(torch.quantile(err, 0.9)) if len(idx) else float("nan"),
        "pred": pred,
        "err_deg": err,
    }


def build_model(cfg: TrainConfig, retina, device: str):
    """The run's net (liNet or FC baseline, cfg.head read-out) on the retina's photoreceptor positions,
    initialised from cfg.seed."""
    from warp_vision.data.foveation import make_eye
    from warp_vision.nn.connectivity import onv_positions
    from warp_vision.nn.heads import foveation_net

    angles = None
    if cfg.head_kind() == "softargmax":
        angles = np.repeat(retina.visual_angles(make_eye(cfg.data_config())), 3, axis=0)
    return foveation_net(cfg.model, onv_positions(retina.domain_xy), cfg.layers, cfg.receptive_field, cfg.reduction,
                         cfg.seed, head=cfg.head_kind(), input_angles=angles).to(device)


def run(cfg: TrainConfig | None = None, resume: str | None = None, progress: bool = True, log=print,
        stop_after_epoch: int | None = None, overwrite: bool = False, epochs: int | None = None) -> dict:
    """Train (or resume) a foveation run; returns the summary dict (also written to summary.json).

    A new run refuses an output directory that already holds a run (its metrics or checkpoints) unless
    ``overwrite``, which deletes them first. ``epochs`` gives a resumed run a new epoch cap (see
    :func:`open_run`; a cosine learning-rate schedule then spans the new count)."""
    from tqdm import tqdm

    cfg, out = open_run(TrainConfig, cfg, resume, overwrite, epochs)
    device = pick_device(cfg.device)
    dd = _Dist(device)
    if dd.on and "WARP_VISION_THREADS" not in os.environ:
        os.environ["WARP_VISION_THREADS"] = str(max(1, (os.cpu_count() or 1) // dd.world))
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // dd.world))
    say = log if dd.rank == 0 else (lambda *a, **k: None)
    if dd.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.json").write_text(json.dumps(asdict(cfg), indent=2))
    t_start = time.perf_counter()
    onv16, target, retina, ddir = load_data(cfg, dd, progress, say)
    t_data = time.perf_counter() - t_start
    tr, va, te = splits(len(target), cfg)
    scale = float(onv16[torch.as_tensor(tr[: min(len(tr), 2000)])].float().mean().clamp_min(1e-12))
    in_mean, in_std = input_stats(onv16, tr, scale)
    norm = {
        "input_scale": scale,
        "input_mean": in_mean,
        "input_std": in_std,
        "target_mean": target[torch.as_tensor(tr)].mean(0),
        "target_std": target[torch.as_tensor(tr)].std(0).clamp_min(1e-6),
    }
    model = build_model(cfg, retina, device)
    model.set_target_norm(norm["target_mean"], norm["target_std"])
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    start_epoch, history, best_val, bad = 0, [], math.inf, 0
    if resume:
        ck = torch.load(out / "latest.pt", weights_only=True, map_location=device)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start_epoch, history, best_val, bad = ck["epoch"] + 1, ck["history"], ck["best_val"], ck["bad_epochs"]
        norm = {k: (v.cpu() if torch.is_tensor(v) else v) for k, v in ck["norm"].items()}
        say(f"resuming {out} after epoch {ck['epoch']}")
    net = torch.nn.parallel.DistributedDataParallel(model) if dd.on else model
    n_params = sum(p.numel() for p in model.parameters())
    say(f"{cfg.model} ({cfg.head_kind()} head): {n_params:,} parameters, layers {getattr(model.backbone, 'layer_sizes', '?')}; "
        f"{len(tr):,} train / {len(va):,} val / {len(te):,} test ONVs; device {device}")
    y_all = (target - norm["target_mean"]) / norm["target_std"]

    def checkpoint(epoch):
        return {"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch, "history": history,
                "best_val": best_val, "bad_epochs": bad, "norm": norm, "config": asdict(cfg)}

    stopped = "max epochs"
    try:
        for epoch in range(start_epoch, cfg.epochs):
            t0 = time.perf_counter()
            if cfg.lr_schedule != "plateau":  # plateau: the optimizer's own rate (lowered below, restored on resume)
                for g in opt.param_groups:
                    g["lr"] = cfg.epoch_lr(epoch)
            lr_now = opt.param_groups[0]["lr"]
            perm = np.random.default_rng([cfg.seed, epoch]).permutation(tr)
            steps = range(0, len(perm), cfg.batch)
            total, total_mse, count = 0.0, 0.0, 0
            bar = tqdm(steps, desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="batch", disable=not progress or dd.rank != 0,
                       dynamic_ncols=True, leave=False)
            for s in bar:
                idx = torch.as_tensor(perm[s : s + cfg.batch])
                idx = idx[dd.rank :: dd.world]
                x = net_input(onv16[idx], norm, device)
                y = y_all[idx].to(device)
                pred = net(x)
                loss = train_loss(cfg.loss, pred, y)
                if not torch.isfinite(loss):
                    raise NonFiniteLoss(
                        f"epoch {epoch + 1}, step {s // cfg.batch}: the loss is {loss.item()}; stopping. "
                        f"The last good checkpoint ({out / 'latest.pt'}) is untouched; try a lower --lr."
                    )
                opt.zero_grad(set_to_none=True)
                loss.backward()
                grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), float("inf"))
                if not torch.isfinite(grad_norm):
                    raise NonFiniteLoss(
                        f"epoch {epoch + 1}, step {s // cfg.batch}: the gradient is {grad_norm.item()}; stopping. "
                        f"The last good checkpoint ({out / 'latest.pt'}) is untouched; try a lower --lr."
                    )
                opt.step()
                total += float(loss.detach()) * len(idx)
                total_mse += float(torch.nn.functional.mse_loss(pred.detach(), y)) * len(idx)
                count += len(idx)
                bar.set_postfix(loss=f"{total / max(count, 1):.4f}")
            tr_loss, train_mse = dd.all_mean(total / max(count, 1)), dd.all_mean(total_mse / max(count, 1))
            ev = evaluate_model(model, onv16, target, va, norm, device, loss=cfg.loss)
            improved = ev["loss"] < best_val
            best_val, bad = (ev["loss"], 0) if improved else (best_val, bad + 1)
            if cfg.lr_schedule == "plateau" and bad and bad % PLATEAU_EPOCHS == 0:
                for g in opt.param_groups:
                    g["lr"] *= PLATEAU_FACTOR
            row = {"epoch": epoch + 1, "train_loss": tr_loss, "train_mse": train_mse, "val_loss": ev["loss"],
                   "val_mse": ev["mse"], "val_median_deg": ev["median_deg"],
                   "val_p90_deg": ev["p90_deg"], "lr": lr_now, "seconds": time.perf_counter() - t0}
            history.append(row)
            if dd.rank == 0:
                record_epoch(out, row, checkpoint(epoch), improved)
                say(f"epoch {epoch + 1:3d}: train {cfg.loss} {tr_loss:.4f} MSE {train_mse:.4f}  val {cfg.loss} {ev['loss']:.4f} "
                    f"MSE {ev['mse']:.4f}  "
                    f"val median {ev['median_deg']:.2f} deg  ({row['seconds']:.1f} s){'  *' if improved else ''}")
            if stop_after_epoch is not None and epoch + 1 >= stop_after_epoch:
                raise _Interrupt()
            if bad >= cfg.patience:
                stopped = f"early stop: no better validation {cfg.loss} for {cfg.patience} epochs"
                break
    except (KeyboardInterrupt, _Interrupt):
        say(f"interrupted: {out / 'latest.pt'} holds the last finished epoch; continue with --resume {out}")
        if stop_after_epoch is None:
            raise
        return {"interrupted": True}
    say(stopped)
    # the best checkpoint on the held-out test split
    best = torch.load(out / "best.pt", weights_only=True, map_location=device) if dd.rank == 0 or not dd.on else None
    if best is not None:
        model.load_state_dict(best["model"])
    summary = {}
    if dd.rank == 0:
        test = evaluate_model(model, onv16, target, te if len(te) else va, norm, device)
        first_below = next((h["epoch"] for h in history if h["train_mse"] < 0.01), None)
        summary = {
            "model": cfg.model,
            "head": cfg.head_kind(),
            "parameters": n_params,
            "epochs": len(history),
            "stopped": stopped,
            "best_epoch": int(best["epoch"]) + 1,
            "loss": cfg.loss,
            "best_val_loss": best_val,
            "best_val_mse": history[int(best["epoch"])]["val_mse"],
            "first_epoch_train_mse_below_0.01": first_below,
            "test_mse": test["mse"],
            "test_median_deg": test["median_deg"],
            "test_p90_deg": test["p90_deg"],
            "seconds_data": t_data,
            "seconds_total": time.perf_counter() - t_start,
            "seconds_per_epoch": float(np.median([h["seconds"] for h in history])) if history else None,
            "peak_rss_mib": peak_rss_mib(),
            "model_state_mib": 16 * n_params / 2**20,  # weights, gradients and Adam's two moments, float32
            "dataset": str(ddir),
        }
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        from warp_vision.train.figures import write_figures

        write_figures(out, history, retina, onv16, target, te if len(te) else va, test["pred"], cfg)
        say(f"test: MSE {test['mse']:.4f}, angular error median {test['median_deg']:.2f} deg, "
            f"90th percentile {test['p90_deg']:.2f} deg; figures in {out / 'figures'}")
    dd.barrier()
    return summary


def evaluate_run(run_dir: str, split: str = "test", log=print) -> dict:
    """Re-evaluate a run's best checkpoint on its held-out split; prints the angular error."""
    ck, cfg = load_best(run_dir, TrainConfig)
    from warp_vision.data.store import ChunkedStore
    from warp_vision.eye.retina import Retina

    ddir = dataset_dir(cfg)
    store = ChunkedStore.open(ddir)
    data = store.load(["onv", "target"])
    onv16, target = torch.from_numpy(data["onv"]), torch.from_numpy(data["target"])
    retina = Retina.load(ddir / "retina.npz")
    tr, va, te = splits(len(target), cfg)
    idx = {"test": te if len(te) else va, "val": va, "train": tr}[split]
    device = pick_device(cfg.device)
    model = build_model(cfg, retina, device)
    model.load_state_dict(ck["model"])
    ev = evaluate_model(model, onv16, target, idx, ck["norm"], device)
    log(f"{run_dir} ({split}, {len(idx):,} ONVs): MSE {ev['mse']:.4f}; angular error median {ev['median_deg']:.3f} deg, "
        f"90th percentile {ev['p90_deg']:.3f} deg")
    return {k: v for k, v in ev.items() if not torch.is_tensor(v)}
