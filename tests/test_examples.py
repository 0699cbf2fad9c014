"""Every script of examples/ runs, on small sizes, into a temporary directory, and says what it should: each
writes its file and prints numbers that make sense (a rendered ONV that sees the ball, a liNet whose Warp
gradients equal the torch reference's, a foveator's estimates in the field, a loop whose eyes reach the ball)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def run(script: str, *args: str, cwd: Path, ok: bool = True) -> str:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, str(EXAMPLES / script), *args], cwd=cwd, capture_output=True, text=True,
                       timeout=600, env=env)
    if ok:
        assert r.returncode == 0, f"{script} failed:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"
    return r.stdout + r.stderr if not ok else r.stdout


def numbers(pattern: str, text: str) -> list[float]:
    m = re.search(pattern, text)
    assert m, f"no line matches {pattern!r} in:\n{text}"
    return [float(g) for g in m.groups()]


def test_every_example_is_tested_and_documented():
    """Each script here has a test below, a docstring that says how to run it, --device and --help."""
    scripts = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert scripts == ["body_loop.py", "foveator_own_scene.py", "linet_onv.py", "render_eye.py"]
    for name in scripts:
        text = (EXAMPLES / name).read_text()
        assert text.startswith('"""') and "Run:" in text and f"python examples/{name}" in text, name
        assert '"--device"' in text and len(text.splitlines()) <= 120, name


def test_render_eye_draws_the_onv(tmp_path):
    out = run("render_eye.py", "--photoreceptors", "1000", "--samples", "2", "--out", str(tmp_path / "o"), cwd=tmp_path)
    assert numbers(r"P = (\d+);", out.replace(",", "")) == [1000]
    assert "ONV: shape (1, 3000)" in out
    mean, peak, fovea = numbers(r"mean ([\d.]+), max ([\d.]+); at the fovea ([\d.]+)", out)
    assert 0 < mean < peak and fovea > mean  # the eye looks at the white ball: its fovea is brighter than the average
    onv = np.load(tmp_path / "o" / "onv.npy")
    assert onv.shape == (3000,) and np.isfinite(onv).all() and onv.min() >= 0
    assert (tmp_path / "o" / "render_eye.png").stat().st_size > 10_000


def test_linet_onv_trains_and_its_gradients_match_the_reference(tmp_path):
    out = run("linet_onv.py", "--photoreceptors", "400", "--batch", "16", "--steps", "5", cwd=tmp_path)
    assert "ONV x: (16, 1200)" in out
    widths = [int(w) for w in re.search(r"liNet widths \[([\d, ]+)\]", out).group(1).split(",")]
    assert widths == [1200, 300, 75, 18]  # N_h = floor(N_{h-1} / 4)
    first, last = (numbers(rf"step +{k}: loss ([\d.]+)", out)[0] for k in (0, 4))
    assert np.isfinite([first, last]).all() and last < first  # Adam on the ball's direction lowers the loss
    norms = re.search(r"step +0: .*per layer: (.*)", out).group(1).split(", ")
    assert len(norms) == 3 and all(float(n) > 0 for n in norms)  # gradients reach every layer
    for d in numbers(r"y ([\d.e+-]+), grad_x ([\d.e+-]+), grad_weight ([\d.e+-]+)$", out.strip()):
        assert d < 1e-5  # float32 sums in another order


def test_foveator_own_scene_says_how_to_make_a_run(tmp_path):
    out = run("foveator_own_scene.py", cwd=tmp_path, ok=False)
    assert "holds no finished foveation run" in out and "python -m warp_vision.train --preset smoke" in out


def test_foveator_own_scene_estimates_the_ball(tmp_path, finished):
    """The smoke run (3 epochs on 160 ONVs) is no good foveator, so the check is of sense, not accuracy."""
    out = run("foveator_own_scene.py", "--run", str(finished), "--views", "4", "--out", str(tmp_path / "o"),
              cwd=tmp_path)
    assert "a generator v7 net, P = 400" in out
    rows = re.findall(r"^ +(\d) +([+-][\d.]+) +([+-][\d.]+) +([+-][\d.]+) +([+-][\d.]+) +([\d.]+)$", out, flags=re.M)
    assert [int(r[0]) for r in rows] == [0, 1, 2, 3]
    values = np.array([[float(v) for v in r[1:]] for r in rows])
    assert np.allclose(values[0, :2], 0.0, atol=0.05)  # view 0 fixates the ball: it is straight ahead
    assert np.abs(values[1:, :2]).max() < 25.0 and np.abs(values[1:, :2]).max() > 1.0  # the others look away
    assert np.isfinite(values).all() and np.abs(values[:, 2:4]).max() < 90  # estimates: directions in the field
    saved = json.loads((tmp_path / "o" / "estimates.json").read_text())
    assert np.allclose(saved["error_deg"], values[:, 4], atol=0.01)


def test_body_loop_fixates_the_ball_and_follows_its_jump(tmp_path):
    out = run("body_loop.py", "--photoreceptors", "300", "--out", str(tmp_path / "o"), cwd=tmp_path)
    assert "100 control periods, 25 frames" in out
    rows = re.findall(r"^ +([\d.]+) +([\d.]+) +([\d.]+) +([+-][\d.]+)$", out, flags=re.M)
    t, left, right, _neck = np.array([[float(v) for v in r] for r in rows]).T
    assert np.allclose(t, np.arange(0.1, 1.01, 0.1), atol=1e-6)
    assert max(left[3], right[3]) < 1.0  # at 0.4 s both eyes are on the ball that appeared 15 deg off
    assert max(left[-1], right[-1]) < 1.0  # and again at 1 s, after its jump at 0.5 s
    tr = np.load(tmp_path / "o" / "trace.npz")
    assert tr["error_left"][0] > 10 and tr["error_left"][50] > 10  # it started off the fovea, and jumped off it
    assert (tmp_path / "o" / "gaze_error.png").stat().st_size > 10_000
