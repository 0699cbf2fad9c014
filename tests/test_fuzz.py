"""The fuzz drill of every command's options (tests/fuzz_cli.py), on a small budget: each case ends in exit 0, in
one ``error:`` line with exit 2, or is still working at its time budget having printed no error, within a memory
cap. ``WARP_VISION_FUZZ_CASES=N`` (default 24) and ``WARP_VISION_FUZZ_SEED`` run more, or others."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import fuzz_cli

CASES = int(os.environ.get("WARP_VISION_FUZZ_CASES", "24"))
SEED = int(os.environ.get("WARP_VISION_FUZZ_SEED", "1"))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="the drill forks a child per case")
def test_every_fuzzed_command_line_ends_in_a_result_or_one_error_line():
    tally = fuzz_cli.drill(CASES, SEED, log=lambda *a: None)
    assert tally["cases"] == CASES
    assert tally["failure"] == 0, "\n\n".join(f"{argv}\n{err}" for argv, err in tally["failures"])
    assert tally["error"] > 0  # the drill reached the checks


def test_the_drill_tells_a_traceback_or_a_usage_block_from_one_error_line():
    ok = 0
    assert fuzz_cli.classify(ok, "") == "ok"
    two = 2 << 8
    assert fuzz_cli.classify(two, "error: --width: expected an integer 1..8,192 pixels, got 0\n") == "error"
    assert fuzz_cli.classify(two, "usage: x [-h]\nx: error: argument --width: invalid int value\n") == "failure"
    assert fuzz_cli.classify(1 << 8, "Traceback (most recent call last):\n  ...\nRuntimeError: boom\n") == "failure"
    assert fuzz_cli.classify(two, "error: one\nerror: two\n") == "failure"
    assert fuzz_cli.classify(signal.SIGALRM, "synthesising 160 ONVs\n") == "working"
    assert fuzz_cli.classify(signal.SIGSEGV, "") == "failure"
    assert fuzz_cli.classify(signal.SIGKILL, "") == "failure"  # killed (the kernel's OOM killer, say)
