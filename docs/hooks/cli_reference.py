"""MkDocs hook: the command-line reference of docs/cli.md, generated at build time from the commands' own
argparse parsers, so that it says what ``--help`` says.

docs/cli.md holds the prose and one marker line, ``<!-- cli-reference -->``, which this hook replaces by a
section per command and subcommand: its usage line, its description and a table of its options, group by
group as ``--help`` shows them. A parser builder that is gone or fails stops the build (the reference
would otherwise be quietly wrong).
"""

from __future__ import annotations

import argparse
import html
import importlib
import sys
from pathlib import Path

MARKER = "<!-- cli-reference -->"
PAGE = "cli.md"


def _train_parsers():
    """train's parsers (the foveation task's, each other task's, evaluate's, compare's), with no summary."""
    cli = importlib.import_module("warp_vision.train.cli")
    yield cli._train_parser(), ""
    for task in cli.TASKS:
        yield cli._task_parser(task), ""
    yield cli._eval_parser(), ""
    yield cli._compare_parser(), ""


def _subcommands(module: str, builder: str):
    """A parser with subcommands, then each subcommand's parser with the line its parent's --help gives it."""
    parser = getattr(importlib.import_module(module), builder)()
    yield parser, ""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            summaries = {a.dest: a.help or "" for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield sub, summaries.get(name, "")


#: each command of ``python -m warp_vision`` and the parsers of its command line, in the order of
#: warp_vision/__main__.py's COMMANDS (a test of the package checks that list against the subpackages)
COMMANDS = {
    "train": _train_parsers,
    "sim": lambda: _subcommands("warp_vision.sim.cli", "parser"),
    "data": lambda: _subcommands("warp_vision.data.cli", "parser"),
    "bench": lambda: _subcommands("warp_vision.bench.cli", "_parser"),
    "scene": lambda: _subcommands("warp_vision.scene.cli", "_parser"),
}


def _text(s: str) -> str:
    """Help text as Markdown that shows it as it is: HTML and Markdown's own characters escaped, on one line."""
    s = html.escape(" ".join(s.split()), quote=False)
    for ch in "\\`*_[]|":
        s = s.replace(ch, "\\" + ch)
    return s


def _invocation(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    return parser._get_formatter()._format_action_invocation(action)


def _help(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    return parser._get_formatter()._expand_help(action) if action.help else ""


def _options(parser: argparse.ArgumentParser) -> list[str]:
    """A table per argument group that has options to show (positionals included; -h and subcommands left out)."""
    out = []
    for group in parser._action_groups:
        actions = [a for a in group._group_actions if a.help is not argparse.SUPPRESS
                   and not isinstance(a, (argparse._HelpAction, argparse._SubParsersAction))]
        if not actions:
            continue
        out += ["", f"**{_text(group.title or 'options')}**", ""]
        if group.description:
            out += [_text(group.description), ""]
        out += ["| option | what it sets |", "|---|---|"]
        out += [f"| `{_invocation(parser, a)}` | {_text(_help(parser, a))} |" for a in actions]
    return out


def _section(parser: argparse.ArgumentParser, summary: str, heading: bool = True) -> list[str]:
    """A parser's usage, description and options; under a heading of its own but for a command's first parser,
    whose section is the command's."""
    usage = parser.format_usage().strip()
    lines = ["", f"### `{parser.prog}`", ""] if heading else [""]
    if summary and not parser.description:
        lines += [_text(summary[:1].upper() + summary[1:]) + ".", ""]
    if parser.description:
        if parser.formatter_class is argparse.RawDescriptionHelpFormatter:
            lines += ["```text", parser.description.strip("\n"), "```", ""]
        else:
            lines += [_text(parser.description), ""]
    lines += ["```text", usage, "```"]
    return lines + _options(parser)


def reference() -> str:
    from warp_vision.__main__ import COMMANDS as PACKAGE_COMMANDS
    from warp_vision.__main__ import usage

    if list(PACKAGE_COMMANDS) != list(COMMANDS):
        raise RuntimeError(f"docs/hooks/cli_reference.py: the commands are {list(PACKAGE_COMMANDS)}, the reference "
                           f"knows {list(COMMANDS)}; add the new command's parsers to COMMANDS")
    lines = ["## `python -m warp_vision`", "", "```text", usage(), "```"]
    for name, parsers in COMMANDS.items():
        what = PACKAGE_COMMANDS[name]
        lines += ["", f"## `python -m warp_vision.{name}`", "", _text(what[:1].upper() + what[1:]) + "."]
        for i, (parser, summary) in enumerate(parsers()):
            lines += _section(parser, summary, heading=i > 0)
    return "\n".join(lines) + "\n"


def on_config(config):
    """The parsers are those of the checkout mkdocs.yml is in (as the API reference's source is), whatever
    warp_vision the environment has installed."""
    root = str(Path(config.config_file_path).resolve().parent)
    if root not in sys.path:
        sys.path.insert(0, root)
    import warp_vision

    if not Path(warp_vision.__file__).resolve().is_relative_to(root):
        raise RuntimeError(f"docs/hooks/cli_reference.py: warp_vision was imported from {warp_vision.__file__}, "
                           f"not from the checkout being documented, {root}")
    return config


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri != PAGE:
        return markdown
    if MARKER not in markdown:
        raise RuntimeError(f"docs/{PAGE}: the line {MARKER} that the generated reference replaces is missing")
    return markdown.replace(MARKER, reference())
