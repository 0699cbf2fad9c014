"""Stage 2 of the ONV renderer: rays into the scene, closest hits, Phong shading, in Warp.

``render_onv`` takes the eye-frame rays of :mod:`warp_vision.kernels.eye_rays` (each photoreceptor's
3 S rays through the pupil, one set per RGB channel), moves them into the world with each batch
element's eye pose, and traces them in packets of 8 (``kernels/packet.py``): closest hit over every
instance's BVH (per-batch rigid transforms), Phong local illumination with shadow rays to every point
light plus ambient light, and mirror reflections followed to ``max_depth`` bounces. One Warp thread
per (batch element, photoreceptor) sums its rays' weighted radiances into the ONV, so there are no
atomics and CPU launches split over threads (bit-identical results).

A pinhole camera (``render_camera``) shares the tracing for third-person images, and
``closest_hit`` exposes bare closest-hit queries (tests, benchmarks). ``raytrace_ref.py`` is the numpy
reference for all of it.

Shapes and units: eye poses are world-from-eye rigid transforms in metres (the eye frame of
DESIGN.md). The ONV is ``[B, 3P]`` float32 and element ``3p + c`` is channel c of photoreceptor p, as
linear irradiance.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp

from warp_vision.eye.optics import NavarroEye
from warp_vision.kernels import launch as _launch
from warp_vision.kernels.bvh import build_bvh
from warp_vision.kernels.eye_rays import EyeRays, _eye_cache, eye_rays, pupil_samples, surface_table  # noqa: F401
from warp_vision.kernels.packet import (
    DEAD,
    FAR,
    BvhData,
    all_negative,
    barycentric,
    concat_bvhs,
    packet_closest,
    packet_occluded,
    vec8,
)

# Per-lane shading loops stay loops (unrolling 8 copies of the shading code only bloats the build).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

#: Offset (m) along the normal for secondary rays, so they do not hit the surface they leave.
RAY_EPSILON_M = wp.constant(1e-5)
#: CPU launch splitting for tracing kernels: threads are heavy and unequal (a ray that reaches the
#: periphery of a BVH costs more than one that hits a wall), so hand out many small slices.
_SPLIT = {"min_per_slice": 64, "chunks_per_thread": 16}
#: Object flags
FLAG_VERTEX_COLORS = wp.constant(1)
FLAG_SMOOTH = wp.constant(2)


@wp.struct
class SceneData:
    """A scene for the kernels. An *instance* is one BVH with one transform per batch element: either one
    dynamic object, or all static objects merged in the world frame. Materials belong to objects; each
    face knows its object."""

    bv: BvhData
    faces: wp.array(dtype=wp.vec3i)  # all instances' triangles (instance-local vertex indices)
    face_offset: wp.array(dtype=int)  # [n_inst]
    face_object: wp.array(dtype=int)  # [n_faces] the object (material) of each face
    face_local: wp.array(dtype=int)  # [n_faces] the face's index within its object's mesh
    normals: wp.array(dtype=wp.vec3)  # per-vertex normals (instance frame), all instances
    colors: wp.array(dtype=wp.vec3)  # per-vertex albedo, all instances
    vert_offset: wp.array(dtype=int)  # [n_inst]
    diffuse: wp.array(dtype=wp.vec3)  # [n_obj] materials
    specular: wp.array(dtype=float)
    shininess: wp.array(dtype=float)
    reflectivity: wp.array(dtype=float)
    emission: wp.array(dtype=wp.vec3)  # [n_obj] emitted radiance
    flags: wp.array(dtype=int)
    light_pos: wp.array2d(dtype=wp.vec3)  # [B or 1, n_lights], m
    light_rad: wp.array2d(dtype=wp.vec3)  # colour * intensity
    ambient: wp.vec3
    background: wp.vec3
    max_depth: int


@wp.func
def packet_radiance(
    sc: SceneData, b: int, ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8, live: vec8
):
    """RGB radiance arriving along a packet of world rays (unit directions) in batch element b's scene.

    ``live``: FAR for a live lane, DEAD for an unused one. Returns (R, G, B) vec8.
    """
    bt = b
    if sc.bv.world_from_inst.shape[0] == 1:
        bt = 0
    bl = b
    if sc.light_pos.shape[0] == 1:
        bl = 0
    R = vec8()
    G = vec8()
    Bc = vec8()
    thr = vec8(1.0)
    thg = vec8(1.0)
    thb = vec8(1.0)
    lim = live
    for depth in range(sc.max_depth + 1):
        t, tri = packet_closest(sc.bv, b, ox, oy, oz, dx, dy, dz, lim)
        # per-lane surface: offset point, normal, albedo and material
        px = vec8()
        py = vec8()
        pz = vec8()
        nx = vec8()
        ny = vec8()
        nz = vec8()
        lr = vec8()
        lg = vec8()
        lb = vec8()
        cr = vec8()
        cg = vec8()
        cb = vec8()
        ks = vec8()
        shin = vec8(1.0)
        refl = vec8()
        hit = vec8(DEAD)
        for l in range(8):
            if lim[l] < 0.0:
                continue
            k = tri[l]
            if k < 0:
                R[l] = R[l] + thr[l] * sc.background[0]
                G[l] = G[l] + thg[l] * sc.background[1]
                Bc[l] = Bc[l] + thb[l] * sc.background[2]
                continue
            o = wp.vec3(ox[l], oy[l], oz[l])
            d = wp.vec3(dx[l], dy[l], dz[l])
            inst = sc.bv.tri_inst[k]
            X = sc.bv.world_from_inst[bt, inst]
            f = sc.face_offset[inst] + sc.bv.tri_face[k]
            obj = sc.face_object[f]
            flags = sc.flags[obj]
            n_i = wp.normalize(wp.cross(sc.bv.tri_e1[k], sc.bv.tri_e2[k]))
            base = sc.diffuse[obj]
            if flags != 0:
                Xi = sc.bv.inst_from_world[bt, inst]
                u, v = barycentric(sc.bv, k, wp.transform_point(Xi, o), wp.transform_vector(Xi, d))
                w2 = 1.0 - u - v
                tv = sc.faces[f]
                vo = sc.vert_offset[inst]
                if (flags & FLAG_SMOOTH) != 0:
                    n_i = wp.normalize(u * sc.normals[vo + tv[0]] + v * sc.normals[vo + tv[1]] + w2 * sc.normals[vo + tv[2]])
                if (flags & FLAG_VERTEX_COLORS) != 0:
                    base = u * sc.colors[vo + tv[0]] + v * sc.colors[vo + tv[1]] + w2 * sc.colors[vo + tv[2]]
            n = wp.transform_vector(X, n_i)
            if wp.dot(n, d) > 0.0:
                n = -n
            p = o + t[l] * d + RAY_EPSILON_M * n
            px[l] = p[0]
            py[l] = p[1]
            pz[l] = p[2]
            nx[l] = n[0]
            ny[l] = n[1]
            nz[l] = n[2]
            cr[l] = base[0]
            cg[l] = base[1]
            cb[l] = base[2]
            em = sc.emission[obj]
            lr[l] = sc.ambient[0] * base[0] + em[0]
            lg[l] = sc.ambient[1] * base[1] + em[1]
            lb[l] = sc.ambient[2] * base[2] + em[2]
            ks[l] = sc.specular[obj]
            shin[l] = sc.shininess[obj]
            refl[l] = sc.reflectivity[obj]
            hit[l] = 1.0
        # one shadow packet per light
        for li in range(sc.light_pos.shape[1]):
            lpos = sc.light_pos[bl, li]
            sx = vec8()
            sy = vec8()
            sz = vec8()
            slim = vec8(DEAD)
            for l in range(8):
                if hit[l] < 0.0:
                    continue
                lv = lpos - wp.vec3(px[l], py[l], pz[l])
                dist = wp.length(lv)
                ld = lv / dist
                if wp.dot(wp.vec3(nx[l], ny[l], nz[l]), ld) > 0.0:
                    sx[l] = ld[0]
                    sy[l] = ld[1]
                    sz[l] = ld[2]
                    slim[l] = dist
            if all_negative(slim):
                continue
            vis = packet_occluded(sc.bv, b, px, py, pz, sx, sy, sz, slim)
            E0 = sc.light_rad[bl, li]
            for l in range(8):
                if slim[l] < 0.0 or vis[l] < 0.0:
                    continue
                n = wp.vec3(nx[l], ny[l], nz[l])
                ld = wp.vec3(sx[l], sy[l], sz[l])
                ndl = wp.dot(n, ld)
                E = E0 / (slim[l] * slim[l])
                shade = wp.vec3(cr[l], cg[l], cb[l]) * (ndl / wp.pi)
                if ks[l] > 0.0:
                    rr = 2.0 * ndl * n - ld
                    rv = wp.max(-wp.dot(rr, wp.vec3(dx[l], dy[l], dz[l])), 0.0)
                    shade = shade + wp.vec3(ks[l] * wp.pow(rv, shin[l]) / wp.pi)
                lr[l] = lr[l] + E[0] * shade[0]
                lg[l] = lg[l] + E[1] * shade[1]
                lb[l] = lb[l] + E[2] * shade[2]
        # accumulate; mirror lanes continue
        nxt = vec8(DEAD)
        for l in range(8):
            if hit[l] < 0.0:
                continue
            keep = 1.0 - refl[l]
            R[l] = R[l] + thr[l] * lr[l] * keep
            G[l] = G[l] + thg[l] * lg[l] * keep
            Bc[l] = Bc[l] + thb[l] * lb[l] * keep
            if refl[l] > 0.0:
                thr[l] = thr[l] * refl[l]
                thg[l] = thg[l] * refl[l]
                thb[l] = thb[l] * refl[l]
                n = wp.vec3(nx[l], ny[l], nz[l])
                d = wp.vec3(dx[l], dy[l], dz[l])
                d = d - 2.0 * wp.dot(d, n) * n
                dx[l] = d[0]
                dy[l] = d[1]
                dz[l] = d[2]
                ox[l] = px[l]
                oy[l] = py[l]
                oz[l] = pz[l]
                nxt[l] = FAR
        if all_negative(nxt):
            break
        lim = nxt
    return R, G, Bc


@wp.kernel
def render_onv_kernel(
    sc: SceneData,
    world_from_eye: wp.array(dtype=wp.transform),
    ray_origin: wp.array(dtype=wp.vec3),
    ray_dir: wp.array(dtype=wp.vec3),
    ray_weight: wp.array(dtype=float),
    P: int,
    S: int,
    offset: int,
    onv_out: wp.array2d(dtype=float),
):
    """Thread (b, p): onv_out[b, 3p + c] = sum_s weight * radiance_c over photoreceptor p's rays, 8 at a time."""
    k = offset + wp.tid()
    b = k / P
    p = k - b * P
    T = world_from_eye[b]
    for c in range(3):
        acc = float(0.0)
        for j in range((S + 7) / 8):
            ox = vec8()
            oy = vec8()
            oz = vec8()
            dx = vec8()
            dy = vec8()
            dz = vec8()
            w = vec8()
            live = vec8(DEAD)
            for l in range(8):
                s = j * 8 + l
                if s >= S:
                    continue
                r = (p * 3 + c) * S + s
                wr = ray_weight[r]
                if wr == 0.0:
                    continue
                o = wp.transform_point(T, ray_origin[r])
                d = wp.transform_vector(T, ray_dir[r])
                ox[l] = o[0]
                oy[l] = o[1]
                oz[l] = o[2]
                dx[l] = d[0]
                dy[l] = d[1]
                dz[l] = d[2]
                w[l] = wr
                live[l] = FAR
            if all_negative(live):
                continue
            R, G, Bc = packet_radiance(sc, b, ox, oy, oz, dx, dy, dz, live)
            if c == 0:
                acc = acc + wp.dot(w, R)
            elif c == 1:
                acc = acc + wp.dot(w, G)
            else:
                acc = acc + wp.dot(w, Bc)
        onv_out[b, p * 3 + c] = acc


@wp.kernel
def camera_kernel(
    sc: SceneData,
    world_from_camera: wp.transform,
    width: int,
    height: int,
    tan_half_fov: float,
    b: int,
    offset: int,
    image_out: wp.array3d(dtype=float),
):
    """Pinhole camera (looks along its -z, +y up, +x right; vertical field of view); a thread traces a
    4 x 2 pixel tile as one packet."""
    k = offset + wp.tid()
    tiles_x = (width + 3) / 4
    ty = k / tiles_x
    tx = k - ty * tiles_x
    aspect = float(width) / float(height)
    o = wp.transform_point(world_from_camera, wp.vec3(0.0))
    ox = vec8(o[0])
    oy = vec8(o[1])
    oz = vec8(o[2])
    dx = vec8()
    dy = vec8()
    dz = vec8()
    live = vec8(DEAD)
    for l in range(8):
        x = tx * 4 + l % 4
        y = ty * 2 + l / 4
        if x >= width or y >= height:
            continue
        px = (2.0 * (float(x) + 0.5) / float(width) - 1.0) * tan_half_fov * aspect
        py = (1.0 - 2.0 * (float(y) + 0.5) / float(height)) * tan_half_fov
        d = wp.normalize(wp.transform_vector(world_from_camera, wp.vec3(px, py, -1.0)))
        dx[l] = d[0]
        dy[l] = d[1]
        dz[l] = d[2]
        live[l] = FAR
    R, G, Bc = packet_radiance(sc, b, ox, oy, oz, dx, dy, dz, live)
    for l in range(8):
        if live[l] < 0.0:
            continue
        x = tx * 4 + l % 4
        y = ty * 2 + l / 4
        image_out[y, x, 0] = R[l]
        image_out[y, x, 1] = G[l]
        image_out[y, x, 2] = Bc[l]


@wp.func
def load_packet(origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3), k: int):
    """Rays 8k .. 8k + 7 as a packet (directions normalised); lanes past the end are dead."""
    n = origins.shape[0]
    ox = vec8()
    oy = vec8()
    oz = vec8()
    dx = vec8()
    dy = vec8()
    dz = vec8()
    live = vec8(DEAD)
    for l in range(8):
        i = k * 8 + l
        if i < n:
            o = origins[i]
            d = wp.normalize(dirs[i])
            ox[l] = o[0]
            oy[l] = o[1]
            oz[l] = o[2]
            dx[l] = d[0]
            dy[l] = d[1]
            dz[l] = d[2]
            live[l] = FAR
    return ox, oy, oz, dx, dy, dz, live


@wp.kernel
def radiance_kernel(
    sc: SceneData,
    origins: wp.array(dtype=wp.vec3),
    dirs: wp.array(dtype=wp.vec3),
    b: int,
    offset: int,
    rgb_out: wp.array2d(dtype=float),
):
    """RGB radiance along world rays, 8 consecutive rays per thread."""
    k = offset + wp.tid()
    n = origins.shape[0]
    ox, oy, oz, dx, dy, dz, live = load_packet(origins, dirs, k)
    R, G, Bc = packet_radiance(sc, b, ox, oy, oz, dx, dy, dz, live)
    for l in range(8):
        i = k * 8 + l
        if i < n:
            rgb_out[i, 0] = R[l]
            rgb_out[i, 1] = G[l]
            rgb_out[i, 2] = Bc[l]


@wp.kernel
def closest_hit_kernel(
    sc: SceneData,
    origins: wp.array(dtype=wp.vec3),
    dirs: wp.array(dtype=wp.vec3),
    b: int,
    offset: int,
    t_out: wp.array(dtype=float),
    obj_out: wp.array(dtype=int),
    face_out: wp.array(dtype=int),
):
    """Bare closest-hit queries, 8 consecutive rays per thread: t (inf on a miss), object and its face (-1)."""
    k = offset + wp.tid()
    n = origins.shape[0]
    ox, oy, oz, dx, dy, dz, live = load_packet(origins, dirs, k)
    t, tri = packet_closest(sc.bv, b, ox, oy, oz, dx, dy, dz, live)
    for l in range(8):
        i = k * 8 + l
        if i >= n:
            continue
        kk = tri[l]
        if kk < 0:
            t_out[i] = wp.inf
            obj_out[i] = -1
            face_out[i] = -1
        else:
            f = sc.face_offset[sc.bv.tri_inst[kk]] + sc.bv.tri_face[kk]
            t_out[i] = t[l]
            obj_out[i] = sc.face_object[f]
            face_out[i] = sc.face_local[f]


# --------------------------------------------------------------------------------------------------
# Host side
# --------------------------------------------------------------------------------------------------


def _transforms_to_wp(T: np.ndarray) -> np.ndarray:
    """[..., 4, 4] rigid matrices -> [..., 7] Warp transforms (p, q as x y z w)."""
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
        return build_bvh(V, F)
    key = (id(obj.mesh), len(V), len(F))
    hit = cache.get(key)
    if hit is None or hit[0] is not obj.mesh:
        cache[key] = hit = (obj.mesh, build_bvh(V, F))
    return hit[1]


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
            Vs, Fs, Ns, Cs, vbase = [], [], [], [], 0
            for i in g:
                o = scene.objects[i]
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
                Vs.append(V)
                Ns.append(N)
                Cs.append(C)
                Fs.append(np.asarray(m.faces, dtype=np.int64) + vbase)
                f_obj.append(np.full(len(m.faces), i, dtype=np.int32))
                f_loc.append(np.arange(len(m.faces), dtype=np.int32))
                vbase += len(V)
            V = np.ascontiguousarray(np.concatenate(Vs), dtype=np.float32)
            F = np.ascontiguousarray(np.concatenate(Fs), dtype=np.int32)
            self.bvhs.append(_cached_bvh(scene, g, V, F))
            faces.append(F)
            normals.append(np.concatenate(Ns))
            colors.append(np.concatenate(Cs))
            f_off.append(nf)
            v_off.append(nv)
            nf += len(F)
            nv += len(V)
        mats = [o.material for o in scene.objects]
        arr = lambda x, dt: wp.array(np.ascontiguousarray(x), dtype=dt, device=device)  # noqa: E731
        packed = concat_bvhs(self.bvhs)
        self.bvh = {k: arr(v, wp.vec3 if v.ndim == 2 else wp.int32) for k, v in packed.items()}
        self.faces = arr(np.concatenate(faces), wp.vec3i)
        self.face_offset = arr(np.array(f_off, np.int32), wp.int32)
        self.face_object = arr(np.concatenate(f_obj), wp.int32)
        self.face_local = arr(np.concatenate(f_loc), wp.int32)
        self.normals = arr(np.concatenate(normals).astype(np.float32), wp.vec3)
        self.colors = arr(np.concatenate(colors).astype(np.float32), wp.vec3)
        self.vert_offset = arr(np.array(v_off, np.int32), wp.int32)
        self.diffuse = arr(np.array([m.diffuse for m in mats], np.float32), wp.vec3)
        self.specular = arr(np.array([m.specular for m in mats], np.float32), wp.float32)
        self.shininess = arr(np.array([m.shininess for m in mats], np.float32), wp.float32)
        self.reflectivity = arr(np.array([m.reflectivity for m in mats], np.float32), wp.float32)
        self.emission = arr(np.array([m.emission for m in mats], np.float32), wp.vec3)
        self.flags = arr(
            np.array([(FLAG_VERTEX_COLORS if m.vertex_colors else 0) | (FLAG_SMOOTH if m.smooth else 0) for m in mats], np.int32),
            wp.int32,
        )


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
    B = scene.batch_size()
    per_inst = [np.eye(4)[None] if k < 0 else scene.objects[k].transform for k in geo.instance_objects]
    T = np.stack([np.broadcast_to(t, (B, 4, 4)) for t in per_inst], axis=1)  # [B, n_inst, 4, 4]
    if all(t.shape[0] == 1 for t in per_inst):
        T = T[:1]
    bv = BvhData()
    for name, a in geo.bvh.items():
        setattr(bv, name, a)
    bv.world_from_inst = wp.array(_transforms_to_wp(T), dtype=wp.transform, device=device)
    bv.inst_from_world = wp.array(_transforms_to_wp(_inverse_rigid(T)), dtype=wp.transform, device=device)
    per_vis = [np.ones(1, dtype=bool) if k < 0 else scene.objects[k].visible for k in geo.instance_objects]
    vis = np.stack([np.broadcast_to(v, (B,)) for v in per_vis], axis=1)  # [B, n_inst]
    if all(len(v) == 1 for v in per_vis):
        vis = vis[:1]
    bv.inst_visible = wp.array(np.ascontiguousarray(vis, dtype=np.int32), dtype=wp.int32, device=device)
    sc = SceneData()
    sc.bv = bv
    for name in (
        "faces face_offset face_object face_local normals colors vert_offset diffuse specular shininess reflectivity emission flags"
    ).split():
        setattr(sc, name, getattr(geo, name))
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
    sc.light_pos = wp.array(np.ascontiguousarray(pos, dtype=np.float32), dtype=wp.vec3, device=device)
    sc.light_rad = wp.array(np.ascontiguousarray(rad, dtype=np.float32), dtype=wp.vec3, device=device)
    sc.ambient = wp.vec3(*[float(x) for x in scene.ambient])
    sc.background = wp.vec3(*[float(x) for x in scene.background])
    sc.max_depth = int(max_depth)
    return sc


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
    R = T[:, :3, :3]
    if np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max() > 1e-4 or np.any(np.linalg.det(R) < 0):
        raise ValueError(f"{name}: expected rigid transforms (orthonormal rotation, det +1)")
    return T


def render_onv(
    scene,
    retina,
    eye: NavarroEye,
    eye_poses,
    samples_per_receptor: int = 16,
    seed: int = 0,
    device: str = "cpu",
    max_depth: int = 2,
) -> torch.Tensor:
    """Render the Optic Nerve Vector of B eye poses: a float32 tensor [B, 3P] (linear irradiance).

    scene: :class:`warp_vision.scene.Scene` (per-batch transforms/lights must have batch B or 1).
    retina: a :class:`warp_vision.eye.retina.Retina` (or its positions_optical_mm [P, 3]).
    eye: the eye's optical state (accommodation, pupil).
    eye_poses: [B, 4, 4] world-from-eye rigid transforms (m).
    samples_per_receptor: S rays per photoreceptor and channel through stratified pupil points.
    seed: the pupil sampling's seed; max_depth: mirror bounces followed (>= 0).
    """
    T = _poses("eye_poses", eye_poses)
    B = T.shape[0]
    Bs = scene.batch_size()
    if Bs not in (1, B):
        raise ValueError(f"scene: its per-batch transforms/lights have batch {Bs}, but eye_poses has {B}")
    rays = eye_rays(retina, eye, samples_per_receptor, seed, device)
    sc = scene_data(scene, device, max_depth)
    onv = torch.zeros((B, 3 * rays.P), dtype=torch.float32, device=device)
    _launch.launch_split(
        render_onv_kernel,
        B * rays.P,
        inputs=[
            sc,
            wp.array(_transforms_to_wp(T), dtype=wp.transform, device=device),
            rays.origins,
            rays.directions,
            rays.weights,
            rays.P,
            rays.S,
        ],
        outputs=[wp.from_torch(onv)],
        device=device,
        **_SPLIT,
    )
    return onv


def look_at(eye_position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """A [4, 4] world-from-camera transform at ``eye_position`` looking at ``target`` (camera -z forward).

    For the eye frame (+z forward) use :func:`eye_look_at`.
    """
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
        raise ValueError(f"fov_deg: expected 0 to 180, got {fov_deg}")
    T = _poses("world_from_camera", world_from_camera, 1)
    Bs = scene.batch_size()
    if not 0 <= batch < Bs:
        raise ValueError(f"batch: expected 0 to {Bs - 1}, got {batch}")
    sc = scene_data(scene, device, max_depth)
    img = torch.zeros((height, width, 3), dtype=torch.float32, device=device)
    tf = _transforms_to_wp(T)[0]
    _launch.launch_split(
        camera_kernel,
        ((width + 3) // 4) * ((height + 1) // 2),
        inputs=[sc, wp.transform(tf[:3], tf[3:]), width, height, math.tan(math.radians(fov_deg) / 2), batch],
        outputs=[wp.from_torch(img)],
        device=device,
        **_SPLIT,
    )
    return img


def closest_hit(scene, origins, directions, batch: int = 0, device: str = "cpu", threads: int | None = None):
    """Closest-hit queries for world rays [N, 3]: (t [N] m, inf on a miss; object [N]; face [N]), numpy."""
    o = np.ascontiguousarray(origins, dtype=np.float32)
    d = np.ascontiguousarray(directions, dtype=np.float32)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins, directions: expected matching [N, 3], got {o.shape} and {d.shape}")
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
        **_SPLIT,
    )
    return t.numpy(), obj.numpy(), face.numpy()


def radiance(scene, origins, directions, batch: int = 0, device: str = "cpu", max_depth: int = 2) -> torch.Tensor:
    """RGB radiance [N, 3] (float32) arriving along world rays origins/directions [N, 3] (m)."""
    o = np.ascontiguousarray(origins, dtype=np.float32)
    d = np.ascontiguousarray(directions, dtype=np.float32)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins, directions: expected matching [N, 3], got {o.shape} and {d.shape}")
    Bs = scene.batch_size()
    if not 0 <= batch < Bs:
        raise ValueError(f"batch: expected 0 to {Bs - 1}, got {batch}")
    sc = scene_data(scene, device, max_depth)
    out = torch.zeros((len(o), 3), dtype=torch.float32, device=device)
    _launch.launch_split(
        radiance_kernel,
        (len(o) + 7) // 8,
        inputs=[sc, wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device), batch],
        outputs=[wp.from_torch(out)],
        device=device,
        **_SPLIT,
    )
    return out
