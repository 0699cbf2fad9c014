"""Procedural textures on meshes: a pattern baked into the per-vertex colours of a finely tessellated
mesh. The renderer interpolates vertex colours across each triangle (``Material(vertex_colors=True)``), so
the finest detail is about two vertex spacings; no texture lookups are needed in the kernels.

:func:`textured_card` is a flat square card whose albedo is a seeded random pattern: a mix of 1/f noise
(natural images' spectrum), a checkerboard of random period and random bars, in proportions that vary
across the card, in grey with a slight tint.
Defocus needs contrast at every scale: these cards are the objects the lens nets learn to focus on.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the return annotation only; trimesh is imported where the card is built
    import trimesh

#: The albedo range of a card's pattern.
ALBEDO_RANGE = (0.08, 0.9)


def card_pattern(n: int, seed) -> np.ndarray:
    """[n, n, 3] albedo in ALBEDO_RANGE: a seeded mix of 1/f noise, a checkerboard and bars, in
    proportions that vary smoothly across the card."""
    rng = np.random.default_rng(seed)
    f = np.fft.fftfreq(n)
    k = np.hypot(*np.meshgrid(f, f, indexing="ij"))
    spec = (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))) / np.maximum(k, 1.0 / n)
    noise = np.fft.ifft2(spec).real
    noise = (noise - noise.mean()) / (noise.std() + 1e-12)
    u, v = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    period = rng.uniform(3, 16)
    checker = np.where((np.floor(u / period) + np.floor(v / period)) % 2 == 0, 1.0, -1.0)
    angle = rng.uniform(0, np.pi)
    bars = np.sign(np.sin((u * np.cos(angle) + v * np.sin(angle)) * 2 * np.pi / rng.uniform(3, 24)))
    # the mix varies across the card (weights from three smooth random fields), so each patch differs
    smooth = np.exp(-((k * n / 3.0) ** 2))
    fields = np.stack([np.fft.ifft2(np.fft.fft2(rng.normal(size=(n, n))) * smooth).real for _ in range(3)])
    w = np.exp(3.0 * fields / (fields.std() + 1e-12))
    w /= w.sum(axis=0)
    g = w[0] * noise / 2 + w[1] * checker + w[2] * bars
    g = (g - g.min()) / (g.max() - g.min() + 1e-12)
    lo, hi = ALBEDO_RANGE
    tint = 1.0 + rng.uniform(-0.1, 0.1, 3)
    return np.clip((lo + (hi - lo) * g)[..., None] * tint, 0.0, 1.0)


def textured_card(size_m: float, n: int, seed) -> trimesh.Trimesh:
    """A square card ``size_m`` across in the object's x-y plane, centred on the origin, facing +z, as an
    n x n grid of vertices coloured by :func:`card_pattern`."""
    import trimesh

    if not size_m > 0 or n < 2:
        raise ValueError(f"textured_card: expected size_m > 0 and n >= 2, got {size_m}, {n}")
    s = np.linspace(-size_m / 2, size_m / 2, n)
    x, y = np.meshgrid(s, s, indexing="ij")
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    i = np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + n, i.ravel() + n + 1, i.ravel() + 1
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if mesh.face_normals[0, 2] < 0:
        mesh.invert()
    rgb = (card_pattern(n, seed).reshape(-1, 3) * 255).round().astype(np.uint8)
    mesh.visual.vertex_colors = np.concatenate([rgb, np.full((n * n, 1), 255, np.uint8)], 1)
    return mesh
