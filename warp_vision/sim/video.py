"""Frames of the closed-loop videos (``python -m warp_vision.sim demo``), and the file that holds them.

Each frame shows the third-person view of the scene beside both eyes' retina images (the ONVs, drawn as
:func:`warp_vision.viz.plot_onv` draws them, but rasterised without matplotlib so a long video stays
cheap), with the simulated time written on it:

    +---------------------------+--------+
    | t = 0.420 s               | left   |
    |                           | retina |
    |   third-person view       +--------+
    |   (H x W)                 | right  |
    |                           | retina |
    +---------------------------+--------+
                                 H/2 wide

* :class:`RetinaRaster` turns one eye's ONV [3P] into a uint8 square image of its retina;
* :func:`label` writes a caption onto an image;
* :func:`compose_frame` lays out one video frame (even width and height, as H.264 in yuv420p needs);
* :class:`VideoWriter` appends frames to an .mp4 (H.264, yuv420p, through imageio's ffmpeg plugin and the
  ffmpeg binary that the imageio-ffmpeg package ships) or a .gif (PIL), written under a temporary name and
  renamed onto the final one at close, so a crash never leaves half a video under that name.
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from warp_vision.fileio import fsync_dir, temporary_path
from warp_vision.viz import tone_map

__all__ = ["RetinaRaster", "label", "compose_frame", "VideoWriter", "check_rgb_u8", "resize_square", "project",
           "draw_gaze"]


def check_rgb_u8(name: str, img: Any) -> np.ndarray:
    """``img`` as a uint8 [H, W, 3] ndarray with H, W >= 1, else ValueError naming ``name``."""
    if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3 \
            or img.shape[0] < 1 or img.shape[1] < 1:
        got = f"dtype {img.dtype}, shape {img.shape}" if isinstance(img, np.ndarray) else type(img).__name__
        raise ValueError(f"{name}: expected a uint8 ndarray of shape [H, W, 3], got {got}")
    return img


class RetinaRaster:
    """One eye's ONV as a square RGB image of its retina, the picture :func:`warp_vision.viz.plot_onv` draws.

    The image covers the retinal domain's disc rho <= rho_max (``retina.domain_xy`` in degrees: x to the
    right, y up, as plot_onv's axes; the optical image is inverted, as on a real retina). Each pixel inside
    the disc takes the colour of its nearest photoreceptor (a Voronoi mosaic, looked up once with a k-d tree
    at construction); pixels outside it are black.

    Attributes:
        size:       the image's side [px].
        P:          the retina's photoreceptor count (an ONV holds 3 P values).
        radius_deg: the disc's radius, rho_max [deg]; the image spans [-radius_deg, radius_deg] in x and y.
        index:      [size, size] int64, the photoreceptor nearest to each pixel's centre.
        mask:       [size, size] bool, the pixels whose centre lies inside the disc.
    """

    def __init__(self, retina, size: int = 240) -> None:
        """Args:
            retina: a :class:`warp_vision.eye.retina.Retina`.
            size:   the image's side in pixels (an int >= 2).
        """
        from scipy.spatial import cKDTree

        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 2:
            raise ValueError(f"size: expected an int >= 2, got {size!r}")
        self.size = int(size)
        self.P = int(retina.P)
        xy = np.degrees(np.asarray(retina.domain_xy, dtype=np.float64))
        self.radius_deg = float(np.degrees(retina.rho_max))
        r = self.radius_deg
        centres = (np.arange(self.size) + 0.5) * (2.0 * r / self.size)
        px_x = -r + centres            # column j: x grows to the right
        px_y = r - centres             # row i: y grows upwards (row 0 is the top)
        gx, gy = np.meshgrid(px_x, px_y)  # [size, size], indexed [row, col]
        self.mask = gx**2 + gy**2 <= r * r
        _, nearest = cKDTree(xy).query(np.stack([gx.ravel(), gy.ravel()], axis=1))
        self.index = np.asarray(nearest, dtype=np.int64).reshape(self.size, self.size)

    def __call__(self, onv, white: float | None = None) -> np.ndarray:
        """The retina image of ``onv``.

        Args:
            onv:   [3P] linear irradiances (a numpy array or a torch tensor, any float dtype); element
                   3p + c is channel c (R, G, B) of photoreceptor p.
            white: the irradiance that maps to full brightness; default: the ONV's 99.5th percentile
                   (1 where that is not positive). Tone mapping is :func:`warp_vision.viz.tone_map`.

        Returns:
            uint8 [size, size, 3].

        Raises:
            ValueError: ``onv`` not of shape [3P], or holding NaN or inf; ``white`` not a positive finite number.
        """
        if hasattr(onv, "detach"):  # a torch tensor; bfloat16 has no numpy dtype, so widen first
            t = onv.detach().cpu()
            onv = (t.double() if t.is_floating_point() else t).numpy()
        v = np.asarray(onv)
        if v.ndim != 1 or v.shape[0] != 3 * self.P:
            raise ValueError(f"onv: expected shape [{3 * self.P}] (3 x P, P = {self.P}), got shape {v.shape}")
        v = v.astype(np.float64)
        if not np.isfinite(v).all():
            raise ValueError(f"onv: expected finite values, got {int((~np.isfinite(v)).sum())} NaN or inf")
        if white is None:
            white = float(np.percentile(v, 99.5))
            white = white if white > 0.0 else 1.0
        elif isinstance(white, bool) or not isinstance(white, (int, float, np.integer, np.floating)) \
                or not math.isfinite(white) or white <= 0.0:
            raise ValueError(f"white: expected a positive finite number or None, got {white!r}")
        colours = np.round(tone_map(v.reshape(self.P, 3), float(white)) * 255.0).astype(np.uint8)
        img = colours[self.index]
        img[~self.mask] = 0
        return img


@functools.lru_cache(maxsize=16)
def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    """DejaVu Sans (shipped with matplotlib) at ``size`` px, or PIL's default font where it cannot be loaded."""
    try:
        from matplotlib import font_manager

        return ImageFont.truetype(font_manager.findfont("DejaVu Sans"), size)
    except Exception:  # no matplotlib, no FreeType, an unreadable font file: any readable font will do
        try:
            return ImageFont.load_default(size=size)
        except TypeError:  # Pillow < 10.1 has one bitmap size only
            return ImageFont.load_default()


def label(img: np.ndarray, text: str, xy: tuple[int, int] = (6, 4)) -> np.ndarray:
    """A copy of ``img`` with ``text`` written at ``xy`` (its top-left corner, in pixels) in white on a dark box,
    readable on any background. The font size follows the image's height (1/20 of it, at least 10 px).

    Args:
        img:  uint8 [H, W, 3].
        text: the text (may hold newlines).
        xy:   (x, y) of the text's top-left corner [px].

    Returns:
        A new uint8 [H, W, 3] array; ``img`` is left as it was.
    """
    img = check_rgb_u8("img", img)
    if not isinstance(text, str):
        raise ValueError(f"text: expected a str, got {type(text).__name__}")
    out = Image.fromarray(img)  # copies
    if not text:
        return np.asarray(out).copy()
    font = _font(max(10, round(img.shape[0] / 20)))
    draw = ImageDraw.Draw(out)
    x, y = int(xy[0]), int(xy[1])
    left, top, right, bottom = draw.multiline_textbbox((x, y), text, font=font)
    pad = 2
    draw.rectangle((left - pad, top - pad, right + pad, bottom + pad), fill=(0, 0, 0))
    draw.multiline_text((x, y), text, font=font, fill=(255, 255, 255))
    return np.asarray(out).copy()


def resize_square(name: str, img: np.ndarray, side: int) -> np.ndarray:
    """``img`` (uint8 [s, s, 3]) resized to [side, side, 3] (PIL, Lanczos); unchanged if already that size."""
    img = check_rgb_u8(name, img)
    if img.shape[0] != img.shape[1]:
        raise ValueError(f"{name}: expected a square image [s, s, 3], got shape {img.shape}")
    if img.shape[0] == side:
        return img
    return np.asarray(Image.fromarray(img).resize((side, side), Image.LANCZOS))


def compose_frame(
    third_person: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    time_s: float,
    captions: tuple[str, str] = ("left retina", "right retina"),
) -> np.ndarray:
    """One video frame: the third-person view with the simulated time, the two retina images to its right.

    Layout (H, W: the third-person view's height and width; h = H // 2)::

        rows [0, H),  cols [0, W):      the third-person view, "t = 0.420 s" at its top-left
        rows [0, h),  cols [W, W + h):  ``left`` scaled to h x h, captioned ``captions[0]``
        rows [h, 2h), cols [W, W + h):  ``right`` scaled to h x h, captioned ``captions[1]``

    The frame is then padded with black at the bottom and right to an even height and width (H.264 in
    yuv420p needs both even): shape [H + H % 2, W + h + (W + h) % 2, 3].

    Args:
        third_person: uint8 [H, W, 3], H >= 2 (e.g. 480 x 640).
        left:         uint8 [s, s, 3] retina image (:class:`RetinaRaster`); any side s.
        right:        the same, the right eye's.
        time_s:       the simulated time [s] (finite).
        captions:     the texts on the left and right retina images ("" for none).

    Returns:
        uint8 [H', W', 3] with H' and W' even.
    """
    third_person = check_rgb_u8("third_person", third_person)
    H, W = third_person.shape[:2]
    if H < 2:
        raise ValueError(f"third_person: expected a height >= 2, got shape {third_person.shape}")
    if isinstance(time_s, bool) or not isinstance(time_s, (int, float, np.integer, np.floating)) \
            or not math.isfinite(time_s):
        raise ValueError(f"time_s: expected a finite number of seconds, got {time_s!r}")
    if len(captions) != 2 or not all(isinstance(c, str) for c in captions):
        raise ValueError(f"captions: expected two str, got {captions!r}")
    h = H // 2
    eyes = [resize_square(name, img, h) for name, img in (("left", left), ("right", right))]
    out_h, out_w = H + H % 2, W + h + (W + h) % 2
    frame = np.zeros((out_h, out_w, 3), dtype=np.uint8)
    frame[:H, :W] = label(third_person, f"t = {float(time_s):.3f} s")
    for k, (eye, caption) in enumerate(zip(eyes, captions)):
        frame[k * h:(k + 1) * h, W:W + h] = label(eye, caption, (4, 3)) if caption else eye
    return frame


class VideoWriter:
    """Frames to a video file: ``.mp4`` (H.264, yuv420p, through imageio's ffmpeg plugin) or ``.gif`` (PIL).

    Use as a context manager::

        with VideoWriter("demo.mp4", fps=30) as video:
            for ...:
                video.append(frame)   # uint8 [H, W, 3], every frame the same size

    The file is written under a hidden temporary name in ``path``'s directory and renamed onto ``path`` by
    :meth:`close`; leaving the ``with`` block by an exception removes it instead, so ``path`` only ever holds
    a whole video. An .mp4 needs an even width and height (see :func:`compose_frame`). A .gif holds every
    frame in memory until :meth:`close`, and PIL merges identical consecutive frames into one longer frame.

    Attributes:
        path:   the final file.
        fps:    frames per second.
        frames: how many frames were appended.
    """

    _SUFFIXES = (".mp4", ".gif")
    MP4_QUALITY = 7  # imageio's 1..10 scale; for libx264, 7 is CRF 15 (visually lossless for these frames)

    def __init__(self, path: str | os.PathLike, fps: float) -> None:
        """Args:
            path: the video file to write; its suffix (.mp4 or .gif, any case) picks the format.
                  Its directory is created if missing.
            fps:  frames per second (a positive finite number).

        Raises:
            ValueError: another suffix, a bad fps.
            RuntimeError: an .mp4 without the imageio and imageio-ffmpeg packages installed.
        """
        self.path = Path(path)
        self.suffix = self.path.suffix.lower()
        if self.suffix not in self._SUFFIXES:
            raise ValueError(f"path: expected a file ending in .mp4 or .gif, got {str(path)!r}")
        if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)) \
                or not math.isfinite(fps) or fps <= 0:
            raise ValueError(f"fps: expected a positive finite number, got {fps!r}")
        self.fps = float(fps)
        if self.suffix == ".mp4":
            try:
                import imageio.v2  # noqa: F401
                import imageio_ffmpeg  # noqa: F401
            except ImportError as exc:
                raise RuntimeError(
                    f"writing {self.path.name} needs the imageio and imageio-ffmpeg packages "
                    f"(pip install imageio imageio-ffmpeg): {exc}"
                ) from None
        self.frames = 0
        self._shape: tuple[int, ...] | None = None
        self._writer: Any = None  # the imageio writer of an .mp4
        self._gif: list[Image.Image] = []
        self._closed = False
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # keep the suffix last: ffmpeg picks the container from the name
        self._tmp = Path(str(temporary_path(self.path)) + self.suffix)

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self._discard()

    def append(self, frame: np.ndarray) -> None:
        """Add one frame: uint8 [H, W, 3], the size of the first frame (and, for an .mp4, H and W even).

        Raises:
            ValueError: a frame of another dtype, rank or size.
            RuntimeError: the writer is closed.
        """
        if self._closed:
            raise RuntimeError(f"{self.path}: the VideoWriter is closed")
        frame = check_rgb_u8("frame", frame)
        if self._shape is None:
            if self.suffix == ".mp4" and (frame.shape[0] % 2 or frame.shape[1] % 2):
                raise ValueError(
                    f"frame: an .mp4 (H.264, yuv420p) needs an even height and width, got shape {frame.shape}; "
                    "pad it (compose_frame does)"
                )
            self._shape = frame.shape
        elif frame.shape != self._shape:
            raise ValueError(f"frame: expected every frame of shape {self._shape}, got {frame.shape}")
        if self.suffix == ".mp4":
            if self._writer is None:
                import imageio.v2 as iio

                self._writer = iio.get_writer(
                    self._tmp, format="FFMPEG", mode="I", fps=self.fps, codec="libx264",
                    quality=self.MP4_QUALITY, pixelformat="yuv420p", macro_block_size=1,
                    output_params=["-movflags", "+faststart"],
                )
            try:
                self._writer.append_data(np.ascontiguousarray(frame))
            except BaseException:
                self._discard()
                raise
        else:
            self._gif.append(Image.fromarray(frame))
        self.frames += 1

    def close(self) -> None:
        """Finish the file and rename it onto ``path``; a no-op when already closed.

        Raises:
            ValueError: no frame was appended (nothing is written).
        """
        if self._closed:
            return
        if self.frames == 0:
            self._discard()
            raise ValueError(f"{self.path}: no frames were appended, so no video was written")
        try:
            if self._writer is not None:
                writer, self._writer = self._writer, None
                writer.close()
            else:
                first, *rest = self._gif
                first.save(self._tmp, format="GIF", save_all=True, append_images=rest,
                           duration=max(1, round(1000.0 / self.fps)), loop=0)
            os.replace(self._tmp, self.path)
            fsync_dir(self.path.parent)
        finally:
            self._discard()

    def _discard(self) -> None:
        """Stop without a video: close the encoder, drop the frames, remove the temporary file."""
        self._closed = True
        self._gif = []
        if self._writer is not None:
            writer, self._writer = self._writer, None
            try:
                writer.close()
            except Exception:
                pass
        if os.path.lexists(self._tmp):
            os.unlink(self._tmp)


def project(cam: np.ndarray, width: int, height: int, fov_deg: float, points) -> list:
    """Each world point of ``points`` [N, 3] (m) on the image of the camera ``cam`` ([4, 4] world from
    camera, looking along its -z, +y up; ``fov_deg`` the vertical field of view): (x, y) pixels, or None
    for a point behind the camera."""
    f = 0.5 * height / np.tan(np.radians(fov_deg) / 2)
    inv = np.linalg.inv(np.asarray(cam, float))
    out = []
    for p in np.asarray(points, float).reshape(-1, 3):
        q = inv[:3, :3] @ p + inv[:3, 3]
        out.append((width / 2 + f * q[0] / -q[2], height / 2 - f * q[1] / -q[2]) if q[2] < -1e-3 else None)
    return out


def draw_gaze(img: np.ndarray, body, cam: np.ndarray, w: int, h: int, fov_deg: float) -> np.ndarray:
    """Each eye of ``body`` its gaze line (1.5 m, red) drawn onto a tone-mapped image [h, w, 3] (floats in
    [0, 1]) of the camera ``cam`` (as :func:`project`); uint8 out."""
    im = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
    dr = ImageDraw.Draw(im)
    for s in ("left", "right"):
        T = body.eye_pose(s)
        a, b = project(cam, w, h, fov_deg, [T[:3, 3], T[:3, 3] + 1.5 * T[:3, 2]])
        if a and b:
            dr.line([a, b], fill=(230, 40, 40), width=2)
    return np.asarray(im)
