"""The ONV renderer's entry points, on the host: argument checks and the launches of the render kernels.

``render_onv`` takes the eye-frame rays of :mod:`warp_vision.kernels.render.eye_rays` (each
photoreceptor's 3 S rays through the pupil, one set per RGB channel), moves them into the world with
each batch element's eye pose, and traces them in packets of 8 through the scene that
:func:`~warp_vision.kernels.render.scene_data.scene_data` packs, shaded by
:func:`~warp_vision.kernels.render.shade.packet_radiance`. A pinhole camera (``render_camera``) shares
the tracing for third-person images, ``radiance`` traces arbitrary world rays, and ``closest_hit``
exposes bare closest-hit queries (tests, benchmarks). :mod:`warp_vision.kernels.render.reference` is
the numpy reference for all of it.

Shapes and units: eye poses are world-from-eye rigid transforms in metres (the eye frame of
docs/ARCHITECTURE.md; :func:`warp_vision.frames.eye_look_at` builds one). The ONV is ``[B, 3P]``
float32 and element ``3p + c`` is channel c of photoreceptor p, as linear irradiance.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp

from warp_vision.eye.optics import NavarroEye
from warp_vision.kernels import launch as _launch
from warp_vision.kernels.render.eye_rays import _check_samples, _retina_positions, eye_rays, eye_rays_bytes
from warp_vision.kernels.render.scene_data import scene_data, to_warp_transforms
from warp_vision.kernels.render.shade import (
    SceneData,
    camera_kernel,
    closest_hit_kernel,
    photoreceptors_per_thread,
    radiance_kernel,
    render_onv_kernel,
)
from warp_vision.resources import require_memory

#: CPU launch splitting for tracing kernels (``launch_split`` keywords): threads are heavy and unequal
#: (a ray that reaches the periphery of a BVH costs more than one that hits a wall), so hand out many
#: small slices.
TRACE_SPLIT = {"min_per_slice": 64, "chunks_per_thread": 16}


def _poses(name: str, T, B: int | None = None) -> np.ndarray:
    if isinstance(T, torch.Tensor):
        T = T.detach().cpu().numpy()
    T = np.asarray(T, dtype=np.float64)
    if T.shape == (4, 4):
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected [B, 4, 4] world-from-eye transforms, got shape {T.shape}")
    if B is not None and T.shape[0] != B:
        raise ValueError(f"{name}: expected batch {B}, got {T.shape[0]}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    if not len(T):
        return T
    if np.abs(T[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        raise ValueError(f"{name}: expected homogeneous transforms with bottom row [0, 0, 0, 1], got "
                         f"{T[np.abs(T[:, 3] - [0, 0, 0, 1]).max(axis=1).argmax(), 3].tolist()}")
    R = T[:, :3, :3]
    if np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max() > 1e-4 or np.any(np.linalg.det(R) < 0):
        raise ValueError(f"{name}: expected rigid transforms (orthonormal rotation, det +1)")
    return T


def _check_batch(scene, batch: int) -> None:
    Bs = scene.batch_size()
    if not 0 <= batch < Bs:
        raise ValueError(f"batch: expected 0 to {Bs - 1}, got {batch}")


def _world_rays(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    """Validated world rays: origins and directions as float32 [N, 3] arrays."""
    o = np.ascontiguousarray(origins, dtype=np.float32)
    d = np.ascontiguousarray(directions, dtype=np.float32)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins, directions: expected matching [N, 3], got {o.shape} and {d.shape}")
    return o, d


def render_onv(
    scene,
    retina,
    eye: NavarroEye,
    eye_poses,
    samples_per_receptor: int = 16,
    seed: int = 0,
    device: str = "cpu",
    max_depth: int = 2,
    packed=None,
) -> torch.Tensor:
    """Render the Optic Nerve Vector of B eye poses: a float32 tensor [B, 3P] (linear irradiance).

    scene: :class:`warp_vision.scene.Scene` (its per-batch transforms, visibility, lights, materials and
        ambient light must have batch B or 1).
    retina: a :class:`warp_vision.eye.retina.Retina` (or its positions_optical_mm [P, 3]).
    eye: the eye's optical state (accommodation, pupil).
    eye_poses: [B, 4, 4] world-from-eye rigid transforms (m).
    samples_per_receptor: S rays per photoreceptor and channel through stratified pupil points.
    seed: the pupil sampling's seed; max_depth: mirror bounces followed (>= 0).
    packed: ``scene_data(scene, device, max_depth)`` made for the scene as it is now, when several eyes
        render one state of it (packing its transforms and lights costs about 1.5 ms a call in the loop's
        scene); by default the scene is packed here.
    """
    T = _poses("eye_poses", eye_poses)
    B = T.shape[0]
    Bs = scene.batch_size()
    if Bs not in (1, B):
        raise ValueError(f"scene: its per-batch transforms/lights/materials/ambient have batch {Bs}, but eye_poses has "
                         f"{B}")
    P, S = len(_retina_positions(retina)), _check_samples(samples_per_receptor)
    require_memory(eye_rays_bytes(P, S) + B * 3 * P * 4,
                   f"render_onv (B={B}, P={P:,}, S={S:,})", "samples_per_receptor, the batch or P")
    rays = eye_rays(retina, eye, samples_per_receptor, seed, device)
    onv = torch.zeros((B, 3 * rays.P), dtype=torch.float32, device=device)
    if B == 0:
        return onv
    sc = scene_data(scene, device, max_depth) if packed is None else packed
    if getattr(sc, "_cls", None) is not SceneData:
        raise ValueError(f"packed: expected scene_data(scene, device, max_depth={max_depth}), got {type(sc).__name__}")
    if sc.max_depth != max_depth:
        raise ValueError(f"packed: expected scene_data(scene, device, max_depth={max_depth}), got "
                         f"max_depth={sc.max_depth}")
    G = photoreceptors_per_thread(rays.S)
    _launch.launch_split(
        render_onv_kernel,
        B * ((rays.P + G - 1) // G),
        inputs=[
            sc,
            wp.array(to_warp_transforms(T), dtype=wp.transform, device=device),
            rays.origins,
            rays.directions,
            rays.weights,
            rays.P,
            rays.S,
            G,
        ],
        outputs=[wp.from_torch(onv)],
        device=device,
        **TRACE_SPLIT,
    )
    return onv


def render_camera(
    scene,
    world_from_camera,
    width: int = 320,
    height: int = 240,
    fov_deg: float = 60.0,
    batch: int = 0,
    device: str = "cpu",
    max_depth: int = 2,
) -> torch.Tensor:
    """Third-person pinhole image [height, width, 3] (linear radiance) of batch element ``batch``.

    The camera looks along its -z axis with +y up; ``fov_deg`` is the vertical field of view.
    """
    if width < 1 or height < 1:
        raise ValueError(f"width, height: expected >= 1, got {width} x {height}")
    if not 0 < fov_deg < 180:
        raise ValueError(f"fov_deg: expected degrees in (0, 180), got {fov_deg}")
    require_memory(width * height * 12, f"render_camera ({width:,} x {height:,})", "width and height")
    T = _poses("world_from_camera", world_from_camera, 1)
    _check_batch(scene, batch)
    sc = scene_data(scene, device, max_depth)
    img = torch.zeros((height, width, 3), dtype=torch.float32, device=device)
    tf = to_warp_transforms(T)[0]
    _launch.launch_split(
        camera_kernel,
        ((width + 3) // 4) * ((height + 1) // 2),
        inputs=[sc, wp.transform(tf[:3], tf[3:]), width, height, math.tan(math.radians(fov_deg) / 2), batch],
        outputs=[wp.from_torch(img)],
        device=device,
        **TRACE_SPLIT,
    )
    return img


def closest_hit(scene, origins, directions, batch: int = 0, device: str = "cpu", threads: int | None = None):
    """Closest-hit queries for world rays [N, 3]: (t [N] m, inf on a miss; object [N]; face [N]), numpy."""
    o, d = _world_rays(origins, directions)
    sc = scene_data(scene, device, 0)
    n = len(o)
    t = wp.empty(n, dtype=wp.float32, device=device)
    obj = wp.empty(n, dtype=wp.int32, device=device)
    face = wp.empty(n, dtype=wp.int32, device=device)
    _launch.launch_split(
        closest_hit_kernel,
        (n + 7) // 8,
        inputs=[sc, wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device), batch],
        outputs=[t, obj, face],
        device=device,
        threads=threads,
        **TRACE_SPLIT,
    )
    return t.numpy(), obj.numpy(), face.numpy()


def radiance(scene, origins, directions, batch: int = 0, device: str = "cpu", max_depth: int = 2) -> torch.Tensor:
    """RGB radiance [N, 3] (float32) arriving along world rays origins/directions [N, 3] (m)."""
    o, d = _world_rays(origins, directions)
    _check_batch(scene, batch)
    sc = scene_data(scene, device, max_depth)
    out = torch.zeros((len(o), 3), dtype=torch.float32, device=device)
    _launch.launch_split(
        radiance_kernel,
        (len(o) + 7) // 8,
        inputs=[sc, wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device), batch],
        outputs=[wp.from_torch(out)],
        device=device,
        **TRACE_SPLIT,
    )
    return out
