"""How the command lines report what went wrong: one line, and a non-zero exit code.

Every ``python -m warp_vision.<command>`` runs its work through :func:`guarded`. Bad input (ValueError)
and file-system faults (OSError: no space, read-only, permissions, a file where a directory belongs)
become one line on stderr, ``error: ...`` naming the file or the option, and exit code 2; a traceback
appears only with ``--debug``.
"""

from __future__ import annotations

import argparse
import sys
from typing import Callable


def error_line(e: BaseException) -> str:
    """One line for an error a user can act on: an OSError as "FILE: what went wrong", others as their message."""
    if isinstance(e, OSError) and e.strerror:
        return f"{e.filename}: {e.strerror}" if e.filename else e.strerror
    return " ".join(str(e).split()) or type(e).__name__


class ArgumentParser(argparse.ArgumentParser):
    """Every command's parser: argparse's, without its matching of abbreviated options, so that a flag a
    command lacks is an error rather than another flag it begins (``data faces --samples 10`` was taken as
    ``--samples-per-receptor 10``). Its subcommands' parsers are of this class too."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)


def add_debug_flag(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    p.add_argument("--debug", action="store_true",
                   help="show the full traceback of an error (default: one line naming the file or option)")
    return p


def guarded(job: Callable[[], object], debug: bool = False, codes: dict[type, int] | None = None) -> int:
    """Run ``job``: 0 when it returns (or its own int exit code); ValueError, OSError and the exception
    types in ``codes`` ({type: exit code}) print one ``error:`` line on stderr and return 2 (or their
    code); Ctrl-C returns 130. With ``debug`` the errors raise, traceback and all."""
    codes = codes or {}
    try:
        r = job()
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError, *codes) as e:
        if debug:
            raise
        print(f"error: {error_line(e)}", file=sys.stderr)
        return next((c for t, c in codes.items() if isinstance(e, t)), 2)
    return r if isinstance(r, int) else 0
