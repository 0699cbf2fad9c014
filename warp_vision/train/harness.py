"""The training harness: everything a training run does that does not depend on what it learns.

A :class:`Task` supplies its dataset, its net (as a spec that :func:`warp_vision.nn.trained.build_net`
builds), its loss, its evaluation, how it picks the best epoch, its summary and its figures. The harness
owns the rest, the same for every task:

- the run directory: a new run claims ``--out`` (refusing one that holds a run unless ``overwrite``);
  ``--resume`` continues one exactly, optionally under a new epoch cap (one that early stopping ended
  trains further only under a higher cap, its patience counted afresh);
- the device and DistributedDataParallel (``torchrun``: gloo on the CPU, nccl on CUDA; each rank builds a
  disjoint shard of the dataset, takes 1/N of every batch and 1/N of the CPU threads; rank 0 writes);
- the epoch loop: the shuffle of epoch e is seeded by (seed, e), the learning-rate schedule is a function
  of the epoch (or lowered on a plateau), progress bars, early stopping;
- a NaN or infinite loss or gradient stops the run with :class:`NonFiniteLoss`, the last good checkpoint
  untouched; Ctrl-C leaves the last finished epoch resumable;
- the run directory's files (:mod:`warp_vision.train.rundir`): the preflight before any expensive work
  (the device exists, the output is a writable directory, the dataset fits on the disk and in memory),
  sealed checkpoints (``latest.pt`` every epoch, the one before it kept as ``previous.pt``, ``best.pt``
  when the task's rule says so), then one ``metrics.jsonl`` row per epoch, ``summary.json`` and
  ``figures/``. A resumed run starts from the newest checkpoint that verifies.

A checkpoint holds plain tensors and numbers (``torch.load(path, weights_only=True)`` reads it): the model
and optimiser state, the epoch, the history, the selection state, the input normalisation, the config,
the net's spec and the data config, so :mod:`warp_vision.nn.trained` can rebuild the net without this
package's training code.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist

from warp_vision.data.store import IncompleteStoreError, waiting_for_writers
from warp_vision.errors import told
from warp_vision.fileio import resolved, write_json
from warp_vision.nn.trained import ONV_DTYPES, build_net, dataset_mismatch, new_binding, read_checkpoint, task_command
from warp_vision.provenance import software
from warp_vision.train.config import check_splits, epoch_lr, onv_dtype_name
from warp_vision.train.rundir import (
    TIMING_FIELDS,
    a_run,
    check_checkpoint_space,
    dataset_dir,
    open_run,
    preflight,
    record_epoch,
    release_run_dir,
    reproducible_config,
    save_checkpoint,
    sync_metrics,
    warm_start,
)
from warp_vision.train.workers import auto_workers, render_in_processes, rendering_lock

#: lr_schedule "plateau": the rate is multiplied by PLATEAU_FACTOR after every PLATEAU_EPOCHS epochs
#: without a better validation metric.
PLATEAU_EPOCHS = 3
PLATEAU_FACTOR = 0.3
class NonFiniteLoss(RuntimeError):
    """The loss or the gradient became NaN or infinite; the last good checkpoint is left as it was."""


class _Interrupt(Exception):
    """Raised by the test hook ``stop_after_epoch`` to simulate Ctrl-C at an epoch boundary."""


# --------------------------------------------------------------------------------------------------
# what a task supplies


class Task:
    """A training task. Subclasses set ``name`` and ``config_cls`` and implement the methods below; the
    harness calls them in the order they are listed. ``self.cfg`` is the run's validated config and
    ``self.log`` prints (on rank 0 only)."""

    name: str = ""
    config_cls: type = object
    #: the epoch being trained (0-based), set by the harness before each epoch's batches
    epoch: int = 0

    def __init__(self, cfg, log=print):
        self.cfg, self.log = cfg, log

    def load(self, shard: tuple[int, int], progress: bool, synthesize: bool = True) -> None:
        """Synthesise (this rank's shard of) the dataset if it is missing (unless not ``synthesize``: then
        a missing dataset is an error), then load it whole."""
        raise NotImplementedError

    def render(self, shard: tuple[int, int], progress: bool) -> None:
        """Render this shard's missing part of the task's dataset(s) without loading them. A task that has
        it (and :meth:`dataset_dirs`) synthesises in several processes when a run asks for ``workers``."""
        raise NotImplementedError

    def dataset_dirs(self) -> list[Path]:
        """The stores :meth:`render` writes; empty (the default): the task renders in this process only."""
        return []

    def training_store(self) -> Path | None:
        """The store the net trains on, once :meth:`load` has run: the task's ``ddir`` where it keeps one, else
        the config's ``data_dir``; None for a task without one."""
        d = getattr(self, "ddir", None) or getattr(self.cfg, "data_dir", "")
        return Path(d) if d else None

    def dataset_digest(self) -> str | None:
        """The training store's id by content (:meth:`warp_vision.data.store.ChunkedStore.content_digest`),
        which the checkpoints carry; None for a task without a store."""
        from warp_vision.data.store import ChunkedStore

        d = self.training_store()
        return ChunkedStore.open(d).content_digest() if d is not None and d.is_dir() else None

    def binding(self) -> dict:
        """What this run's checkpoints belong to (:func:`warp_vision.nn.trained.new_binding`), after :meth:`load`."""
        return new_binding(self.name, asdict(self.cfg), self.data_config(), getattr(self, "dataset", None))

    def splits(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(train, validation, test) sample ids: what the epoch shuffles, and what evaluate() gets."""
        raise NotImplementedError

    def fit_norm(self, train: np.ndarray) -> dict:
        """Input and target normalisation from the training samples (saved with every checkpoint)."""
        return {}

    def net_spec(self) -> dict:
        """The net, as :func:`warp_vision.nn.trained.build_net` builds it (initialised from the config's seed)."""
        raise NotImplementedError

    def data_config(self) -> dict:
        """The dataset's config, saved with checkpoints (what a user of the net must render like)."""
        return {}

    @classmethod
    def resolve_paths(cls, cfg) -> None:
        """Make ``cfg``'s paths absolute (a new run, before anything is written): ``out`` and the dataset
        directory (the cache directory when ``data_dir`` is empty), and a warm start's ``init``. Tasks with
        more paths extend this. A symbolic link that leads nowhere (a loop, or a link to what does not exist) is
        an OSError naming the option (:func:`warp_vision.fileio.resolved`)."""
        cfg.out = str(resolved(cfg.out, "--out"))
        cfg.data_dir = str(resolved(dataset_dir(cfg, cls.name, cfg.data_config()), "--data-dir"))
        if getattr(cfg, "init", ""):
            cfg.init = str(resolved(cfg.init, "--init"))

    @classmethod
    def check_new_run(cls, cfg) -> None:
        """What a new run's config names outside itself, checked before any data is rendered (after
        :meth:`resolve_paths`); nothing by default. The foveation task checks its warm start."""

    def dataset_bytes(self) -> int:
        """An estimate of the dataset's size (on disk, and in memory once loaded), for the preflight."""
        return 0

    def prepare(self, model: torch.nn.Module, norm: dict) -> None:
        """Put the normalisation into the model's buffers, if it has any."""

    def batch_loss(self, net, idx: torch.Tensor, norm: dict, device: str) -> tuple[torch.Tensor, dict]:
        """(the loss to minimise, {train metric: value}) of one batch of sample ids."""
        raise NotImplementedError

    def evaluate(self, model, idx: np.ndarray, norm: dict, device: str) -> dict:
        """Metrics of ``model`` on samples ``idx`` (floats), and its predictions (tensors)."""
        raise NotImplementedError

    def validate(self, model, idx: np.ndarray, norm: dict, device: str) -> dict:
        """The epoch's check on the validation samples (what picks the best epoch): :meth:`evaluate`, unless a
        task's read-out at inference costs far more than the net it trains (the retina CNN's consensus)."""
        return self.evaluate(model, idx, norm, device)

    #: the validation metrics that choose the best epoch: {name: "min" | "max"}
    selection: dict = {"loss": "min"}
    #: with several selection metrics, best.pt is written only at an epoch at least as good in all of them
    #: (ties count); with one, at an epoch strictly better in it

    def describe(self, model) -> str:
        """One line on the net (printed when the run starts)."""
        return f"{type(model).__name__}: {sum(p.numel() for p in model.parameters()):,} parameters"

    def epoch_line(self, row: dict) -> str:
        raise NotImplementedError

    def calibrate(self, model, train_ids: np.ndarray, device: str) -> bool:
        """After training: fit whatever the task calibrates on the trained net (``model`` holds the best
        weights) from the training split into the net's buffers; True if it changed them (best.pt is then
        rewritten with them, and the summary and figures see them)."""
        return False

    def summary(self, test: dict, history: list, model) -> dict:
        """The task's own entries of summary.json (test metrics; ``model`` holds the best weights)."""
        return {}

    def figures(self, out: Path, history: list, test: dict, idx: np.ndarray) -> None:
        """Write the task's figures into ``out/figures``."""

    def eval_line(self, run_dir: str, split: str, n: int, ev: dict) -> str:
        raise NotImplementedError


class OnvTask(Task):
    """A task whose samples are ONVs in a chunked store built by ``data_module`` (``warp_vision.data.
    foveation`` or ``.faces``, with its ``dataset_fields``): the dataset's size, the dtype its net reads
    ONVs in (``cfg.onv_dtype``) and the data config its checkpoints carry."""

    data_module: str = ""

    def dataset_bytes(self) -> int:
        import importlib

        from warp_vision.data.store import dataset_bytes

        dc = self.cfg.data_config()
        return dataset_bytes(importlib.import_module(self.data_module).dataset_fields(dc), dc.samples)

    @property
    def onv_dtype(self) -> torch.dtype:
        return ONV_DTYPES[onv_dtype_name(self.cfg)]

    def data_config(self) -> dict:
        return asdict(self.cfg.data_config())


def select(selection: dict, ev: dict, best: dict) -> tuple[bool, bool, dict]:
    """(improved: some metric strictly better than its best; write best.pt; the updated bests) after an
    epoch with validation metrics ``ev``."""
    better = {k: ev[k] < best[k] if mode == "min" else ev[k] > best[k] for k, mode in selection.items()}
    no_worse = {k: ev[k] <= best[k] if mode == "min" else ev[k] >= best[k] for k, mode in selection.items()}
    improved = any(better.values())
    save_best = improved if len(selection) == 1 else all(no_worse.values())
    new = {k: (min if mode == "min" else max)(best[k], ev[k]) for k, mode in selection.items()}
    return improved, save_best, new


def initial_best(selection: dict) -> dict:
    return {k: math.inf if mode == "min" else -math.inf for k, mode in selection.items()}


# --------------------------------------------------------------------------------------------------
# run directories, devices, processes


def pick_device(name: str) -> str:
    """"auto" -> cuda:0 when Warp and torch see a GPU, else cpu; "cuda" -> cuda:0. A device this machine
    does not have is a ValueError (raised before any work)."""
    from warp_vision.kernels.launch import available_devices, require_device

    if name == "auto":
        return "cuda:0" if "cuda:0" in available_devices() else "cpu"
    return require_device(name)


def world_size() -> int:
    """The processes of this torchrun job (torchrun's WORLD_SIZE; 1 without torchrun)."""
    return int(os.environ.get("WORLD_SIZE", "1"))


class Dist:
    """This process's place in a torchrun job (a job of one without torchrun)."""

    def __init__(self, device: str):
        self.world = world_size()
        self.rank = int(os.environ.get("RANK", "0"))
        self.on = self.world > 1
        self.owner = self.on and not dist.is_initialized()  # this run made the process group: it destroys it
        if self.owner:
            dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
        if self.on and "WARP_VISION_THREADS" not in os.environ:  # the ranks share the cores
            threads = max(1, (os.cpu_count() or 1) // self.world)
            os.environ["WARP_VISION_THREADS"] = str(threads)
            torch.set_num_threads(threads)

    def barrier(self):
        if self.on:
            dist.barrier()

    def close(self):
        """Destroy the process group this run made, after a run every rank finished: left to the
        interpreter's exit, gloo's threads can abort a rank ("terminate called without an active exception",
        pytorch/pytorch#190489), seen in CI under load."""
        if self.owner and dist.is_initialized():
            dist.destroy_process_group()
            self.owner = False

    def all_mean(self, x: float) -> float:
        if not self.on:
            return x
        t = torch.tensor([x], dtype=torch.float64)
        dist.all_reduce(t)
        return float(t.item()) / self.world


def splits(n: int, data_seed: int, val_fraction: float, test_fraction: float, min_test: int = 0, name: str = "samples"):
    """(train, val, test) sample indices: a fixed permutation of ``n`` samples (seeded by ``data_seed``), split
    by :func:`warp_vision.train.config.check_splits` (fewer than 2 left to train: a ValueError naming ``name``)."""
    perm = np.random.default_rng([data_seed, 7919]).permutation(n)
    _, n_val, n_test = check_splits(n, val_fraction, test_fraction, min_test, name)
    return perm[n_test + n_val :], perm[n_test : n_test + n_val], perm[:n_test]


def held_out(ids) -> tuple[str, np.ndarray]:
    """The split a finished run is evaluated on, by name, and its samples, of ``ids`` = (train, val, test): the
    test split, or the validation split where there is none (``--test-fraction 0``, or too few samples)."""
    return ("test", ids[2]) if len(ids[2]) else ("val", ids[1])


def peak_rss_mib() -> float:
    """This process's peak resident memory (MiB) so far: dataset, model, activations and all."""
    import resource
    import sys

    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 2**20 if sys.platform == "darwin" else r / 1024


# --------------------------------------------------------------------------------------------------
# the run


class _State:
    """What a checkpoint restores: the epoch to start at, the history, the selection state."""

    def __init__(self, selection: dict):
        self.start_epoch, self.history, self.best, self.bad = 0, [], initial_best(selection), 0
        self.ended = None  # why a resumed run that early stopping ended trains no further (None: it trains on)


def _patience_spent(task: Task) -> str:
    """Why early stopping ends a run: its patience in epochs without a better validation score."""
    return f"no better validation {'/'.join(task.selection)} for {task.cfg.patience} epochs"


def _nonfinite(what: str, value: float, epoch: int, step: int, out: Path) -> NonFiniteLoss:
    return NonFiniteLoss(f"epoch {epoch + 1}, step {step}: the {what} is {value}; stopping. "
                         f"The last good checkpoint ({out / 'latest.pt'}) is untouched; try a lower --lr.")


def _train_epoch(task: Task, net, model, opt, train_ids, epoch: int, norm: dict, device: str, dd: Dist,
                 progress: bool, out: Path) -> dict:
    """One pass over the training samples in the epoch's seeded order; the mean of each train metric. Under
    torchrun each batch is dealt out over the ranks, and a last batch of fewer samples than ranks is left out
    on every rank alike (its samples, a different few each epoch, train in the other epochs): a rank given
    none would have a loss of NaN (the mean of nothing), and the others would wait on its gradients
    (:func:`run` refuses a batch smaller than the ranks)."""
    from tqdm import tqdm

    cfg = task.cfg
    task.epoch = epoch
    perm = np.random.default_rng([cfg.seed, epoch]).permutation(train_ids)
    sums: dict[str, float] = {}
    count = 0
    bar = tqdm(range(0, len(perm), cfg.batch), desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="batch",
               disable=not progress or dd.rank != 0, dynamic_ncols=True, leave=False)
    for s in bar:
        if min(cfg.batch, len(perm) - s) < dd.world:  # (the last batch; run refuses a --batch under the ranks)
            break
        idx = torch.as_tensor(perm[s : s + cfg.batch])[dd.rank :: dd.world]
        loss, metrics = task.batch_loss(net, idx, norm, device)
        if not torch.isfinite(loss):
            raise _nonfinite("loss", loss.item(), epoch, s // cfg.batch, out)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), float("inf"))
        if not torch.isfinite(grad_norm):
            raise _nonfinite("gradient", grad_norm.item(), epoch, s // cfg.batch, out)
        opt.step()
        for k, v in metrics.items():
            sums[k] = sums.get(k, 0.0) + v * len(idx)
        count += len(idx)
        # refresh=False: the bar shows it at its next throttled refresh (set_postfix's default redraws the
        # bar at every batch, ignoring tqdm's mininterval: a line per batch in a log)
        bar.set_postfix(loss=f"{sums['loss'] / max(count, 1):.4f}" if "loss" in sums else "", refresh=False)
    return {k: dd.all_mean(v / max(count, 1)) for k, v in sums.items()}


def train_precision(model: torch.nn.Module, device: str) -> str:
    """What ``model`` trains in on ``device``: "bfloat16" (a CNN whose ``train_precision``, set by
    :func:`set_train_precision`, resolves to autocast there: :func:`warp_vision.nn.retina_cnn.training_autocast`)
    or "float32" (every other net)."""
    from warp_vision.nn.retina_cnn import training_autocast

    p = getattr(model, "train_precision", "float32")
    return "float32" if training_autocast(p, torch.device(device).type) is None else "bfloat16"


def set_train_precision(task: Task, model: torch.nn.Module, device: str) -> None:
    """A CNN's training precision from its task's config (``precision``; :mod:`warp_vision.nn.retina_cnn`),
    logged as it resolves on ``device``. Other nets train in float32 and are left alone."""
    if hasattr(model, "train_precision") and hasattr(task.cfg, "precision"):
        model.train_precision = task.cfg.precision
        name = train_precision(model, device)
        task.log(f"training precision: {'bfloat16 autocast' if name == 'bfloat16' else 'float32'} "
                 f"(--precision {task.cfg.precision}; evaluation float32)")


def _setup(task: Task, cfg, out: Path, ck: dict | None, dd: Dist, device: str, progress: bool, workers: int = 1,
           new_cap: bool = False):
    """Load the data (synthesising a missing dataset in ``workers`` processes unless under torchrun, whose
    ranks render their own shards), fit the normalisation, build the net and optimiser, restore a resumed
    run from checkpoint ``ck``. A resumed run that early stopping ended trains no further unless given
    ``new_cap`` (``--epochs``) beyond its epochs; then its patience counts afresh."""
    with rendering_lock(task, task.log, take=dd.rank == 0):  # (another run rendering this dataset: wait for it)
        if dd.world == 1:
            render_in_processes(task, workers, progress)
        # the ranks render their shards of a missing dataset, then each reads the whole: one done first waits
        # for the others' chunks (an hour at most) rather than calling the dataset incomplete
        with waiting_for_writers(3600.0 if dd.world > 1 else 0.0):
            try:
                task.load((dd.rank, dd.world), progress)
            except IncompleteStoreError as e:  # (a writer of another shard stopped, or chunks were removed meanwhile)
                raise e.finished_by(f"{task_command(task.name)} --resume {out}") from None
    dd.barrier()
    task.dataset = task.dataset_digest()
    if ck is not None and dataset_mismatch(ck, task.dataset):
        raise ValueError(f"--resume {out}: its dataset {task.training_store()} holds other samples (dataset "
                         f"{task.dataset[:12]}) than its checkpoints were trained on (dataset "
                         f"{ck['binding']['dataset'][:12]})")
    tr, va, te = task.splits()
    norm = task.fit_norm(tr)
    model = build_net(task.net_spec(), device)
    if ck is None and getattr(cfg, "init", ""):
        warm_start(model, cfg.init, task.name)
    task.prepare(model, norm)
    set_train_precision(task, model, device)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, betas=(0.9, 0.999))
    state = _State(task.selection)
    if ck is not None:
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        state.start_epoch, state.history, state.bad = ck["epoch"] + 1, ck["history"], ck["bad_epochs"]
        state.best = ck["best"]
        norm = {k: (v.cpu() if torch.is_tensor(v) else v) for k, v in ck["norm"].items()}
        if dd.rank == 0:
            sync_metrics(out, state.history)
        task.log(f"resuming {out} after epoch {ck['epoch'] + 1}")
        further = f"--epochs N with N > {state.start_epoch} trains it further"
        if state.bad >= cfg.patience and new_cap and cfg.epochs > state.start_epoch:
            state.bad = 0  # (kept, the first epoch without a better score would end it again)
            task.log(f"early stopping ended it; training on to epoch {cfg.epochs}, its patience "
                     f"({cfg.patience} epochs) counted afresh")
        elif state.bad >= cfg.patience:  # early stopping ended it: evaluated again, not trained on
            state.ended = f"early stop: {_patience_spent(task)}"
            task.log(f"early stopping ended it after epoch {state.start_epoch} ({_patience_spent(task)}): its best "
                     f"checkpoint is evaluated again; {further}, its patience counted afresh")
        elif state.start_epoch >= cfg.epochs:  # the log says why no epoch is trained
            task.log(f"no epochs left to train (its cap is {cfg.epochs}): its best checkpoint is evaluated again; "
                     f"{further}")
    return (tr, va, te), norm, model, opt, state


def _epochs(task: Task, net, model, opt, ids, norm, state: _State, device, dd: Dist, progress, out, spec,
            stop_after_epoch) -> str:
    """The epoch loop; returns why it stopped."""
    cfg, (tr, va, _) = task.cfg, ids

    def checkpoint(epoch):
        history = [{k: v for k, v in r.items() if k not in TIMING_FIELDS} for r in state.history]
        return {"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch, "history": history,
                "best": state.best, "bad_epochs": state.bad, "norm": norm, "config": reproducible_config(cfg),
                "task": task.name, "net": spec, "data": task.data_config(), "binding": task.binding()}

    if state.ended:
        return state.ended
    for epoch in range(state.start_epoch, cfg.epochs):
        t0 = time.perf_counter()
        if getattr(cfg, "lr_schedule", "constant") != "plateau":  # plateau: the optimiser's own (restored) rate
            for g in opt.param_groups:
                g["lr"] = epoch_lr(cfg, epoch)
        lr_now = opt.param_groups[0]["lr"]
        train = _train_epoch(task, net, model, opt, tr, epoch, norm, device, dd, progress, out)
        ev = task.validate(model, va, norm, device)
        improved, save_best, state.best = select(task.selection, ev, state.best)
        state.bad = 0 if improved else state.bad + 1
        if getattr(cfg, "lr_schedule", "constant") == "plateau" and state.bad and state.bad % PLATEAU_EPOCHS == 0:
            for g in opt.param_groups:
                g["lr"] *= PLATEAU_FACTOR
        row = {"epoch": epoch + 1, **{f"train_{k}": v for k, v in train.items()},
               **{f"val_{k}": v for k, v in ev.items() if not torch.is_tensor(v)},
               "lr": lr_now, "saved_best": save_best, "seconds": time.perf_counter() - t0}
        state.history.append(row)
        if dd.rank == 0:
            record_epoch(out, row, checkpoint(epoch), save_best)
            task.log(f"{task.epoch_line(row)}  ({row['seconds']:.1f} s){'  *' if save_best else ''}")
        if stop_after_epoch is not None and epoch + 1 >= stop_after_epoch:
            raise _Interrupt()
        if state.bad >= cfg.patience:
            return f"early stop: {_patience_spent(task)}"
    return "max epochs"


def _finish(task: Task, model, ids, norm, state: _State, device, dd: Dist, out: Path, stopped: str,
            t_start: float, t_data: float) -> dict:
    """Evaluate the best checkpoint on the held-out split; summary.json and figures (rank 0)."""
    summary = {}
    if dd.rank == 0:
        best = read_checkpoint(out / "best.pt", map_location=device)
        model.load_state_dict(best["model"])
        if task.calibrate(model, ids[0], device):
            save_checkpoint({**best, "model": model.state_dict()}, out / "best.pt")
        split, test_ids = held_out(ids)
        test = task.evaluate(model, test_ids, norm, device)
        n_params = sum(p.numel() for p in model.parameters())
        h = state.history
        summary = {
            "task": task.name, "parameters": n_params, "epochs": len(h), "stopped": stopped,
            "best_epoch": int(best["epoch"]) + 1, "best_val": state.best,
            **task.summary(test, h, model),
            "seconds_data": t_data, "seconds_total": time.perf_counter() - t_start,
            "seconds_per_epoch": _median_seconds(h),
            "train_precision": train_precision(model, device),
            "peak_rss_mib": peak_rss_mib(),
            "model_state_mib": 16 * n_params / 2**20,  # weights, gradients and Adam's two moments, float32
            "software": software(),
            "evaluated_split": split,
        }
        write_json(out / "summary.json", summary)
        task.figures(out, h, test, test_ids)
        no_test = "" if split == "test" else " (no test split: the summary's test_* are the validation split's)"
        task.log(task.eval_line(str(out), split, len(test_ids), test) + f"; figures in {out / 'figures'}{no_test}")
    dd.barrier()
    return summary


def _median_seconds(history: list) -> float | None:
    """The median epoch time of the rows that carry one (rows restored from a checkpoint carry none)."""
    s = [r["seconds"] for r in history if "seconds" in r]
    return float(np.median(s)) if s else None


def run(task_cls, cfg=None, resume: str | None = None, progress: bool = True, log=print,
        stop_after_epoch: int | None = None, overwrite: bool = False, epochs: int | None = None,
        workers: int | str = "auto") -> dict:
    """Train (or resume) a run of ``task_cls``; returns the summary dict (also written to summary.json).

    A new run refuses an output directory that already holds a run (its metrics or checkpoints) unless
    ``overwrite``, which deletes them first. ``epochs`` gives a resumed run a new epoch cap (see
    :func:`open_run`). ``stop_after_epoch`` (tests) interrupts the run after that epoch, as Ctrl-C would,
    and returns ``{"interrupted": True}``. ``workers``: processes that synthesise a missing dataset
    (:func:`warp_vision.train.workers.render_in_processes`; "auto": :func:`~warp_vision.train.workers.auto_workers`)."""
    if workers != "auto" and (not isinstance(workers, int) or isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers: expected a positive integer or 'auto', got {workers!r}")
    # a task that renders in one process refuses --workers rather than leave it unread
    if workers != "auto" and workers > 1 and task_cls.dataset_dirs is Task.dataset_dirs:
        raise ValueError(f"workers: {a_run(task_cls.name)} renders its dataset in one process (foveation and limb "
                         f"runs render in several); leave --workers out")
    rank0 = int(os.environ.get("RANK", "0")) == 0  # (torchrun's; Dist reads it again below)
    say = log if rank0 else (lambda *a, **k: None)
    cfg, out, ck = open_run(task_cls, cfg, resume, overwrite, epochs, say)
    try:
        return _train(task_cls, cfg, out, ck, progress, say, rank0, stop_after_epoch, workers, epochs is not None)
    finally:
        release_run_dir(out)  # (the lock open_run took on --out)


def _train(task_cls, cfg, out: Path, ck: dict | None, progress: bool, say, rank0: bool,
           stop_after_epoch: int | None, workers: int | str, new_cap: bool = False) -> dict:
    """:func:`run`'s work once the run directory is open (and locked): data, training, evaluation."""
    world = world_size()  # (before Dist below joins the process group: a refusal costs no rendezvous)
    if cfg.batch < world:  # (a rank dealt an empty batch would have a NaN loss)
        raise ValueError(f"batch: expected at least one sample for each of the {world} ranks under torchrun, "
                         f"got {cfg.batch}")
    device = pick_device(cfg.device)
    task = task_cls(cfg, say)
    if rank0:
        preflight(task, out, Path(cfg.data_dir), say)  # (open_run made data_dir absolute)
        write_json(out / "config.json", asdict(cfg))
    dd = Dist(device)
    t_start = time.perf_counter()
    if workers == "auto":
        workers = auto_workers(device, int(getattr(cfg, "samples", 0)))
    try:
        ids, norm, model, opt, state = _setup(task, cfg, out, ck, dd, device, progress, workers, new_cap)
    except KeyboardInterrupt as e:
        say(_interrupted(out))
        raise told(e)  # noqa: B904 (told returns e: the caught exception, raised again)
    t_data = time.perf_counter() - t_start
    spec = task.net_spec()
    if dd.rank == 0:
        check_checkpoint_space(model, out, say)
    net = torch.nn.parallel.DistributedDataParallel(model) if dd.on else model
    say(f"{task.describe(model)}; {len(ids[0]):,} train / {len(ids[1]):,} val / {len(ids[2]):,} test samples; device "
        f"{device}")
    try:
        stopped = _epochs(task, net, model, opt, ids, norm, state, device, dd, progress, out, spec, stop_after_epoch)
    except (KeyboardInterrupt, _Interrupt) as e:
        say(_interrupted(out))
        if stop_after_epoch is None:
            raise told(e)  # noqa: B904 (told returns e: the caught exception, raised again)
        return {"interrupted": True}
    say(stopped)
    summary = _finish(task, model, ids, norm, state, device, dd, out, stopped, t_start, t_data)
    dd.close()
    return summary


def _interrupted(out: Path) -> str:
    """What a run stopped by Ctrl-C tells its user: where it stands and the command that carries on."""
    if (out / "latest.pt").exists():
        return f"interrupted: {out / 'latest.pt'} holds the last finished epoch; continue with --resume {out}"
    return (f"interrupted before any epoch finished (the dataset's chunks written so far are kept); "
            f"--resume {out} starts it again")
