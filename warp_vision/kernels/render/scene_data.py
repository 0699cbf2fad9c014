"""The ONV renderer's scene upload, on the host: a :class:`warp_vision.scene.Scene` packed for the kernels.

A scene's geometry becomes *instances*: instance 0 is every static object merged in the world frame
(when there are any), then one instance per dynamic object in its object frame. Each instance gets a
BVH (:mod:`warp_vision.kernels.render.bvh`, cached per mesh for dynamic objects) and its faces,
normals, vertex colours and materials; that device-side, transform-independent part is built once per
scene version and device (:class:`_SceneGeometry`). :func:`scene_data` adds what changes from call to
call (per-batch instance transforms and visibility, lights, ambient light, background) and returns the
:class:`~warp_vision.kernels.render.shade.SceneData` the kernels take.

Units: metres and the world frame of docs/ARCHITECTURE.md.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warp_vision.kernels import launch as _launch
from warp_vision.kernels.render.bvh import build_bvh_cached
from warp_vision.kernels.render.packet import BvhData, concat_bvhs
from warp_vision.kernels.render.shade import FLAG_SMOOTH, FLAG_VERTEX_COLORS, SceneData


def to_warp_transforms(T: np.ndarray) -> np.ndarray:
    """[..., 4, 4] rigid matrices -> [..., 7] float32 Warp transforms (p, q as x y z w)."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, dtype=np.float64)
    flat = T.reshape(-1, 4, 4)
    q = Rotation.from_matrix(flat[:, :3, :3]).as_quat()  # x y z w
    out = np.concatenate([flat[:, :3, 3], q], axis=1)
    return out.reshape(T.shape[:-2] + (7,)).astype(np.float32)


def _inverse_rigid(T: np.ndarray) -> np.ndarray:
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.broadcast_to(np.eye(4), T.shape).copy()
    Ti[..., :3, :3] = np.swapaxes(R, -1, -2)
    Ti[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    return Ti


def _cached_bvh(scene, group, V, F):
    """Dynamic objects' BVHs outlive geometry changes elsewhere in the scene (keyed by mesh identity)."""
    cache = scene.__dict__.setdefault("_bvh_cache", {})
    obj = scene.objects[group[0]]
    if obj.static:
        return build_bvh_cached(V, F)
    key = (id(obj.mesh), len(V), len(F))
    hit = cache.get(key)
    if hit is None or hit[0] is not obj.mesh:
        cache[key] = hit = (obj.mesh, build_bvh_cached(V, F))
    return hit[1]


def _object_arrays(o):
    """One object's vertices, normals and per-vertex albedo (float64; a static object's in the world
    frame, a dynamic one's in its own) and faces."""
    m = o.mesh
    V = np.asarray(m.vertices, dtype=np.float64)
    N = np.asarray(m.vertex_normals, dtype=np.float64)
    if o.static:  # merged in the world frame
        T = o.transform[0]
        V = V @ T[:3, :3].T + T[:3, 3]
        N = N @ T[:3, :3].T
    vc = getattr(m.visual, "vertex_colors", None) if o.material.vertex_colors else None
    if vc is not None and len(vc) == len(V):
        C = np.asarray(vc[:, :3], dtype=np.float64) / 255.0
    else:
        C = np.tile(np.asarray(o.material.diffuse, np.float64), (len(V), 1))
    return V, N, C, np.asarray(m.faces, dtype=np.int64)


def _merge_group(scene, group):
    """The objects of one instance merged into one mesh: vertices (float32), faces (int32, into the
    merged vertices), normals, albedo, and per face its object and its index within the object's mesh."""
    Vs, Fs, Ns, Cs, f_obj, f_loc, vbase = [], [], [], [], [], [], 0
    for i in group:
        V, N, C, F = _object_arrays(scene.objects[i])
        Vs.append(V)
        Ns.append(N)
        Cs.append(C)
        Fs.append(F + vbase)
        f_obj.append(np.full(len(F), i, dtype=np.int32))
        f_loc.append(np.arange(len(F), dtype=np.int32))
        vbase += len(V)
    V = np.ascontiguousarray(np.concatenate(Vs), dtype=np.float32)
    F = np.ascontiguousarray(np.concatenate(Fs), dtype=np.int32)
    return V, F, np.concatenate(Ns), np.concatenate(Cs), f_obj, f_loc


class _SceneGeometry:
    """The device-side, transform-independent part of a scene: instances' BVHs, faces, normals, materials.

    Instance 0 is every static object merged in the world frame (when there are any); then one instance
    per dynamic object, in its object frame.
    """

    def __init__(self, scene, device: str):
        static = [i for i, o in enumerate(scene.objects) if o.static]
        dynamic = [i for i, o in enumerate(scene.objects) if not o.static]
        groups = ([static] if static else []) + [[i] for i in dynamic]
        self.instance_objects = [g[0] if len(g) == 1 and not scene.objects[g[0]].static else -1 for g in groups]
        self.bvhs = []
        faces, f_obj, f_loc, normals, colors, f_off, v_off, = [], [], [], [], [], [], []
        nf = nv = 0
        for g in groups:
            V, F, N, C, g_obj, g_loc = _merge_group(scene, g)
            self.bvhs.append(_cached_bvh(scene, g, V, F))
            faces.append(F)
            normals.append(N)
            colors.append(C)
            f_obj += g_obj
            f_loc += g_loc
            f_off.append(nf)
            v_off.append(nv)
            nf += len(F)
            nv += len(V)
        arr = lambda x, dt: wp.array(np.ascontiguousarray(x), dtype=dt, device=device)  # noqa: E731
        packed = concat_bvhs(self.bvhs)
        self.root_lo = np.array([b.node_lo[0] for b in self.bvhs], np.float64)  # [n_inst, 3], instance frames
        self.root_hi = np.array([b.node_hi[0] for b in self.bvhs], np.float64)
        self.bvh = {k: arr(v, wp.vec3 if v.ndim == 2 else wp.int32) for k, v in packed.items()}
        self.faces = arr(np.concatenate(faces), wp.vec3i)
        self.face_offset = arr(np.array(f_off, np.int32), wp.int32)
        self.face_object = arr(np.concatenate(f_obj), wp.int32)
        self.face_local = arr(np.concatenate(f_loc), wp.int32)
        self.normals = arr(np.concatenate(normals).astype(np.float32), wp.vec3)
        self.colors = arr(np.concatenate(colors).astype(np.float32), wp.vec3)
        self.vert_offset = arr(np.array(v_off, np.int32), wp.int32)
        self._upload_materials(scene, arr)

    def _upload_materials(self, scene, arr) -> None:
        mats = [o.material for o in scene.objects]
        self.diffuse = arr(np.array([m.diffuse for m in mats], np.float32), wp.vec3)
        self.specular = arr(np.array([m.specular for m in mats], np.float32), wp.float32)
        self.shininess = arr(np.array([m.shininess for m in mats], np.float32), wp.float32)
        self.reflectivity = arr(np.array([m.reflectivity for m in mats], np.float32), wp.float32)
        self.emission = arr(np.array([m.emission for m in mats], np.float32), wp.vec3)
        self.flags = arr(
            np.array([(FLAG_VERTEX_COLORS if m.vertex_colors else 0) | (FLAG_SMOOTH if m.smooth else 0) for m in mats], np.int32),
            wp.int32,
        )


def _world_bounds(geo: _SceneGeometry, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each instance's box in the world, [rows, n_inst, 3] (lo, hi) float32: the 8 corners of its root
    node's box through its transforms T [rows, n_inst, 4, 4], widened by a relative 1e-5 and 1e-6 m so
    float32 rounding never culls a ray that grazes the instance."""
    corners = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3)
    box = np.stack([geo.root_lo, geo.root_hi])  # [2, n_inst, 3]
    pts = np.where(corners[:, None, :] == 0, box[0][None], box[1][None])  # [8, n_inst, 3]
    w = np.einsum("rnij,cnj->rcni", T[..., :3, :3], pts) + T[:, None, :, :3, 3]  # [rows, 8, n_inst, 3]
    lo, hi = w.min(axis=1), w.max(axis=1)
    pad = 1e-5 * np.abs(w).max(axis=1) + 1e-6
    return np.ascontiguousarray(lo - pad, np.float32), np.ascontiguousarray(hi + pad, np.float32)


def _instance_bvh_data(scene, geo: _SceneGeometry, device: str) -> BvhData:
    """The instances' BVHs with their per-batch transforms and visibility (one row when no object
    varies across the batch)."""
    B = scene.batch_size()
    per_inst = [np.eye(4)[None] if k < 0 else scene.objects[k].transform for k in geo.instance_objects]
    T = np.stack([np.broadcast_to(t, (B, 4, 4)) for t in per_inst], axis=1)  # [B, n_inst, 4, 4]
    if all(t.shape[0] == 1 for t in per_inst):
        T = T[:1]
    bv = BvhData()
    for name, a in geo.bvh.items():
        setattr(bv, name, a)
    bv.world_from_inst = wp.array(to_warp_transforms(T), dtype=wp.transform, device=device)
    lo, hi = _world_bounds(geo, T)
    bv.inst_world_lo = wp.array(lo, dtype=wp.vec3, device=device)
    bv.inst_world_hi = wp.array(hi, dtype=wp.vec3, device=device)
    bv.inst_from_world = wp.array(to_warp_transforms(_inverse_rigid(T)), dtype=wp.transform, device=device)
    per_vis = [np.ones(1, dtype=bool) if k < 0 else scene.objects[k].visible for k in geo.instance_objects]
    vis = np.stack([np.broadcast_to(v, (B,)) for v in per_vis], axis=1)  # [B, n_inst]
    if all(len(v) == 1 for v in per_vis):
        vis = vis[:1]
    bv.inst_visible = wp.array(np.ascontiguousarray(vis, dtype=np.int32), dtype=wp.int32, device=device)
    return bv


def _light_arrays(scene) -> tuple[np.ndarray, np.ndarray]:
    """The point lights' positions and radiant intensities (colour * intensity), [B or 1, n_lights, 3]."""
    if scene.lights:
        Bl = max(
            max(np.atleast_2d(li.position).shape[0], np.atleast_2d(li.color).shape[0], np.atleast_1d(li.intensity).shape[0])
            for li in scene.lights
        )
        pos = np.stack([np.broadcast_to(np.atleast_2d(li.position), (Bl, 3)) for li in scene.lights], axis=1)
        rad = np.stack(
            [
                np.broadcast_to(np.atleast_2d(li.color), (Bl, 3)) * np.broadcast_to(np.atleast_1d(li.intensity), (Bl,))[:, None]
                for li in scene.lights
            ],
            axis=1,
        )
    else:
        pos = np.zeros((1, 0, 3))
        rad = np.zeros((1, 0, 3))
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(rad)) and np.all(rad >= 0)):
        raise ValueError("scene lights: positions must be finite and colours * intensities finite and >= 0")
    return pos, rad


def scene_data(scene, device: str = "cpu", max_depth: int = 2) -> SceneData:
    """Pack a :class:`warp_vision.scene.Scene` for the kernels (BVHs cached per scene version and device)."""
    _launch.init()
    if len(scene.objects) == 0:
        raise ValueError("scene: it has no objects")
    if max_depth < 0:
        raise ValueError(f"max_depth: expected >= 0, got {max_depth}")
    key = (scene._version, device)
    geo = scene._gpu.get(key)
    if geo is None:
        scene._gpu.clear()
        geo = scene._gpu[key] = _SceneGeometry(scene, device)
    sc = SceneData()
    sc.bv = _instance_bvh_data(scene, geo, device)
    for name in (
        "faces face_offset face_object face_local normals colors vert_offset diffuse specular shininess reflectivity emission flags"
    ).split():
        setattr(sc, name, getattr(geo, name))
    pos, rad = _light_arrays(scene)
    sc.light_pos = wp.array(np.ascontiguousarray(pos, dtype=np.float32), dtype=wp.vec3, device=device)
    sc.light_rad = wp.array(np.ascontiguousarray(rad, dtype=np.float32), dtype=wp.vec3, device=device)
    sc.ambient = wp.vec3(*[float(x) for x in scene.ambient])
    sc.background = wp.vec3(*[float(x) for x in scene.background])
    sc.max_depth = int(max_depth)
    return sc
