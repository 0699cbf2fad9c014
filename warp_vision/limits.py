"""Every size a user can set, bounded before anything is allocated: one place for the ranges the command lines
and the public constructors accept, and for the memory estimates of the sizes whose cost grows with them.

Two kinds of bound, both checked before any work:

- **ranges** (:data:`SEED`, :data:`PIXELS`, :data:`SUBDIVISIONS`, :data:`VIDEO_FPS`, ...): what a setting can
  mean at all. A seed must fit the 31-bit generators the package seeds (torch, numpy, MuJoCo, Warp) with room
  for the offsets it adds to them; a video's side must fit H.264; a frame rate must be one a player shows.
  :func:`integer` and :func:`number` are their argparse types (the parser names the option), and
  :func:`require_int` the same check for a value that arrives another way (a config field, an argument).
- **memory estimates** (:func:`camera_bytes`, :func:`icosphere_bytes`, :func:`video_bytes`): what a size
  costs, refused by :func:`warp_vision.resources.require_memory` with the estimate beside the memory available.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Range:
    """The closed range ``lo..hi`` a setting may take, and its unit in words (for the error)."""

    lo: float
    hi: float
    unit: str = ""

    def words(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        return f"{_fmt(self.lo)}..{_fmt(self.hi)}{unit}"


def _fmt(x: float) -> str:
    return f"{x:,}" if isinstance(x, int) else f"{x:g}"


#: a seed: 31 bits, so that the seeds derived from it (held-out offsets, per-sample seeds) stay in 64 bits
SEED = Range(0, 2**31 - 1)
#: a rendered view's width or height: H.264's largest frames are 8,192 pixels wide
PIXELS = Range(1, 8192, "pixels")
#: an icosphere's subdivisions: 20 * 4**10 = 21 million triangles at the top
SUBDIVISIONS = Range(0, 10)
#: a written video's frame rate (``--slow-motion`` and ``--video-every`` set it): a GIF's frame lasts at
#: least 1 ms, and a frame shown for more than 100 s is no video
VIDEO_FPS = Range(0.01, 1000.0, "frames a second")
#: a count of work items given on a command line (shots, trials, cards, repeats) at the most
COUNT = Range(1, 10**7)


def check(value, r: Range, name: str) -> None:
    """A ValueError ``"name: expected lo..hi unit, got value"`` unless ``r.lo <= value <= r.hi`` (and finite)."""
    ok = isinstance(value, (int, float)) and not isinstance(value,
                                                            bool) and math.isfinite(value) and r.lo <= value <= r.hi
    if not ok:
        raise ValueError(f"{name}: expected {r.words()}, got {value!r}")


def require_int(value, r: Range, name: str) -> int:
    """``value`` as an int in ``r`` (an integer-valued float is refused: a count or seed is typed as one)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name}: expected an integer {r.words()}, got {value!r}")
    check(value, r, name)
    return value


def _argument_type(r: Range, convert, read_as: str, kind: str, shown):
    """An argparse ``type``: the text read by ``convert`` (int or float; ``read_as`` in words) and within ``r``,
    finite; anything else is an ArgumentTypeError, the option's one-line error ("expected an integer 1..8,192
    pixels, got 100,000"). ``kind``: what a value out of range was expected to be; ``shown(text, value)``: it in
    the error."""

    def parse(text: str):
        try:
            v = convert(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {read_as} {r.words()}, got {text!r}") from None
        if not (math.isfinite(v) and r.lo <= v <= r.hi):
            raise argparse.ArgumentTypeError(f"expected {kind} {r.words()}, got {shown(text, v)}")
        return v

    parse.__name__ = convert.__name__
    return parse


def integer(r: Range):
    """An argparse ``type`` reading an integer in ``r``."""
    return _argument_type(r, int, "an integer", "an integer", lambda text, v: f"{v:,}")


def number(r: Range):
    """An argparse ``type`` reading a finite number in ``r``."""
    return _argument_type(r, float, "a number", "a finite number", lambda text, v: text)


def camera_bytes(width: int, height: int) -> int:
    """The memory of one ray-traced camera view of ``width`` x ``height`` pixels: the rays, the hits and the
    shaded float colours the renderer keeps per pixel, and the 8-bit frame made of them (about 32 bytes a pixel)."""
    return 32 * int(width) * int(height)


def video_frame_shape(width: int, height: int) -> tuple[int, int]:
    """(height, width) of a video frame composed of a ``width`` x ``height`` view and the two retinas beside
    it (:func:`warp_vision.sim.video.compose_frame`)."""
    h = height // 2
    return height + height % 2, width + h + (width + h) % 2


def video_bytes(width: int, height: int, frames: int, kept: bool) -> int:
    """The memory a video of ``frames`` frames costs: one frame being composed, or all of them where they are
    ``kept`` until the file is written (a GIF)."""
    fh, fw = video_frame_shape(width, height)
    return 3 * fh * fw * (max(int(frames), 1) if kept else 2) + camera_bytes(width, height)


def icosphere_bytes(subdivisions: int) -> int:
    """The memory of an icosphere of ``subdivisions`` (20 * 4**s triangles) in the scene: its vertices and
    faces as trimesh builds them, their normals, the renderer's copies and the BVH over it (about 400 bytes a
    triangle)."""
    return 400 * 20 * 4 ** int(subdivisions)
