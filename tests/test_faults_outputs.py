"""Fault drills on what a command writes: it writes a regular file, or into a directory it makes or finds,
and nothing else.

A device, a FIFO, a socket or a symbolic link where a command's output file belongs is refused in one line
before any work, and left as it is (as root, ``--out /dev/null`` is the system's own); a symbolic
link that leads nowhere (a loop, or a link to what does not exist) given to any path option is refused in
one line naming the option, and nothing is made through it; a link to a directory where a directory
belongs is followed. ``fileio.atomic_write`` refuses to rename over anything but a regular file whatever
its caller checked. A training run's latest.pt is there at every moment of its checkpointing.
"""

from __future__ import annotations

import errno
import importlib
import json
import os
import socket
import stat
import tempfile
from pathlib import Path

import pytest
import torch

from warp_vision import fileio
from warp_vision.nn.trained import read_checkpoint
from warp_vision.train.rundir import record_epoch, save_checkpoint

ROOT = os.geteuid() == 0 if hasattr(os, "geteuid") else False


def one_line_naming(err: str, *names: str) -> bool:
    lines = [x for x in err.strip().splitlines() if x.strip()]
    return (len(lines) == 1 and lines[0].startswith("error:") and all(n in lines[0] for n in names)
            and "Traceback" not in err)


def make_node(path: Path, kind: str) -> None:
    """A node of ``kind`` at ``path``: "chardev" (as /dev/null: root only), "fifo", "socket", "loop" (a
    symbolic link in a loop of two), "dangling" (a link to a missing ``gone/dir`` beside it), "filelink"
    (a link to a regular file beside it)."""
    if kind == "chardev":
        if not ROOT:
            pytest.skip("making a device node needs root")
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "socket":
        s = socket.socket(socket.AF_UNIX)
        try:
            s.bind(str(path))
        finally:
            s.close()
    elif kind == "loop":
        other = path.with_name(path.name + "-other")
        other.symlink_to(path.name)
        path.symlink_to(other.name)
    elif kind == "dangling":
        path.symlink_to(path.parent / "gone" / "dir")
    elif kind == "filelink":
        (path.parent / "target.txt").write_text("kept")
        path.symlink_to("target.txt")
    else:
        raise ValueError(kind)


def node_state(path: Path) -> tuple:
    """What ``path`` is (not followed): its type, device number and link target."""
    st = os.lstat(path)
    return stat.S_IFMT(st.st_mode), st.st_rdev, os.readlink(path) if stat.S_ISLNK(st.st_mode) else None


def fake_run(d: Path) -> Path:
    """A foveation run directory with what ``train compare`` reads: config.json and three metrics rows."""
    d.mkdir(parents=True)
    (d / "config.json").write_text(json.dumps({"task": "foveation", "model": "linet", "photoreceptors": 200}))
    (d / "metrics.jsonl").write_text("".join(json.dumps({"epoch": e, "train_mse": 1.0 / e, "val_mse": 1.5 / e}) + "\n"
                                             for e in (1, 2, 3)))
    return d


def run_command(command: str, argv: list[str], capsys, monkeypatch) -> tuple[int, str]:
    """(exit code, stderr) of ``python -m warp_vision.COMMAND ARGV`` run in this process; the simulation
    trains no nets (it fails the test if it tries)."""
    import warp_vision.sim.provision as provision

    monkeypatch.setattr(provision, "provide", lambda *_a, **_k: pytest.fail("nets were trained first"))
    code = importlib.import_module(f"warp_vision.{command}.cli").main(argv)
    return code, capsys.readouterr().err


#: commands with an output file, by the option it is given with: (command, argv with OUT for the path)
FILE_OUTPUTS = {
    "train compare": ("train", ["compare", "RUN", "--out", "OUT"], "--out"),
    "bench linet": ("bench", ["linet", "--photoreceptors", "200", "--batch", "2", "--repeats", "1", "--out", "OUT"],
                    "--out"),
    "data faces --identities-cache": ("data", ["faces", "--preset", "smoke", "--out", "DATA", "--identities-cache",
                                               "OUT"], "--identities-cache"),
}
#: commands with an output directory or a path they resolve
DIR_OPTIONS = {
    "train --out": ("train", ["--preset", "smoke", "--no-progress", "--data-dir", "DATA", "--out", "OUT"], "--out"),
    "train --data-dir": ("train", ["--preset", "smoke", "--no-progress", "--out", "RUN", "--data-dir", "OUT"],
                         "--data-dir"),
    "train --resume": ("train", ["--resume", "OUT", "--no-progress"], "--resume"),
    "train --init": ("train", ["--preset", "smoke", "--no-progress", "--data-dir", "DATA", "--out", "RUN", "--init",
                               "OUT"], "--init"),
    "data --out": ("data", ["foveation", "--preset", "smoke", "--no-progress", "--out", "OUT"], "--out"),
    "scene --out": ("scene", ["demo", "--photoreceptors", "100", "--samples", "1", "--out", "OUT"], "--out"),
    "sim --out": ("sim", ["experiments", "--out", "OUT"], "--out"),
}


def _argv(argv: list[str], tmp_path: Path, out: Path) -> list[str]:
    places = {"OUT": str(out), "DATA": str(tmp_path / "data"), "RUN": str(tmp_path / "run")}
    if "compare" in argv:
        places["RUN"] = str(fake_run(tmp_path / "runs" / "a"))
    return [places.get(a, a) for a in argv]


def _made(tmp_path: Path, out: Path) -> list[str]:
    """What the command made in ``tmp_path`` besides the node and what :func:`make_node` put beside it."""
    keep = {out.name, out.name + "-other", "target.txt", "runs"}
    return sorted(p.name for p in tmp_path.iterdir() if p.name not in keep)


@pytest.mark.parametrize("kind", ["chardev", "fifo", "filelink", "loop", "dangling"])
@pytest.mark.parametrize("name", list(FILE_OUTPUTS))
def test_an_output_file_in_the_place_of_a_node_or_link_is_refused_and_left_as_it_is(name, kind, tmp_path, capsys,
                                                                                       monkeypatch):
    command, argv, flag = FILE_OUTPUTS[name]
    out = tmp_path / "out"
    make_node(out, kind)
    before = node_state(out)
    monkeypatch.chdir(tmp_path)
    code, err = run_command(command, _argv(argv, tmp_path, out), capsys, monkeypatch)
    assert code == 2 and one_line_naming(err, flag, str(out)), err
    assert node_state(out) == before
    assert _made(tmp_path, out) == [], "made something before refusing"
    if kind == "filelink":
        assert (tmp_path / "target.txt").read_text() == "kept"


@pytest.mark.parametrize("kind", ["loop", "dangling"])
@pytest.mark.parametrize("name", list(DIR_OPTIONS))
def test_a_path_option_through_a_link_that_leads_nowhere_is_one_line_and_makes_nothing(name, kind, tmp_path, capsys,
                                                                                      monkeypatch):
    command, argv, flag = DIR_OPTIONS[name]
    out = tmp_path / "out"
    make_node(out, kind)
    monkeypatch.chdir(tmp_path)
    code, err = run_command(command, _argv(argv, tmp_path, out), capsys, monkeypatch)
    what = "a loop of symbolic links" if kind == "loop" else f"a symbolic link to {tmp_path / 'gone' / 'dir'}"
    assert code == 2 and one_line_naming(err, flag, str(out), what), err
    assert _made(tmp_path, out) == [], "made something before refusing"


def test_a_link_that_leads_nowhere_above_the_output_is_named():
    d = Path(tempfile.mkdtemp(prefix="wv-"))
    make_node(d / "a", "loop")
    with pytest.raises(OSError, match=f"--out: {d / 'a'} is a loop of symbolic links") as e:
        fileio.require_output(d / "a" / "run", "--out")
    assert e.value.errno == errno.ELOOP and e.value.filename == str(d / "a" / "run")
    make_node(d / "b", "dangling")
    with pytest.raises(OSError, match=f"--out: {d / 'b'} is a symbolic link to {d / 'gone' / 'dir'}, which does not"):
        fileio.require_output(d / "b" / "fig.png", "--out", kind="file")
    assert not (d / "gone").exists()


def test_a_link_to_a_directory_stays_an_output_directory(tmp_path, capsys):
    """People link runs/ to a scratch disk: a link to a directory is followed, where a directory belongs
    and above an output file."""
    (tmp_path / "scratch").mkdir()
    (tmp_path / "runs").symlink_to("scratch")
    fileio.require_output(tmp_path / "runs", "--out")
    fileio.require_output(tmp_path / "runs" / "new" / "run", "--out")
    fileio.require_output(tmp_path / "runs" / "curves.png", "--out", kind="file")
    assert fileio.resolved(tmp_path / "runs" / "x", "--out") == (tmp_path / "scratch" / "x").resolve()
    from warp_vision.train.cli import main

    run = fake_run(tmp_path / "a")
    assert main(["compare", str(run), "--out", str(tmp_path / "runs" / "curves.png")]) == 0, capsys.readouterr().err
    assert (tmp_path / "scratch" / "curves.png").stat().st_size > 0 and (tmp_path / "runs").is_symlink()


@pytest.mark.parametrize("error", [RuntimeError("Symlink loop from '/x/a'"), OSError(errno.ELOOP, "Too many levels")])
def test_resolved_turns_either_pythons_symlink_loop_into_one_oserror(error, tmp_path, monkeypatch):
    """Python before 3.13 raises pathlib's RuntimeError for a loop, later ones an OSError (ELOOP): here a loop
    made after the links were looked at, which ``resolve`` alone sees."""
    def resolve(self, strict=False):
        raise error

    monkeypatch.setattr(Path, "resolve", resolve)
    with pytest.raises(OSError, match="--init is a loop of symbolic links") as e:
        fileio.resolved(tmp_path / "a", "--init")
    assert e.value.errno == errno.ELOOP and e.value.filename == str(tmp_path / "a")
    error = RuntimeError("another fault")
    with pytest.raises(RuntimeError, match="another fault"):  # (any other RuntimeError is not ours to word)
        fileio.resolved(tmp_path / "a", "--init")


@pytest.mark.parametrize("kind", ["chardev", "fifo", "socket", "filelink", "dangling"])
def test_atomic_write_never_renames_over_what_is_not_a_regular_file(kind):
    d = Path(tempfile.mkdtemp(prefix="wv-"))  # (short: a socket's path is at most 107 bytes)
    target = d / "out"
    make_node(target, kind)
    before = node_state(target)
    with pytest.raises(OSError, match="not a regular file: not replaced") as e:
        fileio.atomic_write(target, b"new")
    assert e.value.filename == str(target)
    with pytest.raises(OSError, match="not a regular file: not replaced"):
        fileio.write_json(target, {"a": 1})
    assert node_state(target) == before
    assert not [p.name for p in d.iterdir() if ".tmp-" in p.name]  # (no temporary left behind)
    if kind == "filelink":
        assert (d / "target.txt").read_text() == "kept"
    assert not (d / "gone").exists()
    fileio.atomic_write(d / "plain", b"x")  # a regular file is replaced as ever
    fileio.atomic_write(d / "plain", b"y")
    assert (d / "plain").read_bytes() == b"y"


# --------------------------------------------------------------------------------------------------
# checkpoint rotation


def _checking_every_step(monkeypatch, latest: Path) -> list[str]:
    """Wrap the os calls that add, rename or remove names, so that after each one latest.pt must be there
    and read as a whole, verified checkpoint: what a reader (``evaluate --checkpoint latest``) finds at any
    moment. Returns the names of the calls made, in order."""
    calls = []

    def checked(name, fn):
        def call(*a, **k):
            r = fn(*a, **k)
            calls.append(name)
            assert latest.is_file(), f"no {latest.name} after os.{name}{a}"
            read_checkpoint(latest)  # (a ValueError if it were cut or half-written)
            return r
        return call

    for name in ("replace", "rename", "unlink", "remove", "link", "symlink", "truncate"):
        monkeypatch.setattr(os, name, checked(name, getattr(os, name)))
    return calls


@pytest.mark.parametrize("hard_links", [True, False])
def test_latest_pt_is_there_at_every_step_of_an_epochs_checkpointing(hard_links, tmp_path, monkeypatch):
    out = tmp_path / "run"
    out.mkdir()
    save_checkpoint({"epoch": 0, "w": torch.zeros(4)}, out / "latest.pt")
    old = (out / "latest.pt").read_bytes()
    if not hard_links:  # a file system without them: previous.pt is a copy
        def no_link(*_a, **_k):
            raise OSError(errno.EPERM, "Operation not permitted")

        monkeypatch.setattr(os, "link", no_link)
    calls = _checking_every_step(monkeypatch, out / "latest.pt")
    record_epoch(out, {"epoch": 2}, {"epoch": 1, "w": torch.ones(4)}, best=True)
    monkeypatch.undo()
    assert "replace" in calls, calls
    assert (out / "previous.pt").read_bytes() == old
    assert read_checkpoint(out / "latest.pt")["epoch"] == 1 and read_checkpoint(out / "best.pt")["epoch"] == 1
    assert (out / "previous.pt").stat().st_ino != (out / "latest.pt").stat().st_ino
    assert sorted(p.name for p in out.iterdir()) == ["best.pt", "latest.pt", "metrics.jsonl", "previous.pt"]
    record_epoch(out, {"epoch": 3}, {"epoch": 2, "w": torch.full((4,), 2.0)}, best=False)  # and once more
    assert read_checkpoint(out / "previous.pt")["epoch"] == 1 and read_checkpoint(out / "latest.pt")["epoch"] == 2
