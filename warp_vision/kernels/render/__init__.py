"""The ONV renderer: ray tracing through the eye's optics into a scene, in Warp.

Stages, one module each:

- :mod:`~warp_vision.kernels.render.eye_rays`: the rays each photoreceptor casts through the pupil,
  lens and cornea (eye frame, cached per retina and eye state);
- :mod:`~warp_vision.kernels.render.bvh`: SAH bounding-volume hierarchies, built on the host;
- :mod:`~warp_vision.kernels.render.packet`: 8-ray packet traversal of those BVHs (closest hit, any hit);
- :mod:`~warp_vision.kernels.render.shade`: the device side of shading (Phong, shadows, mirrors) and
  the render kernels;
- :mod:`~warp_vision.kernels.render.scene_data`: a :class:`warp_vision.scene.Scene` packed for the kernels;
- :mod:`~warp_vision.kernels.render.trace`: the entry points (``render_onv``, ``render_camera``,
  ``radiance``, ``closest_hit``);
- :mod:`~warp_vision.kernels.render.reference`: the brute-force float64 numpy reference of all of it.

The public API is re-exported here. Poses: :func:`warp_vision.frames.eye_look_at` (eye frame) and
:func:`warp_vision.frames.look_at` (camera frame).
"""

from warp_vision.kernels.render.eye_rays import EyeRays, clear_eye_ray_cache, eye_rays, pupil_samples, surface_table
from warp_vision.kernels.render.scene_data import scene_data
from warp_vision.kernels.render.shade import RAY_EPSILON_M, SceneData
from warp_vision.kernels.render.trace import TRACE_SPLIT, closest_hit, radiance, render_camera, render_onv

__all__ = [
    "RAY_EPSILON_M",
    "TRACE_SPLIT",
    "EyeRays",
    "SceneData",
    "clear_eye_ray_cache",
    "closest_hit",
    "eye_rays",
    "pupil_samples",
    "radiance",
    "render_camera",
    "render_onv",
    "scene_data",
    "surface_table",
]
