"""Shared benchmark plumbing: timing with medians, machine info. Results are written with
:func:`warp_vision.fileio.write_json` (atomic)."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable

import numpy as np
import torch


def median_ms(fn: Callable[[], object], repeats: int = 15, warmup: int = 3, setup: Callable[[], object] | None = None,
              device: str | None = None) -> dict:
    """Time ``fn`` ``repeats`` times after ``warmup`` calls; ``setup`` (untimed) runs before each call.
    ``device``: the CUDA device (torch or Warp name) whose outstanding work each timing waits for
    (:func:`sync`); None or "cpu" for CPU work.

    Returns {"median_ms", "min_ms", "max_ms", "repeats"}.
    """
    return interleaved_ms({"fn": (fn, setup)}, repeats, warmup, device)["fn"]


def interleaved_ms(
    cases: dict[str, tuple[Callable[[], object], Callable[[], object] | None]], repeats: int = 15, warmup: int = 3,
    device: str | None = None,
) -> dict[str, dict]:
    """Time several ``(fn, setup)`` cases in interleaved rounds: each round times every case once,
    starting from a rotating position, so drift in the machine's speed (other tenants, clocks,
    caches) falls on all cases alike. Each timing starts and ends with :func:`sync` of ``device``.
    Returns {name: median_ms's dict} per case.
    """
    names = list(cases)
    for name in names:
        fn, setup = cases[name]
        for _ in range(warmup):
            if setup:
                setup()
            fn()
    times: dict[str, list[float]] = {k: [] for k in names}
    for rep in range(repeats):
        for j in range(len(names)):
            name = names[(rep + j) % len(names)]
            fn, setup = cases[name]
            if setup:
                setup()
            sync(device)
            t0 = time.perf_counter()
            fn()
            sync(device)
            times[name].append((time.perf_counter() - t0) * 1e3)
    return {
        k: {"median_ms": float(np.median(v)), "min_ms": float(np.min(v)), "max_ms": float(np.max(v)),
            "repeats": repeats}
        for k, v in times.items()
    }


def sync(device: str | None = None) -> None:
    """Wait for outstanding GPU work: torch's (when CUDA is initialised) and, for a CUDA ``device``
    ("cuda", "cuda:N"), everything on that device, Warp's launches on Warp's own stream included."""
    if device is not None and torch.device(device).type == "cuda":
        import warp as wp

        from warp_vision.kernels.launch import warp_device

        torch.cuda.synchronize(device)
        wp.synchronize_device(warp_device(device))
    elif torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def machine_info() -> dict:
    """What ran the benchmark: CPU model, cores, memory, torch's threads, GPU if any. The versions of the code
    are :func:`warp_vision.provenance.software`'s (a benchmark's JSON carries both, each fact once)."""
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem_gib = None
    try:
        mem_gib = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        pass
    info = {
        "cpu": cpu,
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "memory_gib": mem_gib,
        "platform": platform.platform(),
        "torch_threads": torch.get_num_threads(),
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info
