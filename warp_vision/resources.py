"""How much memory and disk this machine has left, and refusing work that cannot fit before it starts.

A size that would not fit (a retina of 10^9 photoreceptors, 10^9 rays per receptor, a dataset larger
than the memory) is refused with a one-line ``ValueError`` that gives the estimate, the memory available and the option
to lower, before anything is allocated; files that would not fit on their disk (a dataset's missing chunks, a run's
checkpoints), with an ENOSPC ``OSError`` naming the directory, before they are rendered or trained.
"""

from __future__ import annotations

import errno
import math
import os
import shutil
from pathlib import Path


def available_memory_bytes() -> int:
    """Memory that can be allocated without swapping: ``MemAvailable`` of /proc/meminfo on Linux, the
    physical memory elsewhere; the environment variable ``WARP_VISION_MEMORY_LIMIT`` (bytes) caps it."""
    avail = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            avail = 1 << 62
    cap = os.environ.get("WARP_VISION_MEMORY_LIMIT")
    return min(avail, _memory_cap(cap)) if cap else avail


def _memory_cap(text: str) -> int:
    """``WARP_VISION_MEMORY_LIMIT`` in bytes ("8e9" reads too); anything but a positive finite number is a
    ValueError naming the variable."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v >= 1):
        raise ValueError(f"WARP_VISION_MEMORY_LIMIT: expected a number of bytes >= 1 (8e9, say), got {text!r}")
    return int(v)


def threads_from_environment() -> int | None:
    """``WARP_VISION_THREADS``, the worker threads of split CPU launches: None where it is unset or empty;
    anything but a whole number >= 1 is a ValueError naming the variable."""
    text = os.environ.get("WARP_VISION_THREADS")
    if not text:
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"WARP_VISION_THREADS: expected a whole number of threads >= 1 (4, say), got {text!r}")
    return n


def _whole_number(name: str, least: int) -> None:
    """The environment variable ``name``, where set, is a whole number >= ``least``; else a ValueError naming it."""
    text = os.environ.get(name)
    if text is None:
        return
    try:
        ok = int(text) >= least
    except ValueError:
        ok = False
    if not ok:
        raise ValueError(f"{name}: expected a whole number >= {least} (torchrun sets it), got {text!r}")


def check_environment() -> None:
    """Every environment variable the package reads, checked when a command starts (errors.guarded), before
    any work: ``WARP_VISION_THREADS``, ``WARP_VISION_MEMORY_LIMIT``, ``WARP_VISION_KERNEL_CACHE`` (no file where
    its directory belongs) and torchrun's ``RANK`` and ``WORLD_SIZE``; a ValueError or OSError naming the first
    bad one. (``WARP_VISION_CACHE`` may name any directory: a BVH cache that cannot be written is skipped.)"""
    from warp_vision.fileio import require_output

    threads_from_environment()
    cap = os.environ.get("WARP_VISION_MEMORY_LIMIT")
    if cap:
        _memory_cap(cap)
    cache = os.environ.get("WARP_VISION_KERNEL_CACHE")
    if cache:  # (creating nothing: the directory is made, and found writable or not, when Warp starts)
        require_output(cache, "WARP_VISION_KERNEL_CACHE", writable=False)
    _whole_number("WORLD_SIZE", 1)
    _whole_number("RANK", 0)


def human_bytes(n: float) -> str:
    """``n`` bytes as KiB, MiB or GiB."""
    if n < 2**20:
        return f"{n / 2**10:,.0f} KiB"
    return f"{n / 2**20:,.0f} MiB" if n < 2**30 else f"{n / 2**30:,.1f} GiB"


def require_memory(nbytes: float, what: str, lower: str) -> None:
    """Raise ValueError (one line: ``what``, the estimate, what is available, ``lower``: the options to
    lower) when ``nbytes`` exceed the memory available."""
    avail = available_memory_bytes()
    if nbytes > avail:
        raise ValueError(f"{what} needs about {human_bytes(nbytes)}, more than the {human_bytes(avail)} of memory "
                         f"available; lower {lower}")


def free_disk_bytes(path) -> int:
    """The free space of the file system ``path`` is on (or would be: its nearest existing parent)."""
    path = Path(path).absolute()
    return shutil.disk_usage(next(p for p in (path, *path.parents) if p.exists())).free


def require_disk(nbytes: float, path, what: str) -> int:
    """The free space at ``path`` (:func:`free_disk_bytes`); an OSError (ENOSPC, naming ``path``) that says
    how much ``what`` needs when it is less than ``nbytes``."""
    free = free_disk_bytes(path)
    if nbytes > free:
        raise OSError(errno.ENOSPC, f"No space left for {what}: about {human_bytes(nbytes)} needed, "
                                    f"{human_bytes(free)} free", str(path))
    return free
