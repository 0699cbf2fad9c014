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
