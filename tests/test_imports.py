"""The house's shape: the package's imports form no cycle, and no stage imports a later one.

The stages along the data path (docs/ARCHITECTURE.md, "Where each thing lives"), lowest first. A module
may import its own stage and the stages listed before it, never one listed after it. Every import
statement counts, also those inside functions (a lazy import is still a dependency).
"""

from __future__ import annotations

import ast
import itertools
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "warp_vision"

#: stage -> the stages it may import (besides itself). ``frames``,
#: ``fileio``, ``resources``, ``errors`` and ``limits`` are the foundations.
ALLOWED = {
    "foundation": set(),
    "eye": {"foundation"},
    "viz": {"foundation", "eye"},
    "kernels": {"foundation", "eye"},
    "scene": {"foundation", "eye", "viz", "kernels"},
    "nn": {"foundation", "eye", "kernels"},
    "body": {"foundation", "eye"},
    "data": {"foundation", "eye", "viz", "kernels", "scene", "nn", "body"},
    "sim": {"foundation", "eye", "viz", "kernels", "scene", "nn", "body", "data"},
    "train": {"foundation", "eye", "viz", "kernels", "scene", "nn", "body", "data", "sim"},
    "bench": {"foundation", "eye", "viz", "kernels", "scene", "nn", "body", "data", "sim"},
    "package": {"foundation"},
}
# python -m warp_vision: the commands' index, above them all (it runs each command's cli by name)
ALLOWED["index"] = set(ALLOWED) - {"package"}


def stage_of(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "package"
    head = parts[1]
    if head == "__main__":
        return "index"
    if head in ("frames", "fileio", "resources", "errors", "provenance", "limits"):
        return "foundation"
    if head not in ALLOWED:
        raise AssertionError(f"{module}: in no stage; add its stage to ALLOWED and docs/ARCHITECTURE.md")
    return head


def module_name(path: Path, root: Path = PACKAGE) -> str:
    rel = path.relative_to(root.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path, root: Path = PACKAGE) -> set[str]:
    """The package modules (``warp_vision.*``) that the file at ``path`` imports, anywhere in it."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == root.name}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != root.name:
                continue
            for a in node.names:  # "from pkg import module" imports the module
                sub = f"{mod}.{a.name}"
                known = (root.parent / Path(*sub.split("."))).with_suffix(".py").exists() or (
                    root.parent / Path(*sub.split(".")) / "__init__.py").exists()
                out.add(sub if known else mod)
    out.discard(name)
    return out


def import_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    return {module_name(p, root): imports_of(p, root) for p in sorted(root.rglob("*.py"))}


def stage_violations(graph: dict[str, set[str]]) -> list[str]:
    bad = []
    for mod, deps in graph.items():
        s = stage_of(mod)
        for d in sorted(deps):
            t = stage_of(d)
            if t != s and t not in ALLOWED[s]:
                bad.append(f"{mod} ({s}) imports {d} ({t})")
    return bad


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), or a module importing itself.
    Imports of a package's ``__init__`` by its own submodules (``from warp_vision.nn import x``) count."""
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = itertools.count()

    def visit(v):
        index[v] = low[v] = next(counter)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_no_stage_imports_a_later_one():
    assert stage_violations(import_graph()) == []


def test_the_checks_fail_on_a_backward_import_and_a_cycle(tmp_path):
    """A copy of the package with one import added: eye importing nn (backward) and sim importing train
    (backward, forbidden: the simulation loads trained nets through nn), then a cycle."""
    import shutil

    root = tmp_path / "warp_vision"
    shutil.copytree(PACKAGE, root, ignore=shutil.ignore_patterns("__pycache__"))
    graph = import_graph(root)
    assert stage_violations(graph) == [] and cycles(graph) == []
    retina = root / "eye" / "retina.py"
    retina.write_text(retina.read_text() + "\n\ndef _late():\n    from warp_vision.nn import connectivity\n")
    assert any("warp_vision.eye.retina (eye) imports warp_vision.nn" in v for v in stage_violations(import_graph(root)))
    loop = root / "sim" / "loop.py"
    loop.write_text(loop.read_text() + "\nfrom warp_vision.train import harness\n")
    assert any(
        "warp_vision.sim.loop (sim) imports warp_vision.train.harness" in v
        for v in stage_violations(import_graph(root))
    )
    frames = root / "frames.py"
    frames.write_text(frames.read_text() + "\nfrom warp_vision import fileio\n")
    fileio = root / "fileio.py"
    fileio.write_text(fileio.read_text() + "\nimport warp_vision.frames\n")
    assert ["warp_vision.fileio", "warp_vision.frames"] in cycles(import_graph(root))


@pytest.mark.parametrize("stage", ["eye", "kernels"])
def test_lower_stages_import_nothing_above_them(stage):
    graph = import_graph()
    higher = {"nn", "train", "sim", "bench", "data", "scene", "viz"} - ALLOWED[stage]
    for mod, deps in graph.items():
        if stage_of(mod) == stage:
            assert not {stage_of(d) for d in deps} & higher, (mod, deps)
