"""Packet ray queries against the BVHs of :mod:`warp_vision.kernels.render.bvh`, in Warp.

A *packet* is 8 rays held as ``vec8`` lanes (origins, directions, per-lane t limits). One traversal
visits a node when any lane's ray enters its box, so coherent rays (a photoreceptor's rays through the
pupil, a pixel tile, shadow rays from neighbouring hit points to one light) share the node visits and
the triangle loads. A lane whose limit ``t < 0`` is dead: it never hits anything.

The per-lane inner loops (ray-box slabs, Moller-Trumbore) are ``wp.func_native`` snippets: plain C++
loops over the 8 lanes that the compiler turns into SIMD code. Written with Warp's vector builtins
they would not vectorise: Warp's vector ``min``/``max`` follow C's NaN-aware ``fmin``/``fmax``. The
snippets are portable C++, so CUDA compiles them too. The reference for every query here is the
brute-force numpy in :mod:`warp_vision.kernels.render.reference`.

Several instances (BVHs, each with a per-batch rigid transform) are queried one after another with
the packet moved into each instance's frame; rigid transforms keep ``t`` in world units.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warp_vision.kernels.render.bvh import BVH

wp.set_module_options({"enable_backward": False})

LANES = 8
vec8 = wp.types.vector(length=8, dtype=wp.float32)
ivec8 = wp.types.vector(length=8, dtype=wp.int32)
#: traversal stack; a SAH tree over 1e7 triangles is far shallower than this
stack64 = wp.types.vector(length=64, dtype=wp.int32)
DEAD = wp.constant(-1.0)
FAR = wp.constant(1.0e30)


@wp.struct
class BvhData:
    """All instances' BVHs concatenated (indices are global) plus their per-batch transforms."""

    node_lo: wp.array(dtype=wp.vec3)
    node_hi: wp.array(dtype=wp.vec3)
    node_left: wp.array(dtype=int)  # left child (global index; right = left + 1), -1 for a leaf
    node_start: wp.array(dtype=int)  # leaf's first triangle (global)
    node_count: wp.array(dtype=int)
    node_axis: wp.array(dtype=int)
    tri_v0: wp.array(dtype=wp.vec3)  # instance frame
    tri_e1: wp.array(dtype=wp.vec3)
    tri_e2: wp.array(dtype=wp.vec3)
    tri_face: wp.array(dtype=int)  # the triangle's face index within its instance's mesh
    tri_inst: wp.array(dtype=int)  # the triangle's instance
    inst_root: wp.array(dtype=int)  # [n_inst] root node
    world_from_inst: wp.array2d(dtype=wp.transform)  # [B or 1, n_inst]
    inst_from_world: wp.array2d(dtype=wp.transform)
    inst_visible: wp.array2d(dtype=int)  # [B or 1, n_inst]: 0 = hidden (skipped)
    inst_world_lo: wp.array2d(dtype=wp.vec3)  # [B or 1, n_inst]: the instance's bounds in the world
    inst_world_hi: wp.array2d(dtype=wp.vec3)  # (rows as world_from_inst)


def concat_bvhs(bvhs: list[BVH]) -> dict:
    """Concatenate per-instance BVHs into the global arrays of :class:`BvhData` (numpy)."""
    out = {k: [] for k in ("node_lo", "node_hi", "node_left", "node_start", "node_count", "node_axis", "tri_v0",
                           "tri_e1", "tri_e2", "tri_face", "tri_inst")}
    roots = []
    n_off = t_off = 0
    for i, b in enumerate(bvhs):
        roots.append(n_off)
        out["node_lo"].append(b.node_lo)
        out["node_hi"].append(b.node_hi)
        out["node_left"].append(np.where(b.node_left >= 0, b.node_left + n_off, -1))
        out["node_start"].append(b.node_start + t_off)
        out["node_count"].append(b.node_count)
        out["node_axis"].append(b.node_axis)
        for k in ("tri_v0", "tri_e1", "tri_e2", "tri_face"):
            out[k].append(getattr(b, k))
        out["tri_inst"].append(np.full(len(b.tri_face), i, dtype=np.int32))
        n_off += b.num_nodes
        t_off += len(b.tri_face)
    res = {k: np.ascontiguousarray(np.concatenate(v)) for k, v in out.items()}
    for k in ("node_left", "node_start", "node_count", "node_axis", "tri_face", "tri_inst"):
        res[k] = res[k].astype(np.int32)
    res["inst_root"] = np.array(roots, dtype=np.int32)
    return res


# --------------------------------------------------------------------------------------------------
# lane loops (native C++; see the module docstring for why)


@wp.func_native(
    """
    int m = 0;
    for (int i = 0; i < 8; ++i) {
        float ax = ix[i] * lo[0] - oix[i], bx = ix[i] * hi[0] - oix[i];
        float ay = iy[i] * lo[1] - oiy[i], by = iy[i] * hi[1] - oiy[i];
        float az = iz[i] * lo[2] - oiz[i], bz = iz[i] * hi[2] - oiz[i];
        float n0 = ax < bx ? ax : bx, f0 = ax < bx ? bx : ax;
        float n1 = ay < by ? ay : by, f1 = ay < by ? by : ay;
        float n2 = az < bz ? az : bz, f2 = az < bz ? bz : az;
        float tn = n0 > n1 ? n0 : n1; tn = tn > n2 ? tn : n2; tn = tn > 0.0f ? tn : 0.0f;
        float tf = f0 < f1 ? f0 : f1; tf = tf < f2 ? tf : f2; tf = tf < tb[i] ? tf : tb[i];
        m |= (tn <= tf);
    }
    return m != 0;
    """
)
def box_hit(ix: vec8, iy: vec8, iz: vec8, oix: vec8, oiy: vec8, oiz: vec8, lo: wp.vec3, hi: wp.vec3, tb: vec8) -> bool:
    """Does any lane's ray enter the box [lo, hi] before its limit tb? (slab test; oi* = o * inv_dir)"""
    ...


@wp.func_native(
    """
    wp::vec_t<8, float> r;
    for (int i = 0; i < 8; ++i) {
        float px = dy[i] * e2[2] - dz[i] * e2[1];
        float py = dz[i] * e2[0] - dx[i] * e2[2];
        float pz = dx[i] * e2[1] - dy[i] * e2[0];
        float det = px * e1[0] + py * e1[1] + pz * e1[2];
        float inv = 1.0f / det;
        float tx = ox[i] - v0[0], ty = oy[i] - v0[1], tz = oz[i] - v0[2];
        float u = (tx * px + ty * py + tz * pz) * inv;
        float qx = ty * e1[2] - tz * e1[1];
        float qy = tz * e1[0] - tx * e1[2];
        float qz = tx * e1[1] - ty * e1[0];
        float v = (dx[i] * qx + dy[i] * qy + dz[i] * qz) * inv;
        float t = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv;
        bool ok = (u >= 0.0f) & (v >= 0.0f) & (u + v <= 1.0f) & (t > 0.0f) & (t < tb[i]);
        r[i] = ok ? t : tb[i];
    }
    return r;
    """
)
def tri_hit(ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8, v0: wp.vec3, e1: wp.vec3, e2: wp.vec3,
            tb: vec8) -> vec8:
    """Per lane: t of a hit with triangle (v0, v0 + e1, v0 + e2) closer than tb, else tb (NaN-safe)."""
    ...


@wp.func_native(
    """
    int m = 0;
    for (int i = 0; i < 8; ++i) m |= (a[i] < b[i]);
    return m != 0;
    """
)
def any_lt(a: vec8, b: vec8) -> bool:
    """Is a[i] < b[i] for some lane?"""
    ...


@wp.func_native(
    """
    int m = 1;
    for (int i = 0; i < 8; ++i) m &= (a[i] < 0.0f);
    return m != 0;
    """
)
def all_negative(a: vec8) -> bool:
    """Is every lane's value negative (every lane dead or finished)?"""
    ...


# --------------------------------------------------------------------------------------------------
# traversal


@wp.func
def safe_inv(x: float):
    y = x
    if wp.abs(y) < 1.0e-20:
        y = 1.0e-20
        if x < 0.0:
            y = -1.0e-20
    return 1.0 / y


@wp.func
def _to_instance(X: wp.transform, ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8):
    lx = vec8()
    ly = vec8()
    lz = vec8()
    mx = vec8()
    my = vec8()
    mz = vec8()
    for l in range(8):
        o = wp.transform_point(X, wp.vec3(ox[l], oy[l], oz[l]))
        d = wp.transform_vector(X, wp.vec3(dx[l], dy[l], dz[l]))
        lx[l] = o[0]
        ly[l] = o[1]
        lz[l] = o[2]
        mx[l] = d[0]
        my[l] = d[1]
        mz[l] = d[2]
    return lx, ly, lz, mx, my, mz


@wp.func
def _inverse_dirs(dx: vec8, dy: vec8, dz: vec8):
    ix = vec8()
    iy = vec8()
    iz = vec8()
    for l in range(8):
        ix[l] = safe_inv(dx[l])
        iy[l] = safe_inv(dy[l])
        iz[l] = safe_inv(dz[l])
    return ix, iy, iz


@wp.func
def _slab_terms(ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8):
    """What :func:`box_hit` takes of a packet: inverse directions and origin * inverse."""
    ix, iy, iz = _inverse_dirs(dx, dy, dz)
    return ix, iy, iz, wp.cw_mul(ox, ix), wp.cw_mul(oy, iy), wp.cw_mul(oz, iz)


@wp.func
def _packet_in_instance(X: wp.transform, ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8):
    """The packet in an instance's frame: origins, directions, inverse directions, origin * inverse."""
    lx, ly, lz, mx, my, mz = _to_instance(X, ox, oy, oz, dx, dy, dz)
    ix, iy, iz, oix, oiy, oiz = _slab_terms(lx, ly, lz, mx, my, mz)
    return lx, ly, lz, mx, my, mz, ix, iy, iz, oix, oiy, oiz


@wp.func
def batch_row(b: int, rows: int):
    """The row of a per-batch table that batch element b reads: b, or 0 for a table of one row shared by
    the whole batch (transforms, visibility, lights, materials, ambient light)."""
    if rows == 1:
        return 0
    return b


@wp.func
def _batch_rows(bv: BvhData, b: int):
    """The rows of the instance transforms and of the visibility that batch element b reads."""
    return batch_row(b, bv.world_from_inst.shape[0]), batch_row(b, bv.inst_visible.shape[0])


@wp.func
def _children_hit(bv: BvhData, c0: int, ix: vec8, iy: vec8, iz: vec8, oix: vec8, oiy: vec8, oiz: vec8, tb: vec8):
    """Whether the packet (inverse directions, origin * inverse) enters each child box (c0, c0 + 1)
    within its current limits ``tb``."""
    h0 = box_hit(ix, iy, iz, oix, oiy, oiz, bv.node_lo[c0], bv.node_hi[c0], tb)
    h1 = box_hit(ix, iy, iz, oix, oiy, oiz, bv.node_lo[c0 + 1], bv.node_hi[c0 + 1], tb)
    return h0, h1


@wp.func
def _packet_traverse(bv: BvhData, b: int, ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8, t_in: vec8,
                     any_hit: bool):
    """The one BVH traversal behind both queries: a packet (world frame, unit directions) against every
    visible instance of batch element b, each lane's hits limited to (0, t_in).

    Closest hit (``any_hit`` False): children are visited near first along the split axis, a lane's
    limit shrinks to each closer hit, and (t, tri) come back: the hit distance, or t_in where nothing is
    closer, and the global triangle index, or -1. Any hit (True, shadow rays): children in stored order,
    a lane that hits anything is set to DEAD, and the traversal stops once every lane is dead; tri is
    left at -1.

    Length: one function over the docs' ~80 lines. It is the renderer's innermost loop, and its steps share
    and mutate the packet's limits ``tb``, its triangles ``tri``, the 64-entry ``stack`` and its pointer.
    Split into Warp functions, those would travel by value (a copy of the stack per call) or as ``wp.ref``
    parameters; either changes the code Warp generates for the loop that ``bench raytrace`` times, so it
    stays whole until a split is timed there. The steps that need none of that state are helpers already
    (``_slab_terms``, ``_packet_in_instance``, ``_children_hit``, ``tri_hit``).
    """
    tb = t_in
    tri = ivec8()
    for l in range(8):
        tri[l] = -1
    stack = stack64()
    bt, bv_ = _batch_rows(bv, b)
    wix, wiy, wiz, woix, woiy, woiz = _slab_terms(ox, oy, oz, dx, dy, dz)  # for the instances' world boxes
    for inst in range(bv.inst_root.shape[0]):
        if any_hit and all_negative(tb):
            break
        if bv.inst_visible[bv_, inst] == 0:
            continue
        # the instance's world box first: most packets pass most instances by, and this costs a slab test
        # where moving the packet into the instance's frame costs 8 transforms and 24 divisions
        if not box_hit(wix, wiy, wiz, woix, woiy, woiz, bv.inst_world_lo[bt, inst], bv.inst_world_hi[bt, inst], tb):
            continue
        lx, ly, lz, mx, my, mz, ix, iy, iz, oix, oiy, oiz = _packet_in_instance(bv.inst_from_world[bt, inst], ox, oy,
                                                                                oz, dx, dy, dz)
        node = bv.inst_root[inst]
        if not box_hit(ix, iy, iz, oix, oiy, oiz, bv.node_lo[node], bv.node_hi[node], tb):
            continue
        sp = int(0)
        done = bool(False)
        while True:
            c0 = bv.node_left[node]
            if c0 < 0:
                start = bv.node_start[node]
                for k in range(start, start + bv.node_count[node]):
                    tc = tri_hit(lx, ly, lz, mx, my, mz, bv.tri_v0[k], bv.tri_e1[k], bv.tri_e2[k], tb)
                    if any_lt(tc, tb):
                        for l in range(8):
                            if tc[l] < tb[l]:
                                if any_hit:
                                    tb[l] = DEAD
                                else:
                                    tb[l] = tc[l]
                                    tri[l] = k
                        if any_hit and all_negative(tb):
                            done = True
                            break
                if done or sp == 0:
                    break
                sp -= 1
                node = stack[sp]
                continue
            h0, h1 = _children_hit(bv, c0, ix, iy, iz, oix, oiy, oiz, tb)
            if h0 and h1:
                near = c0
                far = c0 + 1
                if not any_hit:
                    ax = bv.node_axis[node]
                    d_ax = mx[0]
                    if ax == 1:
                        d_ax = my[0]
                    elif ax == 2:
                        d_ax = mz[0]
                    if d_ax < 0.0:
                        near = c0 + 1
                        far = c0
                stack[sp] = far
                sp += 1
                node = near
            elif h0:
                node = c0
            elif h1:
                node = c0 + 1
            else:
                if sp == 0:
                    break
                sp -= 1
                node = stack[sp]
    return tb, tri


@wp.func
def packet_closest(bv: BvhData, b: int, ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8, t_in: vec8):
    """Closest hits of a packet (world frame, unit directions) over every visible instance of batch element b.

    Returns (t vec8: the hit distance, or t_in where nothing is closer; tri ivec8: global triangle
    index or -1).
    """
    return _packet_traverse(bv, b, ox, oy, oz, dx, dy, dz, t_in, False)


@wp.func
def packet_occluded(bv: BvhData, b: int, ox: vec8, oy: vec8, oz: vec8, dx: vec8, dy: vec8, dz: vec8, t_in: vec8):
    """Any-hit (shadow) queries: returns t where occluded lanes (anything on (0, t_in)) are set to -1.

    Dead lanes (t_in < 0) stay dead; the traversal stops once every lane is dead or occluded.
    """
    tb, tri = _packet_traverse(bv, b, ox, oy, oz, dx, dy, dz, t_in, True)
    return tb


@wp.func
def barycentric(bv: BvhData, k: int, o: wp.vec3, d: wp.vec3):
    """(u, v) of ray o + t d (instance frame) on triangle k, Warp's convention: u v0 + v v1 + (1-u-v) v2."""
    e1 = bv.tri_e1[k]
    e2 = bv.tri_e2[k]
    p = wp.cross(d, e2)
    inv = 1.0 / wp.dot(e1, p)
    s = o - bv.tri_v0[k]
    b1 = wp.dot(s, p) * inv
    q = wp.cross(s, e1)
    b2 = wp.dot(d, q) * inv
    return 1.0 - b1 - b2, b1
