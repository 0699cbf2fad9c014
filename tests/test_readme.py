"""The README's snippets run: every ```python block executes as written, and every command line of a
```bash block, in the README and in docs/RESULTS.md (the commands behind the measurements), names a
command and flags that exist (its --help parses them); every relative link of the docs reaches a file and a
heading."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
RESULTS = (ROOT / "docs" / "RESULTS.md").read_text()


def blocks(lang: str, text: str = README) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", text, flags=re.S | re.M)


def commands(text: str = README) -> list[list[str]]:
    """``python -m warp_vision.X ...`` lines of the bash blocks of ``text`` (comments dropped), as argv lists."""
    out = []
    for block in blocks("bash", text):
        for line in block.splitlines():
            line = line.split("#", 1)[0].strip()
            if "warp_vision." in line and line.startswith(("python -m", "torchrun")):
                out.append(shlex.split(line))
    return out


def test_the_readme_has_snippets():
    assert len(blocks("python")) >= 2 and len(commands()) >= 10
    assert len(commands(RESULTS)) >= 10


@pytest.mark.parametrize("k", range(len(blocks("python"))))
def test_python_snippet_runs(k, tmp_path):
    code = blocks("python")[k]
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, f"README python block {k} failed:\n{code}\n{r.stderr[-3000:]}"


def _help_argv(argv: list[str]) -> list[str]:
    """The command line that asks the same (sub)command for --help: flags and positionals dropped, the
    module and its subcommand kept."""
    i = argv.index("-m") + 1
    module = argv[i]
    nxt = argv[i + 1:i + 2]  # a subcommand comes right after the module (in "--preset smoke", smoke is a value)
    sub = nxt if nxt and re.fullmatch(r"[a-z]+", nxt[0]) else []
    return [sys.executable, "-m", module, *sub, "--help"]


@pytest.mark.parametrize("argv", commands() + commands(RESULTS), ids=lambda a: " ".join(a)[:60])
def test_bash_command_exists(argv, tmp_path):
    """The command and subcommand exist, and each --flag the README passes is in its --help."""
    r = subprocess.run(_help_argv(argv), cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    after_module = argv[argv.index("-m") + 2:]
    for flag in (a.split("=")[0] for a in after_module if a.startswith("--")):
        assert flag in r.stdout, f"{' '.join(argv)}: {flag} is not an option of {' '.join(_help_argv(argv)[1:])}"


def _training_commands() -> list[list[str]]:
    """The training command lines of the README and RESULTS (not compare, evaluate or --resume), after
    ``python -m warp_vision.train``."""
    out = []
    for argv in commands() + commands(RESULTS):
        i = argv.index("-m")
        rest = argv[i + 2:]
        if (argv[i + 1] == "warp_vision.train" and rest[:1] not in (["compare"], ["evaluate"])
                and "--resume" not in rest):
            out.append(rest)
    return out


def test_the_docs_have_training_commands():
    assert len(_training_commands()) >= 10


@pytest.mark.parametrize("rest", _training_commands(), ids=lambda a: " ".join(a)[:60] or "(defaults)")
def test_training_command_passes_its_checks(rest):
    """Each training command the docs show gives a config: the flags are not only in --help but accepted
    together (a flag the chosen model does not read, say, is refused before any work)."""
    from warp_vision.train.cli import parse_training

    _, cls, _, make, _ = parse_training(rest)
    assert isinstance(make(), cls)


def anchors(path: Path) -> set[str]:
    """The ``#fragment`` of each heading of a Markdown file, as GitHub makes it: lower case, punctuation
    other than "-" and "_" dropped, spaces as "-"."""
    heads = re.findall(r"^#{1,6} (.+?)\s*$", path.read_text(), flags=re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in heads}


@pytest.mark.parametrize("doc", ["README.md", "docs/RESULTS.md", "docs/ARCHITECTURE.md"])
def test_the_docs_links_reach_a_file_and_a_heading(doc):
    """Every relative link of the docs names a file of the repository, and its #fragment a heading there
    (the README pointed to sections of the results by their titles in quotes, which no reader could follow)."""
    page = ROOT / doc
    links = re.findall(r"\]\(([^)\s]+)\)", page.read_text())
    local = [link for link in links if not link.startswith(("http://", "https://", "mailto:"))]
    assert local or doc != "README.md"
    for link in local:
        target, _, fragment = link.partition("#")
        path = (page.parent / target).resolve() if target else page
        assert path.exists(), f"{doc}: {link} names no file"
        if fragment:
            assert fragment in anchors(path), f"{doc}: {link}: no heading of {path.name} makes #{fragment}"
