""".ci/lowest.py, which pins every requirement of pyproject.toml to its floor for ``LOWEST=1 .ci/run``."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest
from packaging.requirements import Requirement

try:
    import tomllib
except ImportError:  # Python 3.10: pytest's own dependency there
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


def _lowest():
    spec = importlib.util.spec_from_file_location("ci_lowest", ROOT / ".ci" / "lowest.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_requirement_is_pinned_to_its_floor():
    ci = _lowest()
    text = (ROOT / "pyproject.toml").read_text()
    reqs = ci.requirements(text)
    project = tomllib.loads(text)["project"]  # what pip reads: the hand-written reader misses nothing
    assert reqs == project["dependencies"] + project["optional-dependencies"]["test"]
    pins = [ci.lowest(r) for r in reqs]
    names = [Requirement(r).name for r in reqs]
    assert {"torch", "mujoco", "numpy", "warp-lang", "pytest"} <= set(names)
    assert len(set(names)) == len(names)
    for req, name, pin in zip(reqs, names, pins):
        assert re.fullmatch(rf"{re.escape(name)}==\d+(\.\d+)*", pin), pin
        assert Requirement(req).specifier.contains(pin.split("==")[1]), (req, pin)  # the floor is in its range
    # .ci/run installs the CPU build on disk before the package: the range must admit it
    torch = next(Requirement(r) for r in reqs if r.startswith("torch"))
    assert torch.specifier.contains("2.13.0")


def test_a_floor_is_taken_from_its_clause_and_a_requirement_without_one_is_refused():
    ci = _lowest()
    assert ci.lowest("torch>=2.5,<=2.13.0") == "torch==2.5"
    assert ci.lowest("mujoco<4,>=3.16") == "mujoco==3.16"
    assert ci.lowest("anny==0.6.2") == "anny==0.6.2"
    assert ci.lowest("pkg[extra]>=1.0") == "pkg==1.0"
    for req in ("numpy", "numpy<2"):
        with pytest.raises(SystemExit, match="names no floor"):
            ci.lowest(req)
    with pytest.raises(SystemExit, match="no 'test"):
        ci.requirements('dependencies = [\n    "numpy>=1",\n]\n')
