"""A chunked, checksummed, resumable, shardable on-disk dataset store (plain numpy).

A dataset of ``total`` samples is split into ``num_chunks = ceil(total / chunk_size)`` chunks; chunk ``c``
holds the global samples ``[c * chunk_size, min(total, (c + 1) * chunk_size))``. Every sample has the same
named fields, each with a fixed per-sample shape and dtype, e.g.::

    fields = {"onv": ((43200,), "float16"), "target": ((2,), "float32")}

On-disk layout of a store rooted at ``root``::

    root/manifest.json                 what the dataset is: format/version, config, total, chunk_size, fields,
                                       a random dataset id and creation info (time, host, pid, versions)
    root/chunk_000007.onv.npy          one uncompressed ``.npy`` per chunk and field, shape [n_c, *shape]
    root/chunk_000007.target.npy
    root/chunk_000007.json             the chunk's record: dataset id, sample range, and per field the file
                                       name, its size in bytes and its sha256. Written last: its presence
                                       marks the chunk as done.

Every file is written to a hidden temporary name in ``root`` and then renamed over its final name
(``os.replace``), after an fsync, so a reader never sees a half-written file under a final name. A chunk
whose record is absent (an interrupted write) counts as missing and is never read; ``write_chunk`` deletes
an old record before it replaces a chunk's data. There is no shared file that writers update: shard ``i``
of ``n`` (``my_chunks``: the chunks with ``c % n == i``) writes only its own chunks' files, so ``n``
processes can fill one directory concurrently. The manifest is created once, with an exclusive
link, and afterwards only read: ``create_or_resume`` with settings that differ from the manifest's raises
``ValueError`` naming the first differing key, so a dataset built with other settings is never reused.

Typical use (one process per shard; ``--shard I/N`` parsed with ``parse_shard``)::

    store = ChunkedStore.create_or_resume(root, config, total, chunk_size, fields, shard=(i, n))
    for c in store.missing_chunks():
        a, b = store.chunk_range(c)
        store.write_chunk(c, synthesize(a, b))      # {"onv": [b - a, 43200] float16, ...}
    ...
    data = ChunkedStore.open(root).load()            # {"onv": [total, 43200] float16, ...}
"""

from __future__ import annotations

import datetime
import hashlib
import json
import math
import os
import platform
import re
import socket
import uuid
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

__all__ = ["ChunkedStore", "CorruptChunkError", "FORMAT_NAME", "FORMAT_VERSION", "parse_shard"]

#: The ``format`` entry of every manifest written by this module.
FORMAT_NAME = "warp_vision.ChunkedStore"
#: The on-disk format version; ``open`` refuses other versions.
FORMAT_VERSION = 1

MANIFEST_NAME = "manifest.json"
_FIELD_NAME = re.compile(r"^[A-Za-z0-9_]+$")
_ALLOWED_KINDS = "biufc"  # bool, signed/unsigned int, float, complex
_IO_BLOCK = 1 << 22  # bytes per read when hashing/reading a file


class CorruptChunkError(ValueError):
    """A chunk's file is missing, truncated, of the wrong size, fails its sha256 check or cannot be read.

    ``path`` is the offending file (a data file or the chunk's record), ``chunk`` the chunk index; the
    message starts with the path and says what is wrong.
    """

    def __init__(self, path: os.PathLike | str, chunk: int, what: str):
        self.path = Path(path)
        self.chunk = int(chunk)
        self.what = what
        super().__init__(f"{self.path}: {what} (chunk {self.chunk})")


def parse_shard(spec: str) -> tuple[int, int]:
    """Parse a shard spec ``"I/N"`` (shard ``I`` of ``N``, ``0 <= I < N``) into ``(I, N)``.

    Raises ``ValueError`` for anything else ("3", "a/b", "2/2", "-1/4", "1/0").
    """
    if not isinstance(spec, str):
        raise ValueError(f"shard spec must be a string 'I/N', got {type(spec).__name__} {spec!r}")
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", spec)
    if m is None:
        raise ValueError(f"shard spec must look like 'I/N' with integers 0 <= I < N, got {spec!r}")
    return _check_shard((int(m.group(1)), int(m.group(2))))


def _check_shard(shard: Any) -> tuple[int, int]:
    try:
        i, n = shard
    except (TypeError, ValueError):
        raise ValueError(f"shard must be a pair (I, N) with 0 <= I < N, got {shard!r}") from None
    if not (_is_int(i) and _is_int(n)):
        raise ValueError(f"shard must be a pair of integers (I, N), got {shard!r}")
    i, n = int(i), int(n)
    if n < 1:
        raise ValueError(f"shard count N must be >= 1, got shard {i}/{n}")
    if not 0 <= i < n:
        raise ValueError(f"shard index I must satisfy 0 <= I < N, got shard {i}/{n}")
    return i, n


def _is_int(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _normalise_fields(fields: Mapping[str, Any]) -> dict[str, tuple[tuple[int, ...], str]]:
    """Check a fields spec and return it as ``{name: (shape tuple, dtype name)}`` in the given order."""
    if not isinstance(fields, Mapping) or not fields:
        raise ValueError(f"fields must be a non-empty dict name -> (shape, dtype), got {fields!r}")
    out: dict[str, tuple[tuple[int, ...], str]] = {}
    for name, spec in fields.items():
        if not isinstance(name, str) or not _FIELD_NAME.match(name):
            raise ValueError(f"field name must match [A-Za-z0-9_]+ (it becomes part of a file name), got {name!r}")
        try:
            shape, dtype = spec
        except (TypeError, ValueError):
            raise ValueError(f"field {name!r}: expected (shape, dtype), got {spec!r}") from None
        if _is_int(shape):
            shape = (shape,)
        try:
            shape = tuple(shape)
        except TypeError:
            raise ValueError(f"field {name!r}: shape must be a tuple of ints, got {shape!r}") from None
        if not all(_is_int(s) and s >= 0 for s in shape):
            raise ValueError(f"field {name!r}: shape must be a tuple of non-negative ints, got {shape!r}")
        try:
            dt = np.dtype(dtype)
        except TypeError:
            raise ValueError(f"field {name!r}: not a numpy dtype: {dtype!r}") from None
        if dt.kind not in _ALLOWED_KINDS or dt.fields is not None or dt.subdtype is not None:
            raise ValueError(f"field {name!r}: dtype must be a plain bool/int/float/complex dtype, got {dtype!r}")
        if not dt.isnative:
            raise ValueError(f"field {name!r}: dtype must be in native byte order, got {dtype!r}")
        out[name] = (tuple(int(s) for s in shape), dt.name)
    return out


def _fields_to_json(fields: Mapping[str, tuple[tuple[int, ...], str]]) -> dict[str, dict]:
    return {name: {"shape": list(shape), "dtype": dtype} for name, (shape, dtype) in fields.items()}


def _fields_from_json(obj: Any) -> dict[str, tuple[tuple[int, ...], str]]:
    if not isinstance(obj, dict):
        raise ValueError(f"'fields' must be an object, got {obj!r}")
    spec = {}
    for name, f in obj.items():
        if not isinstance(f, dict) or "shape" not in f or "dtype" not in f:
            raise ValueError(f"field {name!r} must be an object with 'shape' and 'dtype', got {f!r}")
        spec[name] = (f["shape"], f["dtype"])
    return _normalise_fields(spec)


def _json_roundtrip(config: Any) -> Any:
    """``config`` as it will read back from JSON (tuples become lists); ValueError if not serialisable."""
    try:
        text = json.dumps(config, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as e:
        raise ValueError(f"config must be JSON-serialisable (finite numbers, str keys): {e}") from None
    return json.loads(text)


def _first_difference(path: str, old: Any, new: Any) -> str | None:
    """The path of the first difference between two JSON values, with both values; None if equal."""
    if isinstance(old, dict) and isinstance(new, dict):
        for k in list(old) + [k for k in new if k not in old]:
            if k not in new:
                return f"{path}[{k!r}]: the manifest has {old[k]!r}, the request has no such key"
            if k not in old:
                return f"{path}[{k!r}]: the manifest has no such key, the request has {new[k]!r}"
            d = _first_difference(f"{path}[{k!r}]", old[k], new[k])
            if d is not None:
                return d
        return None
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        for j, (a, b) in enumerate(zip(old, new)):
            d = _first_difference(f"{path}[{j}]", a, b)
            if d is not None:
                return d
        return None
    if type(old) is not type(new) or old != new:
        return f"{path}: the manifest has {old!r}, the request has {new!r}"
    return None


def _tmp_path(final: Path) -> Path:
    return final.with_name(f".{final.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _fsync_dir(d: Path) -> None:
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


def _write_json_atomic(final: Path, obj: Any, exclusive: bool = False) -> bool:
    """Write ``obj`` as JSON to a temporary name, fsync, then rename it to ``final``.

    With ``exclusive`` the rename never replaces an existing file (a hard link, then unlink of the
    temporary); returns False if ``final`` already existed. Otherwise returns True.
    """
    tmp = _tmp_path(final)
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(obj, f, indent=1, allow_nan=False)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        if exclusive:
            try:
                os.link(tmp, final)
            except FileExistsError:
                return False
            except OSError:  # a file system without hard links: fall back to a plain rename
                if final.exists():
                    return False
                os.replace(tmp, final)
        else:
            os.replace(tmp, final)
        return True
    finally:
        if tmp.exists():
            tmp.unlink()


class _HashingWriter:
    """A write-only file wrapper that feeds every byte written through sha256 and counts them."""

    def __init__(self, f):
        self._f = f
        self.sha = hashlib.sha256()
        self.size = 0

    def write(self, data) -> int:
        mv = memoryview(data).cast("B")
        self.sha.update(mv)
        self._f.write(mv)
        self.size += mv.nbytes
        return mv.nbytes


class ChunkedStore:
    """A dataset of ``total`` samples stored as checksummed chunks of ``chunk_size`` samples in ``root``.

    Build one with ``create_or_resume`` (to write, as shard ``(i, n)``) or ``open`` (to read). Attributes:

    - ``root: Path``; ``total: int`` samples; ``chunk_size: int``; ``num_chunks: int = ceil(total / chunk_size)``
    - ``config: dict``: the JSON-normalised config the dataset was built with (tuples read back as lists)
    - ``fields: dict[str, tuple[tuple[int, ...], str]]``: name -> (per-sample shape, numpy dtype name)
    - ``shard: tuple[int, int]``: (i, n); ``(0, 1)`` for a store from ``open``
    - ``dataset_id: str``: a random id written into the manifest and every chunk record
    - ``manifest: dict``: the manifest as read from disk
    """

    def __init__(self, root: os.PathLike | str, manifest: dict, shard: tuple[int, int], writable: bool):
        # Use create_or_resume or open; this only unpacks a checked manifest.
        self.root = Path(root)
        self.manifest = manifest
        self.config = manifest["config"]
        self.total = int(manifest["total"])
        self.chunk_size = int(manifest["chunk_size"])
        self.fields = _fields_from_json(manifest["fields"])
        self.dataset_id = str(manifest["dataset_id"])
        self.num_chunks = math.ceil(self.total / self.chunk_size)
        self.shard = _check_shard(shard)
        self._writable = writable

    # ------------------------------------------------------------------ construction

    @classmethod
    def create_or_resume(
        cls,
        root: os.PathLike | str,
        config: dict,
        total: int,
        chunk_size: int,
        fields: Mapping[str, tuple[tuple[int, ...], str]],
        shard: tuple[int, int] = (0, 1),
    ) -> "ChunkedStore":
        """Create the store in ``root`` (writing ``root/manifest.json``) or resume the one already there.

        config: JSON-serialisable dict of the settings that produced the data (compared on resume).
        total: number of samples (>= 1); chunk_size: samples per chunk (>= 1).
        fields: name -> (per-sample shape, numpy dtype string), e.g. ``{"onv": ((43200,), "float16")}``.
        shard: (i, n): this writer owns the chunks ``c`` with ``c % n == i``.

        Raises ValueError for bad arguments, an unreadable manifest, or a manifest whose config, total,
        chunk_size or fields differ from the arguments (the message names the first differing key).
        """
        if not isinstance(config, dict):
            raise ValueError(f"config must be a dict, got {type(config).__name__}")
        config_json = _json_roundtrip(config)
        if not _is_int(total) or total < 1:
            raise ValueError(f"total must be an int >= 1, got {total!r}")
        if not _is_int(chunk_size) or chunk_size < 1:
            raise ValueError(f"chunk_size must be an int >= 1, got {chunk_size!r}")
        fields_n = _normalise_fields(fields)
        shard = _check_shard(shard)
        root = Path(root)
        root.mkdir(parents=True, exist_ok=True)
        path = root / MANIFEST_NAME

        if not path.exists():
            manifest = {
                "format": FORMAT_NAME,
                "version": FORMAT_VERSION,
                "config": config_json,
                "total": int(total),
                "chunk_size": int(chunk_size),
                "fields": _fields_to_json(fields_n),
                "dataset_id": uuid.uuid4().hex,
                "created": {
                    "time": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                    "host": socket.gethostname(),
                    "pid": os.getpid(),
                    "python": platform.python_version(),
                    "numpy": np.__version__,
                },
            }
            # Exclusive: if another shard process created it first, fall through and compare with theirs.
            if _write_json_atomic(path, manifest, exclusive=True):
                _fsync_dir(root)
                return cls(root, manifest, shard, writable=True)

        manifest = _read_manifest(root)
        requested = {
            "config": config_json,
            "total": int(total),
            "chunk_size": int(chunk_size),
            "fields": _fields_to_json(fields_n),
        }
        for key, new in requested.items():
            diff = _first_difference(key, manifest[key], new)
            if diff is not None:
                raise ValueError(
                    f"{path} was written with other settings; first difference: {diff}. "
                    f"Use another directory, or delete this one to rebuild the dataset."
                )
        return cls(root, manifest, shard, writable=True)

    @classmethod
    def open(cls, root: os.PathLike | str) -> "ChunkedStore":
        """Open an existing store for reading (shard (0, 1); ``write_chunk`` is refused).

        Raises ValueError if ``root/manifest.json`` is missing or not a valid manifest.
        """
        root = Path(root)
        return cls(root, _read_manifest(root), (0, 1), writable=False)

    # ------------------------------------------------------------------ chunk bookkeeping

    def __len__(self) -> int:
        return self.total

    def __repr__(self) -> str:
        i, n = self.shard
        return (
            f"ChunkedStore({str(self.root)!r}, total={self.total}, chunk_size={self.chunk_size}, "
            f"num_chunks={self.num_chunks}, fields={self.fields!r}, shard={i}/{n})"
        )

    def _check_chunk(self, c: Any) -> int:
        if not _is_int(c):
            raise ValueError(f"chunk index must be an int, got {type(c).__name__} {c!r}")
        if not 0 <= c < self.num_chunks:
            raise ValueError(f"chunk index {c} out of range: the store has chunks 0..{self.num_chunks - 1}")
        return int(c)

    def chunk_range(self, c: int) -> tuple[int, int]:
        """Global sample range ``[start, stop)`` of chunk ``c``."""
        c = self._check_chunk(c)
        return c * self.chunk_size, min(self.total, (c + 1) * self.chunk_size)

    def my_chunks(self) -> list[int]:
        """The chunks this shard owns (``c % n == i``), ascending."""
        i, n = self.shard
        return list(range(i, self.num_chunks, n))

    def record_path(self, c: int) -> Path:
        """``root/chunk_{c:06d}.json``: chunk ``c``'s record (present = chunk written)."""
        return self.root / f"chunk_{int(c):06d}.json"

    def data_path(self, c: int, field: str) -> Path:
        """``root/chunk_{c:06d}.{field}.npy``: the data file of one field of chunk ``c``."""
        return self.root / f"chunk_{int(c):06d}.{field}.npy"

    def _read_record(self, c: int) -> dict:
        """Chunk ``c``'s record, checked against the manifest; CorruptChunkError if absent or invalid."""
        rp = self.record_path(c)
        try:
            with open(rp, encoding="utf-8") as f:
                rec = json.load(f)
        except FileNotFoundError:
            raise CorruptChunkError(rp, c, "record missing: the chunk was never written or its write was interrupted") from None
        except (OSError, ValueError) as e:
            raise CorruptChunkError(rp, c, f"record unreadable: {e}") from None
        start, stop = self.chunk_range(c)
        expect = {"dataset_id": self.dataset_id, "chunk": c, "start": start, "stop": stop, "n": stop - start}
        if not isinstance(rec, dict):
            raise CorruptChunkError(rp, c, "record is not a JSON object")
        for k, v in expect.items():
            if rec.get(k) != v:
                raise CorruptChunkError(rp, c, f"record has {k}={rec.get(k)!r}, expected {v!r}")
        files = rec.get("files")
        if not isinstance(files, dict) or set(files) != set(self.fields):
            got = sorted(files) if isinstance(files, dict) else files
            raise CorruptChunkError(rp, c, f"record lists files for {got!r}, expected {sorted(self.fields)!r}")
        for name, entry in files.items():
            ok = (
                isinstance(entry, dict)
                and entry.get("file") == self.data_path(c, name).name
                and _is_int(entry.get("bytes"))
                and isinstance(entry.get("sha256"), str)
                and len(entry["sha256"]) == 64
            )
            if not ok:
                raise CorruptChunkError(rp, c, f"record entry for field {name!r} is malformed: {entry!r}")
        return rec

    def _chunk_present(self, c: int) -> bool:
        """Quick check: valid record, and every data file exists with the recorded size (no hashing)."""
        try:
            rec = self._read_record(c)
        except CorruptChunkError:
            return False
        for name, entry in rec["files"].items():
            try:
                if os.stat(self.data_path(c, name)).st_size != entry["bytes"]:
                    return False
            except OSError:
                return False
        return True

    def missing_chunks(self) -> list[int]:
        """This shard's chunks not (completely) written: no valid record, or a data file absent or of
        the wrong size. Sizes only, no hashing (use ``verify`` for that)."""
        return [c for c in self.my_chunks() if not self._chunk_present(c)]

    def _all_missing(self) -> list[int]:
        return [c for c in range(self.num_chunks) if not self._chunk_present(c)]

    @property
    def complete(self) -> bool:
        """True when every chunk of the dataset (all shards) is written (quick size check, no hashing)."""
        return all(self._chunk_present(c) for c in range(self.num_chunks))

    # ------------------------------------------------------------------ writing

    def write_chunk(self, c: int, arrays: Mapping[str, np.ndarray]) -> None:
        """Write chunk ``c``: ``arrays[name]`` has shape ``[n_c, *shape]`` and exactly the field's dtype,
        ``n_c = stop - start`` of ``chunk_range(c)``; float/complex fields must be finite.

        Each field goes to its own ``.npy`` (temporary name, fsync, rename); the chunk's record with the
        sizes and sha256 of those files is written last. Rewriting a written chunk first removes its
        record, so the chunk reads as missing until the new data is complete.
        Raises ValueError if the store is read-only, ``c`` is not this shard's, or an array is wrong.
        """
        if not self._writable:
            raise ValueError("this store was opened read-only (ChunkedStore.open); use create_or_resume to write")
        c = self._check_chunk(c)
        i, n = self.shard
        if c % n != i:
            raise ValueError(f"chunk {c} belongs to shard {c % n}/{n}, not to this store's shard {i}/{n}")
        if not isinstance(arrays, Mapping):
            raise ValueError(f"arrays must be a dict field -> array, got {type(arrays).__name__}")
        missing = [k for k in self.fields if k not in arrays]
        extra = [k for k in arrays if k not in self.fields]
        if missing or extra:
            raise ValueError(
                f"chunk {c}: arrays must have exactly the fields {list(self.fields)}; "
                f"missing {missing}, unexpected {extra}"
            )
        start, stop = self.chunk_range(c)
        checked: dict[str, np.ndarray] = {}
        for name, (shape, dtype) in self.fields.items():
            a = arrays[name]
            if not isinstance(a, np.ndarray):
                raise ValueError(f"chunk {c} field {name!r}: expected a numpy array, got {type(a).__name__}")
            want = (stop - start, *shape)
            if a.shape != want:
                raise ValueError(f"chunk {c} field {name!r}: expected shape {want}, got {a.shape}")
            if a.dtype != np.dtype(dtype):
                raise ValueError(f"chunk {c} field {name!r}: expected dtype {dtype}, got {a.dtype} (no casting is done)")
            if a.dtype.kind in "fc" and not np.isfinite(a).all():
                bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
                raise ValueError(f"chunk {c} field {name!r}: {bad} non-finite values (NaN or inf)")
            checked[name] = np.ascontiguousarray(a)

        rp = self.record_path(c)
        if rp.exists():
            rp.unlink()
        files = {}
        for name, a in checked.items():
            final = self.data_path(c, name)
            tmp = _tmp_path(final)
            try:
                with open(tmp, "wb") as f:
                    w = _HashingWriter(f)
                    np.lib.format.write_array(w, a, allow_pickle=False)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, final)
            finally:
                if tmp.exists():
                    tmp.unlink()
            files[name] = {"file": final.name, "bytes": w.size, "sha256": w.sha.hexdigest()}
        record = {
            "dataset_id": self.dataset_id,
            "chunk": c,
            "start": start,
            "stop": stop,
            "n": stop - start,
            "files": files,
            "written": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
        _write_json_atomic(rp, record)
        _fsync_dir(self.root)

    # ------------------------------------------------------------------ reading and verification

    def _read_field(self, c: int, name: str, entry: dict, out: np.ndarray | None, check_hash: bool) -> np.ndarray:
        """Read one data file into ``out`` (or a new array), checking size, header and (optionally) sha256."""
        path = self.data_path(c, name)
        shape, dtype = self.fields[name]
        start, stop = self.chunk_range(c)
        want_shape = (stop - start, *shape)
        with self._open_checked(c, path, entry) as f:
            size = entry["bytes"]  # checked by _open_checked
            try:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    hshape, fortran, hdtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    hshape, fortran, hdtype = np.lib.format.read_array_header_2_0(f)
                else:
                    raise ValueError(f"unsupported .npy version {version}")
            except (ValueError, OSError, EOFError, SyntaxError) as e:
                raise CorruptChunkError(path, c, f"unreadable .npy header: {e}") from None
            if tuple(hshape) != want_shape or hdtype != np.dtype(dtype) or fortran:
                raise CorruptChunkError(
                    path, c,
                    f"header says shape {tuple(hshape)} dtype {hdtype} fortran_order={fortran}, "
                    f"expected shape {want_shape} dtype {dtype} in C order",
                )
            offset = f.tell()
            if out is None:
                out = np.empty(want_shape, dtype=np.dtype(dtype))
            nbytes = out.nbytes
            if offset + nbytes != size:
                raise CorruptChunkError(path, c, f"{size} bytes, but header ({offset}) + data ({nbytes}) = {offset + nbytes}")
            sha = hashlib.sha256()
            if check_hash:
                f.seek(0)
                sha.update(f.read(offset))
            if not out.flags.c_contiguous:
                raise ValueError("internal: output buffer must be C-contiguous")
            buf = memoryview(out.reshape(-1).view(np.uint8))
            pos = 0
            while pos < nbytes:
                k = f.readinto(buf[pos:pos + _IO_BLOCK])
                if not k:
                    raise CorruptChunkError(path, c, f"truncated: data ended after {offset + pos} of {size} bytes")
                if check_hash:
                    sha.update(buf[pos:pos + k])
                pos += k
        if check_hash and sha.hexdigest() != entry["sha256"]:
            raise CorruptChunkError(path, c, f"sha256 mismatch: file {sha.hexdigest()}, record {entry['sha256']}")
        return out

    @staticmethod
    def _open_checked(c: int, path: Path, entry: dict):
        """Open a chunk's data file for reading after checking it exists and has the recorded size."""
        try:
            f = open(path, "rb")
        except FileNotFoundError:
            raise CorruptChunkError(path, c, "data file missing") from None
        except OSError as e:
            raise CorruptChunkError(path, c, f"data file unreadable: {e}") from None
        size = os.fstat(f.fileno()).st_size
        if size != entry["bytes"]:
            f.close()
            kind = "truncated" if size < entry["bytes"] else "wrong size"
            raise CorruptChunkError(path, c, f"{kind}: {size} bytes, the record says {entry['bytes']}")
        return f

    def _hash_file(self, c: int, name: str, entry: dict) -> None:
        path = self.data_path(c, name)
        with self._open_checked(c, path, entry) as f:
            sha = hashlib.sha256()
            while block := f.read(_IO_BLOCK):
                sha.update(block)
        if sha.hexdigest() != entry["sha256"]:
            raise CorruptChunkError(path, c, f"sha256 mismatch: file {sha.hexdigest()}, record {entry['sha256']}")

    def verify(self, chunks: Iterable[int] | None = None) -> None:
        """Full check of the given chunks (default: every chunk of the dataset, all shards): each record
        exists and matches the manifest, and each data file has the recorded size and sha256.

        Raises CorruptChunkError naming the first bad file (a missing record included).
        """
        cs = range(self.num_chunks) if chunks is None else [self._check_chunk(c) for c in chunks]
        for c in cs:
            rec = self._read_record(c)
            for name in self.fields:
                self._hash_file(c, name, rec["files"][name])

    def _check_field_names(self, fields: Iterable[str] | None) -> list[str]:
        if fields is None:
            return list(self.fields)
        if isinstance(fields, str):
            fields = [fields]
        names = list(fields)
        unknown = [f for f in names if f not in self.fields]
        if unknown:
            raise ValueError(f"unknown fields {unknown}; the store has {list(self.fields)}")
        return names

    def load_chunk(self, c: int, fields: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """Chunk ``c`` as ``{name: [n_c, *shape] array}`` (all fields, or those named), after checking
        each file's size, header and sha256 against the chunk's record (CorruptChunkError if not)."""
        c = self._check_chunk(c)
        names = self._check_field_names(fields)
        rec = self._read_record(c)
        return {name: self._read_field(c, name, rec["files"][name], None, True) for name in names}

    def load(self, fields: Iterable[str] | None = None, verify: bool = True) -> dict[str, np.ndarray]:
        """The whole dataset: ``{name: [total, *shape] array}`` in global sample order.

        fields: names to load (default all). verify: check every file's sha256 while reading (sizes and
        headers are always checked). Raises ValueError if chunks are missing (how many, which first) and
        CorruptChunkError for a bad chunk.
        """
        names = self._check_field_names(fields)
        missing = self._all_missing()
        if missing:
            head = ", ".join(str(c) for c in missing[:10]) + (", ..." if len(missing) > 10 else "")
            raise ValueError(
                f"{self.root}: dataset incomplete: {len(missing)} of {self.num_chunks} chunks missing "
                f"(chunks {head}); run the writers for their shards to finish it"
            )
        out = {name: np.empty((self.total, *self.fields[name][0]), dtype=np.dtype(self.fields[name][1])) for name in names}
        for c in range(self.num_chunks):
            rec = self._read_record(c)
            start, stop = self.chunk_range(c)
            for name in names:
                self._read_field(c, name, rec["files"][name], out[name][start:stop], verify)
        return out


def _read_manifest(root: Path) -> dict:
    """Read and check ``root/manifest.json``; ValueError if missing or invalid."""
    path = Path(root) / MANIFEST_NAME
    try:
        with open(path, encoding="utf-8") as f:
            m = json.load(f)
    except FileNotFoundError:
        raise ValueError(f"{path} not found: {root} is not a ChunkedStore (or was never created)") from None
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: unreadable manifest: {e}") from None
    if not isinstance(m, dict):
        raise ValueError(f"{path}: manifest is not a JSON object")
    if m.get("format") != FORMAT_NAME:
        raise ValueError(f"{path}: format is {m.get('format')!r}, expected {FORMAT_NAME!r}")
    if m.get("version") != FORMAT_VERSION:
        raise ValueError(f"{path}: format version {m.get('version')!r}, this code reads version {FORMAT_VERSION}")
    for key in ("config", "total", "chunk_size", "fields", "dataset_id"):
        if key not in m:
            raise ValueError(f"{path}: manifest lacks {key!r}")
    if not isinstance(m["config"], dict):
        raise ValueError(f"{path}: 'config' must be an object")
    for key in ("total", "chunk_size"):
        if not _is_int(m[key]) or m[key] < 1:
            raise ValueError(f"{path}: {key!r} must be an int >= 1, got {m[key]!r}")
    try:
        _fields_from_json(m["fields"])
    except ValueError as e:
        raise ValueError(f"{path}: invalid 'fields': {e}") from None
    return m
