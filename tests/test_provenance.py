"""What code produced a result: the package's version, its commit in a checkout, the libraries' versions."""

import shutil
import subprocess

import pytest

import warp_vision
from warp_vision import provenance


def test_software_names_the_package_python_and_each_library():
    info = provenance.software()
    assert info["warp_vision"] == warp_vision.__version__ != "0+unknown"
    assert info["torch"].startswith(__import__("torch").__version__.split("+")[0])
    assert set(provenance.LIBRARIES) <= set(info) and info["python"].count(".") == 2


@pytest.mark.skipif(shutil.which("git") is None, reason="no git")
def test_a_checkout_records_its_commit_and_whether_it_differs(monkeypatch):
    provenance.commit.cache_clear()
    top = provenance._git("rev-parse", "--show-toplevel")
    if top is None:
        pytest.skip("the package is not a git checkout here")
    head = subprocess.run(["git", "-C", top, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    assert provenance.commit()["commit"] == head and provenance.software()["commit"] == head
    # a repository that merely contains the package elsewhere (an installed copy in a project's venv) is not its
    monkeypatch.setattr(provenance, "PACKAGE_DIR", provenance.PACKAGE_DIR / "nn")  # in the checkout, not its package
    provenance.commit.cache_clear()
    assert provenance.commit() is None and "commit" not in provenance.software()
    provenance.commit.cache_clear()


def test_without_git_there_is_no_commit(monkeypatch):
    monkeypatch.setattr(provenance, "_git", lambda *a: None)
    provenance.commit.cache_clear()
    try:
        assert provenance.commit() is None and set(provenance.software()) == {"warp_vision", "python",
                                                                              *provenance.LIBRARIES}
    finally:
        provenance.commit.cache_clear()
