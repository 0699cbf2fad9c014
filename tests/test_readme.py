"""The README's and the docs' snippets run: every ```python block of the README and of the user guide
(docs/guide.md) executes as written, and every command line of a ```bash block, in the README and in every
page of docs/ (docs/RESULTS.md: the commands behind the measurements; the guide; the site's tutorials,
concepts and results), names a command and flags that exist (its --help parses them); every relative link of
the README and of every page of docs/ reaches a file and a heading; the README stays short, and its install
and test commands are the ones .ci/run runs."""

from __future__ import annotations

import functools
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
RESULTS = (ROOT / "docs" / "RESULTS.md").read_text()
#: every Markdown page of docs/ (RESULTS.md, ARCHITECTURE.md and the documentation site's pages), by its path
DOCS = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").rglob("*.md"))
GUIDE = (ROOT / "docs" / "guide.md").read_text()


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


def doc_commands() -> list[list[str]]:
    """The command lines of the README and of every page of docs/, each once (the pages repeat some)."""
    out = []
    for text in [README] + [(ROOT / doc).read_text() for doc in DOCS]:
        out += [argv for argv in commands(text) if argv not in out]
    return out


def test_the_readme_has_snippets():
    """The README: one Python snippet, the quick start's three commands and the list of commands; the
    guide: the longer snippets and every command in depth."""
    assert len(blocks("python")) >= 1 and len(commands()) >= 12
    assert len(blocks("python", GUIDE)) >= 2 and len(commands(GUIDE)) >= 40
    assert len(commands(RESULTS)) >= 10
    assert {"docs/index.md", "docs/cli.md", "docs/tutorials/train-foveation.md", "docs/results/index.md"} <= set(DOCS)
    assert len(doc_commands()) > len(commands()) + 20  # the site's pages show commands of their own


def test_the_readme_is_short():
    """About 150 lines: what it is, the data path, install and test, the quick start, the results, one
    snippet, the commands and the docs; the rest belongs in docs/guide.md."""
    assert len(README.splitlines()) <= 180
    assert len(README.split()) <= 1800


def test_the_readme_install_and_test_commands_are_what_ci_runs():
    """.ci/run's lines after its "# --- README: install ---" and "# --- README: test ---" markers are
    the README's two commands, in one bash block, in that order."""
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    install = ci[ci.index("    # --- README: install ---") + 1].strip()
    test = ci[ci.index("# --- README: test ---") + 1].strip()
    assert any(b.splitlines()[:2] == [install, test] for b in blocks("bash")), (install, test)


SNIPPETS = [("README.md", code) for code in blocks("python")] + [("docs/guide.md",
                                                                  code) for code in blocks("python", GUIDE)]


@pytest.mark.parametrize("doc, code", SNIPPETS, ids=[f"{d}:{k}" for k, (d, _) in enumerate(SNIPPETS)])
def test_python_snippet_runs(doc, code, tmp_path):
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, f"{doc} python block failed:\n{code}\n{r.stderr[-3000:]}"


def _help_argv(argv: list[str]) -> list[str]:
    """The command line that asks the same (sub)command for --help: flags and positionals dropped, the
    module and its subcommand kept."""
    i = argv.index("-m") + 1
    module = argv[i]
    nxt = argv[i + 1:i + 2]  # a subcommand comes right after the module (in "--preset smoke", smoke is a value)
    sub = nxt if nxt and re.fullmatch(r"[a-z]+", nxt[0]) else []
    return [sys.executable, "-m", module, *sub, "--help"]


@functools.lru_cache(maxsize=1)
def _by_help() -> dict[str, list[list[str]]]:
    """The docs' command lines grouped by the --help that checks them (one subprocess per (sub)command)."""
    groups: dict[str, list[list[str]]] = {}
    for argv in doc_commands():
        groups.setdefault(" ".join(_help_argv(argv)[1:]), []).append(argv)
    return groups


@pytest.mark.parametrize("command", sorted(_by_help()))
def test_bash_command_exists(command, tmp_path):
    """The command and subcommand exist, and each --flag that any of the docs' lines passes it is in its --help."""
    r = subprocess.run([sys.executable, *command.split()], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    for argv in _by_help()[command]:
        after_module = argv[argv.index("-m") + 2:]
        for flag in (a.split("=")[0] for a in after_module if a.startswith("--")):
            assert flag in r.stdout, f"{' '.join(argv)}: {flag} is not an option of {command}"


def _training_commands() -> list[list[str]]:
    """The training command lines of the README and the pages of docs/ (not compare, evaluate or --resume),
    after ``python -m warp_vision.train``."""
    out = []
    for argv in doc_commands():
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


@pytest.mark.parametrize("doc", ["README.md", *DOCS])
def test_the_docs_links_reach_a_file_and_a_heading(doc):
    """Every relative link of the docs names a file of the repository, and its #fragment a heading there
    (the README pointed to sections of the results by their titles in quotes, which no reader could follow)."""
    page = ROOT / doc
    links = re.findall(r"\]\(([^)\s]+)\)", page.read_text())
    local = [link for link in links if not link.startswith(("http://", "https://", "mailto:"))]
    assert local or doc not in ("README.md", "docs/guide.md")
    broken = []  # every broken link, not only the first
    for link in local:
        target, _, fragment = link.partition("#")
        path = (page.parent / target).resolve() if target else page
        if not path.exists():
            broken.append(f"{link} names no file")
        elif fragment and fragment not in anchors(path):
            broken.append(f"{link}: no heading of {path.name} makes #{fragment}")
    assert not broken, f"{doc}: " + "; ".join(broken)


def test_every_module_has_an_api_page():
    """Each module of the package (packages' __init__ and the command-line modules aside: docs/cli.md covers
    those) is rendered on one of docs/api's pages, so a new module is not left out of the reference."""
    pages = "\n".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md"))
    listed = set(re.findall(r"^::: (warp_vision[\w.]*)$", pages, flags=re.M))
    modules = {".".join(p.relative_to(ROOT).with_suffix("").parts) for p in (ROOT / "warp_vision").rglob("*.py")
               if p.stem not in ("__init__", "__main__", "cli")}
    missing = sorted(m for m in modules if m not in listed)
    assert not missing, f"modules on no docs/api page: {missing}"
