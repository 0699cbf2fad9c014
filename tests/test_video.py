"""warp_vision.sim.video: the retina raster, frame labels and layout, and the .mp4/.gif writer (CPU, seconds)."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from warp_vision.eye.retina import Retina
from warp_vision.sim.video import RetinaRaster, VideoWriter, compose_frame, label

SIZE = 120


@pytest.fixture(scope="module")
def retina() -> Retina:
    return Retina.log_polar(400, seed=1)


@pytest.fixture(scope="module")
def raster(retina) -> RetinaRaster:
    return RetinaRaster(retina, size=SIZE)


def _pixel_of(raster: RetinaRaster, x_deg: float, y_deg: float) -> tuple[int, int]:
    """(row, col) of the pixel holding retinal-domain point (x, y) [deg]: x to the right, y up (plot_onv's axes)."""
    r = raster.radius_deg
    col = int((x_deg + r) / (2 * r) * raster.size)
    row = int((r - y_deg) / (2 * r) * raster.size)
    return row, col


# --- RetinaRaster ---------------------------------------------------------------------------------


def test_one_hot_onv_lights_that_photoreceptor(retina, raster):
    xy = np.degrees(retina.domain_xy)
    spacing = np.degrees(retina.local_spacing_rad())
    px = 2 * raster.radius_deg / raster.size
    r = raster.radius_deg
    # photoreceptors whose cells span several pixels, off both axes (so a flip of x or y would show)
    ok = (spacing > 6 * px) & (np.abs(xy[:, 0]) > 0.15 * r) & (np.abs(xy[:, 1]) > 0.15 * r) \
        & (np.hypot(xy[:, 0], xy[:, 1]) < 0.9 * r)
    chosen = np.flatnonzero(ok)[:4]
    assert len(chosen) == 4
    rows, cols = np.mgrid[0:SIZE, 0:SIZE]
    centre_x = -r + (cols + 0.5) * px
    centre_y = r - (rows + 0.5) * px
    for p in chosen:
        onv = np.zeros(3 * retina.P, dtype=np.float32)
        onv[3 * p] = 2.0  # red channel only
        img = raster(onv)
        assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8
        bright = img[..., 0] > 0
        assert bright.sum() > 4
        assert not img[..., 1:].any()  # channel order: only red
        assert raster.mask[bright].all()
        assert bright[_pixel_of(raster, *xy[p])]  # the pixel under photoreceptor p is lit
        cx, cy = centre_x[bright].mean(), centre_y[bright].mean()
        assert math.hypot(cx - xy[p, 0], cy - xy[p, 1]) < spacing[p]
        # a photoreceptor at the mirrored place would be far away: the centroid tells x and y apart
        assert math.hypot(cx - xy[p, 0], cy + xy[p, 1]) > spacing[p]


def test_uniform_onv_lights_the_disc_and_leaves_the_corners_black(retina, raster):
    img = raster(np.full(3 * retina.P, 0.3))
    assert (img[raster.mask] == 255).all()
    assert not img[~raster.mask].any()
    for row, col in ((0, 0), (0, SIZE - 1), (SIZE - 1, 0), (SIZE - 1, SIZE - 1)):
        assert not img[row, col].any()
    assert not raster.mask[0, 0] and raster.mask[SIZE // 2, SIZE // 2]
    assert abs(raster.mask.mean() - math.pi / 4) < 0.02
    # an explicit white: 0.3 / 0.6 = 0.5 -> 0.5 ** (1 / 2.2) of full scale
    half = raster(np.full(3 * retina.P, 0.3), white=0.6)
    assert abs(int(half[SIZE // 2, SIZE // 2, 0]) - round(255 * 0.5 ** (1 / 2.2))) <= 1


def test_torch_and_low_precision_inputs(retina, raster):
    rng = np.random.default_rng(0)
    onv = rng.random(3 * retina.P)
    ref = raster(onv)
    assert np.array_equal(raster(torch.from_numpy(onv)), ref)
    for dtype in (torch.float16, torch.bfloat16):
        got = raster(torch.from_numpy(onv).to(dtype)).astype(int)
        assert np.abs(got - ref).max() <= 6


@pytest.mark.parametrize(
    "onv, white, match",
    [
        (np.zeros(3 * 400 - 1), None, "expected shape"),
        (np.zeros((400, 3)), None, "expected shape"),
        (np.r_[np.zeros(1199), np.nan], None, "finite"),
        (np.r_[np.zeros(1199), np.inf], None, "finite"),
        (np.ones(1200), 0.0, "white"),
        (np.ones(1200), float("nan"), "white"),
    ],
)
def test_raster_rejects_bad_inputs(raster, onv, white, match):
    with pytest.raises(ValueError, match=match):
        raster(onv, white=white)


def test_raster_rejects_bad_size(retina):
    for size in (0, 1, 2.5, True):
        with pytest.raises(ValueError, match="size"):
            RetinaRaster(retina, size=size)


# --- label and compose_frame ----------------------------------------------------------------------


def test_label_draws_white_text_on_a_copy():
    img = np.full((60, 200, 3), 128, dtype=np.uint8)
    out = label(img, "t = 1.000 s")
    assert (img == 128).all()  # the input is untouched
    assert out.shape == img.shape and out.dtype == np.uint8
    changed = (out != img).any(axis=2)
    assert changed[:25, :120].sum() > 50 and not changed[40:].any()
    assert (out[:25, :120] == 255).all(axis=2).sum() > 10  # white glyphs
    assert (out[:25, :120] == 0).all(axis=2).sum() > 10  # on a dark box
    with pytest.raises(ValueError):
        label(img.astype(np.float32), "x")


def _eyes(side: int):
    left = np.zeros((side, side, 3), np.uint8)
    left[..., 0] = 255
    right = np.zeros((side, side, 3), np.uint8)
    right[..., 2] = 255
    return left, right


def test_compose_frame_layout():
    tp = np.full((480, 640, 3), 90, np.uint8)
    left, right = _eyes(120)
    frame = compose_frame(tp, left, right, 0.42)
    assert frame.shape == (480, 640 + 240, 3) and frame.dtype == np.uint8
    assert frame.shape[0] % 2 == 0 and frame.shape[1] % 2 == 0
    assert (frame[400:, :600] == 90).all()  # the third-person view, away from the label
    assert tuple(frame[180, 760]) == (255, 0, 0)  # left retina: top right, scaled to 240 x 240
    assert tuple(frame[420, 760]) == (0, 0, 255)  # right retina below it
    assert tuple(frame[120, 879]) == (255, 0, 0) and tuple(frame[479, 879]) == (0, 0, 255)
    # odd sizes are padded with black to even ones
    odd = compose_frame(np.full((101, 151, 3), 90, np.uint8), left, right, 0.0)
    assert odd.shape == (102, 202, 3)
    assert not odd[101].any() and not odd[:, 201].any()
    assert (odd[80:101, :151] == 90).all()


def test_compose_frame_time_label_and_captions():
    tp = np.full((480, 640, 3), 90, np.uint8)
    left, right = _eyes(240)
    a = compose_frame(tp, left, right, 0.42)
    b = compose_frame(tp, left, right, 1.5)
    diff = (a != b).any(axis=2)
    assert diff[:40, :200].sum() > 20  # "t = 0.420 s" vs "t = 1.500 s"
    assert not diff[40:].any() and not diff[:, 200:].any()
    plain = compose_frame(tp, left, right, 0.42, captions=("", ""))
    cap = (a != plain).any(axis=2)
    assert cap[:30, 640:].sum() > 20 and cap[240:270, 640:].sum() > 20
    assert not cap[:, :640].any()
    with pytest.raises(ValueError, match="time_s"):
        compose_frame(tp, left, right, float("nan"))
    with pytest.raises(ValueError, match="square"):
        compose_frame(tp, left[:, :100], right, 0.0)


# --- VideoWriter ----------------------------------------------------------------------------------

COLOURS = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 0), (128, 128, 128)]


def _frames(h: int = 48, w: int = 64) -> list[np.ndarray]:
    return [np.broadcast_to(np.array(c, np.uint8), (h, w, 3)).copy() for c in COLOURS]


def _close_colour(got: np.ndarray, want, tol: int = 40) -> bool:
    return bool(np.abs(got.reshape(-1, 3).mean(axis=0) - np.array(want)).max() < tol)


def test_mp4_round_trip(tmp_path):
    imageio = pytest.importorskip("imageio.v2")
    path = tmp_path / "out" / "clip.mp4"
    with VideoWriter(path, fps=10) as video:
        for f in _frames():
            video.append(f)
            # while it is written, the video sits under a hidden temporary name beside the final one
            assert not path.exists()
            assert all(p.name.startswith(".clip.mp4.tmp-") for p in path.parent.iterdir())
    assert video.frames == 5
    assert sorted(p.name for p in path.parent.iterdir()) == ["clip.mp4"]  # renamed, no temporary left
    reader = imageio.get_reader(path)
    try:
        meta = reader.get_meta_data()
        frames = [np.asarray(f) for f in reader]
    finally:
        reader.close()
    assert meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert abs(meta["fps"] - 10) < 1e-6
    assert len(frames) == 5
    for got, want in zip(frames, COLOURS):
        assert got.shape == (48, 64, 3)
        assert _close_colour(got, want), (got.reshape(-1, 3).mean(axis=0), want)


def test_gif_round_trip(tmp_path):
    path = tmp_path / "clip.GIF"
    with VideoWriter(path, fps=10) as video:
        for f in _frames():
            video.append(f)
    assert video.frames == 5
    assert [p.name for p in tmp_path.iterdir()] == ["clip.GIF"]
    with Image.open(path) as im:
        assert im.format == "GIF" and im.n_frames == 5 and im.info.get("loop") == 0
        for i, want in enumerate(COLOURS):
            im.seek(i)
            assert im.info["duration"] == 100
            rgb = np.asarray(im.convert("RGB"))
            assert rgb.shape == (48, 64, 3)
            assert _close_colour(rgb, want)


def test_writer_rejects_bad_paths_and_frames(tmp_path):
    for name in ("clip.avi", "clip", "clip.mp4.part"):
        with pytest.raises(ValueError, match=r"\.mp4 or \.gif"):
            VideoWriter(tmp_path / name, fps=10)
    for fps in (0, -1, float("inf"), True):
        with pytest.raises(ValueError, match="fps"):
            VideoWriter(tmp_path / "a.gif", fps=fps)
    for suffix in (".mp4", ".gif"):
        path = tmp_path / f"mismatch{suffix}"
        with pytest.raises(ValueError, match="same|every frame"):
            with VideoWriter(path, fps=5) as video:
                video.append(_frames(48, 64)[0])
                video.append(_frames(48, 66)[0])
        assert not path.exists()
    with pytest.raises(ValueError, match="even"):
        with VideoWriter(tmp_path / "odd.mp4", fps=5) as video:
            video.append(_frames(47, 64)[0])
    with pytest.raises(ValueError, match="uint8"):
        with VideoWriter(tmp_path / "float.gif", fps=5) as video:
            video.append(_frames()[0].astype(np.float32))
    with pytest.raises(ValueError, match="no frames"):
        VideoWriter(tmp_path / "empty.gif", fps=5).close()
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporaries left


def test_crash_leaves_no_video(tmp_path):
    path = tmp_path / "crash.mp4"
    with pytest.raises(KeyboardInterrupt):
        with VideoWriter(path, fps=5) as video:
            video.append(_frames()[0])
            raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_mp4_without_imageio_ffmpeg_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # makes `import imageio_ffmpeg` fail
    with pytest.raises(RuntimeError, match="imageio-ffmpeg"):
        VideoWriter(tmp_path / "a.mp4", fps=5)
    VideoWriter(tmp_path / "a.gif", fps=5)  # a .gif does not need it
