"""A seeded fuzz drill of every command's options: each case is one command line with one option (or positional
argument) set to an extreme value (0, -1, huge, nan, inf, an overflowing integer, a long or unicode string, a path
of every file type), run in a forked child of this process under a memory cap and a time budget.

Every outcome must be one of:

- ``ok``: exit 0;
- ``error``: exit 2 (or 3, a non-finite loss) with exactly one line on stderr, beginning ``error:``;
- ``working``: still working at the time budget, having printed no error (an accepted value, whose work began);

anything else (a traceback, another exit code, a signal, several lines of error) is a ``failure``.

``python tests/fuzz_cli.py [CASES] [SEED]`` runs it on its own and prints the tally and each failure; the test
suite runs a small number of cases (tests/test_fuzz.py; ``WARP_VISION_FUZZ_CASES`` sets more).
"""

from __future__ import annotations

import argparse
import os
import random
import resource
import select
import signal
import socket
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

#: what an option is set to: numbers at and past their ends, strings and paths of every kind ({...}: made per run)
VALUES = ["0", "-1", "-1e-3", "1", "99999999999999999999999", "1180591620717411303424", "1e400", "1e-300", "nan", "inf",
          "-inf", "", " ", "x" * 5000, "é🙂\u202e名", "1/0", "-1/2", "0/0", "auto", "{fifo}", "{devnull}", "{loop}",
          "{dangling}", "{dir}", "{file}", "{socket}", "{missing}"]

#: seconds a case may work before it counts as accepted and working; the memory it may take beyond this process's
BUDGET_S = 8.0
MEMORY_CAP = 6 * 2**30


@dataclass
class Command:
    name: str  # as typed after python -m warp_vision
    main: object  # its main(argv) -> int
    prefix: list  # the argv before the option (the subcommand, the task)
    parser: argparse.ArgumentParser


def commands() -> list[Command]:
    """Every command line of the package with the parser that reads it."""
    from warp_vision.bench import cli as bench
    from warp_vision.data import cli as data
    from warp_vision.scene import cli as scene
    from warp_vision.sim import cli as sim
    from warp_vision.train import cli as train

    out = [Command("train", train.main, [], train._train_parser())]
    out += [Command(f"train {t}", train.main, [t], train._task_parser(t)) for t in train.TASKS]
    out += [Command("train evaluate", train.main, ["evaluate"], train._eval_parser()),
            Command("train compare", train.main, ["compare"], train._compare_parser())]
    for module, name, make in ((sim, "sim", sim.parser), (data, "data", data.parser), (bench, "bench", bench._parser),
                               (scene, "scene", scene._parser)):
        p = make()
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        out += [Command(f"{name} {c}", module.main, [c], sp) for c, sp in sub.choices.items()]
    return out


def _slots(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The options and positional arguments of ``parser`` that take values."""
    return [a for a in parser._actions
            if not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction, argparse._StoreTrueAction,
                                  argparse._StoreConstAction, argparse._VersionAction))]


def make_paths(root: Path) -> dict:
    """The paths of every file type the values name, made in ``root``."""
    paths = {"devnull": "/dev/null", "missing": str(root / "missing" / "deeper"), "dir": str(root / "adir"),
             "file": str(root / "afile.txt"), "fifo": str(root / "afifo"), "loop": str(root / "loop_a"),
             "dangling": str(root / "dangling"), "socket": str(root / "asocket")}
    os.makedirs(paths["dir"], exist_ok=True)
    Path(paths["file"]).write_text("not what anything expects\n")
    if not os.path.exists(paths["fifo"]):
        os.mkfifo(paths["fifo"])
    if not os.path.lexists(paths["loop"]):
        os.symlink(root / "loop_b", root / "loop_a")
        os.symlink(root / "loop_a", root / "loop_b")
    if not os.path.lexists(paths["dangling"]):
        os.symlink("/nonexistent/warp_vision_fuzz/dir", paths["dangling"])
    if not os.path.exists(paths["socket"]):
        s = socket.socket(socket.AF_UNIX)
        s.bind(paths["socket"])
        s.close()
    return paths


def cases(n: int, seed: int, paths: dict) -> list[tuple[Command, list[str]]]:
    """``n`` seeded cases: (command, argv)."""
    rng = random.Random(seed)
    cmds = commands()
    out = []
    for _ in range(n):
        c = rng.choice(cmds)
        slots = _slots(c.parser)
        a = rng.choice(slots)
        value = rng.choice(VALUES)
        if value.startswith("{"):
            value = paths[value[1:-1]]
        many = a.nargs in ("*", "+") or isinstance(a.nargs, int) and a.nargs > 1
        values = [value] * (rng.choice((1, 2)) if many else 1)
        argv = list(c.prefix)
        if a.option_strings:
            argv += [a.option_strings[-1], *values]
        else:  # a positional argument
            argv += values
        out.append((c, argv))
    return out


def run_case(command: Command, argv: list[str], cwd: str, budget_s: float = BUDGET_S) -> tuple[str, str]:
    """(outcome, what it printed on stderr) of one case, in a forked child in its own process group."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        code = 1
        try:
            os.close(r)
            os.setpgid(0, 0)
            os.chdir(cwd)
            fd = os.open(os.devnull, os.O_WRONLY)
            os.dup2(fd, 1)
            os.dup2(w, 2)
            sys.stderr = os.fdopen(2, "w", buffering=1)
            sys.stdout = os.fdopen(1, "w")
            soft = _vm_bytes() + MEMORY_CAP
            resource.setrlimit(resource.RLIMIT_AS, (soft, soft))
            signal.signal(signal.SIGALRM, signal.SIG_DFL)
            signal.setitimer(signal.ITIMER_REAL, budget_s)
            code = command.main(argv)
            code = 0 if code is None else code
        except SystemExit as e:
            if isinstance(e.code, str):
                print(e.code, file=sys.stderr)
                code = 1
            else:
                code = e.code or 0
        except BaseException:
            traceback.print_exc()
            code = 1
        finally:
            try:
                sys.stderr.flush()
            finally:
                os._exit(code if isinstance(code, int) else 1)
    os.close(w)
    chunks, status = [], None
    while status is None:  # helpers it started (training, synthesis) hold the pipe too: wait for the child alone
        ready, _, _ = select.select([r], [], [], 0.2)
        if ready:
            chunks.append(os.read(r, 65536))
        done, st = os.waitpid(pid, os.WNOHANG)
        if done:
            status = st
    with _quiet():
        os.killpg(pid, signal.SIGKILL)  # and then they go with it
    while select.select([r], [], [], 0.5)[0] and (b := os.read(r, 65536)):
        chunks.append(b)
    os.close(r)
    err = b"".join(chunks).decode(errors="replace")
    return classify(status, err), err


class _quiet:
    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        return kind is not None and issubclass(kind, ProcessLookupError)


def _vm_bytes() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


def classify(status: int, err: str) -> str:
    lines = [x for x in err.splitlines() if x.strip()]
    errors = [x for x in lines if x.startswith("error:")]
    if os.WIFSIGNALED(status):
        if os.WTERMSIG(status) == signal.SIGALRM and not errors and "Traceback" not in err:
            return "working"
        return "failure"
    code = os.WEXITSTATUS(status)
    if code == 0 and "Traceback" not in err:
        return "ok"
    if code in (2, 3) and len(errors) == 1 and "Traceback" not in err and lines and lines[-1] == errors[0] \
            and all(not x.lower().startswith("usage") for x in lines):
        return "error"
    return "failure"


def drill(n: int, seed: int = 0, log=print) -> dict:
    """Run ``n`` cases; {"cases", "ok", "error", "working", "failure", "failures": [(argv, stderr tail)]}."""
    root = Path(tempfile.mkdtemp(prefix="warp_vision_fuzz_"))
    paths = make_paths(root)
    tally = {"cases": 0, "ok": 0, "error": 0, "working": 0, "failure": 0, "failures": []}
    t0 = time.perf_counter()
    for k, (c, argv) in enumerate(cases(n, seed, paths)):
        cwd = root / f"case{k}"
        cwd.mkdir()
        outcome, err = run_case(c, argv, str(cwd))
        tally["cases"] += 1
        tally[outcome] += 1
        if outcome == "failure":
            shown = [a if len(a) < 60 else a[:20] + f"...({len(a)} chars)" for a in argv]
            tally["failures"].append((f"{c.name.split()[0]} {' '.join(shown)}", err[-1500:]))
            log(f"FAILURE: python -m warp_vision.{c.name.split()[0]} {' '.join(shown)}\n{err[-1500:]}")
    tally["seconds"] = time.perf_counter() - t0
    return tally


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
    t = drill(n, seed)
    print({k: v for k, v in t.items() if k != "failures"})
    sys.exit(1 if t["failure"] else 0)
