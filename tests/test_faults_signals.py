"""Fault drills on signals: SIGTERM during synthesis stops the data command cleanly, every time.

A split CPU launch interrupted in its calling thread (Ctrl-C, SIGTERM) returns only once none of its slices
runs, and launches no further slice: a running slice writes into its arguments' memory, which the caller
frees as the exception unwinds. A SIGTERM that arrives inside an object's ``__del__`` (where Python drops
an exception) is raised once the finaliser has returned. The drill itself kills the data command in its
synthesis and checks what it says, its exit code and the chunks it leaves.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from warp_vision.errors import Terminated, guarded, sigterm_as_interrupt
from warp_vision.kernels import launch


class _Slice:
    """A recorded slice stand-in. The calling thread's slice waits until a worker's slice runs, then is
    interrupted; a worker's slice runs until ``released``."""

    def __init__(self, caller: int, state: dict):
        self.caller, self.state = caller, state

    def launch(self):
        st = self.state
        if threading.get_ident() == self.caller:
            st["worker running"].wait()
            st["interrupted"] = True
            raise KeyboardInterrupt
        with st["lock"]:
            st["running"] += 1
            st["launched after the interruption"] += st["interrupted"]
        st["worker running"].set()
        st["released"].wait()
        with st["lock"]:
            st["running"] -= 1


def _stack(ident: int) -> list[str]:
    frame, names = sys._current_frames().get(ident), []
    while frame is not None:
        names.append(frame.f_code.co_name)
        frame = frame.f_back
    return names


def test_an_interrupted_split_launch_returns_only_once_no_slice_runs():
    caller = threading.get_ident()
    st = {"lock": threading.Lock(), "running": 0, "interrupted": False, "launched after the interruption": 0,
          "worker running": threading.Event(), "released": threading.Event(), "caught": threading.Event()}

    def release():
        """Let the workers' slices end once the calling thread, its own slice interrupted, waits inside the
        launch (as it must), or once the interruption has reached the caller."""
        while not st["caught"].is_set():
            names = _stack(caller)
            if st["interrupted"] and "_run" in names and "wait" in names and "launch" not in names:
                break
            time.sleep(0.001)
        st["released"].set()

    watcher = threading.Thread(target=release, daemon=True)
    watcher.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            try:
                launch._run([_Slice(caller, st) for _ in range(6)], 2)
            finally:
                running_when_raised = st["running"]
                st["caught"].set()
    finally:
        st["released"].set()
        watcher.join()
    assert running_when_raised == 0, "the launch raised while a worker's slice still ran"
    assert st["launched after the interruption"] == 0


def test_a_split_launch_still_runs_every_slice():
    done = []

    class Slice:
        def __init__(self, i):
            self.i = i

        def launch(self):
            done.append(self.i)

    for n, k in ((2, 2), (2, 7), (3, 2)):
        done.clear()
        launch._run([Slice(i) for i in range(k)], n)
        assert sorted(done) == list(range(k)), (n, k)


class _SignalledInFinaliser:
    """An object whose ``__del__`` sends this process SIGTERM and goes on running (as Warp's array
    deallocator may be running when the signal comes)."""

    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        x = 0
        for i in range(1000):  # (Python code after the signal: its handler runs here, in the finaliser)
            x += i


def test_a_sigterm_that_arrives_in_a_finaliser_is_raised_after_it():
    with pytest.raises(Terminated):
        with sigterm_as_interrupt():
            obj = _SignalledInFinaliser()
            del obj

    def job():
        obj = _SignalledInFinaliser()
        del obj
        return 0

    assert guarded(job) == 143


# --------------------------------------------------------------------------------------------------
# the drill

#: chunks the drill lets the data command write before its SIGTERM comes, at most
KILL_AFTER_CHUNKS = 4


def _kill_during_synthesis(out: Path, rng: random.Random) -> tuple[int, str]:
    """Start ``python -m warp_vision.data foveation`` into ``out``; once it has written some chunks (a random
    1 to KILL_AFTER_CHUNKS of them) and a random moment more, SIGTERM it. (exit code, output)."""
    argv = [sys.executable, "-m", "warp_vision.data", "foveation", "--preset", "smoke", "--samples", "8000",
            "--out", str(out), "--no-progress"]
    p = subprocess.Popen(argv, env=dict(os.environ, PYTHONUNBUFFERED="1", PYTHONFAULTHANDLER="1"),
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    want = rng.randint(1, KILL_AFTER_CHUNKS)
    try:
        while len(list(out.glob("chunk_*.json"))) < want and p.poll() is None:
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 1.0))
        p.send_signal(signal.SIGTERM)
        text, _ = p.communicate(timeout=300)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    return p.returncode, text


def test_sigterm_during_synthesis_always_stops_cleanly(tmp_path):
    """SIGTERM at random moments of the data command's synthesis: every time exit 143, its "interrupted"
    line, and the chunks written whole (each verifies against its checksum; no temporaries), the rest
    missing. A few kills by default; ``WARP_VISION_KILL_DRILL=N`` runs N of them (50 for the full drill)."""
    from warp_vision.data.store import ChunkedStore

    kills = int(os.environ.get("WARP_VISION_KILL_DRILL", "3"))
    rng = random.Random(kills)
    outcomes = []
    for i in range(kills):
        out = tmp_path / f"data{i}"
        code, text = _kill_during_synthesis(out, rng)
        store = ChunkedStore.open(out)
        written = sorted(set(store.my_chunks()) - set(store.missing_chunks()))
        store.verify(written)
        left = [p.name for p in out.iterdir() if ".tmp" in p.name]
        ok = (code == 143 and "interrupted: the chunks written are kept" in text and "Fatal Python error" not in text
              and not left and written and store.missing_chunks())
        outcomes.append((code, bool(ok), text if not ok else ""))
        if ok:
            shutil.rmtree(out)
    bad = [(code, text) for code, ok, text in outcomes if not ok]
    codes = sorted({code for code, _, _ in outcomes})
    assert not bad, (f"{len(bad)} of {kills} kills went wrong (exit codes {[c for c, _ in bad]}; all: {codes}); "
                     f"the first said:\n{bad[0][1]}")
