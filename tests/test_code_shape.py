"""The package's functions stay short (docs/ARCHITECTURE.md, Conventions, "Sizes"): none over ``MAX_LINES``
lines from its ``def`` to its last line, but the Warp kernels and functions of ``ALLOWED``, whose docstrings
say why (a paragraph that begins "Length:")."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "warp_vision"
MAX_LINES = 80

#: (module path, qualified name): Warp kernels or functions longer than MAX_LINES, each docstring saying why.
ALLOWED = {
    ("warp_vision/kernels/render/packet.py", "_packet_traverse"),
}


def functions(path: Path):
    """(qualified name, node) of every function and method of the module at ``path``, nested ones included."""
    def walk(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield prefix + child.name, child
                yield from walk(child, f"{prefix}{child.name}.")
            elif isinstance(child, ast.ClassDef):
                yield from walk(child, f"{prefix}{child.name}.")
            else:
                yield from walk(child, prefix)

    yield from walk(ast.parse(path.read_text(), filename=str(path)), "")


def length(node) -> int:
    return node.end_lineno - node.lineno + 1


def every_function():
    for path in sorted(PACKAGE.rglob("*.py")):
        for name, node in functions(path):
            yield path.relative_to(ROOT).as_posix(), name, node


def is_warp(node) -> bool:
    """Decorated with ``wp.kernel`` or ``wp.func`` (called or not)."""
    for d in node.decorator_list:
        f = d.func if isinstance(d, ast.Call) else d
        if isinstance(f, ast.Attribute) and f.attr in ("kernel", "func") and getattr(f.value, "id", "") == "wp":
            return True
    return False


def test_no_function_is_longer_than_the_limit():
    long = [f"{path}: {name}, {length(node)} lines" for path, name, node in every_function()
            if length(node) > MAX_LINES and (path, name) not in ALLOWED]
    assert not long, f"over {MAX_LINES} lines (split into named steps): " + "; ".join(long)


@pytest.mark.parametrize("path, name", sorted(ALLOWED))
def test_an_allowed_long_function_is_a_warp_kernel_that_says_why(path, name):
    node = dict((n, d) for n, d in functions(ROOT / path)).get(name)
    assert node is not None, f"{path}: no {name} (remove it from ALLOWED)"
    assert is_warp(node), f"{path}: {name} is not a Warp kernel or function: split it"
    assert length(node) > MAX_LINES, f"{path}: {name} is {length(node)} lines now: remove it from ALLOWED"
    assert "Length:" in (ast.get_docstring(node) or ""), f"{path}: {name}'s docstring does not say why it is long"


def test_the_check_finds_a_long_function(tmp_path):
    body = "\n".join(f"        x{i} = {i}" for i in range(MAX_LINES))
    (tmp_path / "m.py").write_text(f"class C:\n    def f(self):\n{body}\n\n\ndef g():\n    return 1\n")
    found = {name: length(node) for name, node in functions(tmp_path / "m.py")}
    assert found == {"C.f": MAX_LINES + 1, "g": 2}
