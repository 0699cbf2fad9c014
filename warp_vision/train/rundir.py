"""A training run's directory: claiming or resuming it, the preflight, sealed checkpoints, metrics rows.

``RUN_DIR/config.json`` holds the run's config with its paths made absolute when the run was created
(:meth:`warp_vision.train.harness.Task.resolve_paths`), so ``--resume`` and ``evaluate`` work from any
working directory. Checkpoints (``latest.pt``, ``previous.pt``: the one before it, ``best.pt``) are
sealed with a sha256 (:func:`warp_vision.nn.trained.seal`) that every reader checks, and carry the
config without paths and the history without timings, so identical runs write identical bytes. A
checkpoint is written before its ``metrics.jsonl`` row; a resumed run starts from the newest checkpoint
that verifies and brings ``metrics.jsonl`` to exactly its epochs.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import sys
from dataclasses import asdict, fields
from pathlib import Path

import torch

from warp_vision.data.store import ChunkedStore
from warp_vision.fileio import FileLock, atomic_copy, atomic_write, probe_writable, require_output, resolved
from warp_vision.nn.trained import (
    TRAINING_LOCK,
    read_checkpoint,
    read_run_config,
    require_binding,
    run_identity,
    saved_task,
    seal,
    task_command,
)

#: the files a run directory's run consists of (a new run refuses a directory holding any of them)
RUN_FILES = ("metrics.jsonl", "latest.pt", "previous.pt", "best.pt", "summary.json")
#: the checkpoints a resumed run may start from, newest first
RESUME_FROM = ("latest.pt", "previous.pt", "best.pt")
#: config fields that are paths: resolved to absolute paths when a run is created, kept out of checkpoints
PATH_FIELDS = ("out", "data_dir", "identities_cache")
#: metrics-row entries that vary between identical runs: kept out of checkpoints
TIMING_FIELDS = ("seconds",)


def a_run(task: str) -> str:
    """"a foveation run", "an arm run": a task's run in words."""
    return f"{'an' if task[:1] in 'aeiou' else 'a'} {task} run"


def claim_out_dir(out: Path, overwrite: bool) -> None:
    """Refuse to start a new run in a directory that holds one (its metrics or checkpoints), unless
    ``overwrite``: then delete them (rank 0)."""
    old = [out / n for n in RUN_FILES]
    if any(f.exists() for f in old):
        if not overwrite:
            raise ValueError(f"--out {out} already holds a run; continue it with --resume {out}, "
                             f"choose another --out, or pass --overwrite to replace it")
        if int(os.environ.get("RANK", "0")) == 0:
            for f in old:
                f.unlink(missing_ok=True)


def require_own_checkpoint(task_cls, ck: dict, path, run_dir, cfg) -> None:
    """Refuse checkpoint ``ck`` (read from ``path``) unless it belongs to the run in ``run_dir``, whose config
    (config.json, read as ``task_cls.config_cls``) is ``cfg``: the same task, eye or side, and run id
    (:func:`warp_vision.nn.trained.run_identity`: every setting but paths and the epoch cap). One ValueError
    names what the checkpoint belongs to, the run, and the settings that differ. Both configs are compared
    as the config class reads them, so a run written before a setting existed compares under its legacy default."""
    settings = asdict(cfg)
    theirs = ck
    if "binding" not in ck and isinstance(ck.get("config"), dict):
        try:
            paths = {k: settings[k] for k in PATH_FIELDS if k in settings}
            full = asdict(config_from_saved(task_cls.config_cls, {**paths, **ck["config"]}, path))
        except (ValueError, TypeError):
            full = ck["config"]
        theirs = {**ck, "config": full, "binding": run_identity(str(ck.get("task", task_cls.name)), full)}
    require_binding(theirs, run_identity(task_cls.name, settings), path, f"the run in {run_dir}", settings)


def init_checkpoint(init) -> Path:
    """The checkpoint a warm start ``init`` names: a run directory's ``best.pt``, or a checkpoint file."""
    p = Path(init)
    return p if p.is_file() else p / "best.pt"


def warm_start(model: torch.nn.Module, run_dir, task: str | None = None) -> None:
    """Start ``model`` from the best weights of the run in ``run_dir`` (or of the checkpoint file it names:
    a net of ``task`` (when given) of the same model and sizes, e.g. the other eye's where the task allows it, checked
    before the run began by its ``check_new_run``; the normalisation is this run's own, set after). A mismatch
    is a ValueError."""
    best = init_checkpoint(run_dir)
    ck = read_checkpoint(best)
    if task is not None:
        require_binding(ck, {"task": task}, best, f"this {task} run's --init")
    config = read_run_config(best.parent)
    if config is not None:  # (what check_new_run read of the run is what the checkpoint is)
        require_binding(ck, run_identity(saved_task(best.parent, config), config), best, f"the run in {best.parent}",
                        config)
    state = ck["model"]
    try:
        model.load_state_dict(state)
    except RuntimeError as e:
        raise ValueError(f"init: {best} holds another net than this run builds ({str(e).splitlines()[0]})") from None


def _usable_checkpoint(out: Path, log, task_cls=None, cfg=None) -> dict | None:
    """The newest checkpoint of run ``out`` that reads and verifies (latest.pt, else previous.pt, else
    best.pt), saying which when it is not latest.pt; one ValueError naming them all if none does. None
    for a run stopped before its first epoch ended (no run file at all but its config): it starts again.
    With ``task_cls`` and ``cfg`` (the run's config), a checkpoint of another run (copied in) is refused
    (:func:`require_own_checkpoint`), never resumed."""
    if not any((out / n).exists() for n in RUN_FILES):
        log(f"no epoch of {out} finished: training it from the start, as its config.json says")
        return None
    problems = []
    for name in RESUME_FROM:
        path = out / name
        if not path.exists():
            problems.append(f"{path}: missing")
            continue
        try:
            ck = read_checkpoint(path)
        except ValueError as e:
            problems.append(str(e))
            continue
        if task_cls is not None:
            require_own_checkpoint(task_cls, ck, path, out, cfg)
        if problems:
            log(f"{'; '.join(problems)}; resuming from {path} (epoch {ck['epoch'] + 1}) instead")
        return ck
    raise ValueError(f"--resume {out}: no checkpoint to resume from: {'; '.join(problems)}")


def open_run(task_cls, cfg, resume: str | None, overwrite: bool, epochs: int | None = None, log=print):
    """(validated config, output directory, checkpoint to resume from or None) of the run to resume (its
    config.json read as ``task_cls.config_cls``) or of the new run ``cfg`` (refusing an --out that holds a run unless
    ``overwrite``). Reads nothing but small files and checkpoints: a damaged run fails here, before any
    data is loaded.

    ``epochs`` (resume only) changes the resumed run's epoch cap: more to extend it, or the epochs
    already done to end it now (the best checkpoint is then evaluated and the figures written).
    """
    ck = None
    if resume:
        out = resolved(resume, "--resume")
        if not (out / "config.json").exists():
            raise FileNotFoundError(errno.ENOENT, "no config.json: not a training run directory",
                                    str(out / "config.json"))
        task = saved_task(out)
        if task != task_cls.name:
            raise ValueError(f"--resume {resume}: {a_run(task)}, not {a_run(task_cls.name)}; resume it with "
                             f"{task_command(task)} --resume {resume}")
        cfg = config_from_saved(task_cls.config_cls, read_run_config(out), out / "config.json")
        try:
            cfg.validate()
        except ValueError as e:  # (it named the setting alone, as if given on the command line)
            raise ValueError(f"{out / 'config.json'}: {e}") from None
        if epochs is not None:
            cfg.epochs = epochs
            cfg.validate()
        cfg.out = str(out)
        task_cls.resolve_paths(cfg)  # (a run made before paths were recorded absolute: as the working directory says)
        _check_device(cfg.device)
        hold_run_dir(out)  # (before a checkpoint is read: another process may be writing them)
        with _released_on_error(out):
            ck = _usable_checkpoint(out, log, task_cls, cfg)
            if epochs is not None and ck is not None and epochs < ck["epoch"] + 1:  # (it became the saved cap)
                raise ValueError(f"--epochs {epochs}: {resume} has trained {ck['epoch'] + 1} epochs; expected "
                                 f"{ck['epoch'] + 1} (end it now) or more (train it further)")
    elif epochs is not None:
        raise ValueError("epochs: only a resumed run takes a new epoch cap; set it in the config otherwise")
    elif cfg is None:
        raise ValueError("run: give a config or a run directory to resume")
    else:
        cfg.validate()
        _check_device(cfg.device)  # before anything is written
        task_cls.resolve_paths(cfg)
        task_cls.check_new_run(cfg)
        # a --data-dir holding a dataset of other settings: refused before the run directory is claimed
        ChunkedStore.check_settings(cfg.data_dir, cfg.data_config().manifest())
        out = Path(cfg.out)
        require_output(out, "--out")
        # a complete dataset may sit in a read-only directory; one still to be rendered needs a directory that
        # can be made and written, checked before the run directory is claimed
        data_dir = getattr(cfg, "data_dir", "") or "."
        require_output(data_dir, "--data-dir", writable=not ChunkedStore.whole_at(data_dir))
        hold_run_dir(out)  # (before --overwrite deletes a run another process may be training)
        with _released_on_error(out):
            claim_out_dir(out, overwrite)
    return cfg, out, ck


@contextlib.contextmanager
def _released_on_error(out: Path):
    """Within the block, an exception lets go of ``out``'s run lock before it propagates."""
    try:
        yield
    except BaseException:
        release_run_dir(out)
        raise


_held: dict[Path, FileLock] = {}


def hold_run_dir(out: Path) -> None:
    """Take ``out``'s run lock for this process (rank 0 of a distributed run; the others share its run),
    creating ``out``; a ValueError naming the process that holds it when another training process does:
    two processes training one run directory would interleave its checkpoints and metrics rows, and
    ``--overwrite`` would delete them under the other. Released by :func:`release_run_dir` or at exit."""
    if int(os.environ.get("RANK", "0")) != 0 or out in _held:
        return
    out.mkdir(parents=True, exist_ok=True)
    lock = FileLock(out / TRAINING_LOCK)
    if not lock.acquire():
        raise ValueError(f"--out {out} is being trained by process {lock.holder} (it holds {lock.path}); "
                         f"wait for it to end, stop it, or choose another --out")
    _held[out] = lock


def release_run_dir(out: Path) -> None:
    """Let go of ``out``'s run lock, if this process holds it."""
    lock = _held.pop(out, None)
    if lock is not None:
        lock.release()


def _check_device(name: str) -> None:
    """A device this machine lacks is a ValueError (``auto`` always resolves)."""
    if name != "auto":
        from warp_vision.kernels.launch import require_device

        require_device(name)


def preflight(task, out: Path, data_dir: Path, log) -> None:
    """Before any expensive work: ``out`` is a writable directory; the dataset (when it is not all
    there) fits in the free space of its directory; the dataset fits in memory. Prints the estimates;
    raises OSError (no space, read-only, permissions) or ValueError (memory) otherwise."""
    from warp_vision.resources import available_memory_bytes, free_disk_bytes, require_disk, require_memory
    from warp_vision.resources import human_bytes as _mib

    probe_writable(out)
    need = task.dataset_bytes()
    if not need:
        return
    complete = ChunkedStore.whole_at(data_dir)
    log(f"dataset: about {_mib(need)} at {data_dir} "
        f"({'already there' if complete else f'{_mib(free_disk_bytes(data_dir))} free'}); "
        f"{_mib(available_memory_bytes())} of memory available")
    if not complete:
        require_disk(need, data_dir, "the dataset")
    require_memory(need, "loading the dataset", "--samples or --photoreceptors")


def check_checkpoint_space(model, out: Path, log) -> None:
    """Before the first epoch: room in ``out`` for the run's three checkpoints (weights and Adam's two
    moments, float32, each), or an ENOSPC OSError that says how much is needed."""
    from warp_vision.resources import free_disk_bytes, human_bytes, require_disk

    need = 3 * 12 * sum(p.numel() for p in model.parameters())
    log(f"checkpoints: about {human_bytes(need)} in {out} ({human_bytes(free_disk_bytes(out))} free)")
    require_disk(need, out, "the checkpoints")


def dataset_dir(cfg, kind: str, data_config) -> Path:
    """``cfg.data_dir``, or the cache directory ``runs/datasets/<kind>-<data config hash>`` (relative to the
    working directory: a new run records it as an absolute path, see
    :meth:`warp_vision.train.harness.Task.resolve_paths`)."""
    return Path(cfg.data_dir) if cfg.data_dir else Path("runs/datasets") / f"{kind}-{data_config.key()}"


def save_checkpoint(obj: dict, path: Path) -> None:
    """``obj`` sealed with its checksum (:func:`warp_vision.nn.trained.seal`) to ``path``, atomically: the
    bytes are built in memory first, so a failed write leaves the old file and no temporary."""
    buf = io.BytesIO()
    torch.save(seal(_unshared(obj)), buf)
    atomic_write(path, buf.getvalue())


def _unshared(x):
    """``x`` in a canonical form for the pickler, so the same contents always give the same bytes: every
    tensor in a storage of its own (torch.save writes a storage shared by two entries, such as a
    normalisation tensor that is also a model buffer, once) and every string interned (pickle writes a
    string object it has seen as a back-reference, and a resumed run's strings come from unpickling)."""
    if torch.is_tensor(x):
        return x.detach().clone()
    if isinstance(x, str):
        return sys.intern(x)
    if isinstance(x, dict):
        return {_unshared(k): _unshared(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_unshared(v) for v in x)
    return x


def record_epoch(out: Path, row: dict, checkpoint: dict, best: bool) -> None:
    """Write latest.pt (the one before it becomes previous.pt), best.pt when ``best``, then append the
    epoch's metrics row: a row is never in metrics.jsonl before its checkpoint is on disk. latest.pt is there
    throughout: previous.pt is made from it before the new one is renamed over it (``evaluate --checkpoint
    latest`` of a run in training reads one or the other)."""
    latest = out / "latest.pt"
    if latest.exists():
        atomic_copy(latest, out / "previous.pt")
    save_checkpoint(checkpoint, latest)
    if best:
        save_checkpoint(checkpoint, out / "best.pt")
    with open(out / "metrics.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")


def sync_metrics(out: Path, history: list) -> None:
    """Make ``out/metrics.jsonl`` hold exactly one row per epoch of a resumed checkpoint's ``history``:
    rows past it (epochs the checkpoint lacks) are cut; a row the run died before appending is restored
    from the history (without its timing)."""
    path = out / "metrics.jsonl"
    rows = [x for x in path.read_text().splitlines() if x.strip()] if path.exists() else []
    by_epoch = {int(r["epoch"]): json.dumps(r) for r in history}  # every epoch the checkpoint holds ...
    for x in rows:  # ... with its own row (and timing) where metrics.jsonl has one; nothing past them
        if _row_epoch(x) in by_epoch:
            by_epoch[_row_epoch(x)] = x
    kept = [by_epoch[e] for e in sorted(by_epoch)]
    if kept != rows:
        atomic_write(path, "".join(x + "\n" for x in kept))


def read_metrics(path, need: tuple[str, ...] = ("epoch",)) -> list[dict]:
    """The rows of a run's ``metrics.jsonl``; a line that is not a JSON object holding the keys ``need`` is a
    ValueError naming the file and the line, not a bare JSON error or a KeyError's traceback."""
    rows = []
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except ValueError as e:
            raise ValueError(f"{path}: line {n} is not a metrics row ({e})") from None
        missing = [k for k in need if not isinstance(row, dict) or k not in row]
        if missing:
            raise ValueError(f"{path}: line {n} is not a metrics row: no {', '.join(missing)}")
        rows.append(row)
    return rows


def _row_epoch(line: str) -> int:
    try:
        return int(json.loads(line)["epoch"])
    except (ValueError, KeyError, TypeError):
        return 1 << 30  # a torn last line: dropped


def reproducible_config(cfg) -> dict:
    """The config as checkpoints carry it: without paths."""
    return {k: v for k, v in asdict(cfg).items() if k not in PATH_FIELDS}


def saved_config(task_cls, run_dir):
    """The config of the run in ``run_dir`` as its config.json holds it, read as ``task_cls.config_cls``."""
    saved = read_run_config(run_dir)
    if saved is None:
        raise FileNotFoundError(errno.ENOENT, "no config.json: not a training run directory",
                                str(Path(run_dir) / "config.json"))
    return config_from_saved(task_cls.config_cls, saved, Path(run_dir) / "config.json")


def run_config(task_cls, run_dir, ck: dict, checkpoint=None):
    """The config of the run in ``run_dir`` whose checkpoint is ``ck`` (the file ``checkpoint``, named where a
    setting is missing from it): the checkpoint's config (which carries no paths) with the paths of
    ``run_dir/config.json``, where it has them."""
    saved = read_run_config(run_dir) or {}
    paths = {k: v for k, v in saved.items() if k in PATH_FIELDS}
    source = Path(run_dir) / "config.json"
    missing = missing_settings(task_cls.config_cls, {**ck["config"], **paths}, optional=PATH_FIELDS)
    if missing and checkpoint is not None:
        source = checkpoint  # (the settings but the paths are the checkpoint's)
    return config_from_saved(task_cls.config_cls, {**ck["config"], **paths}, source, optional=PATH_FIELDS)


_JSON_TYPES = {"bool": (bool,), "int": (int,), "float": (int, float), "str": (str,)}


def missing_settings(cls, saved: dict, optional=()) -> list[str]:
    """The settings of ``cls`` that ``saved`` lacks, but those of ``cls.LEGACY_DEFAULTS`` and ``optional``."""
    legacy = getattr(cls, "LEGACY_DEFAULTS", {})
    return [f.name for f in fields(cls) if f.name not in saved and f.name not in legacy and f.name not in optional]


def config_from_saved(cls, saved: dict, source, optional=()):
    """A ``cls`` config from the settings of a saved run (config.json; a checkpoint's config with its
    paths), under ``cls.LEGACY_DEFAULTS`` (settings added since). A setting ``cls`` lacks, a value of
    another type (``"lr": "fast"``) or a setting missing (but those of ``LEGACY_DEFAULTS`` and ``optional``,
    which take ``cls``'s defaults) is a ValueError naming ``source`` and the settings: a default put in for a
    run's own setting would describe another run."""
    kinds = {f.name: f.type for f in fields(cls)}
    unknown = [k for k in saved if k not in kinds]
    if unknown:
        raise ValueError(f"{source}: {', '.join(map(repr, unknown))}: not "
                         f"{'a setting' if len(unknown) == 1 else 'settings'} of this run's task (edited by hand, or "
                         "written by another version?)")
    missing = missing_settings(cls, saved, optional)
    if missing:
        raise ValueError(f"{source}: the setting{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))} "
                         f"{'are' if len(missing) > 1 else 'is'} missing (edited by hand, or cut short?); a default "
                         f"would not be the run's own, so none is put in")
    for k, v in saved.items():
        ok = _JSON_TYPES.get(kinds[k])
        if ok is not None and (not isinstance(v, ok) or (isinstance(v, bool) and bool not in ok)):
            raise ValueError(f"{source}: {k!r} is {v!r}; expected {'an' if kinds[k] == 'int' else 'a'} {kinds[k]}")
    return cls(**{**getattr(cls, "LEGACY_DEFAULTS", {}), **saved})
