"""What the dataset generators share: a store with its retina beside it, and rendering its missing chunks."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from warp_vision.data.store import ChunkedStore, dataset_bytes


def open_store(out_dir, manifest: dict, total: int, chunk_size: int, fields: dict, shard, retina,
               batch: int) -> ChunkedStore:
    """Create or resume the store in ``out_dir`` and keep ``retina`` in ``out_dir/retina.npz`` (a store
    whose saved retina differs from ``retina`` is refused with ``ValueError``)."""
    from warp_vision.eye.retina import Retina

    if batch < 1:
        raise ValueError(f"batch: expected >= 1, got {batch}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    store = ChunkedStore.create_or_resume(out, manifest, total, chunk_size, fields, shard=tuple(shard))
    path = out / "retina.npz"
    if path.exists():
        saved = Retina.load(path)
        if not np.array_equal(saved.rho, retina.rho) or not np.array_equal(saved.theta, retina.theta):
            raise ValueError(f"{path}: holds a different retina than this config builds")
    else:
        retina.save(path)
    return store


def pending(store: ChunkedStore) -> tuple[int, int]:
    """(samples still to render, samples of this shard) of ``store``."""
    size = lambda cs: sum(store.chunk_range(c)[1] - store.chunk_range(c)[0] for c in cs)  # noqa: E731
    return size(store.missing_chunks()), size(store.my_chunks())


def render_missing(store: ChunkedStore, render: Callable[[range], dict], batch: int, progress: bool, log,
                   what: str = "ONVs") -> None:
    """Render this shard's missing chunks, ``batch`` samples per ``render(range)`` call, with a progress
    bar (rate and time left), and write each chunk when it is whole; a chunk another process wrote
    meanwhile is skipped."""
    from tqdm import tqdm

    from warp_vision.fileio import probe_writable
    from warp_vision.resources import require_disk

    todo, mine = pending(store)
    if todo:
        probe_writable(store.root)  # a read-only or full directory fails now, not after the first chunk
        # (a small disk, too)
        require_disk(dataset_bytes(store.fields, todo), store.root, "the dataset's missing chunks")
    t0, skipped = time.perf_counter(), 0
    unit = "ONV" if what == "ONVs" else "sample"
    with tqdm(total=mine, initial=mine - todo, unit=unit, desc="synthesis", disable=not progress,
              dynamic_ncols=True) as bar:
        for c in store.missing_chunks():
            lo, hi = store.chunk_range(c)
            if store.written(c):  # another process (a run of the same dataset, `data`) wrote it meanwhile
                bar.update(hi - lo)
                skipped += hi - lo
                continue
            parts = []
            for s in range(lo, hi, batch):
                parts.append(render(range(s, min(hi, s + batch))))
                bar.update(min(hi, s + batch) - s)
            if not store.written(c):  # (written meanwhile: the same bytes, and a rewrite would hide it from readers)
                store.write_chunk(c, {k: np.concatenate([p[k] for p in parts]) for k in parts[0]})
    dt, done = time.perf_counter() - t0, todo - skipped
    log(f"synthesised {done:,} {what} in {dt:.0f} s ({done / dt:.1f} {what}/s)"
        + (f"; {skipped:,} were written meanwhile by another process" if skipped else ""))
