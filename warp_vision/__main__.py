"""``python -m warp_vision``: the package's commands, one line each; ``python -m warp_vision COMMAND ...``
runs ``python -m warp_vision.COMMAND ...`` (the same arguments, the same exit code)."""

from __future__ import annotations

import importlib
import sys

from warp_vision.errors import not_a_command

#: command -> what it does (each a package with a ``cli.main(argv)``)
COMMANDS = {
    "train": "train a net (foveation by default; faces, oculomotor, arm, limb, pupil, lens), "
             "and evaluate or compare runs",
    "sim": "the virtual human's closed loop: demo video, experiments, intraocular, oculomotor, intercept",
    "data": "build a training preset's dataset alone (foveation, faces), a shard at a time if you like",
    "bench": "microbenchmarks against the alternatives (linet, memory, raytrace, loop, readout, cnn), as JSON",
    "scene": "render the furnished room with a ball through one eye, and write figures",
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: python -m warp_vision COMMAND [ARGS ...]   (the same as python -m warp_vision.COMMAND ARGS ...)",
             "       python -m warp_vision --version",
             "", "commands:"]
    lines += [f"  {name:<{width}}  {what}" for name, what in COMMANDS.items()]
    lines += ["",
              "python -m warp_vision COMMAND --help says more; the README's quick start: python -m warp_vision.train"]
    return "\n".join(lines)


def version_line() -> str:
    """``warp_vision 0.1.0 (commit abc123def456, with local changes)``: what :mod:`warp_vision.provenance` records."""
    from warp_vision.provenance import commit, package_version

    c = commit()
    where = "" if c is None else f" (commit {c['commit'][:12]}{', with local changes' if c['dirty'] else ''})"
    return f"warp_vision {package_version()}{where}"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    if argv[0] == "--version":
        print(version_line())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"error: {not_a_command(name, COMMANDS)} (python -m warp_vision --help says more)", file=sys.stderr)
        return 2
    return importlib.import_module(f"warp_vision.{name}.cli").main(rest)


if __name__ == "__main__":
    raise SystemExit(main())
