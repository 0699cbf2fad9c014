"""The ONV renderer's scene upload, on the host: a :class:`warp_vision.scene.Scene` packed for the kernels.

A scene's geometry becomes *instances*: instance 0 is every static object merged in the world frame
(when there are any), then one instance per dynamic object in its object frame. Each instance gets a
BVH (:mod:`warp_vision.kernels.render.bvh`, cached per mesh for dynamic objects) and its faces,
normals, vertex colours and per-object shading flags; that device-side, transform-independent part is
built once per scene version and device (:class:`_SceneGeometry`). :func:`scene_data` adds what may
change from call to call, and what may differ per batch element, and returns the
:class:`~warp_vision.kernels.render.shade.SceneData` the kernels take: per-batch instance transforms
and visibility, lights, materials (``[1, n_obj]`` arrays cached with the geometry while every object
shares one material across the batch, re-uploaded after :meth:`~warp_vision.scene.Scene.set_material`;
``[B, n_obj]``, built per call, once some object has per-batch materials), ambient light (``[1]`` or
``[B]``) and background.

Units: metres and the world frame of docs/ARCHITECTURE.md.
"""

from __future__ import annotations

import weakref

import numpy as np
import warp as wp

from warp_vision.kernels import launch as _launch
from warp_vision.kernels.render.bvh import build_bvh_cached
from warp_vision.kernels.render.packet import BvhData, concat_bvhs
from warp_vision.kernels.render.shade import FLAG_SMOOTH, FLAG_VERTEX_COLORS, SceneData

#: The shading values of a Material that may vary per batch element (the kernels' material arrays).
MATERIAL_FIELDS = ("diffuse", "specular", "shininess", "reflectivity", "emission")


def material_arrays(materials) -> dict[str, np.ndarray]:
    """Materials [M] packed as float64 arrays: diffuse and emission [M, 3], specular, shininess and
    reflectivity [M]."""
    return {f: np.array([getattr(m, f) for m in materials], dtype=np.float64) for f in MATERIAL_FIELDS}


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


#: Dynamic objects' BVHs by mesh identity, shared by every scene that holds the same mesh object (a
#: generator that builds a scene per room reuses its balls' and body's BVHs): id(mesh) -> (weak reference
#: to the mesh, (vertices, faces) counts, BVH); an entry goes when its mesh does.
_MESH_BVHS: dict = {}


def _cached_bvh(scene, group, V, F):
    """An instance's BVH: the static objects' merged mesh through the disk cache; a dynamic object's by
    its mesh's identity, so it outlives geometry changes elsewhere in the scene and the scene itself."""
    obj = scene.objects[group[0]]
    if obj.static:
        return build_bvh_cached(V, F)
    key, counts = id(obj.mesh), (len(V), len(F))
    hit = _MESH_BVHS.get(key)
    if hit is None or hit[0]() is not obj.mesh or hit[1] != counts:
        ref = weakref.ref(obj.mesh, lambda _, k=key: _MESH_BVHS.pop(k, None))
        _MESH_BVHS[key] = hit = (ref, counts, build_bvh_cached(V, F))
    return hit[2]


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
    vc = _vertex_colors(o)
    if vc is not None:
        C = np.asarray(vc[:, :3], dtype=np.float64) / 255.0
    else:  # unused: the object's albedo is its (possibly per-batch) material's diffuse
        C = np.tile(np.asarray(o.material.diffuse, np.float64), (len(V), 1))
    return V, N, C, np.asarray(m.faces, dtype=np.int64)


def _vertex_colors(o):
    """The object's per-vertex colours [V, 4] uint8 when its material asks for them and its mesh has
    one per vertex, else None (then its albedo is the material's diffuse, as in the reference)."""
    if not o.material.vertex_colors:
        return None
    vc = getattr(o.mesh.visual, "vertex_colors", None)
    return vc if vc is not None and len(vc) == len(o.mesh.vertices) else None


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
        flags = [
            (FLAG_VERTEX_COLORS if _vertex_colors(o) is not None else 0) | (FLAG_SMOOTH if o.material.smooth else 0)
            for o in scene.objects
        ]
        self.flags = arr(np.array(flags, np.int32), wp.int32)
        self.device = device
        self.materials_version = None  # the scene._materials_version of the shared materials below
        self.materials = None

    def shared_materials(self, scene) -> dict:
        """The objects' own materials as [1, n_obj] device arrays, uploaded again only after a
        :meth:`~warp_vision.scene.Scene.set_material`."""
        if self.materials is None or self.materials_version != scene._materials_version:
            packed = material_arrays([o.material for o in scene.objects])
            self.materials = _upload_materials({k: v[None] for k, v in packed.items()}, self.device)
            self.materials_version = scene._materials_version
        return self.materials


def _upload_materials(packed: dict, device: str) -> dict:
    """[Bm, n_obj] (and [Bm, n_obj, 3]) float64 material arrays -> float32 Warp 2-D arrays."""
    out = {}
    for k, v in packed.items():
        dt = wp.vec3 if v.ndim == 3 else wp.float32
        out[k] = wp.array(np.ascontiguousarray(v, dtype=np.float32), dtype=dt, device=device)
    return out


def _batch_materials(scene, B: int) -> dict:
    """Every object's material per batch element, [B, n_obj] (diffuse and emission [B, n_obj, 3]),
    float64: the object's per-batch list where it has one, else its own material broadcast."""
    n = len(scene.objects)
    out = {f: np.empty((B, n, 3) if f in ("diffuse", "emission") else (B, n)) for f in MATERIAL_FIELDS}
    for i, o in enumerate(scene.objects):
        per = o.batch_material_arrays
        if per is None:
            per = {f: np.asarray(getattr(o.material, f), dtype=np.float64)[None] for f in MATERIAL_FIELDS}
        for f in MATERIAL_FIELDS:
            out[f][:, i] = per[f]  # [1 or B(, 3)] broadcast over the batch
    return out


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
            max(np.atleast_2d(li.position).shape[0], np.atleast_2d(li.color).shape[0],
                np.atleast_1d(li.intensity).shape[0])
            for li in scene.lights
        )
        pos = np.stack([np.broadcast_to(np.atleast_2d(li.position), (Bl, 3)) for li in scene.lights], axis=1)
        rad = np.stack(
            [
                np.broadcast_to(np.atleast_2d(li.color),
                                (Bl, 3)) * np.broadcast_to(np.atleast_1d(li.intensity), (Bl,))[:, None]
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
    B = scene.batch_size()  # also checks that the per-batch quantities agree
    sc = SceneData()
    sc.bv = _instance_bvh_data(scene, geo, device)
    for name in "faces face_offset face_object face_local normals colors vert_offset flags".split():
        setattr(sc, name, getattr(geo, name))
    Bm = max((len(o.batch_materials) for o in scene.objects if o.batch_materials is not None), default=0)
    if Bm == 0:  # every object shares its own material across the batch: cached
        mats = geo.shared_materials(scene)
    else:  # [B, n_obj] (a per-batch list of one material is shared: [1, n_obj])
        mats = _upload_materials(_batch_materials(scene, B if Bm > 1 else 1), device)
    for name, a in mats.items():
        setattr(sc, name, a)
    pos, rad = _light_arrays(scene)
    sc.light_pos = wp.array(np.ascontiguousarray(pos, dtype=np.float32), dtype=wp.vec3, device=device)
    sc.light_rad = wp.array(np.ascontiguousarray(rad, dtype=np.float32), dtype=wp.vec3, device=device)
    amb = np.atleast_2d(scene.ambient)  # [1 or B, 3]
    sc.ambient = wp.array(np.ascontiguousarray(amb, dtype=np.float32), dtype=wp.vec3, device=device)
    sc.background = wp.vec3(*[float(x) for x in scene.background])
    sc.max_depth = int(max_depth)
    return sc
