"""Tests of warp_vision.data.store: round trip, resume, shards, corruption detection, validation."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from warp_vision.data.store import ChunkedStore, CorruptChunkError, ForeignChunkError, MissingStoreError, parse_shard

FIELDS = {"onv": ((6,), "float16"), "target": ((2,), "float32"), "label": ((), "int64")}
CONFIG = {"seed": 3, "retina": {"n": 1000, "layout": "logpolar"}, "sizes": (1, 2)}
TOTAL, CHUNK = 23, 5  # 5 chunks, the last one holds 3 samples


def make_data(total=TOTAL, seed=0):
    """Deterministic data with values that float16 represents exactly or not (bit-exactness matters)."""
    rng = np.random.default_rng(seed)
    return {
        "onv": rng.standard_normal((total, 6)).astype(np.float16),
        "target": rng.standard_normal((total, 2)).astype(np.float32),
        "label": np.arange(total, dtype=np.int64) * 7,
    }


def chunk_of(store, data, c):
    a, b = store.chunk_range(c)
    return {k: v[a:b] for k, v in data.items()}


def new_store(root, shard=(0, 1), config=CONFIG, total=TOTAL, chunk=CHUNK, fields=FIELDS):
    return ChunkedStore.create_or_resume(root, config, total, chunk, fields, shard=shard)


def fill(store, data, chunks=None):
    for c in store.my_chunks() if chunks is None else chunks:
        store.write_chunk(c, chunk_of(store, data, c))


def assert_bit_equal(got, want):
    assert set(got) == set(want)
    for k in want:
        assert got[k].dtype == want[k].dtype, k
        assert got[k].shape == want[k].shape, k
        assert got[k].tobytes() == want[k].tobytes(), k


# ---------------------------------------------------------------------------- round trip and layout


def test_round_trip_bit_exact(tmp_path):
    data = make_data()
    store = new_store(tmp_path)
    assert store.num_chunks == 5 and len(store) == TOTAL
    assert [store.chunk_range(c) for c in range(5)] == [(0, 5), (5, 10), (10, 15), (15, 20), (20, 23)]
    assert store.missing_chunks() == [0, 1, 2, 3, 4]
    assert not store.complete
    fill(store, data)
    assert store.missing_chunks() == [] and store.complete
    store.verify()

    ro = ChunkedStore.open(tmp_path)
    assert ro.fields == {"onv": ((6,), "float16"), "target": ((2,), "float32"), "label": ((), "int64")}
    assert ro.config == {"seed": 3, "retina": {"n": 1000, "layout": "logpolar"}, "sizes": [1, 2]}
    assert (ro.total, ro.chunk_size, ro.num_chunks) == (TOTAL, CHUNK, 5)
    assert_bit_equal(ro.load(), data)
    assert_bit_equal(ro.load(verify=False), data)
    assert_bit_equal(ro.load(fields=["target"]), {"target": data["target"]})
    assert_bit_equal(ro.load_chunk(4), chunk_of(ro, data, 4))
    # loaded arrays are ordinary writable arrays
    out = ro.load_chunk(1)
    out["onv"][0, 0] = 1.0

    names = sorted(p.name for p in tmp_path.iterdir())
    assert "manifest.json" in names and "chunk_000004.json" in names and "chunk_000004.onv.npy" in names
    assert not [n for n in names if ".tmp" in n]  # no temporary files left behind
    # data files are ordinary .npy files
    np.testing.assert_array_equal(np.load(tmp_path / "chunk_000002.target.npy"), data["target"][10:15])
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["total"] == TOTAL and manifest["fields"]["onv"] == {"shape": [6], "dtype": "float16"}
    assert "created" in manifest


def test_open_rejects_missing_or_invalid_manifest(tmp_path):
    with pytest.raises(ValueError, match="manifest.json"):
        ChunkedStore.open(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(ValueError, match="unreadable manifest"):
        ChunkedStore.open(tmp_path)
    (tmp_path / "manifest.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(ValueError, match="format"):
        ChunkedStore.open(tmp_path)


def test_open_is_read_only(tmp_path):
    data = make_data()
    new_store(tmp_path)
    ro = ChunkedStore.open(tmp_path)
    with pytest.raises(ValueError, match="read-only"):
        ro.write_chunk(0, chunk_of(ro, data, 0))


# ---------------------------------------------------------------------------- resume


def test_resume_reports_missing_and_checks_settings(tmp_path):
    data = make_data()
    s1 = new_store(tmp_path)
    fill(s1, data, chunks=[0, 3])
    assert s1.missing_chunks() == [1, 2, 4]

    s2 = new_store(tmp_path)  # same arguments: resumes
    assert s2.missing_chunks() == [1, 2, 4]
    assert s2.dataset_id == s1.dataset_id
    # dtype given differently but meaning the same thing still matches
    s3 = ChunkedStore.create_or_resume(tmp_path, dict(CONFIG), TOTAL, CHUNK,
                                       {"onv": ((6,), "f2"), "target": ([2], np.float32), "label": ((), "i8")})
    assert s3.missing_chunks() == [1, 2, 4]
    fill(s2, data, chunks=s2.missing_chunks())
    assert s1.complete
    assert_bit_equal(ChunkedStore.open(tmp_path).load(), data)

    with pytest.raises(ValueError, match=r"config\['retina'\]\['n'\].*1000.*999"):
        new_store(tmp_path, config={**CONFIG, "retina": {"n": 999, "layout": "logpolar"}})
    with pytest.raises(ValueError, match=r"config\['extra'\]"):
        new_store(tmp_path, config={**CONFIG, "extra": 1})
    with pytest.raises(ValueError, match=r"config\['seed'\]"):
        new_store(tmp_path, config={**CONFIG, "seed": 3.0})  # int vs float counts as a difference
    with pytest.raises(ValueError, match="total"):
        new_store(tmp_path, total=24)
    with pytest.raises(ValueError, match="chunk_size"):
        new_store(tmp_path, chunk=4)
    with pytest.raises(ValueError, match=r"fields\['onv'\]"):
        new_store(tmp_path, fields={**FIELDS, "onv": ((6,), "float32")})
    with pytest.raises(ValueError, match=r"fields\['extra'\]"):
        new_store(tmp_path, fields={**FIELDS, "extra": ((1,), "float32")})


def test_check_settings_refuses_what_resuming_would_and_writes_nothing(tmp_path):
    ChunkedStore.check_settings(tmp_path / "none", CONFIG)  # no store yet: nothing to compare
    assert not (tmp_path / "none").exists()
    new_store(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    ChunkedStore.check_settings(tmp_path, dict(CONFIG))  # (tuples compare as the JSON lists they become)
    with pytest.raises(ValueError, match=r"manifest.json was written with other settings.*config\['retina'\]\['n'\]"):
        ChunkedStore.check_settings(tmp_path, {**CONFIG, "retina": {"n": 999, "layout": "logpolar"}})
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    (tmp_path / "manifest.json").write_text("{")
    with pytest.raises(ValueError, match="manifest"):
        ChunkedStore.check_settings(tmp_path, CONFIG)


def test_a_store_of_another_kind_is_called_so_and_not_offered_for_deletion(tmp_path):
    new_store(tmp_path)
    other = {k: v for k, v in CONFIG.items() if k != "retina"} | {"gazes": 10}  # each lacks a setting of the other
    for refuse in (lambda: ChunkedStore.check_settings(tmp_path, other),
                   lambda: ChunkedStore.create_or_resume(tmp_path, other, TOTAL, CHUNK, FIELDS)):
        with pytest.raises(ValueError) as e:
            refuse()
        assert "holds another kind of dataset: its samples hold onv, target, label;" in str(e.value)
        assert "does not (retina) and lacks its (gazes)" in str(e.value) and "delete" not in str(e.value)
    # a dataset of the kind from before a setting was added (one side only) is the kind's, of other settings
    with pytest.raises(ValueError, match=r"first difference: config\['gazes'\]: the manifest has no such key"):
        ChunkedStore.check_settings(tmp_path, CONFIG | {"gazes": 10})


def test_missing_record_means_missing_chunk_and_is_not_read(tmp_path):
    data = make_data()
    store = new_store(tmp_path)
    fill(store, data)
    # an interrupted write: data files there, the record (written last) not
    (tmp_path / "chunk_000002.json").unlink()
    # make the orphaned data garbage: it must never be read
    with open(tmp_path / "chunk_000002.onv.npy", "r+b") as f:
        f.seek(-1, os.SEEK_END)
        f.write(b"\xff")
    assert store.missing_chunks() == [2]
    assert not store.complete
    with pytest.raises(ValueError, match="1 of 5 chunks missing") as e:
        store.load()
    assert not isinstance(e.value, CorruptChunkError)
    with pytest.raises(CorruptChunkError, match="chunk_000002.json"):
        store.load_chunk(2)
    with pytest.raises(CorruptChunkError, match="chunk_000002.json"):
        store.verify()
    store.verify([0, 1, 3, 4])
    # resuming rewrites it
    resumed = new_store(tmp_path)
    fill(resumed, data, chunks=resumed.missing_chunks())
    assert resumed.complete
    assert_bit_equal(resumed.load(), data)


def test_quick_check_counts_wrong_size_or_absent_data_as_missing(tmp_path):
    data = make_data()
    store = new_store(tmp_path)
    fill(store, data)
    (tmp_path / "chunk_000001.target.npy").unlink()
    with open(tmp_path / "chunk_000003.onv.npy", "ab") as f:
        f.write(b"\0")
    assert store.missing_chunks() == [1, 3]
    # a record from another dataset (manifest deleted and recreated) is neither present nor missing: it is named
    (tmp_path / "manifest.json").unlink()
    fresh = new_store(tmp_path)
    assert fresh.dataset_id != store.dataset_id
    with pytest.raises(ForeignChunkError) as e:
        fresh.missing_chunks()
    assert (f"chunk 0 belongs to another dataset: its record's dataset_id is '{store.dataset_id}', this dataset's "
            f"(manifest.json) '{fresh.dataset_id}'") in str(e.value)
    with pytest.raises(CorruptChunkError, match="dataset_id"):
        fresh.load_chunk(0)


def test_rewriting_a_chunk_replaces_it(tmp_path):
    data = make_data()
    other = make_data(seed=1)
    store = new_store(tmp_path)
    fill(store, data)
    store.write_chunk(1, chunk_of(store, other, 1))
    store.verify()
    assert_bit_equal(store.load_chunk(1), chunk_of(store, other, 1))
    assert_bit_equal(store.load_chunk(0), chunk_of(store, data, 0))


def test_failed_rewrite_leaves_chunk_missing(tmp_path, monkeypatch):
    """A rewrite that dies after replacing some data files must not leave the old record vouching
    for a mix of old and new files; and its temporary file is cleaned up."""
    data = make_data()
    other = make_data(seed=1)
    store = new_store(tmp_path)
    fill(store, data)
    real = np.lib.format.write_array
    calls = []

    def dying_write_array(fp, array, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            fp.write(b"partial")
            raise OSError("disk full")
        return real(fp, array, *args, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array", dying_write_array)
    with pytest.raises(OSError, match="disk full"):
        store.write_chunk(1, chunk_of(store, other, 1))
    monkeypatch.undo()
    assert store.missing_chunks() == [1]
    assert not [p.name for p in tmp_path.iterdir() if ".tmp" in p.name]
    fill(store, other, chunks=[1])
    assert_bit_equal(store.load_chunk(1), chunk_of(store, other, 1))


# ---------------------------------------------------------------------------- shards


def test_two_shards_into_one_directory(tmp_path):
    data = make_data()
    s0 = new_store(tmp_path, shard=(0, 2))
    s1 = new_store(tmp_path, shard=(1, 2))
    assert s0.my_chunks() == [0, 2, 4] and s1.my_chunks() == [1, 3]
    # interleave the writes like two concurrent processes
    s1.write_chunk(3, chunk_of(s1, data, 3))
    s0.write_chunk(0, chunk_of(s0, data, 0))
    assert s0.missing_chunks() == [2, 4] and s1.missing_chunks() == [1]
    assert not s0.complete
    fill(s0, data, chunks=s0.missing_chunks())
    assert s0.missing_chunks() == [] and not s0.complete and not s1.complete
    fill(s1, data, chunks=s1.missing_chunks())
    assert s0.complete and s1.complete
    ro = ChunkedStore.open(tmp_path)
    ro.verify()
    assert_bit_equal(ro.load(), data)
    # a different split of the same directory sees the same chunks as written
    assert new_store(tmp_path, shard=(2, 3)).my_chunks() == [2]
    assert new_store(tmp_path, shard=(2, 3)).missing_chunks() == []


def test_write_chunk_not_owned_by_shard(tmp_path):
    data = make_data()
    s1 = new_store(tmp_path, shard=(1, 2))
    with pytest.raises(ValueError, match="chunk 2 belongs to shard 0/2"):
        s1.write_chunk(2, chunk_of(s1, data, 2))
    assert not (tmp_path / "chunk_000002.onv.npy").exists()


# ---------------------------------------------------------------------------- corruption


def _corrupt_truncate(path):
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(size - 3)


def _corrupt_flip(path):
    with open(path, "r+b") as f:
        f.seek(-2, os.SEEK_END)  # inside the data, after the header: size unchanged
        b = f.read(1)
        f.seek(-2, os.SEEK_END)
        f.write(bytes([b[0] ^ 0x01]))


def _corrupt_flip_header(path):
    with open(path, "r+b") as f:
        f.seek(20)
        b = f.read(1)
        f.seek(20)
        f.write(bytes([b[0] ^ 0x20]))


def _corrupt_unclose_header(path):
    # numpy's header filter raised tokenize.TokenError through load_chunk (and, on Python 3.12+, for
    # flip-header-byte too): not a CorruptChunkError
    with open(path, "r+b") as f:
        head = f.read(128)
        f.seek(head.index(b"}"))
        f.write(b" ")


def _corrupt_delete(path):
    path.unlink()


@pytest.mark.parametrize(
    "corrupt, what",
    [
        (_corrupt_truncate, "truncated"),
        (_corrupt_flip, "sha256 mismatch"),
        (_corrupt_flip_header, "sha256 mismatch|header"),
        (_corrupt_unclose_header, "sha256 mismatch|header"),
        (_corrupt_delete, "missing"),
    ],
    ids=["truncate", "flip-data-byte", "flip-header-byte", "unclosed-header", "delete"],
)
@pytest.mark.parametrize("field", ["onv", "target"])
def test_corruption_is_detected(tmp_path, corrupt, what, field):
    data = make_data()
    store = new_store(tmp_path)
    fill(store, data)
    name = f"chunk_000003.{field}.npy"
    corrupt(tmp_path / name)
    ro = ChunkedStore.open(tmp_path)

    with pytest.raises(CorruptChunkError, match=what) as e:
        ro.verify()
    assert name in str(e.value) and e.value.chunk == 3
    with pytest.raises(CorruptChunkError, match=what) as e:
        ro.load_chunk(3)
    assert name in str(e.value)
    ro.verify([0, 1, 2, 4])  # the other chunks are fine
    assert_bit_equal(ro.load_chunk(2), chunk_of(ro, data, 2))

    if corrupt in (_corrupt_truncate, _corrupt_delete):
        # the quick size check already sees these: the chunk counts as missing
        assert ro.missing_chunks() == [3]
        with pytest.raises(ValueError, match="1 of 5 chunks missing"):
            ro.load()
    else:
        # same size: only hashing finds it
        assert ro.missing_chunks() == []
        with pytest.raises(CorruptChunkError, match=what) as e:
            ro.load()
        assert name in str(e.value)
        if corrupt is _corrupt_flip:
            flipped = ro.load(verify=False)  # without hashes the flipped byte goes unnoticed
            assert flipped[field].tobytes() != data[field].tobytes()


def test_corrupt_record_is_reported(tmp_path):
    data = make_data()
    store = new_store(tmp_path)
    fill(store, data)
    rp = tmp_path / "chunk_000001.json"
    rec = json.loads(rp.read_text())
    rec["files"]["onv"]["sha256"] = "0" * 64
    rp.write_text(json.dumps(rec))
    with pytest.raises(CorruptChunkError, match="chunk_000001.onv.npy.*sha256 mismatch"):
        store.verify()
    rp.write_text("{truncated")
    assert store.missing_chunks() == [1]
    with pytest.raises(CorruptChunkError, match="chunk_000001.json.*unreadable"):
        store.load_chunk(1)


# ---------------------------------------------------------------------------- validation


def test_write_chunk_validation(tmp_path):
    data = make_data()
    store = new_store(tmp_path)
    good = chunk_of(store, data, 4)  # the short last chunk: 3 samples

    def bad(**changes):
        return {**good, **changes}

    with pytest.raises(ValueError, match=r"'onv': expected shape \(3, 6\), got \(5, 6\)"):
        store.write_chunk(4, bad(onv=data["onv"][:5]))
    with pytest.raises(ValueError, match=r"'target': expected shape \(3, 2\), got \(3, 3\)"):
        store.write_chunk(4, bad(target=np.zeros((3, 3), np.float32)))
    with pytest.raises(ValueError, match="expected dtype float16, got float32"):
        store.write_chunk(4, bad(onv=good["onv"].astype(np.float32)))
    with pytest.raises(ValueError, match="expected dtype int64, got int32"):
        store.write_chunk(4, bad(label=good["label"].astype(np.int32)))
    for v in (np.nan, np.inf, -np.inf):
        t = good["target"].copy()
        t[1, 0] = v
        with pytest.raises(ValueError, match="'target': 1 non-finite"):
            store.write_chunk(4, bad(target=t))
    o = good["onv"].copy()
    o[0, 0] = np.float16(np.inf)
    with pytest.raises(ValueError, match="'onv': 1 non-finite"):
        store.write_chunk(4, bad(onv=o))
    with pytest.raises(ValueError, match=r"missing \['label'\]"):
        store.write_chunk(4, {k: v for k, v in good.items() if k != "label"})
    with pytest.raises(ValueError, match=r"unexpected \['extra'\]"):
        store.write_chunk(4, bad(extra=np.zeros(3)))
    with pytest.raises(ValueError, match="numpy array"):
        store.write_chunk(4, bad(label=list(range(3))))
    with pytest.raises(ValueError, match="out of range"):
        store.write_chunk(5, good)
    with pytest.raises(ValueError, match="out of range"):
        store.chunk_range(-1)
    # nothing was written by the failed calls
    assert store.missing_chunks() == [0, 1, 2, 3, 4]
    assert [p.name for p in tmp_path.iterdir()] == ["manifest.json"]
    # non-contiguous input of the right shape and dtype is fine
    nc = {**good, "onv": np.asfortranarray(good["onv"])}
    store.write_chunk(4, nc)
    assert_bit_equal(store.load_chunk(4), good)


def test_create_argument_validation(tmp_path):
    with pytest.raises(ValueError, match="JSON"):
        new_store(tmp_path / "a", config={"f": object()})
    with pytest.raises(ValueError, match="JSON"):
        new_store(tmp_path / "a", config={"x": float("nan")})
    with pytest.raises(ValueError, match="total"):
        new_store(tmp_path / "a", total=0)
    with pytest.raises(ValueError, match="chunk_size"):
        new_store(tmp_path / "a", chunk=0)
    with pytest.raises(ValueError, match="field name"):
        new_store(tmp_path / "a", fields={"a.b": ((1,), "float32")})
    with pytest.raises(ValueError, match="dtype"):
        new_store(tmp_path / "a", fields={"a": ((1,), "object")})
    with pytest.raises(ValueError, match="shard"):
        new_store(tmp_path / "a", shard=(2, 2))
    assert not (tmp_path / "a" / "manifest.json").exists()
    with pytest.raises(ValueError, match="unknown fields"):
        fill(new_store(tmp_path / "b"), make_data())
        ChunkedStore.open(tmp_path / "b").load(fields=["nope"])


def test_parse_shard():
    assert parse_shard("0/1") == (0, 1)
    assert parse_shard("3/4") == (3, 4)
    assert parse_shard(" 2 / 8 ") == (2, 8)
    for bad in ["4/4", "5/4", "-1/4", "1/0", "0/0", "1", "a/b", "1/2/3", "", "1.0/2"]:
        with pytest.raises(ValueError, match="shard"):
            parse_shard(bad)
    with pytest.raises(ValueError, match="shard"):
        parse_shard((0, 1))


def test_a_reader_waits_for_the_other_writers_shards_when_asked(tmp_path):
    """A distributed run's rank that rendered its shard first reads the whole dataset only once the other
    ranks' chunks are there (waiting_for_writers); outside that block a missing chunk is an error at once,
    and a wait that runs out is the same error."""
    import threading

    from warp_vision.data.store import waiting_for_writers

    data = make_data()
    mine, theirs = new_store(tmp_path / "d", shard=(0, 2)), new_store(tmp_path / "d", shard=(1, 2))
    fill(mine, data)
    with pytest.raises(ValueError, match="dataset incomplete"):
        ChunkedStore.open(tmp_path / "d").load()
    with waiting_for_writers(0.3), pytest.raises(ValueError, match="dataset incomplete"):
        ChunkedStore.open(tmp_path / "d").load()
    writer = threading.Timer(0.5, lambda: fill(theirs, data))
    writer.start()
    with waiting_for_writers(30.0):
        got = ChunkedStore.open(tmp_path / "d").load()
    writer.join()
    assert_bit_equal(got, data)
    from warp_vision.data import store

    assert store.WAIT_FOR_WRITERS_S == 0.0  # the block restores it


def test_a_store_that_is_not_there_is_its_own_error(tmp_path):
    # evaluate tells it from a damaged store and renders the dataset again (a cache that was deleted)
    with pytest.raises(MissingStoreError, match="is not a ChunkedStore") as e:
        ChunkedStore.open(tmp_path / "gone")
    assert e.value.root == tmp_path / "gone" and isinstance(e.value, ValueError)


def test_render_missing_skips_a_chunk_another_process_wrote_meanwhile(tmp_path):
    from warp_vision.data.synth import render_missing

    data = make_data()
    mine, other = new_store(tmp_path), new_store(tmp_path)  # two writers of one dataset
    asked, said = [], []

    theirs = make_data(seed=1)  # (told apart from this writer's here; the same bytes in a real dataset)

    def render(r):
        asked.append((r.start, r.stop))
        if len(asked) == 1:  # while this one renders chunk 0, the other writes chunks 1 and 3
            fill(other, data, chunks=[1, 3])
        if len(asked) == 2:  # and chunk 2 while both render it: this one leaves it as the other wrote it
            fill(other, theirs, chunks=[2])
        return {k: v[r.start:r.stop] for k, v in data.items()}

    render_missing(mine, render, batch=CHUNK, progress=False, log=said.append)
    assert asked == [mine.chunk_range(c) for c in (0, 2, 4)]
    assert said[0].startswith("synthesised 13 ONVs") and "10 were written meanwhile by another process" in said[0]
    a, b = mine.chunk_range(2)
    assert_bit_equal(ChunkedStore.open(tmp_path).load(), {k: np.concatenate([v[:a], theirs[k][a:b], v[b:]])
                                                           for k, v in data.items()})


def test_whole_at_says_whether_a_directory_holds_a_whole_store(tmp_path):
    assert not ChunkedStore.whole_at(tmp_path / "none")  # no store yet
    store = new_store(tmp_path)
    fill(store, make_data(), chunks=[0, 1])
    assert not ChunkedStore.whole_at(tmp_path)  # chunks missing
    fill(store, make_data())
    assert ChunkedStore.whole_at(tmp_path)
    (tmp_path / "manifest.json").write_text("{")
    assert not ChunkedStore.whole_at(tmp_path)  # a store that does not open
