"""Device helpers and the CPU thread-split launch.

Warp's CPU backend runs one launch on one thread. A kernel whose threads are independent (each
writes only its own outputs: a *gather*) can instead be launched as several contiguous slices of its
index range, one slice per worker thread; the native launch is a ctypes call that releases the GIL,
so the slices run in parallel. Kernels launched this way take the index of their first thread as
their last input (``offset: int``) and compute ``t = offset + wp.tid()``.

Never split a kernel that scatters with ``wp.atomic_add``: on the CPU it is not atomic.

A ``wp.launch`` spends as much Python time (argument type inference and packing) as a small kernel
takes to run. :func:`launch_split` therefore records each (kernel, argument types, size, slicing)
launch once and afterwards only rebinds its arguments, which costs far less.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os
import sys
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import torch
import warp as wp

from warp_vision.resources import threads_from_environment

wp.config.quiet = True
wp.config.log_level = wp.LOG_WARNING

_init_lock = threading.Lock()
_initialised = False
_pool: ThreadPoolExecutor | None = None
_pool_threads = 0

#: Below this many kernel threads a CPU launch is not split (the pool's overhead would dominate).
MIN_THREADS_PER_SLICE = 4096


#: The line Warp's native library prints on stderr, whatever ``wp.config.quiet`` says, when it cannot
#: load the CUDA driver.
NO_DRIVER_WARNING = b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"


def nvidia_device_present() -> bool:
    """Whether this machine may have an NVIDIA GPU: an ``/dev/nvidia<N>`` node on Linux; elsewhere
    we cannot tell cheaply, so True."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(glob.glob("/dev/nvidia[0-9]*"))


def drop_no_driver_warning(text: bytes) -> bytes:
    """``text`` without Warp's no-CUDA-driver line, every other line kept as it was."""
    return b"".join(line for line in text.splitlines(keepends=True) if not line.startswith(NO_DRIVER_WARNING))


def run_without_no_driver_warning(fn) -> Any:
    """Call ``fn()`` with file descriptor 2 (stderr, where native code writes) captured, then write
    back to it everything printed there but Warp's no-CUDA-driver line. That line is dropped only on
    a machine with no NVIDIA device (:func:`nvidia_device_present`), where it says nothing a user can
    act on; where a GPU is present but its driver did not load, it is kept."""
    if nvidia_device_present():
        return fn()
    try:
        saved = os.dup(2)
    except OSError:  # no descriptor 2 to capture
        return fn()
    with contextlib.suppress(AttributeError, ValueError):
        sys.stderr.flush()
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            return fn()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            kept = drop_no_driver_warning(tmp.read())
            if kept:
                os.write(2, kept)


def init() -> None:
    """Initialise Warp once, quietly; honour ``WARP_VISION_KERNEL_CACHE`` for the kernel cache. On a
    machine without an NVIDIA device, Warp's native warning that it found no CUDA driver is not shown
    (:func:`run_without_no_driver_warning`)."""
    global _initialised
    if _initialised:
        return
    with _init_lock:
        if _initialised:
            return
        cache = os.environ.get("WARP_VISION_KERNEL_CACHE")
        if cache:
            try:
                os.makedirs(cache, exist_ok=True)
            except OSError as e:  # (Warp's own error names a subdirectory, not the variable)
                raise OSError(e.errno, f"WARP_VISION_KERNEL_CACHE: {e.strerror}", cache) from None
            wp.config.kernel_cache_dir = cache
        run_without_no_driver_warning(wp.init)
        _initialised = True


def cpu_threads() -> int:
    """Worker threads for split CPU launches: ``WARP_VISION_THREADS`` or the usable core count."""
    n = threads_from_environment()
    if n is not None:
        return n
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def threads_set(n: int | None):
    """Within the block, split launches use ``n`` threads (``WARP_VISION_THREADS``; None: unchanged);
    the variable's previous state is restored after."""
    old = os.environ.get("WARP_VISION_THREADS")
    if n is not None:
        os.environ["WARP_VISION_THREADS"] = str(n)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("WARP_VISION_THREADS", None)
        else:
            os.environ["WARP_VISION_THREADS"] = old


def _get_pool(n: int) -> ThreadPoolExecutor:
    global _pool, _pool_threads
    with _init_lock:
        if _pool is None or _pool_threads != n:
            if _pool is not None:
                _pool.shutdown(wait=True)
            _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="warp_vision_launch")
            _pool_threads = n
        return _pool


def warp_device(device: str | torch.device) -> str:
    """The Warp device name ("cpu", "cuda:0", ...) for a torch device or device string."""
    d = torch.device(device)
    if d.type == "cpu":
        return "cpu"
    if d.type == "cuda":
        return f"cuda:{d.index if d.index is not None else torch.cuda.current_device()}"
    raise ValueError(f"device: expected a cpu or cuda device, got {device!r}")


def available_devices() -> list[str]:
    """Torch device names Warp can run on here: always "cpu", plus "cuda:0" when Warp sees a GPU."""
    init()
    devs = ["cpu"]
    if wp.is_cuda_available() and torch.cuda.is_available():
        devs.append("cuda:0")
    return devs


def require_device(name: str) -> str:
    """The torch device name for ``name`` ("cpu", "cuda" meaning "cuda:0", or "cuda:N"), or a one-line
    ValueError when this machine cannot run Warp and torch on it (checked before any work is done)."""
    dev = "cuda:0" if name == "cuda" else str(name)
    if dev == "cpu":
        return dev
    if not dev.startswith("cuda:") or not dev[5:].isdigit():
        raise ValueError(f"device: expected cpu, cuda or cuda:N, got {name!r}")
    init()
    n = torch.cuda.device_count() if torch.cuda.is_available() and wp.is_cuda_available() else 0
    if int(dev[5:]) >= n:
        raise ValueError(f"device: {name} requested, but Warp and torch see {n} CUDA device(s) on this machine; "
                         f"use --device cpu")
    return dev


def slices(total: int, parts: int) -> list[tuple[int, int]]:
    """Split ``range(total)`` into at most ``parts`` contiguous (start, length) slices of near-equal size."""
    parts = max(1, min(parts, total))
    base, extra = divmod(total, parts)
    out, start = [], 0
    for i in range(parts):
        length = base + (1 if i < extra else 0)
        if length:
            out.append((start, length))
        start += length
    return out


class _RecordedLaunches:
    """One recorded ``wp.Launch`` per slice of a split launch, rebound on every use (under ``lock``:
    two threads must not interleave rebinding and running the same commands). ``exe`` is the loaded
    module they call into, kept alive with them."""

    def __init__(self, cmds: list, exe: Any):
        self.cmds = cmds
        self.exe = exe
        self.lock = threading.Lock()

    def bind(self, inputs: Sequence, outputs: Sequence) -> None:
        """Pack every argument once (for the first slice) and hand the other slices the same packed values:
        packing a large struct (the renderer's scene) per slice cost about 2 ms a render of 16 slices."""
        n_in = len(inputs)
        index = [*range(n_in), *range(n_in + 1, n_in + 1 + len(outputs))]  # n_in: the slice's own offset, recorded
        first = self.cmds[0]
        for i, a in zip(index, (*inputs, *outputs)):
            first.set_param_at_index(i, a)
        for cmd in self.cmds[1:]:
            for i in index:
                packed = first.params[i + 1]  # params[0]: the launch bounds
                cmd.set_param_at_index_from_ctype(
                    i, packed if isinstance(packed, (ctypes.Structure, ctypes.Array)) else packed.value)

    def release(self) -> None:
        """Drop the commands' references to the last arguments (Warp keeps the arrays, and so the
        tensors behind them, alive for graph capture): a recording must not hold a batch in memory."""
        for cmd in self.cmds:
            if cmd.fwd_args is not None:
                cmd.fwd_args = [None] * len(cmd.fwd_args)


#: Recorded launches, least recently used first; at most :data:`LAUNCH_CACHE_SIZE` of them.
_recorded: OrderedDict[tuple, _RecordedLaunches] = OrderedDict()
_recorded_lock = threading.Lock()
LAUNCH_CACHE_SIZE = 512


def _arg_key(a: Any) -> Any:
    """What a recorded launch depends on in an argument: its type (arrays: also dtype and rank,
    which select the kernel overload), never its value."""
    if isinstance(a, wp.array):
        return type(a), a.dtype, a.ndim
    return type(a)


def _recorded_launches(kernel, parts: list[tuple[int, int]], inputs: Sequence, outputs: Sequence,
                       device: str) -> _RecordedLaunches:
    exe = kernel.module.load(device)  # also: compile here, never racing in the workers
    key = (kernel, device, tuple(parts), tuple(map(_arg_key, inputs)), tuple(map(_arg_key, outputs)))
    with _recorded_lock:
        hit = _recorded.get(key)
        if hit is not None and hit.exe is exe:  # a rebuilt module has new entry points: record again
            _recorded.move_to_end(key)
            return hit
    cmds = [
        wp.launch(kernel, dim=length, inputs=[*inputs, start], outputs=outputs, device=device,
                  record_tape=False, record_cmd=True)
        for start, length in parts
    ]
    rec = _RecordedLaunches(cmds, exe)
    with _recorded_lock:
        hit = _recorded.get(key)
        if hit is not None and hit.exe is exe:  # another thread recorded it meanwhile
            return hit
        _recorded[key] = rec
        while len(_recorded) > LAUNCH_CACHE_SIZE:
            _recorded.popitem(last=False)
    return rec


def launch_split(
    kernel,
    dim: int,
    inputs: Sequence,
    outputs: Sequence,
    device: str,
    threads: int | None = None,
    min_per_slice: int = MIN_THREADS_PER_SLICE,
    chunks_per_thread: int = 1,
) -> None:
    """Launch a 1D gather kernel over ``dim`` threads, split across CPU worker threads.

    ``kernel``'s last input must be ``offset: int`` (not included in ``inputs``); thread ``t`` of the
    full launch is ``offset + wp.tid()``. On CUDA (or with one thread, or a small ``dim``) this is one
    ordinary launch with ``offset = 0``. Launches are recorded once per kernel, argument types, size
    and slicing, and rebound to the given arguments on later calls.

    min_per_slice: the fewest kernel threads worth a slice (lower it for heavy kernel threads).
    chunks_per_thread: cut the range into this many slices per worker, handed out as workers free up,
        which balances kernels whose threads cost unequal time (ray tracing).
    """
    if dim <= 0:
        return
    n = 1 if device != "cpu" else (threads or cpu_threads())
    n = min(n, max(1, dim // max(1, min_per_slice)))
    parts = [(0, dim)] if n == 1 else slices(dim,
                                             n * max(1, min(chunks_per_thread, dim // (n * max(1, min_per_slice)))))
    rec = _recorded_launches(kernel, parts, inputs, outputs, device)
    with rec.lock:
        rec.bind(inputs, outputs)
        try:
            _run(rec.cmds, n)
        finally:
            rec.release()


class _Slices:
    """The recorded slices of one launch, handed out one at a time to the threads that :meth:`drain` them,
    with a count of those running."""

    def __init__(self, cmds: list):
        self._next = iter(cmds)
        self._cond = threading.Condition()
        self._running = 0
        self._stopped = False

    def drain(self) -> None:
        """Run slices until none is left (or :meth:`stop`)."""
        while True:
            with self._cond:
                c = None if self._stopped else next(self._next, None)
                if c is None:
                    return
                self._running += 1
            try:
                c.launch()
            finally:
                with self._cond:
                    self._running -= 1
                    self._cond.notify_all()

    def stop(self) -> None:
        """Hand out no more slices and return once none is running. An interruption (Ctrl-C, SIGTERM) that
        arrives during the wait does not end it: it is raised after."""
        interrupted = None
        while True:
            try:
                with self._cond:
                    self._stopped = True
                    while self._running:
                        self._cond.wait()
                break
            except BaseException as e:  # (KeyboardInterrupt, errors.Terminated): the wait goes on
                interrupted = interrupted or e
        if interrupted is not None:
            raise interrupted


def _run(cmds: list, n: int) -> None:
    """Run recorded slices on ``n`` threads (the calling thread included), each thread taking the next slice
    as it frees up. Returns or raises only once no slice runs: a running launch reads and writes its
    arguments' memory, which the caller frees as an exception (Ctrl-C, SIGTERM, raised in this thread)
    unwinds. An interruption launches no further slice."""
    if len(cmds) == 1:
        cmds[0].launch()
        return
    pool = _get_pool(n)
    slices = _Slices(cmds)
    futures = []
    try:
        for _ in range(min(n, len(cmds)) - 1):
            futures.append(pool.submit(slices.drain))
        slices.drain()
        for f in futures:
            f.result()  # (a worker's error raised here)
    finally:
        slices.stop()
