"""The eye demo command and the figures it draws."""

import numpy as np
import pytest

from warp_vision import viz
from warp_vision.eye.optics import NavarroEye
from warp_vision.eye.retina import Retina
from warp_vision.scene.cli import main


def test_demo_writes_its_figures(tmp_path, capsys):
    assert main(["demo", "--photoreceptors", "400", "--samples", "2", "--out", str(tmp_path)]) == 0
    for name in ("onv.png", "camera.png", "eye_rays.png", "retina.png", "onv.npy"):
        assert (tmp_path / name).stat().st_size > 1000
    onv = np.load(tmp_path / "onv.npy")
    assert onv.shape == (1200,) and onv.max() > 0
    assert "ONV: P=400" in capsys.readouterr().out


def test_tone_map():
    x = np.array([[0.0, 0.5, 2.0]])
    y = viz.tone_map(x, white=1.0)
    assert y[0, 0] == 0 and y[0, 2] == 1.0 and y[0, 1] == pytest.approx(0.5 ** (1 / 2.2))


def test_plot_onv_checks_size():
    r = Retina.log_polar(100, seed=0)
    fig = viz.plot_onv(r, np.ones(300), mark=[(0.0, 0.0), (1.0, 1.0)])
    assert len(fig.axes) == 1
    with pytest.raises(ValueError, match="onv"):
        viz.plot_onv(r, np.ones(299))


def test_eye_ray_paths_end_where_trace_to_world_says():
    eye = NavarroEye(pupil_diameter_mm=3.0)
    q = np.array([[0.0, -6.0, 22.392]])
    q[0] = [0, 0, 12.00398] + 12.0 * (q[0] - [0, 0, 12.00398]) / np.linalg.norm(q[0] - [0, 0, 12.00398])
    pxy = np.array([[0.0, 1.0]])
    path = eye.trace_path(q, pxy, 543.0, world_length_mm=5.0)
    o, d, ok = eye.trace_to_world(q, pxy, 543.0)
    assert ok[0] and path.shape == (1, 7, 3)
    np.testing.assert_allclose(path[0, 5], o[0], atol=1e-9)
    np.testing.assert_allclose(path[0, 6], o[0] + 5.0 * d[0], atol=1e-9)
    np.testing.assert_allclose(path[0, 3, :2], pxy[0], atol=1e-8)  # through the stop point asked for
    assert len(viz.plot_eye_rays(eye, (0.0, 20.0), samples=3).axes) == 1


def test_demo_refuses_a_device_this_machine_lacks_in_one_line(tmp_path, capsys):
    # "cuda" on a machine without a GPU was Warp's traceback from inside the renderer
    for device, says in (("cuda:99", "CUDA device(s) on this machine"), ("gpu", "expected cpu, cuda or cuda:N")):
        assert main(["demo", "--photoreceptors", "100", "--samples", "1", "--device", device, "--out",
                     str(tmp_path / "d")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: --device:") and says in err and err.count("\n") == 1, err  # (the option typed)
    assert not list(tmp_path.iterdir())
