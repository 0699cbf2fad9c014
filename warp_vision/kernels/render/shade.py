"""The ONV renderer's device side: what a packet of 8 world rays sees, and the render kernels, in Warp.

:func:`packet_radiance` follows a packet through the scene of a :class:`SceneData`: closest hits over
every instance's BVH (:mod:`warp_vision.kernels.render.packet`), Phong local illumination with one
shadow packet per point light plus ambient light and emission, and mirror reflections followed to
``max_depth`` bounces. Its steps are the ``_hit_surfaces``, ``_direct_light``, ``_add_surface_light`` and
``_mirror`` functions below, each a loop over the 8 lanes.

What may differ per batch element b has one row per element, or a single row shared by the batch, and
``packet_radiance`` picks the row (0 for a shared one): instance transforms and visibility (``bt``),
lights (``bl``), materials (``bm``: diffuse, specular, shininess, reflectivity, emission, ``[1 or B,
n_obj]``; the smooth / vertex-colour flags are per object) and ambient light (``ba``, ``[1 or B]``).

The kernels launch one thread per group of G photoreceptors (``render_onv_kernel``: their rays, 8 at a
time in full packets, summed by their weights into the ONV; G = 2 at S = 4), per 4 x 2 pixel tile (``camera_kernel``) or
per 8 rays (``radiance_kernel``, ``closest_hit_kernel``). Every thread writes only its own outputs, so there are
no atomics and CPU launches split over threads give bit-identical results. The host side (scene
upload, argument checks, launches) is :mod:`warp_vision.kernels.render.scene_data` and
:mod:`warp_vision.kernels.render.trace`.
"""

from __future__ import annotations

import math

import warp as wp

from warp_vision.kernels.render.packet import (
    DEAD,
    FAR,
    BvhData,
    all_negative,
    barycentric,
    batch_row,
    ivec8,
    packet_closest,
    packet_occluded,
    vec8,
)

# Per-lane shading loops stay loops (unrolling 8 copies of the shading code only bloats the build).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

#: Offset (m) along the normal for secondary rays, so they do not hit the surface they leave.
RAY_EPSILON_M = wp.constant(1e-5)
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
    diffuse: wp.array2d(dtype=wp.vec3)  # [B or 1, n_obj] materials (a row per batch element, or shared)
    specular: wp.array2d(dtype=float)
    shininess: wp.array2d(dtype=float)
    reflectivity: wp.array2d(dtype=float)
    emission: wp.array2d(dtype=wp.vec3)  # [B or 1, n_obj] emitted radiance
    flags: wp.array(dtype=int)  # [n_obj] FLAG_SMOOTH | FLAG_VERTEX_COLORS (per object, whatever the batch)
    light_pos: wp.array2d(dtype=wp.vec3)  # [B or 1, n_lights], m
    light_rad: wp.array2d(dtype=wp.vec3)  # colour * intensity
    ambient: wp.array(dtype=wp.vec3)  # [B or 1] RGB ambient irradiance
    background: wp.vec3
    max_depth: int


# --------------------------------------------------------------------------------------------------
# packet_radiance and its steps


@wp.func
def _interpolated(sc: SceneData, bt: int, inst: int, k: int, f: int, flags: int, o: wp.vec3, d: wp.vec3,
                  n_i: wp.vec3, base: wp.vec3):
    """The smooth normal and/or vertex colour at ray o + t d's hit on triangle k (face f of instance
    ``inst``), as ``flags`` ask; else the flat normal ``n_i`` and material colour ``base``."""
    Xi = sc.bv.inst_from_world[bt, inst]
    u, v = barycentric(sc.bv, k, wp.transform_point(Xi, o), wp.transform_vector(Xi, d))
    w2 = 1.0 - u - v
    tv = sc.faces[f]
    vo = sc.vert_offset[inst]
    n_out = n_i
    base_out = base
    if (flags & FLAG_SMOOTH) != 0:
        n_out = wp.normalize(u * sc.normals[vo + tv[0]] + v * sc.normals[vo + tv[1]] + w2 * sc.normals[vo + tv[2]])
    if (flags & FLAG_VERTEX_COLORS) != 0:
        base_out = u * sc.colors[vo + tv[0]] + v * sc.colors[vo + tv[1]] + w2 * sc.colors[vo + tv[2]]
    return n_out, base_out


@wp.func
def _lane_surface(sc: SceneData, bt: int, bm: int, k: int, o: wp.vec3, d: wp.vec3, t: float):
    """The surface that ray o + t d hits on global triangle k: (point offset off the surface, world
    normal facing the ray, albedo, object)."""
    inst = sc.bv.tri_inst[k]
    X = sc.bv.world_from_inst[bt, inst]
    f = sc.face_offset[inst] + sc.bv.tri_face[k]
    obj = sc.face_object[f]
    flags = sc.flags[obj]
    n_i = wp.normalize(wp.cross(sc.bv.tri_e1[k], sc.bv.tri_e2[k]))
    base = sc.diffuse[bm, obj]
    if flags != 0:
        n_i, base = _interpolated(sc, bt, inst, k, f, flags, o, d, n_i, base)
    n = wp.transform_vector(X, n_i)
    if wp.dot(n, d) > 0.0:
        n = -n
    p = o + t * d + RAY_EPSILON_M * n
    return p, n, base, obj


@wp.func
def _add_background(sc: SceneData, lim: vec8, tri: ivec8, thr: vec8, thg: vec8, thb: vec8, R: vec8, G: vec8,
                    Bc: vec8):
    """Adds the background, weighted by the lanes' throughputs, to the live lanes that hit nothing."""
    for l in range(8):
        if lim[l] < 0.0:
            continue
        if tri[l] < 0:
            R[l] = R[l] + thr[l] * sc.background[0]
            G[l] = G[l] + thg[l] * sc.background[1]
            Bc[l] = Bc[l] + thb[l] * sc.background[2]
    return R, G, Bc


@wp.func
def _hit_surfaces(sc: SceneData, bt: int, bm: int, ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8,
                  lim: vec8, t: vec8, tri: ivec8):
    """Per lane, the surface the closest hit (t, tri) lies on: offset point (px, py, pz), facing normal
    (nx, ny, nz), albedo (cr, cg, cb) and object (``obj``: -1 for a lane that is dead or hit nothing)."""
    px = vec8()
    py = vec8()
    pz = vec8()
    nx = vec8()
    ny = vec8()
    nz = vec8()
    cr = vec8()
    cg = vec8()
    cb = vec8()
    obj = ivec8()
    for l in range(8):
        obj[l] = -1
        if lim[l] < 0.0 or tri[l] < 0:
            continue
        p, n, base, ob = _lane_surface(sc, bt, bm, tri[l], wp.vec3(ox[l], oy[l], oz[l]), wp.vec3(dx[l], dy[l], dz[l]),
                                       t[l])
        px[l] = p[0]
        py[l] = p[1]
        pz[l] = p[2]
        nx[l] = n[0]
        ny[l] = n[1]
        nz[l] = n[2]
        cr[l] = base[0]
        cg[l] = base[1]
        cb[l] = base[2]
        obj[l] = ob
    return px, py, pz, nx, ny, nz, cr, cg, cb, obj


@wp.func
def _shadow_packet(lpos: wp.vec3, px: vec8, py: vec8, pz: vec8, nx: vec8, ny: vec8, nz: vec8, obj: ivec8):
    """Shadow rays from the lanes' surface points toward a light at ``lpos``: unit directions and, as
    the limit, the distance to the light; dead (DEAD) for lanes without a surface or facing away."""
    sx = vec8()
    sy = vec8()
    sz = vec8()
    slim = vec8(DEAD)
    for l in range(8):
        if obj[l] < 0:
            continue
        lv = lpos - wp.vec3(px[l], py[l], pz[l])
        dist = wp.length(lv)
        ld = lv / dist
        if wp.dot(wp.vec3(nx[l], ny[l], nz[l]), ld) > 0.0:
            sx[l] = ld[0]
            sy[l] = ld[1]
            sz[l] = ld[2]
            slim[l] = dist
    return sx, sy, sz, slim


@wp.func
def _phong(n: wp.vec3, ld: wp.vec3, d: wp.vec3, dist: float, E0: wp.vec3, base: wp.vec3, ks: float, shin: float):
    """Radiance toward -d from a light of radiant intensity E0 at distance ``dist`` in direction ``ld``:
    Lambert plus a Phong highlight (when ``ks`` > 0), per channel."""
    ndl = wp.dot(n, ld)
    E = E0 / (dist * dist)
    shade = base * (ndl / wp.pi)
    if ks > 0.0:
        rr = 2.0 * ndl * n - ld
        rv = wp.max(-wp.dot(rr, d), 0.0)
        shade = shade + wp.vec3(ks * wp.pow(rv, shin) / wp.pi)
    return wp.cw_mul(E, shade)


@wp.func
def _direct_light(sc: SceneData, b: int, bl: int, bm: int, ba: int, px: vec8, py: vec8, pz: vec8, nx: vec8, ny: vec8,
                  nz: vec8, cr: vec8, cg: vec8, cb: vec8, obj: ivec8, dx: vec8, dy: vec8, dz: vec8):
    """Radiance (lr, lg, lb) leaving each lane's surface toward its ray: ambient light and emission,
    plus every point light that a shadow packet finds unoccluded."""
    lr = vec8()
    lg = vec8()
    lb = vec8()
    amb = sc.ambient[ba]
    for l in range(8):
        if obj[l] < 0:
            continue
        em = sc.emission[bm, obj[l]]
        lr[l] = amb[0] * cr[l] + em[0]
        lg[l] = amb[1] * cg[l] + em[1]
        lb[l] = amb[2] * cb[l] + em[2]
    for li in range(sc.light_pos.shape[1]):
        sx, sy, sz, slim = _shadow_packet(sc.light_pos[bl, li], px, py, pz, nx, ny, nz, obj)
        if all_negative(slim):
            continue
        vis = packet_occluded(sc.bv, b, px, py, pz, sx, sy, sz, slim)
        E0 = sc.light_rad[bl, li]
        for l in range(8):
            if slim[l] < 0.0 or vis[l] < 0.0:
                continue
            c = _phong(wp.vec3(nx[l], ny[l], nz[l]), wp.vec3(sx[l], sy[l], sz[l]), wp.vec3(dx[l], dy[l], dz[l]),
                       slim[l], E0, wp.vec3(cr[l], cg[l], cb[l]), sc.specular[bm, obj[l]], sc.shininess[bm, obj[l]])
            lr[l] = lr[l] + c[0]
            lg[l] = lg[l] + c[1]
            lb[l] = lb[l] + c[2]
    return lr, lg, lb


@wp.func
def _add_surface_light(sc: SceneData, bm: int, obj: ivec8, lr: vec8, lg: vec8, lb: vec8, thr: vec8, thg: vec8,
                       thb: vec8, R: vec8, G: vec8, Bc: vec8):
    """Adds each lane's surface radiance, less the share its mirror reflects, weighted by its throughput."""
    for l in range(8):
        if obj[l] < 0:
            continue
        keep = 1.0 - sc.reflectivity[bm, obj[l]]
        R[l] = R[l] + thr[l] * lr[l] * keep
        G[l] = G[l] + thg[l] * lg[l] * keep
        Bc[l] = Bc[l] + thb[l] * lb[l] * keep
    return R, G, Bc


@wp.func
def _mirror(sc: SceneData, bm: int, obj: ivec8, px: vec8, py: vec8, pz: vec8, nx: vec8, ny: vec8, nz: vec8,
            ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8, thr: vec8, thg: vec8, thb: vec8):
    """The next bounce: lanes on a reflective surface continue as the mirrored ray from their surface
    point, their throughput scaled by the reflectivity; the others keep their rays and die
    (``nxt``: FAR for a continuing lane, DEAD for the rest)."""
    nxt = vec8(DEAD)
    for l in range(8):
        if obj[l] < 0:
            continue
        refl = sc.reflectivity[bm, obj[l]]
        if refl > 0.0:
            thr[l] = thr[l] * refl
            thg[l] = thg[l] * refl
            thb[l] = thb[l] * refl
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
    return ox, oy, oz, dx, dy, dz, thr, thg, thb, nxt


@wp.func
def packet_radiance(
    sc: SceneData, b: int, ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8, live: vec8
):
    """RGB radiance arriving along a packet of world rays (unit directions) in batch element b's scene.

    ``live``: FAR for a live lane, DEAD for an unused one. Returns (R, G, B) vec8. Each bounce: the
    closest hits, the background for lanes that miss, the surfaces' direct light, then the mirrored
    rays of reflective lanes (until ``sc.max_depth`` bounces or no lane continues).
    """
    # batch rows of the transforms, lights, materials and ambient light (each may be shared: 1 row)
    bt = batch_row(b, sc.bv.world_from_inst.shape[0])
    bl = batch_row(b, sc.light_pos.shape[0])
    bm = batch_row(b, sc.diffuse.shape[0])
    ba = batch_row(b, sc.ambient.shape[0])
    R = vec8()
    G = vec8()
    Bc = vec8()
    thr = vec8(1.0)
    thg = vec8(1.0)
    thb = vec8(1.0)
    lim = live
    for _depth in range(sc.max_depth + 1):
        t, tri = packet_closest(sc.bv, b, ox, oy, oz, dx, dy, dz, lim)
        R, G, Bc = _add_background(sc, lim, tri, thr, thg, thb, R, G, Bc)
        px, py, pz, nx, ny, nz, cr, cg, cb, obj = _hit_surfaces(sc, bt, bm, ox, oy, oz, dx, dy, dz, lim, t, tri)
        lr, lg, lb = _direct_light(sc, b, bl, bm, ba, px, py, pz, nx, ny, nz, cr, cg, cb, obj, dx, dy, dz)
        R, G, Bc = _add_surface_light(sc, bm, obj, lr, lg, lb, thr, thg, thb, R, G, Bc)
        ox, oy, oz, dx, dy, dz, thr, thg, thb, nxt = _mirror(sc, bm, obj, px, py, pz, nx, ny, nz, ox, oy, oz, dx, dy,
                                                             dz, thr, thg, thb)
        if all_negative(nxt):
            break
        lim = nxt
    return R, G, Bc


# --------------------------------------------------------------------------------------------------
# kernels (1D launches; ``offset`` is the first thread of a split launch)


@wp.kernel
def render_onv_kernel(
    sc: SceneData,
    world_from_eye: wp.array(dtype=wp.transform),
    ray_origin: wp.array(dtype=wp.vec3),
    ray_dir: wp.array(dtype=wp.vec3),
    ray_weight: wp.array(dtype=float),
    P: int,
    S: int,
    G: int,
    offset: int,
    onv_out: wp.array2d(dtype=float),
):
    """Thread (b, group): onv_out[b, 3p + c] = sum_s weight * radiance_c over the rays of photoreceptors
    p = group * G ... group * G + G - 1 (clipped to P), traced 8 at a time.

    The group's G * 3 S rays (photoreceptor-major, then channel, then pupil sample, as ``eye_rays``
    stores them) fill packets whole whatever the channel or photoreceptor: G is the smallest count for
    which G * 3 S is a multiple of 8 (:func:`photoreceptors_per_thread`; S = 4 packs 2 photoreceptors'
    24 rays into 3 packets where one packet per channel traced 6 half-empty ones). Photoreceptors are in
    Morton order, so a group's rays are neighbours and its packets stay coherent. A lane adds its
    weighted radiance of its own channel to its photoreceptor's entry; only this thread writes them."""
    k = offset + wp.tid()
    groups = (P + G - 1) / G
    b = k / groups
    p0 = (k - b * groups) * G
    T = world_from_eye[b]
    n = wp.min(G, P - p0) * 3 * S  # this group's rays
    base = p0 * 3 * S
    for j in range((n + 7) / 8):
        ox = vec8()
        oy = vec8()
        oz = vec8()
        dx = vec8()
        dy = vec8()
        dz = vec8()
        w = vec8()
        live = vec8(DEAD)
        for l in range(8):
            q = j * 8 + l
            if q >= n:
                continue
            r = base + q
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
        R, G_, Bc = packet_radiance(sc, b, ox, oy, oz, dx, dy, dz, live)
        for l in range(8):
            if live[l] < 0.0:
                continue
            e = (base + j * 8 + l) / S  # photoreceptor * 3 + channel
            c = e % 3
            v = R[l]
            if c == 1:
                v = G_[l]
            elif c == 2:
                v = Bc[l]
            onv_out[b, e] = onv_out[b, e] + w[l] * v


def photoreceptors_per_thread(S: int) -> int:
    """G, the photoreceptors one render_onv_kernel thread traces: the fewest whose 3 S rays fill packets of 8."""
    return 8 // math.gcd(3 * int(S), 8)


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
