"""What the closed loop needs, made on first use: each eye's foveation net and oculomotor net (and,
for ``sim intercept``, the arm's motor nets and each eye's limb vision net).

``python -m warp_vision.sim demo`` (and ``experiments``, ``intraocular``, ``intercept``) call :func:`provide`
before they build the loop.
It looks for each net's run directory (``best.pt``), prints the plan for the missing ones with an
estimate of their wall time, and trains them with the training command (``python -m warp_vision.train
...``, a process of its own: the simulation never imports the training code), whose progress bars show.
A stopped training run (``latest.pt`` without ``summary.json``: Ctrl-C or a crash part way) is resumed, not
used half-trained. A net that another simulation is having trained, or a training command started by hand
is training, is waited for and then used (:func:`_training_slot`). Later runs find the nets there and
reuse them; the datasets behind them stay cached in ``runs/datasets``.

Two sets: the default nets (``runs/foveation_left``, ``runs/foveation_right``, ``runs/oculomotor/<eye>``,
``runs/arm/<side>``, ``runs/limb/<eye>``, the training presets ``default``) and, with ``--quick``, smaller
ones (``runs/quick/...``, the presets
``quick``) for a first look in a few minutes. :func:`manifest` records which nets a simulation used:
their run directories, training configs and the SHA-256 of their checkpoints.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import subprocess
import sys
import time
from dataclasses import dataclass

from warp_vision.body import SIDES
from warp_vision.errors import Terminated
from warp_vision.fileio import FileLock
from warp_vision.nn.trained import (
    TRAINING_LOCK,
    read_checkpoint,
    read_run_config,
    require_binding,
    run_identity,
    saved_task,
)

#: the lock a simulation holds in a net's run directory while it has the net trained there: a second
#: simulation that needs the net waits for it rather than starting a training the run lock refuses
PROVIDING_LOCK = ".providing.lock"

#: Wall minutes of each training on the 2-core reference CPU (docs/RESULTS.md has the runs): the
#: foveation net's dataset synthesis plus its training, the oculomotor net's holding-activation dataset
#: plus its training, the pupil and lens nets' datasets plus their training (the lens net's first run on
#: a machine also builds its textured cards' BVHs, about 2 minutes, cached on disk afterwards); an arm's
#: motor nets (holding activations, training, body checks) and an eye's limb vision net (rendering its
#: ONVs, then training) as their presets' comments in :mod:`warp_vision.train.config_body` estimate them.
MINUTES = {("foveation", "default"): 15.0, ("foveation", "quick"): 2.0,
           ("oculomotor", "default"): 2.5, ("oculomotor", "quick"): 0.5,
           ("pupil", "default"): 2.5, ("pupil", "quick"): 1.5, ("lens", "default"): 10.0, ("lens", "quick"): 3.0,
           ("arm", "default"): 6.0, ("arm", "quick"): 1.5, ("limb", "default"): 11.0, ("limb", "quick"): 2.0,
           ("verify", "default"): 12.0, ("verify", "quick"): 3.0}

#: A net's kind in words, where its name is not one (``NetSpec.what``).
_WORDS = {"limb": "limb vision", "verify": "foveal verification"}

#: Training commands whose side flag is ``--side`` (the arm's) rather than ``--eye``.
_SIDE_FLAG = {"arm": "--side"}


@dataclass
class NetSpec:
    """One net the loop needs: its kind (foveation | oculomotor | pupil | lens | limb | arm), side (``eye``: the
    eye's, or for kind ``arm`` the arm's: left or right), run directory and training preset. (An ``arm``
    run holds two nets, posture and voluntary; one spec stands for both.)"""

    kind: str
    eye: str
    run: str
    preset: str

    @property
    def checkpoint(self) -> str:
        return os.path.join(self.run, "best.pt")

    def ready(self) -> bool:
        """Whether the run holds its trained net: ``best.pt``, and not a stopped run's (``latest.pt``
        without the ``summary.json`` a run writes once its net is final), which :meth:`command` resumes rather
        than the loop using a net stopped part way (by Ctrl-C, a crash, or the other process still training it)."""
        def has(name: str) -> bool:
            return os.path.isfile(os.path.join(self.run, name))

        return os.path.isfile(self.checkpoint) and (has("summary.json") or not has("latest.pt"))

    def command(self) -> list[str]:
        """The training command (after ``python -m warp_vision.train``)."""
        head = [] if self.kind == "foveation" else [self.kind]  # foveation is the command's default task
        if os.path.isfile(os.path.join(self.run, "latest.pt")):  # a stopped run: carry on
            return head + ["--resume", self.run]
        return head + ["--preset", self.preset, _SIDE_FLAG.get(self.kind, "--eye"), self.eye, "--out", self.run]

    @property
    def what(self) -> str:
        """The net in words: "left eye's foveation net", "left eye's limb vision net", "left arm's motor nets"."""
        if self.kind == "arm":
            return f"{self.eye} arm's motor nets"
        return f"{self.eye} eye's {_WORDS.get(self.kind, self.kind)} net"

    def minutes(self) -> float:
        return MINUTES.get((self.kind, self.preset), MINUTES[(self.kind, "default")])

    def mismatch(self) -> str | None:
        """Why the run directory holds another net than this one, or None: it is this net's run, or holds no run
        yet. Read from its ``config.json`` (another task, or the other eye or arm) and from its ``best.pt``,
        which must belong to that run and to this net (a checkpoint copied in from another run)."""
        config = read_run_config(self.run)
        if config is None:
            return None
        kind = saved_task(self.run, config)
        side = config.get("side" if kind == "arm" else "eye")
        if kind != self.kind or side not in (None, self.eye):
            found = f"the {NetSpec(kind, side, self.run, self.preset).what}" if side in SIDES else f"a {kind} run"
            return f"{self.run} holds {found}, not the {self.what}"
        try:
            ck = read_checkpoint(self.checkpoint)
        except (OSError, ValueError):  # none yet, or damaged: the loader names a damaged file when it reads it
            return None
        try:
            require_binding(ck, {"task": self.kind, _SIDE_FLAG.get(self.kind, "--eye")[2:]: self.eye}, self.checkpoint)
            require_binding(ck, run_identity(kind, config), self.checkpoint, f"the run in {self.run}", config)
        except ValueError as e:
            return str(e)
        return None


def default_runs(quick: bool) -> dict:
    """The run directories of the default (or ``quick``) nets: {"left", "right", "oculomotor", "pupil", "lens",
    "arm", "limb", "verify"} (the last six: directories holding one run per side, ``<dir>/left`` and
    ``<dir>/right``)."""
    root = os.path.join("runs", "quick") if quick else "runs"
    return {"left": os.path.join(root, "foveation_left"), "right": os.path.join(root, "foveation_right"),
            "oculomotor": os.path.join(root, "oculomotor"), "pupil": os.path.join(root, "pupil"),
            "lens": os.path.join(root, "lens"), "arm": os.path.join(root, "arm"), "limb": os.path.join(root, "limb"),
            "verify": os.path.join(root, "verify")}


def plan(left: str, right: str, oculomotor: str, quick: bool = False, pupil: str | None = None,
         lens: str | None = None) -> list[NetSpec]:
    """The nets of the loop: both eyes' foveation nets in ``left`` and ``right``, their oculomotor nets in
    ``oculomotor/<eye>``, and (with ``pupil`` and ``lens``) their pupil and lens nets in ``pupil/<eye>`` and
    ``lens/<eye>``, in that order; ``quick`` trains missing ones with the ``quick`` presets."""
    preset = "quick" if quick else "default"
    fov = {"left": left, "right": right}
    return ([NetSpec("foveation", s, fov[s], preset) for s in SIDES]
            + [NetSpec("oculomotor", s, os.path.join(oculomotor, s), preset) for s in SIDES]
            + [NetSpec(kind, s, os.path.join(root, s), preset) for kind,
               root in (("pupil", pupil), ("lens", lens)) if root
               for s in SIDES])


def strike_plan(side: str, arm: str, limb: str | None, quick: bool = False) -> list[NetSpec]:
    """The nets the interception adds to the loop's: ``side``'s arm motor nets in ``arm/<side>`` and (with
    ``limb``; None when the arm's perception is the true ball) both eyes' limb vision nets in ``limb/<eye>``,
    in that order; ``quick`` trains missing ones with the ``quick`` presets."""
    if side not in SIDES:
        raise ValueError(f"side: expected one of {SIDES}, got {side!r}")
    preset = "quick" if quick else "default"
    return ([NetSpec("arm", side, os.path.join(arm, side), preset)]
            + ([NetSpec("limb", s, os.path.join(limb, s), preset) for s in SIDES] if limb else []))


def search_plan(verify: str, quick: bool = False) -> list[NetSpec]:
    """The nets the active search adds to the loop's: both eyes' foveal verification nets in ``verify/<eye>``;
    ``quick`` trains missing ones with the ``quick`` presets."""
    return [NetSpec("verify", s, os.path.join(verify, s), "quick" if quick else "default") for s in SIDES]


def _about(minutes: float) -> str:
    """An estimate in words: "about 14 min", or "under a minute" (not "about 0 min")."""
    return "under a minute" if minutes < 1 else f"about {minutes:.0f} min"


def _run_training(cmd: list[str]) -> int:
    """Run a training command; its exit code. On Ctrl-C (which the training got too) it is given time to
    stop its helpers and say where it stands, where ``subprocess.run`` killed it after a quarter second; on
    SIGTERM (:class:`warp_vision.errors.Terminated`) the training is sent SIGTERM and given the same time."""
    p = subprocess.Popen(cmd)
    try:
        return p.wait()
    except KeyboardInterrupt as e:
        if isinstance(e, Terminated):  # SIGTERM came to this process alone (Ctrl-C reaches the training too)
            p.terminate()
        try:
            p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            p.kill()
        raise


_CHECK = " (check the run directories given to the command)"


def provide(specs: list[NetSpec], progress: bool = True, log=print, runner=None) -> list[NetSpec]:
    """Train every net of ``specs`` that is missing; returns those it trained. Prints the plan and its
    estimated wall time first. ``runner(cmd) -> returncode`` runs a command (default: a subprocess);
    a failed training stops the simulation with the command to rerun. A run directory that holds
    another net (:meth:`NetSpec.mismatch`: ``--left runs/arm/left``, say) is a ValueError, raised before
    anything is trained."""
    wrong = [m for m in (s.mismatch() for s in specs) if m]
    if wrong:
        raise ValueError("; ".join(wrong) + _CHECK)
    todo = [s for s in specs if not s.ready()]
    if not todo:
        return []
    total = sum(s.minutes() for s in todo)
    log(f"the closed loop needs {len(todo)} net(s) not trained yet; {_about(total)} on a 2-core CPU, "
        "cached for later runs:")
    for k, s in enumerate(todo, 1):
        log(f"  {k}. {s.what} into {s.run} ({_about(s.minutes())}): "
            f"python -m warp_vision.train {' '.join(s.command())}")
    runner = runner or _run_training
    t0 = time.perf_counter()
    trained = []
    for k, s in enumerate(todo, 1):
        with _training_slot(s, log):
            if wrong := s.mismatch():  # (what another process trained there while this one waited)
                raise ValueError(wrong + _CHECK)
            if s.ready():
                log(f"[{k}/{len(todo)}] the {s.what} is ready: another process trained it into {s.run}")
                continue
            cmd = [sys.executable, "-m", "warp_vision.train", *s.command()] + ([] if progress else ["--no-progress"])
            log(f"[{k}/{len(todo)}] training the {s.what} ({(time.perf_counter() - t0) / 60:.1f} min so far)")
            if runner(cmd) != 0 or not s.ready():
                raise SystemExit(f"training the {s.what} failed (see above); rerun it with\n"
                                 f"  python -m warp_vision.train {' '.join(s.command())}")
            trained.append(s)
    log(f"trained {len(trained)} net(s) in {(time.perf_counter() - t0) / 60:.1f} min")
    return trained


@contextlib.contextmanager
def _training_slot(s: NetSpec, log):
    """Within the block, ``s``'s run directory is this process's to have trained: another simulation
    having it trained holds :data:`PROVIDING_LOCK` there, and a training command started by hand holds
    the run's :data:`TRAINING_LOCK`; this one waits for each, saying so (the run is then ready, or is
    resumed where the other stopped). So two simulations started together on a fresh clone train each net
    once, where without the wait the second's training would be refused by the run lock."""
    os.makedirs(s.run, exist_ok=True)
    slot = FileLock(os.path.join(s.run, PROVIDING_LOCK))
    if not slot.acquire():
        log(f"waiting for process {slot.holder}, which is having the {s.what} trained into {s.run}")
        slot.acquire(block=True)
    try:
        training = FileLock(os.path.join(s.run, TRAINING_LOCK))
        if not training.acquire():
            log(f"waiting for process {training.holder}, which is training the {s.what} into {s.run}")
            training.acquire(block=True)
        training.release()  # (the training command takes it)
        yield
    finally:
        slot.release()


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def manifest(specs: list[NetSpec]) -> dict:
    """Which nets a simulation used: per net its run directory, training config and checkpoint SHA-256."""
    out = {}
    for s in specs:
        out[f"{s.kind}_{s.eye}"] = {"run": os.path.abspath(s.run), "checkpoint": os.path.abspath(s.checkpoint),
                                    "sha256": sha256_file(s.checkpoint), "config": read_run_config(s.run)}
    return out
