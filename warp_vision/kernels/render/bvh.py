"""A bounding-volume hierarchy built on the host (numpy, binned SAH) for packet traversal in Warp.

Layout (flat arrays, one BVH or many concatenated with offsets):
- nodes: ``node_lo``/``node_hi`` [n_nodes] float32 boxes; ``node_left`` [n_nodes]: for an inner node the
  index of its left child (the right child is ``left + 1``), for a leaf ``-1``; ``node_start`` /
  ``node_count``: the leaf's triangles ``[start, start + count)``; ``node_axis``: an inner node's split
  axis (the left child holds the smaller coordinates), which orders the traversal.
- triangles in leaf order, precomputed for Moller-Trumbore: ``tri_v0``, ``tri_e1 = v1 - v0``,
  ``tri_e2 = v2 - v0`` [n_tris, 3] and ``tri_face`` [n_tris], the original face index.

Why not ``wp.Mesh``'s own BVH: its queries are one ray at a time, and the ray tracer's rays come in
coherent packets (a photoreceptor's rays through the pupil), and traversing a packet of 8 rays per
node visit with vector arithmetic shares each node's loads among them (``python -m warp_vision.bench
raytrace`` compares the two). The layout is plain arrays, so the same kernels run on CUDA.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Leaves hold at most this many triangles. Nodes over 16 triangles split by binned SAH, smaller
#: ones at the centroid median of their widest axis.
MAX_LEAF = 4
#: SAH bins per axis
BINS = 16
#: Meshes with at least this many triangles keep their BVH on disk (:func:`build_bvh_cached`): building
#: one of myo-sim's hands (114k triangles) takes seconds, loading it milliseconds.
DISK_CACHE_MIN_TRIANGLES = 20_000
#: Bump when build_bvh's output changes for the same mesh (cached BVHs are keyed by it).
BVH_FORMAT = 1


@dataclass
class BVH:
    node_lo: np.ndarray  # [n_nodes, 3] float32
    node_hi: np.ndarray
    node_left: np.ndarray  # [n_nodes] int32, -1 for leaves
    node_start: np.ndarray  # [n_nodes] int32
    node_count: np.ndarray  # [n_nodes] int32
    node_axis: np.ndarray  # [n_nodes] int32
    tri_v0: np.ndarray  # [n_tris, 3] float32
    tri_e1: np.ndarray
    tri_e2: np.ndarray
    tri_face: np.ndarray  # [n_tris] int32

    @property
    def num_nodes(self) -> int:
        return len(self.node_left)

    def depth(self) -> int:
        d = np.zeros(self.num_nodes, dtype=np.int64)
        for i in range(self.num_nodes):  # children come after parents
            if self.node_left[i] >= 0:
                d[self.node_left[i]] = d[self.node_left[i] + 1] = d[i] + 1
        return int(d.max()) + 1


def _area(lo, hi):
    e = np.maximum(hi - lo, 0.0)
    return 2.0 * (e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0])


def _check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise ValueError(f"faces: expected a non-empty [F, 3] array, got shape {F.shape}")
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError("faces: vertex index out of range")
    return V, F


def _sah_axis_cost(b: np.ndarray, tlo: np.ndarray, thi: np.ndarray) -> np.ndarray:
    """SAH cost of splitting after each of the first BINS - 1 bins, for triangles (boxes tlo, thi) in
    bins ``b`` along one axis (inf where a side would be empty)."""
    m = len(b)
    cnt = np.bincount(b, minlength=BINS)
    srt = np.argsort(b, kind="stable")
    bs = b[srt]
    starts = np.searchsorted(bs, np.arange(BINS))
    nonempty = cnt > 0
    blo_b = np.full((BINS, 3), np.inf)
    bhi_b = np.full((BINS, 3), -np.inf)
    red_lo = np.minimum.reduceat(tlo[srt], starts[nonempty], axis=0)
    red_hi = np.maximum.reduceat(thi[srt], starts[nonempty], axis=0)
    blo_b[nonempty], bhi_b[nonempty] = red_lo, red_hi
    llo = np.minimum.accumulate(blo_b, axis=0)[:-1]
    lhi = np.maximum.accumulate(bhi_b, axis=0)[:-1]
    rlo = np.minimum.accumulate(blo_b[::-1], axis=0)[::-1][1:]
    rhi = np.maximum.accumulate(bhi_b[::-1], axis=0)[::-1][1:]
    nl = np.cumsum(cnt)[:-1]
    nr = m - nl
    with np.errstate(invalid="ignore"):
        return np.where((nl > 0) & (nr > 0), _area(llo, lhi) * nl + _area(rlo, rhi) * nr, np.inf)


def _sah_split(cen: np.ndarray, tlo: np.ndarray, thi: np.ndarray, clo: np.ndarray, ext: np.ndarray):
    """The cheapest binned-SAH split of a node's triangles (centroids ``cen``, boxes tlo/thi):
    (axis, mask of the left child's triangles), or (-1, None) if no split separates them."""
    best, split_axis, split_mask = np.inf, -1, None
    for ax in range(3):
        if ext[ax] <= 0:
            continue
        b = np.minimum(((cen[:, ax] - clo[ax]) / ext[ax] * BINS).astype(np.int64), BINS - 1)
        cost = _sah_axis_cost(b, tlo, thi)
        k = int(np.argmin(cost))
        if cost[k] < best:
            best, split_axis, split_mask = cost[k], ax, b <= k
    return split_axis, split_mask


def _median_split(cen: np.ndarray, ext: np.ndarray, blo: np.ndarray, bhi: np.ndarray):
    """Split at the centroid median along the widest centroid extent (or, if the centroids coincide,
    the node box's widest axis): (axis, mask of the left child's triangles)."""
    m = len(cen)
    split_axis = int(np.argmax(ext)) if ext.max() > 0 else int(np.argmax(bhi - blo))
    srt = np.argsort(cen[:, split_axis], kind="stable")
    split_mask = np.zeros(m, dtype=bool)
    split_mask[srt[: m // 2]] = True
    return split_axis, split_mask


def _choose_split(cen: np.ndarray, tlo: np.ndarray, thi: np.ndarray, blo: np.ndarray, bhi: np.ndarray):
    """How to split a node of m >= 2 triangles: binned SAH over 16 triangles, else (or when SAH finds
    no split) a leaf up to MAX_LEAF triangles, else a median split. (axis, left mask), or (-1, None)
    for a leaf."""
    m = len(cen)
    clo, chi = cen.min(axis=0), cen.max(axis=0)
    ext = chi - clo
    split_axis, split_mask = -1, None
    if m > 16:
        split_axis, split_mask = _sah_split(cen, tlo, thi, clo, ext)
    if split_axis < 0:
        if m <= MAX_LEAF:
            return -1, None
        split_axis, split_mask = _median_split(cen, ext, blo, bhi)
    return split_axis, split_mask


def _build_nodes(tlo: np.ndarray, thi: np.ndarray, cen: np.ndarray):
    """The node arrays (lo, hi, left, start, count, axis; the first ``used`` entries are the tree) and
    the triangles' leaf order, built top-down from the root (children come after their parent)."""
    n = len(cen)
    cap = 2 * n
    lo = np.zeros((cap, 3))
    hi = np.zeros((cap, 3))
    left = np.full(cap, -1, dtype=np.int32)
    start = np.zeros(cap, dtype=np.int32)
    count = np.zeros(cap, dtype=np.int32)
    axis_arr = np.zeros(cap, dtype=np.int32)
    order = np.arange(n)
    used = 1
    stack = [(0, 0, n)]
    while stack:
        ni, s, e = stack.pop()
        idx = order[s:e]
        blo, bhi = tlo[idx].min(axis=0), thi[idx].max(axis=0)
        lo[ni], hi[ni] = blo, bhi
        m = e - s
        split_axis, split_mask = (-1, None) if m <= 1 else _choose_split(cen[idx], tlo[idx], thi[idx], blo, bhi)
        if split_axis < 0:
            start[ni], count[ni] = s, m
            continue
        order[s:e] = np.concatenate([idx[split_mask], idx[~split_mask]])
        mid = s + int(split_mask.sum())
        li = used
        used += 2
        left[ni] = li
        axis_arr[ni] = split_axis
        stack.append((li + 1, mid, e))
        stack.append((li, s, mid))
    return (lo[:used], hi[:used], left[:used].copy(), start[:used].copy(), count[:used].copy(),
            axis_arr[:used].copy()), order


def build_bvh(vertices: np.ndarray, faces: np.ndarray) -> BVH:
    """Binned-SAH BVH over triangles ``vertices[faces]`` (vertices [V, 3], faces [F, 3])."""
    V, F = _check_mesh(vertices, faces)
    tri = V[F]
    tlo, thi = tri.min(axis=1), tri.max(axis=1)
    cen = 0.5 * (tlo + thi)
    (lo, hi, left, start, count, axis_arr), order = _build_nodes(tlo, thi, cen)
    tri_o = tri[order]
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    return BVH(
        f32(lo),
        f32(hi),
        left,
        start,
        count,
        axis_arr,
        f32(tri_o[:, 0]),
        f32(tri_o[:, 1] - tri_o[:, 0]),
        f32(tri_o[:, 2] - tri_o[:, 0]),
        np.ascontiguousarray(order, dtype=np.int32),
    )


def bvh_cache_dir() -> Path | None:
    """Where :func:`build_bvh_cached` keeps BVHs: ``$WARP_VISION_CACHE/bvh`` (``off`` turns the cache
    off), else ``$XDG_CACHE_HOME/warp_vision/bvh``, else ``~/.cache/warp_vision/bvh``."""
    root = os.environ.get("WARP_VISION_CACHE")
    if root is not None and root.strip().lower() == "off":
        return None
    if not root:
        root = os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"),
                            "warp_vision")
    return Path(root) / "bvh"


def _bvh_key(V: np.ndarray, F: np.ndarray) -> str:
    h = hashlib.sha256(f"bvh v{BVH_FORMAT} leaf{MAX_LEAF} bins{BINS} {V.dtype} {V.shape} {F.dtype} {F.shape}".encode())
    h.update(np.ascontiguousarray(V).tobytes())
    h.update(np.ascontiguousarray(F).tobytes())
    return h.hexdigest()


def build_bvh_cached(vertices: np.ndarray, faces: np.ndarray) -> BVH:
    """:func:`build_bvh`, kept on disk (:func:`bvh_cache_dir`, keyed by the mesh's bytes) for meshes of at
    least ``DISK_CACHE_MIN_TRIANGLES`` triangles. An unreadable or mismatched cache file is rebuilt and
    replaced; a cache directory that cannot be written is skipped."""
    from warp_vision.fileio import NPY_FORMAT_ERRORS, atomic_write

    V, F = _check_mesh(vertices, faces)
    root = bvh_cache_dir()
    if root is None or len(F) < DISK_CACHE_MIN_TRIANGLES:
        return build_bvh(V, F)
    path = root / f"{_bvh_key(V, F)}.npz"
    try:
        with np.load(path) as z:
            b = BVH(**{f.name: z[f.name] for f in dataclasses.fields(BVH)})
        if len(b.tri_face) == len(F) and len(b.node_lo) == len(b.node_left) > 0:
            return b
    except (OSError, KeyError, *NPY_FORMAT_ERRORS):
        pass
    b = build_bvh(V, F)
    try:
        atomic_write(path, lambda f: np.savez(f, **dataclasses.asdict(b)))
    except OSError:
        pass
    return b
