"""Synthesis of a run's missing dataset in several processes, without torchrun (``--workers``).

A single process's split Warp launches leave about half a core idle in the per-sample Python and scene
work, so :func:`render_in_processes` renders shard 0 here and the other shards in spawned helpers, each
with 1/N of the CPU threads; the samples do not depend on the shard that renders them, so the dataset is
the same as one process's. A helper leaves Ctrl-C to its parent (which stops it), unwinds on the parent's
SIGTERM, and ends on its own once the parent is gone. :func:`auto_workers` picks N.

Two runs of one missing dataset (a sweep started at once) render it once: :func:`rendering_lock` lets the
first render it while the others wait, then find it whole; :func:`dataset_lock` does the same for any
dataset directory (the held-out condition sets of ``evaluate --conditions``).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time
from pathlib import Path

import torch

from warp_vision.data.store import ChunkedStore


def auto_workers(device: str, samples: int) -> int:
    """Synthesis processes a run uses by default: on the CPU one per usable core (at most
    :data:`MAX_WORKERS`) for a dataset of at least :data:`AUTO_MIN_SAMPLES`; otherwise one (a helper's
    start, importing torch and Warp and building its scene, costs seconds; on a GPU the launches are
    not where the time goes)."""
    from warp_vision.kernels.launch import cpu_threads

    if device.startswith("cuda") or samples < AUTO_MIN_SAMPLES:
        return 1
    return max(1, min(MAX_WORKERS, cpu_threads()))


#: The most synthesis processes ``workers="auto"`` starts (each holds its own Warp, torch and scene).
MAX_WORKERS = 8
#: ``workers="auto"`` renders datasets smaller than this in one process (the smoke preset's, tests').
AUTO_MIN_SAMPLES = 1000


#: the lock a process rendering a dataset holds in its directory (:func:`rendering_lock`)
RENDER_LOCK = ".render.lock"


def rendering_lock(task, log=print, take: bool = True):
    """A context within which ``task``'s (a :class:`warp_vision.train.harness.Task`) dataset directory is
    this process's to render (:func:`dataset_lock`); nothing is locked when ``take`` is False (a torchrun
    rank but the first)."""
    if not take:
        return contextlib.nullcontext()
    root = Path(task.cfg.data_dir)
    return dataset_lock(root, log, [Path(d) for d in task.dataset_dirs()] or [root])


@contextlib.contextmanager
def dataset_lock(root: Path, log=print, stores: list[Path] | None = None):
    """Within the block, the dataset directory ``root`` (holding the stores ``stores``, default ``root``
    itself) is this process's to render: another process rendering it holds ``RENDER_LOCK`` there, and
    this one waits for it, saying so (it then finds the dataset whole, or carries on where that one
    stopped). Nothing is locked when the stores are whole or the directory cannot be written (a complete
    dataset read in place)."""
    from warp_vision.fileio import FileLock

    root = Path(root)
    if all(ChunkedStore.whole_at(d) for d in (stores or [root])):
        yield
        return
    try:
        root.mkdir(parents=True, exist_ok=True)
        lock = FileLock(root / RENDER_LOCK)
        taken = lock.acquire()
    except OSError:
        yield
        return
    if not taken:
        log(f"waiting for process {lock.holder}, which is rendering the dataset {root} (it is used once whole)")
        lock.acquire(block=True)
    try:
        yield
    finally:
        lock.release()


def _exit_with(parent: int, every_s: float = 1.0) -> None:
    """End this process once ``parent`` is gone (killed outright, it can stop no helper): a daemon thread
    that looks every ``every_s`` seconds (the render launches release the GIL)."""
    import threading

    def watch():
        while os.getppid() == parent:
            time.sleep(every_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _render_shard(task_cls, cfg, shard: tuple[int, int], threads: int) -> None:
    """A helper process of :func:`render_in_processes`: render shard ``shard`` quietly. Ctrl-C, which the
    terminal sends to every process of the command, is left to the parent, which stops its helpers (each
    printed a traceback of its own)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # the parent's terminate(): unwind (the semaphores this process registered are released, where a plain
    # SIGTERM left the resource tracker to warn of them at exit)
    signal.signal(signal.SIGTERM, lambda *_a: sys.exit(128 + signal.SIGTERM))
    _exit_with(os.getppid())
    os.environ["WARP_VISION_THREADS"] = str(threads)
    torch.set_num_threads(threads)
    task_cls(cfg, log=lambda *a, **k: None).render(shard, progress=False)


def render_in_processes(task, workers: int, progress: bool) -> bool:
    """Synthesise ``task``'s (a :class:`warp_vision.train.harness.Task`) missing dataset in ``workers`` processes: this
    one renders shard 0 of ``workers`` (with the progress bar), ``workers - 1`` spawned helpers the others, all at once
    (the samples do not depend on the shard that renders them: the dataset is the same as one process's).
    Returns False, doing nothing, when there is nothing to render, one worker, or a task that renders
    in one process only. A helper that fails is a RuntimeError after the others finish (the chunks
    written stay: run again to resume)."""
    import multiprocessing as mp

    from warp_vision.kernels.launch import cpu_threads, threads_set

    dirs = task.dataset_dirs()
    if workers <= 1 or not dirs or all(ChunkedStore.whole_at(d) for d in dirs):
        return False
    threads = max(1, cpu_threads() // workers)
    task.log(f"synthesis in {workers} processes (this one and {workers - 1} helper{'s' if workers > 2 else ''}), "
             f"{threads} thread{'s' if threads > 1 else ''} each; the bar counts this process's shard")
    ctx = mp.get_context("spawn")  # a fresh interpreter: no fork of torch's or Warp's threads
    helpers = [ctx.Process(target=_render_shard, args=(type(task), task.cfg, (i, workers), threads), daemon=True)
               for i in range(1, workers)]
    for h in helpers:
        h.start()
    try:
        with threads_set(threads):
            task.render((0, workers), progress)
    except BaseException:
        for h in helpers:
            h.terminate()
        raise
    finally:
        for h in helpers:
            h.join()
    failed = [h.exitcode for h in helpers if h.exitcode != 0]
    if failed:
        raise RuntimeError(f"{len(failed)} of {workers - 1} synthesis helper(s) failed (exit code {failed[0]}); the "
                           "chunks written are kept: run the same command again to resume, or with --workers 1 to see "
                           "the error")
    return True
