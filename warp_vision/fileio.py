"""Atomic file writes: the one way the package writes a file that a reader may open while it is written,
or that must survive a crash whole (checkpoints, manifests, chunks, layouts, results, figures).

A write goes to a temporary file in the destination's directory, is flushed and fsynced, and is then
renamed over the destination (``os.replace``: atomic on POSIX), and the directory is fsynced. A reader
sees the old file or the new one, never a part. When anything fails (the writer raises, the disk is full,
the directory is read-only) the temporary file is removed and the error propagates: nothing is left
behind under either name. A write replaces a regular file only: a device (``/dev/null``), a FIFO, a socket or
a symbolic link in its place is an OSError, left as it is.

Outputs: :func:`require_output` checks a command's output path before any work, and :func:`resolved` makes a
path option absolute; both refuse a symbolic link that leads nowhere (a loop, or a link to what does not
exist, through which a write would make its target), naming the option.

Reads: :data:`NPY_FORMAT_ERRORS` is what numpy raises for a file that is there but is not a readable
``.npy`` or ``.npz``, for every reader of such files to catch alike.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import stat
import tempfile
import tokenize
import uuid
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

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


def what_is(mode: int) -> str:
    """What an ``st_mode`` is, in words: "a file", "a directory", "a character device", "a FIFO", ..."""
    for test, words in ((stat.S_ISREG, "a file"), (stat.S_ISDIR, "a directory"), (stat.S_ISLNK, "a symbolic link"),
                        (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                        (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return words
    return "not a file"


def _refuse_replacing(final: Path) -> None:
    """An OSError (EEXIST) when ``final`` is there and is not a regular file: a rename would put the file in the
    place of a device (as root, ``/dev/null`` itself), a FIFO, a socket or a symbolic link."""
    try:
        st = os.lstat(final)
    except FileNotFoundError:
        return
    if stat.S_ISREG(st.st_mode):
        return
    if stat.S_ISLNK(st.st_mode):
        raise OSError(errno.EEXIST, f"a symbolic link (to {os.readlink(final)}), not a regular file: not replaced",
                      str(final))
    raise OSError(errno.EEXIST, f"{what_is(st.st_mode)}, not a regular file: not replaced", str(final))


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
                if os.path.lexists(final):
                    return False
                os.replace(tmp, final)
        else:
            _refuse_replacing(final)
            os.replace(tmp, final)
        fsync_dir(final.parent)
        return True
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)


def atomic_copy(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Make ``dst`` hold ``src``'s bytes, atomically, leaving ``src`` where it is: a reader finds the old ``dst``
    or the new one, and ``src`` throughout. A hard link to ``src`` under a temporary name renamed over ``dst``
    (no bytes copied); where the file system has no hard links, a copy through :func:`atomic_write`. Like it,
    it replaces a regular file only."""
    src, dst = Path(src), Path(dst)
    tmp = temporary_path(dst)
    try:
        os.link(src, tmp)
    except OSError:  # a file system without hard links (its other faults are the copy's to name)
        with open(src, "rb") as f:
            atomic_write(dst, lambda out: shutil.copyfileobj(f, out))
        return
    try:
        _refuse_replacing(dst)
        os.replace(tmp, dst)
        fsync_dir(dst.parent)
    except OSError as e:  # (named by the file asked for, as atomic_write's are)
        if e.filename == str(dst) or e.errno is None:
            raise
        raise OSError(e.errno, e.strerror, str(dst)) from e
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


def _link_loop(link: Path, flag: str, named: Path) -> OSError:
    where = "" if link == named else f": {link}"
    return OSError(errno.ELOOP, f"{flag}{where} is a loop of symbolic links", str(named))


def refuse_broken_links(path: str | os.PathLike, flag: str) -> None:
    """An OSError naming ``flag`` and ``path`` when ``path`` or a directory above it is a symbolic link that
    leads nowhere: a loop (ELOOP), or a link to what does not exist (ENOENT; a write through it, or a ``mkdir``
    of its resolved path, would make the target)."""
    p = Path(path)
    for a in (p, *p.parents):
        if os.path.exists(a):
            return
        if not os.path.islink(a):  # (missing, or below a link that leads nowhere: looked for further up)
            continue
        try:
            os.stat(a)
        except OSError as e:
            if e.errno == errno.ELOOP:
                raise _link_loop(a, flag, p) from None
            if e.errno not in (errno.ENOENT, errno.ENOTDIR):
                raise
        where = "" if a == p else f": {a}"
        raise OSError(errno.ENOENT, f"{flag}{where} is a symbolic link to {os.path.realpath(a)}, which does not exist",
                      str(p))


def resolved(path: str | os.PathLike, flag: str) -> Path:
    """``Path(path).resolve()``: the absolute path with its symbolic links followed, or an OSError naming
    ``flag`` and ``path`` where a link leads nowhere (:func:`refuse_broken_links`). Python before 3.13 raises
    pathlib's RuntimeError for a loop, later ones an OSError; both become the one OSError."""
    p = Path(path)
    refuse_broken_links(p, flag)
    try:
        return p.resolve()
    except RuntimeError as e:  # ("Symlink loop from ...": a link made since the check)
        if "loop" not in str(e).lower():
            raise
        raise _link_loop(p, flag, p) from None
    except OSError as e:
        if e.errno != errno.ELOOP:
            raise
        raise _link_loop(p, flag, p) from None


def require_output(path: str | os.PathLike, flag: str = "--out", kind: str = "dir", writable: bool = True) -> None:
    """Refuse, before any work and creating nothing, an output ``path`` (``kind`` "dir" or "file") that
    cannot be written: a file where the directory belongs (or a directory where the file belongs), a file
    among its parents, or (``writable``) a first existing parent where nothing can be made: read-only, not
    ours, or refusing whatever its mode says (``/proc``; probed by making an empty directory there and
    removing it). A command writes only to a regular file or a directory: a device, a FIFO or a socket in its
    place is refused, as is a symbolic link where the file belongs (the write would replace the link) and a
    link that leads nowhere (:func:`refuse_broken_links`); a link to a directory where the directory belongs
    is followed. Raises the OSError, its message naming ``flag``; a path that can be made is left for the
    writer to make."""
    p = Path(path)
    if kind not in ("dir", "file"):
        raise ValueError(f"kind: expected 'dir' or 'file', got {kind!r}")
    refuse_broken_links(p, flag)
    if kind == "file" and os.path.islink(p):
        raise OSError(errno.EEXIST, f"{flag} is a symbolic link (to {os.readlink(p)}), which the file would replace; "
                                    f"give the path it leads to, or another", str(p))
    if p.exists():
        mode = os.stat(p).st_mode
        if kind == "dir" and not stat.S_ISDIR(mode):
            raise NotADirectoryError(errno.ENOTDIR, f"{flag} names {what_is(mode)}, not a directory", str(p))
        if kind == "file" and stat.S_ISDIR(mode):
            raise IsADirectoryError(errno.EISDIR, f"{flag} names a directory, not a file", str(p))
        if kind == "file" and not stat.S_ISREG(mode):
            raise OSError(errno.EEXIST, f"{flag} names {what_is(mode)}, not a regular file", str(p))
    a = p if kind == "dir" else p.parent
    while not a.exists() and a != a.parent:
        a = a.parent
    if not a.is_dir():
        what = what_is(os.stat(a).st_mode)
        raise NotADirectoryError(errno.ENOTDIR, f"{flag}: {a} is {what}, not a directory", str(p))
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
