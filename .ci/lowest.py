"""Print pip constraints that pin each requirement of pyproject.toml (the package's and the test extra's)
to the oldest release its range admits: ``name>=X,...`` becomes ``name==X``; ``name==X`` stays.

``LOWEST=1 .ci/run`` installs with them, so that the floors pyproject.toml states are run, not assumed. It
runs on the venv's Python, which may lack tomllib (3.10), so this reads the two lists itself; a requirement
without a floor is an error (its oldest release is not a floor anyone chose).
"""

from __future__ import annotations

import re
import sys
from pathlib import Path


def requirements(pyproject: str) -> list[str]:
    """The quoted entries of ``dependencies = [...]`` and of ``test = [...]``, comments left out."""
    out = []
    for key in ("dependencies", "test"):
        m = re.search(rf"^{key}\s*=\s*\[(.*?)\]\s*$", pyproject, re.S | re.M)
        if not m:
            raise SystemExit(f"lowest.py: no '{key} = [...]' in pyproject.toml")
        body = "\n".join(line.split("#", 1)[0] for line in m.group(1).splitlines())
        out += re.findall(r'"([^"]+)"', body)
    return out


def lowest(req: str) -> str:
    """``name==floor`` for one requirement string."""
    m = re.fullmatch(r"([A-Za-z0-9_.\-]+)(\[[^\]]*\])?\s*(.*)", req.strip())
    name, spec = m.group(1), m.group(3)
    for clause in (c.strip() for c in spec.split(",")):
        op = re.match(r"(==|>=)\s*([0-9][^\s;]*)", clause)
        if op:
            return f"{name}=={op.group(2)}"
    raise SystemExit(f"lowest.py: {req!r} names no floor (>= or ==)")


if __name__ == "__main__":
    text = Path(sys.argv[1] if len(sys.argv) > 1 else "pyproject.toml").read_text()
    print("\n".join(lowest(r) for r in requirements(text)))
