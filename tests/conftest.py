"""Shared fixtures: the ``device`` fixture, a kernel cache owned by the test session, a smoke dataset and a
finished smoke run on it (one per module), and a numpy archive whose headers are damaged."""

from __future__ import annotations

import os
import tempfile
import zipfile

import pytest


def pytest_configure(config):
    # Warp compiles kernels into a cache directory. The tests use their own (a fresh temporary one,
    # or WARP_VISION_TEST_KERNEL_CACHE to reuse one between runs) so a run never depends on what
    # some other program left in ~/.cache/warp. This must happen before Warp is initialised.
    cache = os.environ.get("WARP_VISION_TEST_KERNEL_CACHE") or tempfile.mkdtemp(prefix="warp_vision_kernels_")
    os.environ["WARP_VISION_KERNEL_CACHE"] = cache
    # ... and the BVHs kept on disk go to a directory of the session's own, never the user's cache
    os.environ["WARP_VISION_CACHE"] = tempfile.mkdtemp(prefix="warp_vision_cache_")
    import warp as wp

    wp.config.kernel_cache_dir = cache


def _devices() -> list[str]:
    from warp_vision.kernels.launch import available_devices

    return available_devices()


@pytest.fixture(params=_devices())
def device(request) -> str:
    """A torch device string: "cpu", plus "cuda:0" when Warp and torch see a GPU."""
    return request.param


@pytest.fixture
def cuda_device() -> str:
    """"cuda:0" for GPU-only tests; skips (never fails) where there is no GPU."""
    if "cuda:0" not in _devices():
        pytest.skip("no CUDA device visible to Warp and torch")
    return "cuda:0"


def _unclose_npz_headers(path) -> None:
    """Replace the closing brace of the ``.npy`` header of every member of the ``.npz`` at ``path`` by a space
    (the archive rewritten with good CRCs): numpy then raises tokenize.TokenError, on every Python."""

    def unclosed(data: bytes) -> bytes:
        b = bytearray(data)
        b[b.index(b"}")] = ord(" ")
        return bytes(b)

    with zipfile.ZipFile(path) as z:
        members = {name: z.read(name) for name in z.namelist()}
    with zipfile.ZipFile(path, "w") as z:
        for name, data in members.items():
            z.writestr(name, unclosed(data))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A smoke preset's dataset, synthesised once per test module."""
    from warp_vision.data.foveation import synthesize
    from warp_vision.train.config import resolve

    d = tmp_path_factory.mktemp("data")
    synthesize(d, resolve("smoke", {"data_dir": str(d)}).data_config(), progress=False, log=lambda *a: None)
    return d


@pytest.fixture(scope="module")
def finished(tmp_path_factory, data):
    """A finished smoke run (3 epochs, the left eye) on :func:`data`, copied by each test that damages it."""
    from warp_vision.train import foveation
    from warp_vision.train.config import resolve

    out = tmp_path_factory.mktemp("finished") / "run"
    foveation.run(resolve("smoke", {"out": str(out), "data_dir": str(data)}), progress=False, log=lambda *a: None)
    return out


@pytest.fixture
def unclose_npz_headers():
    """A function that damages an ``.npz`` archive's headers the way numpy's tokenizer, not its parser, rejects."""
    return _unclose_npz_headers
