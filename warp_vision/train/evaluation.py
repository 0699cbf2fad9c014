"""A finished run read again: its checkpoint (best or latest) evaluated on one of its splits, the dataset
rendered again where it is gone from the cache. ``python -m warp_vision.train evaluate`` (each task's
``evaluate_run``) and ``evaluate --conditions`` (:mod:`warp_vision.train.conditions`) read runs through it."""

from __future__ import annotations

from pathlib import Path

import torch

from warp_vision.nn.trained import binding, checkpoint_path, dataset_mismatch, net_from_checkpoint, read_checkpoint
from warp_vision.train.harness import Task, held_out, pick_device
from warp_vision.train.rundir import require_own_checkpoint, run_config, saved_config
from warp_vision.train.workers import rendering_lock


def read_label(run_dir, checkpoint: str, epoch: int, views: int | None) -> str:
    """How ``evaluate`` names a run read other than as it stands: "RUN (latest.pt, epoch 9; views 1)";
    the run's best checkpoint with its own views is just "RUN". ``epoch``: the checkpoint's, 0-based."""
    how = [f"{checkpoint}.pt, epoch {epoch + 1}"] if checkpoint != "best" else []
    how += [f"views {views}"] if views is not None else []
    return f"{run_dir} ({'; '.join(how)})" if how else str(run_dir)


def load_for_evaluation(task: Task, log=print, progress: bool = True, ck: dict | None = None) -> None:
    """Load a finished run's dataset to evaluate it. A store gone from the cache (deleted to free the disk, or
    a run copied from another machine), or chunks of it gone, are rendered again, the same samples as in training,
    saying so. With ``ck`` (the checkpoint to evaluate), a store that holds other samples than ``ck`` was trained on
    (its data_dir pointed at another dataset) is refused; one rendered again here that differs (another machine's
    arithmetic) is said to differ."""
    from warp_vision.data.store import IncompleteStoreError, MissingStoreError

    try:
        task.load((0, 1), progress=False, synthesize=False)
        again = False
    except MissingStoreError as e:
        log(f"the run's dataset {e.root} is gone: rendering it again (the same samples as in training)")
        again = True
    except IncompleteStoreError as e:
        log(f"the run's dataset {e.root} lacks {len(e.missing)} of its {e.num_chunks} chunks: rendering them again "
            f"(the same samples as in training)")
        again = True
    if again:
        with rendering_lock(task, log):
            task.load((0, 1), progress=progress, synthesize=True)
    if ck is None:
        return
    digest = task.dataset_digest()
    if dataset_mismatch(ck, digest):
        trained = binding(ck)["dataset"][:12]
        if not again:
            raise ValueError(f"{task.training_store()} holds other samples (dataset {digest[:12]}) than "
                             f"{task.cfg.out}'s net was trained on (dataset {trained}): its config.json's data_dir "
                             "names another dataset")
        log(f"the dataset rendered again differs from the one the net was trained on (dataset {digest[:12]}, "
            f"trained on {trained}; rendered by another machine or version): evaluating on it all the same")


def evaluate_run(task_cls, run_dir: str, split: str = "test", log=print, detail=None, checkpoint: str = "best",
                 views: int | None = None, progress: bool = True) -> dict:
    """Re-evaluate a run's ``checkpoint`` ("best": the best validation epoch's weights; "latest": the last
    epoch's) on one of its splits; prints the task's metrics. ``views``: read a foveation CNN out by the
    consensus of that many views instead of its spec's (1: the plain image). ``detail``:
    ``detail(task, idx, ev, log) -> dict``, more analysis of the evaluation ``ev`` (its tensors included)
    whose entries join the returned metrics. ``progress``: a bar while a dataset gone from its cache is
    rendered again (:func:`load_for_evaluation`)."""
    path = checkpoint_path(run_dir, checkpoint)
    ck = read_checkpoint(path)
    require_own_checkpoint(task_cls, ck, path, run_dir, saved_config(task_cls, run_dir))
    cfg = run_config(task_cls, Path(run_dir), ck, path)
    task = task_cls(cfg, log)
    load_for_evaluation(task, log, progress, ck)
    ids = task.splits()
    if split == "test":
        split, idx = held_out(ids)
        if split != "test":  # the validation split stands in: say so, rather than call it "test"
            log(f"{run_dir}: no test split (--test-fraction 0, or too few samples); the validation split's, as the "
                f"run's summary")
    else:
        idx = ids[{"train": 0, "val": 1}[split]]
    device = pick_device(cfg.device)
    model = net_from_checkpoint(ck, device, views, source=path)
    ev = task.evaluate(model, idx, ck["norm"], device)
    log(task.eval_line(read_label(run_dir, checkpoint, ck["epoch"], views), split, len(idx), ev))
    more = detail(task, idx, ev, log) if detail is not None else {}
    return {**{k: v for k, v in ev.items() if not torch.is_tensor(v)}, **more}
