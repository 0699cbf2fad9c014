"""How the command lines report what went wrong: one line, and a non-zero exit code.

Every ``python -m warp_vision.<command>`` runs its work through :func:`guarded`. Bad input (ValueError)
and file-system faults (OSError: no space, read-only, permissions, a file where a directory belongs)
become one line on stderr, ``error: ...`` naming the file or the option, and exit code 2; so does a
failed allocation (settings too large for the machine's memory). A traceback appears only with ``--debug``.
Ctrl-C exits with 130; SIGTERM is taken as Ctrl-C is (the same clean stop) and exits with 143.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import difflib
import os
import re
import signal
import sys
import threading
from collections.abc import Callable

from warp_vision.resources import check_environment


def error_line(e: BaseException) -> str:
    """One line for an error a user can act on: an OSError as "FILE: what went wrong", others as their message."""
    if isinstance(e, OSError) and e.strerror:
        return f"{e.filename}: {e.strerror}" if e.filename else e.strerror
    return " ".join(str(e).split()) or type(e).__name__


_NEGATIVE_NUMBER = re.compile(r"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$")


class ArgumentParser(argparse.ArgumentParser):
    """Every command's parser: argparse's, without its matching of abbreviated options, so that a flag a
    command lacks is an error rather than another flag it begins (argparse would take ``data faces --samples
    10`` for ``--samples-per-receptor 10``). Its subcommands' parsers are of this class too."""

    #: A callable giving other commands' parsers by name, for commands that are separate parsers rather than
    #: subcommands (train's tasks, evaluate and compare): a flag this parser lacks is named as theirs
    #: ("--samples is an option of the foveation task, limb, pupil, lens and evaluate"). Called only then.
    siblings = None

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
        # argparse reads '-1' and '-0.5' as negative numbers (a value) but '-1e-3' as an option, so a list
        # option's '--perception-error-cm -1e1' said "unrecognized arguments: -1e1"; this reads the exponent
        # forms as numbers too, and the value reaches the option's own check
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message: str):
        """One line on stderr, ``error: <message> (<prog> --help says more)``, and exit code 2, as the typed checks
        give: no usage block, --help says the rest (a message that names a command line to type needs no pointer
        to it). Its words for a missing or mistyped subcommand are replaced by ours: "the following arguments are
        required: cmd" named the parser's internal field, and "invalid choice: 'experiment' (choose from ...)" left
        finding the nearest command to the user; its other messages name the option as the typed checks do
        (``--checkpoint: expected one of best, latest, got 'previous'``)."""
        sub = _subcommands(self)
        if sub is not None:
            names = list(sub.choices)
            if message == f"the following arguments are required: {sub.dest}":
                message = f"expected a command: one of {', '.join(names)} ({self.prog} COMMAND --help says more)"
            m = re.fullmatch(rf"argument {re.escape(sub.dest)}: invalid choice: (.+?) \(choose from .*\)", message)
            if m:
                try:
                    word = ast.literal_eval(m.group(1))
                except (ValueError, SyntaxError):
                    word = None
                if isinstance(word, str):
                    message = not_a_command(word, names)
        message = _as_typed(message)
        more = "" if "--help" in message or "python -m" in message else f" ({self.prog} --help says more)"
        self.exit(2, f"error: {message}{more}\n")

    def parse_args(self, args=None, namespace=None):
        """argparse's, naming the nearest option of the command for a mistyped flag (``--photoreceptor``:
        did you mean --photoreceptors?) and the commands an option belongs to when it is another's (or one
        near it is: ``train oculomotor --photoreceptor``: did you mean --photoreceptors, an option of ...?), and a
        command's option given before the command (:meth:`_misplaced`). A value
        that begins with '-' and a digit is its option's (:func:`_values_joined`)."""
        args = _values_joined(self, sys.argv[1:] if args is None else list(args))
        misplaced = self._misplaced(args)
        if misplaced:
            self.error(misplaced)
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:  # (said by the command chosen, whose --help the line points to)
            self._chosen(parsed).error(f"unrecognized arguments: {' '.join(extras)}{self._hint(parsed, extras)}")
        return parsed

    def _chosen(self, parsed: argparse.Namespace) -> argparse.ArgumentParser:
        """The parser of the (sub)command ``parsed`` chose: this one, or the subcommand it names, and so on."""
        chosen = self
        while (sub := _subcommands(chosen)) is not None and getattr(parsed, sub.dest, None) in sub.choices:
            chosen = sub.choices[getattr(parsed, sub.dest)]
        return chosen

    def _misplaced(self, args: list[str]) -> str | None:
        """Where a command's option was given before the command (``sim --quick demo``, ``data --preset quick
        foveation``): "--quick goes after the command: python -m warp_vision.sim demo --quick". argparse said
        "unrecognized arguments: --quick (--quick is an option of experiments, ...)", as if demo lacked it, or
        took the option's value for the command ("'quick' is not a command"). None when nothing is misplaced."""
        sub = _subcommands(self)
        if sub is None:
            return None
        own = _options(self)
        at = next((i for i, token in enumerate(args) if token in sub.choices), len(args))
        before = args[:at]
        flags = [f for f in (t.split("=", 1)[0] for t in before if t.startswith("-")) if f not in own]
        if not flags:
            return None
        if at < len(args) and flags[0] in _options(sub.choices[args[at]]):
            return f"{flags[0]} goes after the command: {' '.join([self.prog, *args[at:], *before])}"
        owners = [name for name, p in sub.choices.items() if flags[0] in _options(p)]
        if not owners:
            return None
        return (f"{flags[0]} is an option of {_listed(owners)}, given after the command: "
                f"{' '.join([self.prog, 'COMMAND', *before])}")

    def _hint(self, parsed: argparse.Namespace, extras: list[str]) -> str:
        chosen, neighbours = self, []  # (name, parser) of the commands beside the one chosen
        while (sub := _subcommands(chosen)) is not None:
            name = getattr(parsed, sub.dest, None)
            neighbours += [(other, p) for other, p in sub.choices.items() if other != name]
            if name not in sub.choices:
                break
            chosen = sub.choices[name]
        siblings = chosen.siblings() if chosen.siblings is not None else {}
        others = {}  # option -> the commands beside the chosen one that have it
        for other, p in [*neighbours, *siblings.items()]:
            for o in _options(p):
                others.setdefault(o, []).append(other)
        own = [o for o in _options(chosen) if o.startswith("--")]
        hints = [f"{word} is a command: name it first, before the options" for word in extras if word in siblings]
        for flag in (e.split("=", 1)[0] for e in extras if e.startswith("--")):
            near = difflib.get_close_matches(flag, own, n=1, cutoff=0.75)  # (0.6 took --shots for --out)
            if flag in others:
                hints.append(f"{flag} is an option of {_listed(others[flag])}")
            elif near:
                hints.append(f"did you mean {near[0]}?")
            elif near := difflib.get_close_matches(flag, [o for o in others if o.startswith("--")], n=1, cutoff=0.75):
                hints.append(f"did you mean {near[0]}, an option of {_listed(others[near[0]])}?")
        return f" ({'; '.join(hints)})" if hints else ""


def _options(parser: argparse.ArgumentParser) -> list[str]:
    """``parser``'s own option strings (not its subcommands'), in the order they were added."""
    return [o for a in parser._actions for o in a.option_strings]


def _listed(names: list[str]) -> str:
    """"a", "a and b", "a, b and c"."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"


_ARGPARSE_VALUE = re.compile(r"argument (\S+): (?:invalid (\w+) value|invalid choice): (.+?)(?: \(choose from (.*)\))?")
_KINDS = {"int": "an integer", "float": "a number"}


def _as_typed(message: str) -> str:
    """An argparse message in the typed checks' words: "argument --lr: ..." as "--lr: ...", and a value its
    type or choices refuse as "--samples: expected an integer, got 'abc'" or "--checkpoint: expected one of
    best, latest, got 'previous'" (an option with a short form, "-o/--out", by its long one)."""
    m = _ARGPARSE_VALUE.fullmatch(message)
    if m:
        option, kind, value, choices = m.groups()
        option = option.split("/")[-1]
        if choices is not None:
            unquoted = re.sub(r"'([^']*)'", r"\1", choices)
            return f"{option}: expected one of {unquoted}, got {value}"
        if kind is not None:
            return f"{option}: expected {_KINDS.get(kind, f'a {kind} value')}, got {value}"
    m = re.match(r"argument (\S+): ", message)
    return f"{m.group(1).split('/')[-1]}: {message[m.end():]}" if m else message


def _values_joined(parser: argparse.ArgumentParser, argv: list[str]) -> list[str]:
    """``--shard -1/2`` as ``--shard=-1/2``, for every option of ``parser`` (and of its subcommands) that takes
    one value: argparse takes a value that begins with '-' for an option unless it reads as a negative number
    (``_NEGATIVE_NUMBER``: -1, -0.5, -1e-3), and said only "argument --shard: expected one argument". Joined,
    the value reaches the option's own check ("--shard: expected 'I/N' with integers 0 <= I < N, got '-1/2'")."""
    one_value = _one_value_options(parser)
    out = []
    for i, token in enumerate(argv):
        if token == "--":  # the rest are positional
            return out + argv[i:]
        if out and out[-1] in one_value and re.match(r"-\.?\d", token):
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def _one_value_options(parser: argparse.ArgumentParser) -> set[str]:
    """The options of ``parser`` and of its subcommands' parsers that take exactly one value."""
    names = {o for a in parser._actions if a.nargs is None for o in a.option_strings}
    sub = _subcommands(parser)
    for p in (sub.choices.values() if sub is not None else ()):
        names |= _one_value_options(p)
    return names


def _subcommands(parser: argparse.ArgumentParser):
    """``parser``'s subcommands (its ``add_subparsers`` action), or None."""
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def not_a_command(word: str, names, what: str = "a command") -> str:
    """"'evalute' is not a command (did you mean 'evaluate'?): expected one of ...": the nearest of
    ``names`` to a mistyped ``word``, when one is near."""
    names = list(names)
    near = difflib.get_close_matches(word, names, n=1)
    return (f"{word!r} is not {what}{f' (did you mean {near[0]!r}?)' if near else ''}: expected one of "
            f"{', '.join(names)}")


def add_debug_flag(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--debug", action="store_true",
                   help="show the full traceback of an error (default: one line naming the file or option)")
    return p


def field_help(cls, name: str) -> str:
    """The comment after field ``name`` in the source of dataclass ``cls`` (``samples: int = 4000  # number of
    ONVs``): a config's --help text, written once beside the field. A comment too long for one line goes on in the
    comment lines below whose ``#`` stands in the same column, joined with a space."""
    import inspect

    lines = inspect.getsource(cls).splitlines()
    for i, line in enumerate(lines):
        s = line.strip()
        if s.startswith(f"{name}:") and "#" in s:
            col = line.index("#")
            words = [line[col + 1:].strip()]
            for more in lines[i + 1:]:
                if len(more) <= col or more[col] != "#" or more[:col].strip():
                    break
                words.append(more[col + 1:].strip())
            return " ".join(words)
    return ""


def field_sections(cls) -> dict[str, str]:
    """Field -> the section of dataclass ``cls`` it stands in: the comment line heading it in the source
    (``# the dataset``, ``# optimisation``); "the run" for the fields before the first. A config's --help
    groups its flags by these."""
    import inspect

    names = {f.name for f in dataclasses.fields(cls)}
    section, sections = "the run", {}
    for line in inspect.getsource(cls).splitlines():
        name = line[4:].split(":", 1)[0]
        if line.startswith("    # "):
            section = line[6:].strip()
        elif line.startswith("    ") and not line.startswith("     ") and name in names:
            sections[name] = section
    return sections


def preset_defaults(presets: dict, name: str, value) -> str:
    """The default preset's value of field ``name`` and the other presets' where they differ, for --help:
    "default: 8; --preset smoke: 7" (``value``: the field's own default, kept by a preset that does not set it)."""
    shown = presets.get("default", {}).get(name, value)
    others = [f"{k}: {v.get(name, value)!r}" for k,
              v in presets.items() if k != "default" and v.get(name, value) != shown]
    return "; ".join([f"default: {shown!r}"] + [f"--preset {o}" for o in others])


def require_seeds(cfg) -> None:
    """Every field of the dataclass ``cfg`` named ``seed`` or ``*_seed`` is a seed of
    :data:`warp_vision.limits.SEED` (numpy takes no negative seed, torch none past 64 bits)."""
    from warp_vision.limits import SEED

    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if f.name.endswith("seed") and not (isinstance(v, int) and SEED.lo <= v <= SEED.hi):
            raise ValueError(f"{f.name}: expected a seed {SEED.words()}, got {v}")


def require_positive(args, names, flags: bool = True) -> None:
    """Each attribute of ``args`` in ``names`` (an int, or a list of them) is positive, or a ValueError naming
    it and its value, before any work: as the command line's option (``--chunk-size``), or with ``flags``
    False as a config's field (``chunk_size``)."""
    for name in names:
        value = getattr(args, name)
        many = isinstance(value, (list, tuple))
        if min(value if many else [value]) < 1:
            label = f"--{name.replace('_', '-')}" if flags else name
            raise ValueError(f"{label}: expected {'positive integers' if many else 'a positive integer'}, got {value}")


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a batch scheduler's preemption), raised where Python is when it arrives, as Ctrl-C
    raises KeyboardInterrupt: what stops cleanly on Ctrl-C (a training run's "interrupted" line, its
    synthesis helpers) stops the same way, and the command exits with 143 (128 + SIGTERM)."""


def told(e: BaseException) -> BaseException:
    """Mark an interruption whose command has told its user where things stand (a training run's
    "interrupted: ..." line): :func:`guarded` then adds no line of its own. Returns ``e``."""
    e.told = True
    return e


#: how long a SIGTERM that arrived inside a finaliser waits before it is sent again (:func:`_terminate`)
RESEND_SECONDS = 0.01
#: the timers that will send such a SIGTERM again
_resends: list[threading.Timer] = []


def _in_finaliser(frame) -> bool:
    """Whether ``frame`` runs inside an object's ``__del__`` (it or a frame that called it)."""
    while frame is not None:
        if frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def _terminate(signum, frame):
    """SIGTERM's handler: :class:`Terminated` raised where Python is. Not inside a ``__del__`` (Warp frees an
    array's memory in one): Python prints an exception that leaves a finaliser and drops it, and the command
    would run on to its end as if no signal had come. There the signal is sent again a moment later, to be
    raised once the finaliser has returned."""
    if _in_finaliser(frame):
        timer = threading.Timer(RESEND_SECONDS, os.kill, (os.getpid(), signum))
        timer.daemon = True
        _resends.append(timer)
        timer.start()
        return
    _cancel_resends()
    raise Terminated(f"signal {signum}")


def _cancel_resends() -> bool:
    """Cancel the SIGTERMs waiting to be sent again; whether there were any."""
    waiting = bool(_resends)
    while _resends:
        _resends.pop().cancel()
    return waiting


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Within the block (in the main thread), SIGTERM raises :class:`Terminated`; the old handler after. A
    SIGTERM still waiting to be sent again (:func:`_terminate`) when the block ends is raised then."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        waiting = _cancel_resends()
        signal.signal(signal.SIGTERM, old)
    if waiting:
        raise Terminated(f"signal {int(signal.SIGTERM)}")


def long_options(parser: argparse.ArgumentParser) -> frozenset[str]:
    """Every ``--option`` of ``parser`` and of its subcommands' parsers."""
    names = {o for o in _options(parser) if o.startswith("--")}
    sub = _subcommands(parser)
    for p in (sub.choices.values() if sub is not None else ()):
        names |= long_options(p)
    return frozenset(names)


def as_option(line: str, options) -> str:
    """An error line that begins with a setting's name (``lr: expected > 0``, as a config's checks word
    it) begun with the command-line option the user typed instead (``--lr: expected > 0``), where
    ``options`` holds one of that name; other lines as they are."""
    m = re.match(r"([a-z][A-Za-z0-9_]*): ", line)
    option = m and "--" + m.group(1).replace("_", "-")
    return option + line[m.end(1):] if option in options else line


def guarded(job: Callable[[], object], debug: bool = False, codes: dict[type, int] | None = None,
            options=frozenset()) -> int:
    """Run ``job``: 0 when it returns (or its own int exit code); ValueError, OSError and the exception
    types in ``codes`` ({type: exit code}) print one ``error:`` line on stderr and return 2 (or their
    code), as does a failed allocation (:func:`out_of_memory`; other RuntimeErrors raise); Ctrl-C returns
    130, SIGTERM 143 (:class:`Terminated`), saying so in a line unless the command has said where it stopped
    (:func:`told`). A line that begins with a setting's name begins with its option where ``options``
    (the command's, :func:`long_options`) holds one (:func:`as_option`). The environment variables the package
    reads are checked first (:func:`warp_vision.resources.check_environment`). With ``debug`` the errors raise,
    traceback and all."""
    codes = codes or {}
    try:
        check_environment()  # (before any work, bar or file)
        with sigterm_as_interrupt():
            r = job()
    except Terminated as e:
        if not getattr(e, "told", False):
            print("stopped (SIGTERM)", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt as e:
        if not getattr(e, "told", False):  # every interruption ends with a line, the command's or this one
            print("interrupted (Ctrl-C)", file=sys.stderr)
        return 130
    except (ValueError, OSError, *codes) as e:
        if debug:
            raise
        line = error_line(e)  # (an OSError's begins with a file's name, which may be an option's word)
        print(f"error: {line if isinstance(e, OSError) else as_option(line, options)}", file=sys.stderr)
        return next((c for t, c in codes.items() if isinstance(e, t)), 2)
    except (MemoryError, RuntimeError) as e:
        if debug or not out_of_memory(e):
            raise
        print(f"error: out of memory, settings too large for this machine (a smaller --batch, net or dataset): "
              f"{error_line(e)}", file=sys.stderr)
        return 2
    return r if isinstance(r, int) else 0


def out_of_memory(e: BaseException) -> bool:
    """Whether ``e`` says an allocation failed: Python's MemoryError, or torch's RuntimeError for the CPU
    allocator ("can't allocate memory") or a GPU's ("out of memory", torch.OutOfMemoryError)."""
    text = str(e).lower()
    return isinstance(e, MemoryError) or (isinstance(e, RuntimeError)
                                          and ("can't allocate memory" in text or "out of memory" in text))
