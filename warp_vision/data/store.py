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

Every file is written to a hidden temporary name in ``root`` and then renamed over its final name, after
an fsync (:mod:`warp_vision.fileio`), so a reader never sees a half-written file under a final name. A
chunk whose record is absent (an interrupted write) counts as missing and is never read; one whose record
carries another dataset's id (its files copied in from another dataset's directory) is named, with both ids
(``ForeignChunkError``), wherever chunks are counted or read, and is not rendered over; ``write_chunk``
deletes an old record before it replaces a chunk's data. There is no shared file that writers update: shard ``i``
of ``n`` (``my_chunks``: the chunks with ``c % n == i``) writes only its own chunks' files, so ``n``
processes can fill one directory concurrently. The manifest is created once, with an exclusive
link, and afterwards only read: ``create_or_resume`` with settings that differ from the manifest's raises
``ValueError`` naming the first differing key (or, where each side has settings the other lacks, saying it
is another kind of dataset and what its samples hold), so a dataset built with other settings is never reused.
The files themselves (manifest, records, checksummed ``.npy``) are read and written by
:mod:`warp_vision.data.chunk_files`.

Typical use (one process per shard; ``--shard I/N`` parsed with ``parse_shard``)::

    store = ChunkedStore.create_or_resume(root, config, total, chunk_size, fields, shard=(i, n))
    for c in store.missing_chunks():
        a, b = store.chunk_range(c)
        store.write_chunk(c, synthesize(a, b))      # {"onv": [b - a, 43200] float16, ...}
    ...
    data = ChunkedStore.open(root).load()            # {"onv": [total, 43200] float16, ...}
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from warp_vision.data.chunk_files import (
    FORMAT_NAME,
    FORMAT_VERSION,
    MANIFEST_NAME,
    CorruptChunkError,
    ForeignChunkError,
    IncompleteStoreError,
    MissingStoreError,
    fields_from_json,
    fields_to_json,
    first_difference,
    hash_npy,
    is_int,
    json_roundtrip,
    new_manifest,
    new_record,
    normalise_fields,
    read_manifest,
    read_npy,
    read_record,
    write_json_file,
    write_npy,
)

__all__ = ["ChunkedStore", "CorruptChunkError", "FORMAT_NAME", "FORMAT_VERSION", "ForeignChunkError",
           "IncompleteStoreError", "MissingStoreError", "parse_shard"]


def dataset_bytes(fields: Mapping[str, tuple], samples: int) -> int:
    """The size of ``samples`` samples of ``fields`` ({name: (shape, dtype)}): their data files on disk,
    and the arrays ``load`` returns."""
    per = sum(int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize for shape, dtype in fields.values())
    return int(per) * int(samples)


def parse_shard(spec: str) -> tuple[int, int]:
    """Parse a shard spec ``"I/N"`` (shard ``I`` of ``N``, ``0 <= I < N``) into ``(I, N)``.

    Raises ``ValueError`` for anything else ("3", "a/b", "2/2", "-1/4", "1/0").
    """
    if not isinstance(spec, str):
        raise ValueError(f"shard: expected a string 'I/N', got {type(spec).__name__} {spec!r}")
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", spec)
    if m is None:
        raise ValueError(f"shard: expected 'I/N' with integers 0 <= I < N, got {spec!r}")
    return _check_shard((int(m.group(1)), int(m.group(2))))


def _check_shard(shard: Any) -> tuple[int, int]:
    try:
        i, n = shard
    except (TypeError, ValueError):
        raise ValueError(f"shard: expected a pair (I, N) with 0 <= I < N, got {shard!r}") from None
    if not (is_int(i) and is_int(n)):
        raise ValueError(f"shard: expected a pair of integers (I, N), got {shard!r}")
    i, n = int(i), int(n)
    if n < 1:
        raise ValueError(f"shard: the count N in I/N must be >= 1, got {i}/{n}")
    if not 0 <= i < n:
        raise ValueError(f"shard: the index I in I/N must satisfy 0 <= I < N, got {i}/{n}")
    return i, n


#: Seconds :meth:`ChunkedStore.load` waits for missing chunks to appear before it calls the dataset
#: incomplete (0: it does not wait). Set by :func:`waiting_for_writers` while the ranks of a distributed run
#: each render their own shard and then read the whole: a rank done first must not read before the others.
WAIT_FOR_WRITERS_S = 0.0


@contextlib.contextmanager
def waiting_for_writers(seconds: float):
    """Within the block, :meth:`ChunkedStore.load` waits up to ``seconds`` for chunks other writers are
    still writing (see :data:`WAIT_FOR_WRITERS_S`)."""
    global WAIT_FOR_WRITERS_S
    old, WAIT_FOR_WRITERS_S = WAIT_FOR_WRITERS_S, float(seconds)
    try:
        yield
    finally:
        WAIT_FOR_WRITERS_S = old


def _another_kind(manifest: dict, config: Any) -> bool:
    """Whether a manifest's settings are of another kind of dataset than ``config``: each has settings the
    other lacks. (A newer generator of one kind only adds settings, so an older dataset of the kind is not
    called another kind; manifests do not record their kind.)"""
    old = manifest.get("config")
    return isinstance(old, dict) and isinstance(config, dict) and bool(set(old) - set(config)) \
        and bool(set(config) - set(old))


def _refuse_other_settings(path: Path, manifest: dict, requested: dict) -> None:
    """ValueError naming the first of ``requested``'s entries that differs from ``manifest``'s; or, for a
    dataset of another kind, saying so (with what its samples hold) rather than advising to delete it."""
    if "config" in requested and _another_kind(manifest, requested["config"]):
        old, new = set(manifest["config"]), set(requested["config"])
        held = ", ".join(manifest.get("fields") or {}) or "no fields"
        raise ValueError(
            f"{path} holds another kind of dataset: its samples hold {held}; it has settings the one asked for "
            f"does not ({', '.join(sorted(old - new))}) and lacks its ({', '.join(sorted(new - old))}). "
            f"Use another directory: this one's dataset belongs to another kind of run."
        )
    for key, new in requested.items():
        diff = first_difference(key, manifest[key], new)
        if diff is not None:
            raise ValueError(
                f"{path} was written with other settings; first difference: {diff}. "
                f"Use another directory, or delete this one to rebuild the dataset."
            )


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
        self.fields = fields_from_json(manifest["fields"])
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
    ) -> ChunkedStore:
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
        config_json = json_roundtrip(config)
        if not is_int(total) or total < 1:
            raise ValueError(f"total must be an int >= 1, got {total!r}")
        if not is_int(chunk_size) or chunk_size < 1:
            raise ValueError(f"chunk_size must be an int >= 1, got {chunk_size!r}")
        fields_n = normalise_fields(fields)
        shard = _check_shard(shard)
        root = Path(root)
        root.mkdir(parents=True, exist_ok=True)
        path = root / MANIFEST_NAME

        if not path.exists():
            manifest = new_manifest(config_json, total, chunk_size, fields_n)
            # Exclusive: if another shard process created it first, fall through and compare with theirs.
            if write_json_file(path, manifest, exclusive=True):
                return cls(root, manifest, shard, writable=True)

        manifest = read_manifest(root)
        _refuse_other_settings(path, manifest, {
            "config": config_json,
            "total": int(total),
            "chunk_size": int(chunk_size),
            "fields": fields_to_json(fields_n),
        })
        return cls(root, manifest, shard, writable=True)

    @staticmethod
    def check_settings(root: os.PathLike | str, config: dict) -> None:
        """Refuse now what :meth:`create_or_resume` and the writers would refuse later: ``root`` holding a store
        written with another ``config`` (ValueError naming the first difference, or an unreadable manifest), or a
        chunk of another dataset (:class:`ForeignChunkError`). Nothing is written; a directory without a
        manifest passes (its store is yet to be made)."""
        root = Path(root)
        if (root / MANIFEST_NAME).exists():
            manifest = read_manifest(root)
            _refuse_other_settings(root / MANIFEST_NAME, manifest, {"config": json_roundtrip(config)})
            _ = ChunkedStore(root, manifest, (0, 1), writable=False).complete  # (a chunk of another dataset: named)

    @classmethod
    def open(cls, root: os.PathLike | str) -> ChunkedStore:
        """Open an existing store for reading (shard (0, 1); ``write_chunk`` is refused).

        Raises ValueError if ``root/manifest.json`` is missing or not a valid manifest.
        """
        root = Path(root)
        return cls(root, read_manifest(root), (0, 1), writable=False)

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
        if not is_int(c):
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

    def _record_expect(self, c: int) -> dict:
        """What chunk ``c``'s record must say: dataset id, chunk index, sample range and count."""
        start, stop = self.chunk_range(c)
        return {"dataset_id": self.dataset_id, "chunk": c, "start": start, "stop": stop, "n": stop - start}

    def _read_record(self, c: int) -> dict:
        """Chunk ``c``'s record, checked against the manifest; CorruptChunkError if absent or invalid."""
        data_files = {name: self.data_path(c, name).name for name in self.fields}
        return read_record(self.record_path(c), c, self._record_expect(c), data_files)

    def _chunk_present(self, c: int) -> bool:
        """Quick check: valid record, and every data file exists with the recorded size (no hashing). A
        chunk of another dataset is not missing: :class:`ForeignChunkError` names it."""
        try:
            rec = self._read_record(c)
        except ForeignChunkError:
            raise
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
        the wrong size. Sizes only, no hashing (use ``verify`` for that). ForeignChunkError for a chunk
        of another dataset."""
        return [c for c in self.my_chunks() if not self._chunk_present(c)]

    def written(self, c: int) -> bool:
        """Whether chunk ``c`` is written whole now (the quick check of :meth:`missing_chunks`): a writer
        asks again before rendering a chunk that another process may have written meanwhile."""
        return self._chunk_present(self._check_chunk(c))

    def _all_missing(self) -> list[int]:
        return [c for c in range(self.num_chunks) if not self._chunk_present(c)]

    def content_digest(self) -> str:
        """The dataset's id by content: a sha256 over every chunk's recorded data checksums, so two stores
        holding the same samples (one rendered again with the same settings, or copied) have the same digest,
        and a store with any other sample has another. Reads the chunk records only (no data is hashed);
        CorruptChunkError for a chunk that is not written."""
        import hashlib

        h = hashlib.sha256(f"{self.total}:{self.chunk_size}:".encode())
        for c in range(self.num_chunks):
            files = self._read_record(c)["files"]
            for name in sorted(files):
                h.update(f"{c}:{name}:{files[name]['sha256']};".encode())
        return h.hexdigest()

    @property
    def complete(self) -> bool:
        """True when every chunk of the dataset (all shards) is written (quick size check, no hashing)."""
        return all(self._chunk_present(c) for c in range(self.num_chunks))

    @classmethod
    def whole_at(cls, root: os.PathLike | str) -> bool:
        """Whether ``root`` holds a store with every chunk written (:attr:`complete`); False where there is
        no store yet, or one that does not open."""
        try:
            return cls.open(root).complete
        except (ValueError, OSError):
            return False

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
        checked = self._check_arrays(c, arrays)
        rp = self.record_path(c)
        if rp.exists():
            rp.unlink()
        files = {name: write_npy(self.data_path(c, name), a) for name, a in checked.items()}
        write_json_file(rp, new_record(self._record_expect(c), files))

    def _check_arrays(self, c: int, arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Chunk ``c``'s arrays, checked against the fields (names, shapes, dtypes, finite), C-contiguous."""
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
                raise ValueError(
                    f"chunk {c} field {name!r}: expected dtype {dtype}, got {a.dtype} (no casting is done)"
                )
            if a.dtype.kind in "fc" and not np.isfinite(a).all():
                bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
                raise ValueError(f"chunk {c} field {name!r}: {bad} non-finite values (NaN or inf)")
            checked[name] = np.ascontiguousarray(a)
        return checked

    # ------------------------------------------------------------------ reading and verification

    def _read_field(self, c: int, name: str, entry: dict, out: np.ndarray | None, check_hash: bool) -> np.ndarray:
        """Read one data file into ``out`` (or a new array), checking size, header and (optionally) sha256."""
        shape, dtype = self.fields[name]
        start, stop = self.chunk_range(c)
        return read_npy(self.data_path(c, name), c, entry, (stop - start, *shape), dtype, out, check_hash)

    def verify(self, chunks: Iterable[int] | None = None) -> None:
        """Full check of the given chunks (default: every chunk of the dataset, all shards): each record
        exists and matches the manifest, and each data file has the recorded size and sha256.

        Raises CorruptChunkError naming the first bad file (a missing record included).
        """
        cs = range(self.num_chunks) if chunks is None else [self._check_chunk(c) for c in chunks]
        for c in cs:
            rec = self._read_record(c)
            for name in self.fields:
                hash_npy(self.data_path(c, name), c, rec["files"][name])

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
        headers are always checked). Raises IncompleteStoreError if chunks are missing (how many, which first),
        CorruptChunkError for a bad chunk and ForeignChunkError for another dataset's.
        """
        names = self._check_field_names(fields)
        missing = self._all_missing()
        deadline = time.monotonic() + WAIT_FOR_WRITERS_S
        while missing and time.monotonic() < deadline:  # other ranks still writing their shards
            time.sleep(min(2.0, max(0.0, deadline - time.monotonic())))
            missing = self._all_missing()
        if missing:
            raise IncompleteStoreError(self.root, missing, self.num_chunks)
        out = {name: np.empty((self.total, *self.fields[name][0]),
                              dtype=np.dtype(self.fields[name][1])) for name in names}
        for c in range(self.num_chunks):
            rec = self._read_record(c)
            start, stop = self.chunk_range(c)
            for name in names:
                self._read_field(c, name, rec["files"][name], out[name][start:stop], verify)
        return out
