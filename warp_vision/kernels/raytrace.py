"""Ray tracing through the eye and into the scene: the ONV renderer, in Warp.

Two stages, one kernel each:

1. :func:`eye_rays` (kernel ``eye_rays_kernel``): for every photoreceptor p, colour channel c and pupil
   sample s, the ray from the photoreceptor through the s-th point of the pupil, refracted out through
   the lens and the cornea with channel c's refractive indices (exact conic surfaces and vector Snell
   in float32, the same maths as :class:`warp_vision.eye.optics.NavarroEye`). Each ray carries the
   irradiance weight ``A_pupil / S * n_v^2 cos(theta_retina) d(omega)/dA_pupil`` (sr), so that a
   photoreceptor's value, the weighted sum of its rays' radiances, is its irradiance: it grows with the
   pupil area and a blocked ray carries nothing. The rays depend only on the retina and the eye's
   state, not on the scene, so they are cached.
2. ``render_onv_kernel``: one thread per (batch element, photoreceptor) moves its 3 S rays into the world
   with that batch element's eye pose, finds the closest hit over every object's ``wp.Mesh`` BVH (each
   object in its own frame, per-batch rigid transforms), shades it (Phong with shadow rays, point lights
   and ambient) and follows mirror reflections to ``max_depth`` bounces.

A pinhole camera (``camera_kernel``) shares the scene tracing for third-person images; ``closest_hit``
exposes bare closest-hit queries (tests, benchmarks). ``raytrace_ref.py`` is the numpy reference.

Shapes and units: eye poses are world-from-eye rigid transforms in metres (eye frame of DESIGN.md); the
ONV is ``[B, 3P]`` float32, element ``3p + c`` = channel c of photoreceptor p, linear irradiance.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from warp_vision.eye.optics import CHANNEL_WAVELENGTHS_NM, EYE_CENTRE_MM, NavarroEye
from warp_vision.kernels import launch as _launch

wp.set_module_options({"enable_backward": False})

#: Offset (m) along the normal for secondary rays, so they do not hit the surface they leave.
RAY_EPSILON_M = wp.constant(1e-5)
#: Object flags
FLAG_VERTEX_COLORS = wp.constant(1)
FLAG_SMOOTH = wp.constant(2)
#: Newton iterations of the ray aiming through the lens (quadratic convergence: 6 is plenty in float32)
AIM_ITERATIONS = wp.constant(6)
#: Central-difference step (mm) for the aiming Jacobian
AIM_STEP_MM = wp.constant(0.01)
#: A ray is valid if aiming lands within this distance (mm) of its pupil point
AIM_TOLERANCE_MM = wp.constant(1e-3)
_EYE_CENTRE_MM = wp.constant(EYE_CENTRE_MM)


# --------------------------------------------------------------------------------------------------
# The eye: conic surfaces, Snell, aiming through the lens
# --------------------------------------------------------------------------------------------------


@wp.func
def conic_hit(o: wp.vec3, d: wp.vec3, z0: float, R: float, Q: float, semi: float):
    """Closest forward hit of o + t d with the vertex sheet of a conicoid; returns (ok, t, unit normal)."""
    k = 1.0 + Q
    oz = o[2] - z0
    a = d[0] * d[0] + d[1] * d[1] + k * d[2] * d[2]
    b = 2.0 * (o[0] * d[0] + o[1] * d[1] + k * oz * d[2] - R * d[2])
    c = o[0] * o[0] + o[1] * o[1] + k * oz * oz - 2.0 * R * oz
    disc = b * b - 4.0 * a * c
    best = float(1.0e30)
    if disc >= 0.0:
        sq = wp.sqrt(disc)
        sgn = float(1.0)
        if b < 0.0:
            sgn = -1.0
        q = -0.5 * (b + sgn * sq)  # stable roots: q / a and c / q
        for i in range(2):
            t = float(1.0e30)
            if i == 0:
                if a != 0.0:
                    t = q / a
            else:
                if q != 0.0:
                    t = c / q
            if t > 1.0e-5 and t < best:
                px = o[0] + t * d[0]
                py = o[1] + t * d[1]
                ps = o[2] + t * d[2] - z0
                if (k * ps - R) * R < 0.0 and px * px + py * py <= semi * semi:
                    best = t
    ok = best < 1.0e29
    t = float(0.0)
    if ok:
        t = best
    p = o + t * d
    n = wp.normalize(wp.vec3(-p[0], -p[1], R - k * (p[2] - z0)))
    return ok, t, n


@wp.func
def refract_dir(d: wp.vec3, n: wp.vec3, eta: float):
    """Vector Snell (eta = n1 / n2); returns (ok, refracted unit direction); ok is False on TIR."""
    cos_i = -wp.dot(d, n)
    nn = n
    if cos_i < 0.0:
        nn = -n
        cos_i = -cos_i
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    out = d
    ok = k >= 0.0
    if ok:
        out = wp.normalize(eta * d + (eta * cos_i - wp.sqrt(k)) * nn)
    return ok, out


@wp.func
def through_surface(
    o: wp.vec3, d: wp.vec3, surf: wp.array3d(dtype=float), c: int, j: int, backwards: int
):
    """Hit surface j of channel c and refract (front->back medium, or back->front if ``backwards``)."""
    ok, t, n = conic_hit(o, d, surf[c, j, 0], surf[c, j, 1], surf[c, j, 2], surf[c, j, 5])
    p = o + t * d
    eta = surf[c, j, 3] / surf[c, j, 4]
    if backwards != 0:
        eta = surf[c, j, 4] / surf[c, j, 3]
    ok2, d2 = refract_dir(d, n, eta)
    return ok and ok2, p, d2


@wp.func
def retina_to_stop(q: wp.vec3, aim: wp.vec2, surf: wp.array3d(dtype=float), c: int, pupil_z: float):
    """From retina point q toward ``aim`` on the lens-back vertex plane, out through the lens to the stop.

    Returns (ok, point on the stop plane, direction in the aqueous).
    """
    d = wp.normalize(wp.vec3(aim[0], aim[1], surf[c, 3, 0]) - q)
    ok1, p1, d1 = through_surface(q, d, surf, c, 3, 1)
    ok2, p2, d2 = through_surface(p1, d1, surf, c, 2, 1)
    ok = ok1 and ok2 and d2[2] < 0.0
    t = float(0.0)
    if ok:
        t = (pupil_z - p2[2]) / d2[2]
    return ok, p2 + t * d2, d2


@wp.kernel
def eye_rays_kernel(
    retina_mm: wp.array(dtype=wp.vec3),
    pupil_xy_mm: wp.array(dtype=wp.vec2),
    surf: wp.array3d(dtype=float),
    pupil_z: float,
    pupil_r: float,
    weight_scale: float,
    S: int,
    offset: int,
    origin_out: wp.array(dtype=wp.vec3),
    dir_out: wp.array(dtype=wp.vec3),
    weight_out: wp.array(dtype=float),
):
    """Ray k = (p * 3 + c) * S + s: photoreceptor p, channel c, pupil sample s -> eye-frame ray and weight.

    surf[c, j, :] = (z0, R, Q, n_front, n_back, semi_diameter) of surface j (cornea front, cornea back,
    lens front, lens back) at channel c's wavelength, mm; weight_scale = pupil area / S (mm^2).
    """
    k = offset + wp.tid()
    p = k / (3 * S)
    c = (k / S) % 3
    q = retina_mm[p]
    target = pupil_xy_mm[p * S + k % S]
    z_aim = surf[c, 3, 0]
    f = (z_aim - q[2]) / (pupil_z - q[2])
    aim = wp.vec2(q[0] + (target[0] - q[0]) * f, q[1] + (target[1] - q[1]) * f)
    h = AIM_STEP_MM
    ok = bool(True)
    j00 = float(1.0)
    j01 = float(0.0)
    j10 = float(0.0)
    j11 = float(1.0)
    for it in range(AIM_ITERATIONS + 1):
        ok0, s0, d0 = retina_to_stop(q, aim, surf, c, pupil_z)
        okx1, sx1, dx1 = retina_to_stop(q, aim + wp.vec2(h, 0.0), surf, c, pupil_z)
        okx0, sx0, dx0 = retina_to_stop(q, aim - wp.vec2(h, 0.0), surf, c, pupil_z)
        oky1, sy1, dy1 = retina_to_stop(q, aim + wp.vec2(0.0, h), surf, c, pupil_z)
        oky0, sy0, dy0 = retina_to_stop(q, aim - wp.vec2(0.0, h), surf, c, pupil_z)
        ok = ok0 and okx1 and okx0 and oky1 and oky0
        if not ok:
            break
        j00 = (sx1[0] - sx0[0]) / (2.0 * h)
        j10 = (sx1[1] - sx0[1]) / (2.0 * h)
        j01 = (sy1[0] - sy0[0]) / (2.0 * h)
        j11 = (sy1[1] - sy0[1]) / (2.0 * h)
        if it == AIM_ITERATIONS:
            break  # the last pass only refreshes the Jacobian at the converged aim
        ex = s0[0] - target[0]
        ey = s0[1] - target[1]
        det = j00 * j11 - j01 * j10
        if det == 0.0:
            ok = False
            break
        aim = aim - wp.vec2((j11 * ex - j01 * ey) / det, (-j10 * ex + j00 * ey) / det)
    w = float(0.0)
    o = wp.vec3(0.0)
    dout = wp.vec3(0.0, 0.0, 1.0)
    if ok:
        okf, sp, dd = retina_to_stop(q, aim, surf, c, pupil_z)
        miss = wp.length(wp.vec2(sp[0] - target[0], sp[1] - target[1]))
        inside = target[0] * target[0] + target[1] * target[1] <= pupil_r * pupil_r
        ok1, p1, d1 = through_surface(sp, dd, surf, c, 1, 1)
        ok2, p2, d2 = through_surface(p1, d1, surf, c, 0, 1)
        if okf and ok1 and ok2 and inside and miss < AIM_TOLERANCE_MM:
            v = wp.vec3(aim[0], aim[1], z_aim) - q
            dist = wp.length(v)
            u = v / dist
            n_in = wp.normalize(wp.vec3(0.0, 0.0, _EYE_CENTRE_MM) - q)
            nv = surf[c, 3, 4]
            det = wp.abs(j00 * j11 - j01 * j10)
            w = weight_scale * nv * nv * wp.abs(wp.dot(u, n_in)) * wp.abs(u[2]) / (dist * dist * det)
            # optical frame (mm, +z into the eye) -> eye frame (m, +z out of the pupil)
            o = wp.vec3(-p2[0] * 0.001, p2[1] * 0.001, (_EYE_CENTRE_MM - p2[2]) * 0.001)
            dout = wp.vec3(-d2[0], d2[1], -d2[2])
    origin_out[k] = o
    dir_out[k] = dout
    weight_out[k] = w


# --------------------------------------------------------------------------------------------------
# The scene: closest hit over objects, shadows, Phong, reflections
# --------------------------------------------------------------------------------------------------


@wp.struct
class SceneData:
    """A scene for the kernels. An *instance* is one BVH with one transform per batch element: either one
    dynamic object, or all static objects merged in the world frame. Materials belong to objects; each
    face knows its object."""

    mesh_ids: wp.array(dtype=wp.uint64)  # [n_inst]
    faces: wp.array(dtype=wp.vec3i)  # all instances' triangles (instance-local vertex indices)
    face_offset: wp.array(dtype=int)  # [n_inst]
    face_object: wp.array(dtype=int)  # [n_faces] the object (material) of each face
    face_local: wp.array(dtype=int)  # [n_faces] the face's index within its object's mesh
    normals: wp.array(dtype=wp.vec3)  # per-vertex normals (instance frame), all instances
    colors: wp.array(dtype=wp.vec3)  # per-vertex albedo, all instances
    vert_offset: wp.array(dtype=int)  # [n_inst]
    bound_centre: wp.array(dtype=wp.vec3)  # instance-frame bounding sphere
    bound_radius: wp.array(dtype=float)
    diffuse: wp.array(dtype=wp.vec3)  # [n_obj] materials
    specular: wp.array(dtype=float)
    shininess: wp.array(dtype=float)
    reflectivity: wp.array(dtype=float)
    flags: wp.array(dtype=int)
    world_from_inst: wp.array2d(dtype=wp.transform)  # [B or 1, n_inst]
    inst_from_world: wp.array2d(dtype=wp.transform)
    light_pos: wp.array2d(dtype=wp.vec3)  # [B or 1, n_lights], m
    light_rad: wp.array2d(dtype=wp.vec3)  # colour * intensity
    ambient: wp.vec3
    background: wp.vec3
    max_depth: int


@wp.func
def scene_closest_hit(sc: SceneData, b: int, o: wp.vec3, d: wp.vec3, t_max: float):
    """Closest hit over all instances; returns (instance or -1, t, face, u, v, face normal in its frame)."""
    bt = b
    if sc.world_from_inst.shape[0] == 1:
        bt = 0
    best_obj = int(-1)
    best_t = t_max
    best_face = int(-1)
    best_u = float(0.0)
    best_v = float(0.0)
    best_n = wp.vec3(0.0, 0.0, 1.0)
    for i in range(sc.mesh_ids.shape[0]):
        X = sc.inst_from_world[bt, i]
        ol = wp.transform_point(X, o)
        dl = wp.transform_vector(X, d)
        # bounding-sphere rejection
        oc = ol - sc.bound_centre[i]
        r = sc.bound_radius[i]
        bb = wp.dot(oc, dl)
        cc = wp.dot(oc, oc) - r * r
        disc = bb * bb - cc
        if disc < 0.0:
            continue
        sq = wp.sqrt(disc)
        if -bb + sq < 0.0 or -bb - sq > best_t:
            continue
        qr = wp.mesh_query_ray(sc.mesh_ids[i], ol, dl, best_t)
        if qr.result:
            best_obj = i
            best_t = qr.t
            best_face = qr.face
            best_u = qr.u
            best_v = qr.v
            best_n = qr.normal
    return best_obj, best_t, best_face, best_u, best_v, best_n


@wp.func
def scene_occluded(sc: SceneData, bt: int, o: wp.vec3, d: wp.vec3, t_max: float):
    """True if anything lies on o + t d for 0 < t < t_max."""
    hit = bool(False)
    for i in range(sc.mesh_ids.shape[0]):
        X = sc.inst_from_world[bt, i]
        ol = wp.transform_point(X, o)
        dl = wp.transform_vector(X, d)
        oc = ol - sc.bound_centre[i]
        r = sc.bound_radius[i]
        bb = wp.dot(oc, dl)
        cc = wp.dot(oc, oc) - r * r
        disc = bb * bb - cc
        if disc < 0.0:
            continue
        sq = wp.sqrt(disc)
        if -bb + sq < 0.0 or -bb - sq > t_max:
            continue
        if wp.mesh_query_ray_anyhit(sc.mesh_ids[i], ol, dl, t_max):
            hit = True
            break
    return hit


@wp.func
def scene_radiance(sc: SceneData, b: int, o_in: wp.vec3, d_in: wp.vec3):
    """RGB radiance arriving along the ray o + t d (world frame, d unit) from batch element b's scene."""
    bt = b
    if sc.world_from_inst.shape[0] == 1:
        bt = 0
    bl = b
    if sc.light_pos.shape[0] == 1:
        bl = 0
    o = o_in
    d = d_in
    result = wp.vec3(0.0)
    throughput = wp.vec3(1.0)
    for depth in range(sc.max_depth + 1):
        inst, t, face, u, v, n_face = scene_closest_hit(sc, b, o, d, 1.0e30)
        if inst < 0:
            result = result + wp.cw_mul(throughput, sc.background)
            break
        X = sc.world_from_inst[bt, inst]
        p = o + t * d
        f = sc.face_offset[inst] + face
        tri = sc.faces[f]
        obj = sc.face_object[f]
        vo = sc.vert_offset[inst]
        flags = sc.flags[obj]
        n_l = n_face
        if (flags & FLAG_SMOOTH) != 0:
            n_l = wp.normalize(
                u * sc.normals[vo + tri[0]] + v * sc.normals[vo + tri[1]] + (1.0 - u - v) * sc.normals[vo + tri[2]]
            )
        n = wp.transform_vector(X, n_l)
        if wp.dot(n, d) > 0.0:
            n = -n
        base = sc.diffuse[obj]
        if (flags & FLAG_VERTEX_COLORS) != 0:
            base = u * sc.colors[vo + tri[0]] + v * sc.colors[vo + tri[1]] + (1.0 - u - v) * sc.colors[vo + tri[2]]
        local = wp.cw_mul(sc.ambient, base)
        ks = sc.specular[obj]
        shin = sc.shininess[obj]
        p_off = p + RAY_EPSILON_M * n
        for li in range(sc.light_pos.shape[1]):
            lv = sc.light_pos[bl, li] - p_off
            dist = wp.length(lv)
            l = lv / dist
            ndl = wp.dot(n, l)
            if ndl <= 0.0:
                continue
            if scene_occluded(sc, bt, p_off, l, dist):
                continue
            E = sc.light_rad[bl, li] / (dist * dist)
            shade = base * (ndl / wp.pi)
            if ks > 0.0:
                r = 2.0 * ndl * n - l
                rv = wp.max(-wp.dot(r, d), 0.0)
                shade = shade + wp.vec3(ks * wp.pow(rv, shin) / wp.pi)
            local = local + wp.cw_mul(E, shade)
        refl = sc.reflectivity[obj]
        result = result + wp.cw_mul(throughput, local) * (1.0 - refl)
        if refl <= 0.0:
            break
        throughput = throughput * refl
        d = d - 2.0 * wp.dot(d, n) * n
        o = p_off
    return result


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
    """Thread (b, p): onv_out[b, 3p + c] = sum_s weight * radiance_c of photoreceptor p's rays."""
    k = offset + wp.tid()
    b = k / P
    p = k - b * P
    T = world_from_eye[b]
    for c in range(3):
        acc = float(0.0)
        for s in range(S):
            r = (p * 3 + c) * S + s
            w = ray_weight[r]
            if w == 0.0:
                continue
            o = wp.transform_point(T, ray_origin[r])
            d = wp.transform_vector(T, ray_dir[r])
            L = scene_radiance(sc, b, o, d)
            acc = acc + w * L[c]
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
    """Pinhole camera (looks along its -z, +y up, +x right; vertical field of view), one pixel a thread."""
    k = offset + wp.tid()
    y = k / width
    x = k - y * width
    aspect = float(width) / float(height)
    px = (2.0 * (float(x) + 0.5) / float(width) - 1.0) * tan_half_fov * aspect
    py = (1.0 - 2.0 * (float(y) + 0.5) / float(height)) * tan_half_fov
    o = wp.transform_point(world_from_camera, wp.vec3(0.0))
    d = wp.normalize(wp.transform_vector(world_from_camera, wp.vec3(px, py, -1.0)))
    L = scene_radiance(sc, b, o, d)
    image_out[y, x, 0] = L[0]
    image_out[y, x, 1] = L[1]
    image_out[y, x, 2] = L[2]


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
    """Bare closest-hit queries: t (inf on a miss), object index and its face (-1 on a miss)."""
    k = offset + wp.tid()
    inst, t, face, u, v, n = scene_closest_hit(sc, b, origins[k], wp.normalize(dirs[k]), 1.0e30)
    obj = int(-1)
    if inst < 0:
        t = wp.inf
        face = -1
    else:
        f = sc.face_offset[inst] + face
        obj = sc.face_object[f]
        face = sc.face_local[f]
    t_out[k] = t
    obj_out[k] = obj
    face_out[k] = face


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
        self.meshes = []
        faces, f_obj, f_loc, normals, colors, f_off, v_off, centres, radii = [], [], [], [], [], [], [], [], []
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
            self.meshes.append(
                wp.Mesh(points=wp.array(V, dtype=wp.vec3, device=device), indices=wp.array(F.ravel(), dtype=wp.int32, device=device))
            )
            faces.append(F)
            normals.append(np.concatenate(Ns))
            colors.append(np.concatenate(Cs))
            f_off.append(nf)
            v_off.append(nv)
            nf += len(F)
            nv += len(V)
            c = 0.5 * (V.min(axis=0) + V.max(axis=0))
            centres.append(c)
            radii.append(float(np.linalg.norm(V - c, axis=1).max()) * 1.0001 + 1e-6)
        self.groups = groups
        mats = [o.material for o in scene.objects]
        arr = lambda x, dt: wp.array(np.ascontiguousarray(x), dtype=dt, device=device)  # noqa: E731
        self.mesh_ids = arr(np.array([m.id for m in self.meshes], dtype=np.uint64), wp.uint64)
        self.faces = arr(np.concatenate(faces), wp.vec3i)
        self.face_offset = arr(np.array(f_off, np.int32), wp.int32)
        self.face_object = arr(np.concatenate(f_obj), wp.int32)
        self.face_local = arr(np.concatenate(f_loc), wp.int32)
        self.normals = arr(np.concatenate(normals).astype(np.float32), wp.vec3)
        self.colors = arr(np.concatenate(colors).astype(np.float32), wp.vec3)
        self.vert_offset = arr(np.array(v_off, np.int32), wp.int32)
        self.bound_centre = arr(np.array(centres, np.float32), wp.vec3)
        self.bound_radius = arr(np.array(radii, np.float32), wp.float32)
        self.diffuse = arr(np.array([m.diffuse for m in mats], np.float32), wp.vec3)
        self.specular = arr(np.array([m.specular for m in mats], np.float32), wp.float32)
        self.shininess = arr(np.array([m.shininess for m in mats], np.float32), wp.float32)
        self.reflectivity = arr(np.array([m.reflectivity for m in mats], np.float32), wp.float32)
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
    sc = SceneData()
    for name in (
        "mesh_ids faces face_offset face_object face_local normals colors vert_offset bound_centre bound_radius "
        "diffuse specular shininess reflectivity flags"
    ).split():
        setattr(sc, name, getattr(geo, name))
    sc.world_from_inst = wp.array(_transforms_to_wp(T), dtype=wp.transform, device=device)
    sc.inst_from_world = wp.array(_transforms_to_wp(_inverse_rigid(T)), dtype=wp.transform, device=device)
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


def pupil_samples(P: int, S: int, radius_mm: float, seed: int = 0) -> np.ndarray:
    """Stratified points of the pupil disc for each photoreceptor: [P, S, 2] mm.

    The S strata are the cells of an nx x ny grid (nx the largest divisor of S not above sqrt(S)) mapped
    to the disc by Shirley and Chiu's equal-area concentric map; each photoreceptor takes the cells'
    centres, rotated by its own random angle (seeded). S = 1 gives the pupil centre (the chief ray).
    """
    if S < 1:
        raise ValueError(f"samples_per_receptor: expected >= 1, got {S}")
    nx = max(d for d in range(1, int(math.isqrt(S)) + 1) if S % d == 0)
    ny = S // nx
    a = (np.arange(nx) + 0.5) / nx * 2 - 1
    b = (np.arange(ny) + 0.5) / ny * 2 - 1
    A, Bm = np.meshgrid(a, b, indexing="ij")
    A, Bm = A.ravel(), Bm.ravel()
    with np.errstate(divide="ignore", invalid="ignore"):
        use_a = np.abs(A) > np.abs(Bm)
        r = np.where(use_a, A, Bm)
        phi = np.where(use_a, (np.pi / 4) * Bm / A, np.pi / 2 - (np.pi / 4) * A / Bm)
    phi = np.where(r == 0, 0.0, phi)
    rot = np.random.default_rng(seed).uniform(0, 2 * np.pi, size=(P, 1))
    ang = phi[None, :] + rot
    xy = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=-1) * radius_mm
    return xy


@dataclass
class EyeRays:
    """Eye-frame rays of a retina seen through one eye state: each [P * 3 * S], ray k = (p * 3 + c) * S + s."""

    origins: wp.array  # vec3, m, on the cornea
    directions: wp.array  # vec3, unit, out of the eye
    weights: wp.array  # float, sr (irradiance per unit radiance)
    P: int
    S: int


_eye_cache: OrderedDict = OrderedDict()
_eye_cache_lock = threading.Lock()
_EYE_CACHE_SIZE = 8


def _retina_positions(retina) -> np.ndarray:
    pos = getattr(retina, "positions_optical_mm", retina)
    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or len(pos) == 0:
        raise ValueError(f"retina: expected photoreceptor positions [P, 3] mm (optical frame), got shape {pos.shape}")
    if not np.all(np.isfinite(pos)):
        raise ValueError("retina: photoreceptor positions must be finite")
    return pos


def surface_table(eye: NavarroEye) -> np.ndarray:
    """[3, 4, 6] float32: per RGB channel and surface, (z0, R, Q, n_front, n_back, semi_diameter)."""
    return np.array(
        [[[s.z0, s.R, s.Q, s.n_front, s.n_back, s.semi_diameter] for s in eye.surfaces(wl)] for wl in CHANNEL_WAVELENGTHS_NM],
        dtype=np.float32,
    )


def eye_rays(retina, eye: NavarroEye, samples_per_receptor: int = 16, seed: int = 0, device: str = "cpu") -> EyeRays:
    """The rays each photoreceptor casts into the world through ``eye`` (cached; see the module doc)."""
    _launch.init()
    pos = _retina_positions(retina)
    S = int(samples_per_receptor)
    key = (
        hash(pos.tobytes()),
        pos.shape,
        eye.accommodation_D,
        eye.pupil_diameter_mm,
        eye.cornea_semi_diameter_mm,
        eye.lens_semi_diameter_mm,
        S,
        seed,
        device,
    )
    with _eye_cache_lock:
        hit = _eye_cache.get(key)
        if hit is not None:
            _eye_cache.move_to_end(key)
            return hit
    P = len(pos)
    pxy = pupil_samples(P, S, eye.pupil_radius_mm, seed).reshape(-1, 2)
    n = P * 3 * S
    out = EyeRays(
        wp.empty(n, dtype=wp.vec3, device=device),
        wp.empty(n, dtype=wp.vec3, device=device),
        wp.empty(n, dtype=wp.float32, device=device),
        P,
        S,
    )
    _launch.launch_split(
        eye_rays_kernel,
        n,
        inputs=[
            wp.array(pos.astype(np.float32), dtype=wp.vec3, device=device),
            wp.array(pxy.astype(np.float32), dtype=wp.vec2, device=device),
            wp.array(surface_table(eye), dtype=wp.float32, device=device),
            float(eye.pupil_z_mm),
            float(eye.pupil_radius_mm),
            float(eye.pupil_area_mm2 / S),
            S,
        ],
        outputs=[out.origins, out.directions, out.weights],
        device=device,
    )
    with _eye_cache_lock:
        _eye_cache[key] = out
        while len(_eye_cache) > _EYE_CACHE_SIZE:
            _eye_cache.popitem(last=False)
    return out


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
        width * height,
        inputs=[sc, wp.transform(tf[:3], tf[3:]), width, height, math.tan(math.radians(fov_deg) / 2), batch],
        outputs=[wp.from_torch(img)],
        device=device,
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
        n,
        inputs=[sc, wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device), batch],
        outputs=[t, obj, face],
        device=device,
        threads=threads,
    )
    return t.numpy(), obj.numpy(), face.numpy()
