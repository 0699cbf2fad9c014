"""Frames, angles and orderings shared by every stage (see docs/ARCHITECTURE.md, "Frames and units").

Conventions:

- **Eye frame**: +z along the optical axis (forward), +y up, +x = +y cross +z. A gaze (yaw, pitch) in
  radians is the direction ``(sin(yaw) cos(pitch), sin(pitch), cos(yaw) cos(pitch))``: yaw turns +z toward
  +x, pitch lifts it toward +y (Fick angles: yaw about +y first, then pitch about the turned -x, so no
  torsion by construction).
- **Camera frame** (third-person renders only): -z forward, +y up (the graphics convention).
- **World**: metres, +z up. A pose is a [4, 4] world-from-local rigid transform (rotation columns = the
  local axes in world coordinates, last column the origin), or a batch of them [B, 4, 4].

Every function here takes numpy arrays; the gaze conversions also take torch tensors (and return the same
kind). Nothing here imports another part of the package.
"""

from __future__ import annotations

import sys

import numpy as np


def _is_tensor(x) -> bool:
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


# --------------------------------------------------------------------------------------------------
# gaze angles <-> directions


def gaze_direction(yaw, pitch):
    """The unit direction [..., 3] of gaze angles ``yaw``, ``pitch`` (radians, eye frame); numpy arrays
    (float64) or torch tensors (their dtype). The inverse of :func:`gaze_angles`."""
    if _is_tensor(yaw):
        import torch

        return torch.stack([torch.cos(pitch) * torch.sin(yaw), torch.sin(pitch), torch.cos(pitch) * torch.cos(yaw)],
                           dim=-1)
    yaw, pitch = np.asarray(yaw, float), np.asarray(pitch, float)
    return np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)], -1)


def gaze_directions(yaw_pitch):
    """[..., 2] (yaw, pitch) radians -> unit directions [..., 3] (numpy or torch, as given)."""
    return gaze_direction(yaw_pitch[..., 0], yaw_pitch[..., 1])


def gaze_angles(direction):
    """(yaw, pitch) radians [..., 2] of directions [..., 3] in the eye frame (need not be unit length);
    numpy arrays (float64) or torch tensors. The inverse of :func:`gaze_direction`."""
    if _is_tensor(direction):
        import torch

        d = direction
        return torch.stack([torch.atan2(d[..., 0], d[..., 2]),
                            torch.atan2(d[..., 1], torch.hypot(d[..., 0], d[..., 2]))], -1)
    d = np.asarray(direction, float)
    return np.stack([np.arctan2(d[..., 0], d[..., 2]), np.arctan2(d[..., 1], np.hypot(d[..., 0], d[..., 2]))], -1)


def fick_rotation(yaw: float, pitch: float) -> np.ndarray:
    """The [3, 3] rotation turning +z to gaze (yaw, pitch): about +y by yaw, then about the turned -x by
    pitch (a Fick gimbal: no torsion by construction)."""
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, sp], [0, -sp, cp]])  # +z -> (0, sin p, cos p)
    return Ry @ Rx


def torsion_angle(R, yaw: float, pitch: float) -> float:
    """The rotation about the line of sight (rad, + about +z) that takes Fick's (yaw, pitch) to ``R``."""
    Rt = fick_rotation(yaw, pitch).T @ np.asarray(R, float)
    return float(np.arctan2(Rt[1, 0], Rt[0, 0]))


# --------------------------------------------------------------------------------------------------
# rigid transforms


def look_rotation(forward, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """The [3, 3] world-from-eye rotation whose +z is ``forward`` and whose +y is as close to ``up`` as
    possible (+x = +y cross +z); ``forward`` must not be parallel to ``up``."""
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross(np.asarray(up, dtype=np.float64), z)
    n = np.linalg.norm(x)
    if not n > 1e-12:
        raise ValueError("look_rotation: forward is parallel to up")
    x /= n
    return np.stack([x, np.cross(z, x), z], axis=1)


def translation(xyz) -> np.ndarray:
    """A [4, 4] (or [B, 4, 4] for xyz [B, 3]) pure translation."""
    xyz = np.asarray(xyz, dtype=np.float64)
    T = np.broadcast_to(np.eye(4), xyz.shape[:-1] + (4, 4)).copy()
    T[..., :3, 3] = xyz
    return T


def look_at(eye_position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A [4, 4] world-from-camera transform at ``eye_position`` looking at ``target`` (camera frame: -z
    forward). For the eye frame (+z forward) use :func:`eye_look_at`."""
    p = np.asarray(eye_position, float)
    f = np.asarray(target, float) - p
    f /= np.linalg.norm(f)
    x = np.cross(f, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(f, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(x, f)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, -f, p
    return T


def eye_look_at(eye_centre, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A [4, 4] world-from-eye transform: eye centre at ``eye_centre`` (m), optical axis (+z) at ``target``."""
    T = look_at(eye_centre, target, up)
    T[:3, 0] *= -1.0  # +x = y cross z with z forward
    T[:3, 2] *= -1.0
    return T


# --------------------------------------------------------------------------------------------------
# orderings of points on the retina

_MORTON_BITS = 31


def line_crossing(o1, u1, o2, u2, parallel: float = 1e-12) -> tuple[float, float] | None:
    """(s1, s2): the parameters of the closest points ``o1 + s1 u1`` and ``o2 + s2 u2`` of two lines with
    unit directions ``u1``, ``u2`` (where two gaze lines cross, or nearly); None when they are parallel
    (1 - (u1 . u2)^2 below ``parallel``)."""
    o1, u1, o2, u2 = (np.asarray(x, float) for x in (o1, u1, o2, u2))
    w = o1 - o2
    b = float(u1 @ u2)
    den = 1.0 - b * b
    if den < parallel:
        return None
    return float((b * (u2 @ w) - (u1 @ w)) / den), float(((u2 @ w) - b * (u1 @ w)) / den)


def _spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert a zero bit above each of the low 32 bits of uint64 ``v`` (bit i moves to bit 2i)."""
    v = v & np.uint64(0x00000000FFFFFFFF)
    v = (v | (v << np.uint64(16))) & np.uint64(0x0000FFFF0000FFFF)
    v = (v | (v << np.uint64(8))) & np.uint64(0x00FF00FF00FF00FF)
    v = (v | (v << np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    v = (v | (v << np.uint64(2))) & np.uint64(0x3333333333333333)
    v = (v | (v << np.uint64(1))) & np.uint64(0x5555555555555555)
    return v


def check_positions(name: str, positions) -> np.ndarray:
    """Validate [N, 2] finite real positions (N >= 1); returns them as a float64 array, or raises a
    ``ValueError`` that names ``name``."""
    if hasattr(positions, "domain_xy"):  # a Retina: say which of its positions to pass, not its shape
        raise ValueError(f"{name}: expected positions [N, 2], got a {type(positions).__name__}: pass retina.domain_xy "
                         f"(its photoreceptors' positions) or onv_positions(retina.domain_xy) (its ONV's, three per "
                         f"photoreceptor)")
    arr = np.asarray(positions)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 1:
        raise ValueError(f"{name}: expected shape [N, 2] with N >= 1, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{name}: expected real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: expected finite values, got {int((~np.isfinite(arr)).sum())} NaN/inf entries")
    return arr


def morton_order(positions: np.ndarray) -> np.ndarray:
    """The permutation that sorts points along a Morton (Z-order) curve.

    Positions are quantised to a square grid of 2^31 cells per side over their bounding box; ties
    (points in one cell) keep their input order.

    Args:
        positions: [N, 2] finite positions.

    Returns:
        [N] int64 permutation: ``positions[order]`` is in Z-order.
    """
    pos = check_positions("positions", positions)
    lo = pos.min(axis=0)
    span = float((pos.max(axis=0) - lo).max())
    top = float(2**_MORTON_BITS - 1)
    scale = top / span if span > 0 else 0.0
    q = np.clip(np.floor((pos - lo) * scale), 0.0, top).astype(np.uint64)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1))
    return np.argsort(code, kind="stable").astype(np.int64)
