"""What code produced a result: this package's version and, in a git checkout, its commit; and the versions
of the libraries that decide the numbers. Training summaries, benchmark results and the simulation's
results record it as ``software``, so a number can be traced to the code that gave it.

Read from the installed distributions' metadata (nothing heavy is imported) and from git when the package
is a checkout's own ``warp_vision/`` (never a repository that merely contains an installed copy).
"""

from __future__ import annotations

import functools
import platform
import subprocess
from importlib import metadata
from pathlib import Path

#: the distributions whose versions are recorded, by their names on the package registry
LIBRARIES = ("numpy", "torch", "warp-lang", "mujoco", "scipy")

PACKAGE_DIR = Path(__file__).resolve().parent


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def package_version() -> str:
    """This package's installed version; ``0+unknown`` for a source tree that was never installed."""
    return _version("warp_vision") or "0+unknown"


def _git(*args: str) -> str | None:
    try:
        r = subprocess.run(["git", "-C", str(PACKAGE_DIR), *args], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


@functools.lru_cache(maxsize=1)
def commit() -> dict | None:
    """{"commit": the checkout's HEAD, "dirty": whether tracked files differ from it} where this package is
    a git checkout's ``warp_vision/``; None otherwise (an installed copy, no git)."""
    top = _git("rev-parse", "--show-toplevel")
    if top is None or Path(top).resolve() / "warp_vision" != PACKAGE_DIR:
        return None
    head = _git("rev-parse", "HEAD")
    if head is None:
        return None
    status = _git("status", "--porcelain", "--untracked-files=no")
    return {"commit": head, "dirty": None if status is None else bool(status)}


def software() -> dict:
    """This package's version (and commit, :func:`commit`), Python's, and :data:`LIBRARIES`' (None where
    one is not installed)."""
    info = {"warp_vision": package_version(), **(commit() or {}), "python": platform.python_version()}
    info.update({dist: _version(dist) for dist in LIBRARIES})
    return info
