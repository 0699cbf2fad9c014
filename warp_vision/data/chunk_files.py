"""The on-disk format of a :class:`warp_vision.data.store.ChunkedStore`: its manifest, its field specs,
its chunk records and its checksummed ``.npy`` data files (see the store's module docstring for the
layout of a store's directory).

Every file is written through :mod:`warp_vision.fileio` (a temporary name, fsync, rename): the manifest
and the records as JSON with ``indent=1`` and no NaN, the data files with ``numpy.lib.format.write_array``
through a writer that hashes every byte. Reading checks every file against what the manifest and the
chunk's record say (shape, dtype, size, sha256) and raises :class:`CorruptChunkError` naming the file.
"""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import platform
import re
import socket
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from warp_vision.fileio import NPY_FORMAT_ERRORS, atomic_write, write_json

__all__ = ["CorruptChunkError", "FORMAT_NAME", "FORMAT_VERSION", "ForeignChunkError", "IncompleteStoreError",
           "MANIFEST_NAME"]

#: The ``format`` entry of every manifest written by the store.
FORMAT_NAME = "warp_vision.ChunkedStore"
#: The on-disk format version; ``open`` refuses other versions.
FORMAT_VERSION = 1

MANIFEST_NAME = "manifest.json"
_FIELD_NAME = re.compile(r"^[A-Za-z0-9_]+$")
_ALLOWED_KINDS = "biufc"  # bool, signed/unsigned int, float, complex
_IO_BLOCK = 1 << 22  # bytes per read when hashing/reading a file

#: A field spec: name -> (per-sample shape, numpy dtype name).
Fields = dict[str, tuple[tuple[int, ...], str]]


class MissingStoreError(ValueError):
    """No store at ``root`` (no manifest): never created, or deleted (datasets are a cache)."""

    def __init__(self, root: os.PathLike | str):
        self.root = Path(root)
        super().__init__(f"{self.root / MANIFEST_NAME} not found: {self.root} is not a ChunkedStore (or was never "
                         "created)")


class IncompleteStoreError(ValueError):
    """Chunks missing when a store is read whole (``missing``: their indices, of ``num_chunks``). ``finish``: the
    command that renders them, where the reader knows it (the run whose dataset it is); a reader that does can
    name it on an error raised without one (:meth:`finished_by`)."""

    def __init__(self, root: os.PathLike | str, missing: list[int], num_chunks: int, finish: str | None = None):
        self.root, self.missing, self.num_chunks, self.finish = Path(root), list(missing), int(num_chunks), finish
        head = ", ".join(str(c) for c in self.missing[:10]) + (", ..." if len(self.missing) > 10 else "")
        how = (f"{finish} renders them" if finish else
               "the command that made it renders them when run again (a training run's dataset: python -m "
               "warp_vision.train evaluate RUN_DIR)")
        super().__init__(f"{self.root}: dataset incomplete: {len(self.missing)} of {self.num_chunks} chunks missing "
                         f"(chunks {head}); {how}")

    def finished_by(self, command: str) -> IncompleteStoreError:
        """This error, naming ``command`` as the one that renders the missing chunks."""
        return IncompleteStoreError(self.root, self.missing, self.num_chunks, command)


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


class ForeignChunkError(CorruptChunkError):
    """A chunk whose record carries another dataset's id than the manifest's: its files were copied in from
    another dataset's directory (or the manifest was made anew over old chunks). It is neither this dataset's
    nor missing: it is named, and rendered again only once its files are removed."""

    def __init__(self, path: os.PathLike | str, chunk: int, theirs: Any, ours: str):
        self.path, self.chunk, self.theirs, self.ours = Path(path), int(chunk), theirs, ours
        self.what = (f"chunk {self.chunk} belongs to another dataset: its record's dataset_id is {theirs!r}, this "
                     f"dataset's ({MANIFEST_NAME}) {ours!r} (copied in from another dataset's directory?); remove its "
                     f"files ({self.path.parent / f'chunk_{self.chunk:06d}.*'}) to have it rendered again")
        ValueError.__init__(self, f"{self.path}: {self.what}")


def is_int(x: Any) -> bool:
    """An int or numpy integer, not a bool."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def write_json_file(path: Path, obj: Any, exclusive: bool = False) -> bool:
    """``obj`` as the store's JSON (``indent=1``, no NaN, a trailing newline), atomically; with
    ``exclusive`` never over an existing file (returns False then)."""
    return write_json(path, obj, indent=1, exclusive=exclusive, allow_nan=False)


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


# ------------------------------------------------------------------ fields


def normalise_fields(fields: Mapping[str, Any]) -> Fields:
    """Check a fields spec and return it as ``{name: (shape tuple, dtype name)}`` in the given order."""
    if not isinstance(fields, Mapping) or not fields:
        raise ValueError(f"fields must be a non-empty dict name -> (shape, dtype), got {fields!r}")
    return {name: _normalise_field(name, spec) for name, spec in fields.items()}


def _normalise_field(name: Any, spec: Any) -> tuple[tuple[int, ...], str]:
    if not isinstance(name, str) or not _FIELD_NAME.match(name):
        raise ValueError(f"field name must match [A-Za-z0-9_]+ (it becomes part of a file name), got {name!r}")
    try:
        shape, dtype = spec
    except (TypeError, ValueError):
        raise ValueError(f"field {name!r}: expected (shape, dtype), got {spec!r}") from None
    if is_int(shape):
        shape = (shape,)
    try:
        shape = tuple(shape)
    except TypeError:
        raise ValueError(f"field {name!r}: shape must be a tuple of ints, got {shape!r}") from None
    if not all(is_int(s) and s >= 0 for s in shape):
        raise ValueError(f"field {name!r}: shape must be a tuple of non-negative ints, got {shape!r}")
    try:
        dt = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"field {name!r}: not a numpy dtype: {dtype!r}") from None
    if dt.kind not in _ALLOWED_KINDS or dt.fields is not None or dt.subdtype is not None:
        raise ValueError(f"field {name!r}: dtype must be a plain bool/int/float/complex dtype, got {dtype!r}")
    if not dt.isnative:
        raise ValueError(f"field {name!r}: dtype must be in native byte order, got {dtype!r}")
    return tuple(int(s) for s in shape), dt.name


def fields_to_json(fields: Mapping[str, tuple[tuple[int, ...], str]]) -> dict[str, dict]:
    return {name: {"shape": list(shape), "dtype": dtype} for name, (shape, dtype) in fields.items()}


def fields_from_json(obj: Any) -> Fields:
    if not isinstance(obj, dict):
        raise ValueError(f"'fields' must be an object, got {obj!r}")
    spec = {}
    for name, f in obj.items():
        if not isinstance(f, dict) or "shape" not in f or "dtype" not in f:
            raise ValueError(f"field {name!r} must be an object with 'shape' and 'dtype', got {f!r}")
        spec[name] = (f["shape"], f["dtype"])
    return normalise_fields(spec)


# ------------------------------------------------------------------ the manifest


def json_roundtrip(config: Any) -> Any:
    """``config`` as it will read back from JSON (tuples become lists); ValueError if not serialisable."""
    try:
        text = json.dumps(config, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as e:
        raise ValueError(f"config must be JSON-serialisable (finite numbers, str keys): {e}") from None
    return json.loads(text)


def first_difference(path: str, old: Any, new: Any) -> str | None:
    """The path of the first difference between two JSON values, with both values; None if equal."""
    if isinstance(old, dict) and isinstance(new, dict):
        for k in list(old) + [k for k in new if k not in old]:
            if k not in new:
                return f"{path}[{k!r}]: the manifest has {old[k]!r}, the request has no such key"
            if k not in old:
                return f"{path}[{k!r}]: the manifest has no such key, the request has {new[k]!r}"
            d = first_difference(f"{path}[{k!r}]", old[k], new[k])
            if d is not None:
                return d
        return None
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        for j, (a, b) in enumerate(zip(old, new)):
            d = first_difference(f"{path}[{j}]", a, b)
            if d is not None:
                return d
        return None
    if type(old) is not type(new) or old != new:
        return f"{path}: the manifest has {old!r}, the request has {new!r}"
    return None


def new_manifest(config_json: Any, total: int, chunk_size: int, fields: Fields) -> dict:
    """A new dataset's manifest: the settings, a random dataset id and creation info."""
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "config": config_json,
        "total": int(total),
        "chunk_size": int(chunk_size),
        "fields": fields_to_json(fields),
        "dataset_id": uuid.uuid4().hex,
        "created": {
            "time": _now(),
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "python": platform.python_version(),
            "numpy": np.__version__,
        },
    }


def read_manifest(root: Path) -> dict:
    """Read and check ``root/manifest.json``; ValueError if invalid (:class:`MissingStoreError` if missing)."""
    path = Path(root) / MANIFEST_NAME
    try:
        with open(path, encoding="utf-8") as f:
            m = json.load(f)
    except FileNotFoundError:
        raise MissingStoreError(root) from None
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
        if not is_int(m[key]) or m[key] < 1:
            raise ValueError(f"{path}: {key!r} must be an int >= 1, got {m[key]!r}")
    try:
        fields_from_json(m["fields"])
    except ValueError as e:
        raise ValueError(f"{path}: invalid 'fields': {e}") from None
    return m


# ------------------------------------------------------------------ chunk records


def new_record(expect: dict, files: dict) -> dict:
    """A chunk's record: ``expect`` (dataset_id, chunk, start, stop, n), the data files' entries, the time."""
    return {**expect, "files": files, "written": _now()}


def read_record(path: Path, c: int, expect: Mapping[str, Any], data_files: Mapping[str, str]) -> dict:
    """Chunk ``c``'s record at ``path``, checked: each key of ``expect`` has its value, and ``files`` has
    a well-formed entry for exactly the fields of ``data_files`` (field -> data file name).

    Raises CorruptChunkError if the record is absent or invalid.
    """
    try:
        with open(path, encoding="utf-8") as f:
            rec = json.load(f)
    except FileNotFoundError:
        raise CorruptChunkError(path, c,
                                "record missing: the chunk was never written or its write was interrupted") from None
    except (OSError, ValueError) as e:
        raise CorruptChunkError(path, c, f"record unreadable: {e}") from None
    if not isinstance(rec, dict):
        raise CorruptChunkError(path, c, "record is not a JSON object")
    if "dataset_id" in expect and rec.get("dataset_id") != expect["dataset_id"]:
        raise ForeignChunkError(path, c, rec.get("dataset_id"), expect["dataset_id"])
    for k, v in expect.items():
        if rec.get(k) != v:
            raise CorruptChunkError(path, c, f"record has {k}={rec.get(k)!r}, expected {v!r}")
    files = rec.get("files")
    if not isinstance(files, dict) or set(files) != set(data_files):
        got = sorted(files) if isinstance(files, dict) else files
        raise CorruptChunkError(path, c, f"record lists files for {got!r}, expected {sorted(data_files)!r}")
    for name, entry in files.items():
        ok = (
            isinstance(entry, dict)
            and entry.get("file") == data_files[name]
            and is_int(entry.get("bytes"))
            and isinstance(entry.get("sha256"), str)
            and len(entry["sha256"]) == 64
        )
        if not ok:
            raise CorruptChunkError(path, c, f"record entry for field {name!r} is malformed: {entry!r}")
    return rec


# ------------------------------------------------------------------ data files


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


def write_npy(path: Path, a: np.ndarray) -> dict:
    """Write ``a`` to ``path`` as an ``.npy``, atomically; returns its record entry (file name, size in
    bytes, sha256 of the bytes written)."""
    writer: list[_HashingWriter] = []

    def write(f) -> None:
        writer.append(_HashingWriter(f))
        np.lib.format.write_array(writer[0], a, allow_pickle=False)

    atomic_write(path, write, mkdir=False)
    w = writer[0]
    return {"file": path.name, "bytes": w.size, "sha256": w.sha.hexdigest()}


def open_checked(c: int, path: Path, entry: dict):
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


def _check_sha256(path: Path, c: int, sha, entry: dict) -> None:
    if sha.hexdigest() != entry["sha256"]:
        raise CorruptChunkError(path, c, f"sha256 mismatch: file {sha.hexdigest()}, record {entry['sha256']}")


def hash_npy(path: Path, c: int, entry: dict) -> None:
    """Check a data file's size and sha256 against its record entry (CorruptChunkError if not)."""
    with open_checked(c, path, entry) as f:
        sha = hashlib.sha256()
        while block := f.read(_IO_BLOCK):
            sha.update(block)
    _check_sha256(path, c, sha, entry)


def _read_header(f, path: Path, c: int, want_shape: tuple, dtype: str) -> None:
    """Read and check an ``.npy`` header: C order, ``want_shape`` and ``dtype``."""
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            hshape, fortran, hdtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            hshape, fortran, hdtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except (OSError, *NPY_FORMAT_ERRORS) as e:
        raise CorruptChunkError(path, c, f"unreadable .npy header: {e}") from None
    if tuple(hshape) != want_shape or hdtype != np.dtype(dtype) or fortran:
        raise CorruptChunkError(
            path, c,
            f"header says shape {tuple(hshape)} dtype {hdtype} fortran_order={fortran}, "
            f"expected shape {want_shape} dtype {dtype} in C order",
        )


def read_npy(path: Path, c: int, entry: dict, want_shape: tuple, dtype: str, out: np.ndarray | None,
             check_hash: bool) -> np.ndarray:
    """Read one data file into ``out`` (or a new array), checking size, header and (optionally) sha256."""
    with open_checked(c, path, entry) as f:
        size = entry["bytes"]  # checked by open_checked
        _read_header(f, path, c, want_shape, dtype)
        offset = f.tell()
        if out is None:
            out = np.empty(want_shape, dtype=np.dtype(dtype))
        nbytes = out.nbytes
        if offset + nbytes != size:
            raise CorruptChunkError(path, c,
                                    f"{size} bytes, but header ({offset}) + data ({nbytes}) = {offset + nbytes}")
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
    if check_hash:
        _check_sha256(path, c, sha, entry)
    return out
