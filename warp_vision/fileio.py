"""Atomic file writes: the one way the package writes a file that a reader may open while it is written,
or that must survive a crash whole (checkpoints, manifests, chunks, layouts, results, figures).

A write goes to a temporary file in the destination's directory, is flushed and fsynced, and is then
renamed over the destination (``os.replace``: atomic on POSIX), and the directory is fsynced. A reader
sees the old file or the new one, never a part. When anything fails (the writer raises, the disk is full,
the directory is read-only) the temporary file is removed and the error propagates: nothing is left
behind under either name.

Reads: :data:`NPY_FORMAT_ERRORS` is what numpy raises for a file that is there but is not a readable
``.npy`` or ``.npz``, for every reader of such files to catch alike.
"""

from __future__ import annotations

import errno
import json
import os
import tempfile
import tokenize
import uuid
import zipfile
from pathlib import Path
from typing import Any, BinaryIO, Callable

#: What numpy raises reading a damaged ``.npy`` or ``.npz`` member, beside OSError (which each reader
#: treats as it must: a missing file is often not damage). A header that is not a Python literal is
#: parsed again through :mod:`tokenize`, which raises ``tokenize.TokenError``, neither a ValueError nor a
#: SyntaxError, for brackets that never close, and on Python 3.12 and later for a control byte.
NPY_FORMAT_ERRORS = (ValueError, SyntaxError, EOFError, tokenize.TokenError, zipfile.BadZipFile)


def temporary_path(final: str | os.PathLike) -> Path:
    """A hidden, unique temporary name beside ``final`` (same directory, so the rename is atomic)."""
    final = Path(final)
    return final.with_name(f".{final.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def fsync_dir(d: str | os.PathLike) -> None:
    """fsync a directory (so a rename in it is durable); a no-op where the platform refuses."""
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, content: str | bytes | Callable[[BinaryIO], Any],
                 exclusive: bool = False, mkdir: bool = True) -> bool:
    """Write ``content`` to ``path`` atomically.

    Args:
        path: the destination.
        content: text (written as UTF-8), bytes, or a callable that writes to the binary file object it is
            given (``lambda f: torch.save(obj, f)``, ``lambda f: fig.savefig(f, format="png")``).
        exclusive: never replace an existing ``path`` (a hard link, then the temporary is unlinked); returns
            False, writing nothing, if ``path`` already exists.
        mkdir: create the destination's directory (and its parents) first.

    Returns:
        True when ``path`` now holds ``content``.
    """
    final = Path(path)
    try:
        return _write(final, content, exclusive, mkdir)
    except OSError as e:  # name the file the caller asked for, not its temporary
        if e.filename == str(final) or e.errno is None:
            raise
        raise OSError(e.errno, e.strerror, str(final)) from e


def _write(final: Path, content, exclusive: bool, mkdir: bool) -> bool:
    if mkdir:
        final.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_path(final)
    try:
        with open(tmp, "wb") as f:
            if isinstance(content, str):
                f.write(content.encode("utf-8"))
            elif isinstance(content, (bytes, bytearray, memoryview)):
                f.write(content)
            else:
                content(f)
            f.flush()
            os.fsync(f.fileno())
        if exclusive:
            try:
                os.link(tmp, final)
            except FileExistsError:
                return False
            except OSError:  # a file system without hard links: a plain rename after a check
                if final.exists():
                    return False
                os.replace(tmp, final)
        else:
            os.replace(tmp, final)
        fsync_dir(final.parent)
        return True
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)


def probe_writable(directory: str | os.PathLike) -> None:
    """Create ``directory`` (and its parents) and check that a file can be written in it: raises the
    OSError (read-only file system, no space, permission, a file in the way) before any expensive work."""
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "not a directory", str(d))
    atomic_write(d / ".write-probe", b"")
    (d / ".write-probe").unlink()


def require_output(path: str | os.PathLike, flag: str = "--out", kind: str = "dir", writable: bool = True) -> None:
    """Refuse, before any work and creating nothing, an output ``path`` (``kind`` "dir" or "file") that
    cannot be written: a file where the directory belongs (or a directory where the file belongs), a file
    among its parents, or (``writable``) a first existing parent where nothing can be made: read-only, not
    ours, or refusing whatever its mode says (``/proc``; probed by making an empty directory there and
    removing it). Raises the OSError, its message naming ``flag``; a path that can be made is left for the
    writer to make."""
    p = Path(path)
    if kind not in ("dir", "file"):
        raise ValueError(f"kind: expected 'dir' or 'file', got {kind!r}")
    if kind == "dir" and p.exists() and not p.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, f"{flag} names a file, not a directory", str(p))
    if kind == "file" and p.is_dir():
        raise IsADirectoryError(errno.EISDIR, f"{flag} names a directory, not a file", str(p))
    a = p if kind == "dir" else p.parent
    while not a.exists() and a != a.parent:
        a = a.parent
    if not a.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, f"{flag}: {a} is a file, not a directory", str(p))
    if writable and not os.access(a, os.W_OK | os.X_OK):
        read_only = bool(os.statvfs(a).f_flag & os.ST_RDONLY) if hasattr(os, "statvfs") else False
        code = errno.EROFS if read_only else errno.EACCES
        raise OSError(code, f"{flag}: {a}: {os.strerror(code)}", str(p))
    if writable:  # what the mode bits allow is not always what can be made there (/proc, a root-squashed share)
        try:
            os.rmdir(tempfile.mkdtemp(prefix=".warp_vision-probe-", dir=a))
        except OSError as exc:
            raise OSError(exc.errno, f"{flag}: {a}: nothing can be made there ({exc.strerror})", str(p)) from None


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2, exclusive: bool = False,
               allow_nan: bool = True) -> bool:
    """``obj`` as JSON (a trailing newline) to ``path``, atomically (see :func:`atomic_write`)."""
    return atomic_write(path, json.dumps(obj, indent=indent, allow_nan=allow_nan) + "\n", exclusive=exclusive)


class FileLock:
    """An exclusive ``flock`` on ``path`` (created; it holds the owner's pid while held), which the kernel
    drops when the owning process ends, however it ends: no stale lock to clean up. The file stays after
    :meth:`release` (removing it could let two processes lock two different files of one name). A file
    system without ``flock`` (some network mounts), or a platform without it (not POSIX), counts as locked."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.fd: int | None = None
        #: the pid the holder wrote, after an :meth:`acquire` that found the lock taken
        self.holder = ""

    def acquire(self, block: bool = False) -> bool:
        """Take the lock: True; False (without ``block``) when another process holds it, its pid in
        :attr:`holder`. With ``block``, wait for it (Ctrl-C interrupts the wait)."""
        try:
            import fcntl
        except ImportError:  # (not POSIX: no flock to take)
            return True
        if self.fd is not None:
            return True
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if block else fcntl.LOCK_NB))
        except BlockingIOError:
            self.holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "another process"
            os.close(fd)
            return False
        except OSError as e:
            if e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                os.close(fd)
                raise
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self.fd = fd
        return True

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
