"""The split CPU launch and its recorded launches: rebinding must never reuse stale arguments."""

from __future__ import annotations

import gc
import os
import threading
import time
import weakref
from typing import Any

import pytest
import torch
import warp as wp

from warp_vision.kernels import launch


@wp.kernel
def _scale_add(x: wp.array(dtype=Any), s: Any, offset: int, y: wp.array(dtype=Any)):
    t = offset + wp.tid()
    y[t] = s * x[t] + x.dtype(t)


for _dt in (wp.float32, wp.float64):
    wp.overload(_scale_add, [wp.array(dtype=_dt), _dt, int, wp.array(dtype=_dt)])


def _run(x: torch.Tensor, s: float, threads: int, device: str, **kw) -> torch.Tensor:
    launch.init()
    y = torch.full_like(x, float("nan"))
    wdt = wp.dtype_from_torch(x.dtype)
    launch.launch_split(_scale_add, x.numel(), [wp.from_torch(x), wdt(s)], [wp.from_torch(y)],
                        launch.warp_device(device), threads=threads, min_per_slice=1, **kw)
    return y


def _want(x: torch.Tensor, s: float) -> torch.Tensor:
    return s * x + torch.arange(x.numel(), dtype=x.dtype, device=x.device)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("threads,chunks", [(1, 1), (2, 1), (3, 1), (2, 4)])
def test_recorded_launches_are_rebound_to_new_arguments(dtype, threads, chunks, device):
    # The same kernel, types, size and slicing again and again: one recording, fresh arguments
    # (inputs, scalar and output) every call.
    g = torch.Generator().manual_seed(threads * 10 + chunks)
    for call in range(4):
        x = torch.randn(1000, generator=g, dtype=dtype).to(device)
        s = 0.5 + call
        y = _run(x, s, threads, device, chunks_per_thread=chunks)
        torch.testing.assert_close(y, _want(x, s))


def test_argument_dtypes_select_their_own_recording():
    x32 = torch.randn(257)
    x64 = torch.randn(257, dtype=torch.float64)
    for _ in range(2):  # interleaved: each dtype must keep hitting its own overload
        torch.testing.assert_close(_run(x32, 2.0, 2, "cpu"), _want(x32, 2.0))
        torch.testing.assert_close(_run(x64, 3.0, 2, "cpu"), _want(x64, 3.0))


def test_recorded_launches_stay_bounded(monkeypatch):
    monkeypatch.setattr(launch, "LAUNCH_CACHE_SIZE", 3)
    for n in range(10, 20):  # ten sizes: ten recordings, the oldest evicted
        x = torch.randn(n)
        torch.testing.assert_close(_run(x, 1.5, 1, "cpu"), _want(x, 1.5))
    assert len(launch._recorded) <= 3


def test_two_threads_sharing_a_recording_do_not_mix_arguments(monkeypatch):
    # A pause between rebinding and launching (the GIL released) invites the other threads to
    # rebind the same recorded commands: only the per-recording lock keeps their arguments apart.
    bind = launch._RecordedLaunches.bind

    def slow_bind(self, inputs, outputs):
        bind(self, inputs, outputs)
        time.sleep(0.002)

    monkeypatch.setattr(launch._RecordedLaunches, "bind", slow_bind)
    errors = []

    def worker(seed: int) -> None:
        g = torch.Generator().manual_seed(seed)
        for _ in range(10):
            x = torch.randn(4096, generator=g)
            s = float(seed)
            y = _run(x, s, 2, "cpu")
            if not torch.allclose(y, _want(x, s)):
                errors.append(seed)

    threads = [threading.Thread(target=worker, args=(seed,)) for seed in (1, 2, 3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors


def test_a_recording_does_not_keep_its_last_arguments_alive():
    x = torch.randn(5000)
    y = _run(x, 1.0, 2, "cpu")
    refs = [weakref.ref(x), weakref.ref(y)]
    del x, y
    gc.collect()
    assert all(r() is None for r in refs), "a recorded launch still holds the last call's tensors"


def _print_natively(lines: list[bytes]) -> int:
    """Write lines to file descriptor 2 as native code does (bypassing sys.stderr); returns 7."""
    for line in lines:
        os.write(2, line)
    return 7


_NO_DRIVER_LINE = launch.NO_DRIVER_WARNING + b". GPU execution will not be available.\n"


def test_no_driver_warning_is_dropped_only_where_no_gpu_is_present(monkeypatch, capfd):
    lines = [b"before\n", _NO_DRIVER_LINE, b"Warp CUDA error: something else\n"]
    monkeypatch.setattr(launch, "nvidia_device_present", lambda: False)
    assert launch.run_without_no_driver_warning(lambda: _print_natively(lines)) == 7
    err = capfd.readouterr().err
    assert err == "before\nWarp CUDA error: something else\n"

    monkeypatch.setattr(launch, "nvidia_device_present", lambda: True)
    launch.run_without_no_driver_warning(lambda: _print_natively(lines))
    assert capfd.readouterr().err == b"".join(lines).decode()


def test_stderr_is_restored_when_the_call_raises(monkeypatch, capfd):
    monkeypatch.setattr(launch, "nvidia_device_present", lambda: False)

    def fail():
        _print_natively([_NO_DRIVER_LINE, b"why it failed\n"])
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        launch.run_without_no_driver_warning(fail)
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "why it failed\nafter\n"


@pytest.mark.parametrize("value", ["0", "-2", "abc", "1.5"])
def test_a_bad_thread_count_in_the_environment_is_refused_by_name(value, monkeypatch):
    """WARP_VISION_THREADS=abc said only "invalid literal for int() with base 10: 'abc'"."""
    monkeypatch.setenv("WARP_VISION_THREADS", value)
    says = f"^WARP_VISION_THREADS: expected a whole number of threads >= 1 .*, got '{value}'$"
    with pytest.raises(ValueError, match=says):
        launch.cpu_threads()
    monkeypatch.setenv("WARP_VISION_THREADS", "3")
    assert launch.cpu_threads() == 3
