"""``python -m warp_vision.bench raytrace``: closest-hit throughput and ONV rendering rate.

Closest hits on a ~100k-triangle scene, on the same rays in the same run:
- warp_packet: our Warp kernel (8-ray packets over our SAH BVH), 1 and 2 threads;
- warp_mesh: ``wp.mesh_query_ray`` one ray per thread (Warp's own BVH), 1 thread;
- embree: Embree through ``embreex`` (``pip install -e ".[bench]"``), its single-ray API, 1 thread.

Two ray sets: ``eye``, the rays the eye casts for one ONV (P photoreceptors x 3 channels x S pupil
samples, in the renderer's order, so each packet is one photoreceptor's rays), and ``random``,
incoherent rays from random points of the room in random directions (the worst case for packets).

Then ONVs per second for P=14,400, S=16 in the furnished room with the ball (Phong, shadows,
reflections to depth 2), and the time to build the eye rays.

``--device cuda`` (or ``cuda:N``) runs the Warp paths on the GPU: the eye rays, the packet kernel and
the ``wp.mesh_query_ray`` kernel (each one launch over all rays, keys ``warp_packet`` and ``warp_mesh``:
thread counts mean nothing there) and the ONV render, every timing synchronised with the device.
``agree_with_warp_mesh`` still compares the packet kernel's hit distances with ``wp.Mesh``'s (both on
the GPU). Embree, a CPU library, is not timed there: with ``embreex`` installed its hits (one untimed
CPU run per ray set) remain the CPU reference of ``agree_with_embree``. The JSON names what was
skipped under ``"skipped"`` (:data:`CUDA_SKIPPED`) and holds ``"device"`` and ``"device_name"``
instead of ``"threads"``.
"""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from warp_vision.bench.common import median_ms
from warp_vision.eye.optics import NavarroEye
from warp_vision.eye.retina import Retina
from warp_vision.frames import eye_look_at
from warp_vision.kernels import launch as _launch
from warp_vision.kernels import render as rt
from warp_vision.kernels.render.shade import closest_hit_kernel
from warp_vision.scene import Material
from warp_vision.scene.room import make_room

EYE_CENTRE = np.array([0.0, -1.5, 1.2])
EYE_TARGET = np.array([0.0, 1.0, 1.1])

#: What a run on a CUDA device leaves out, and why (its JSON's ``"skipped"``).
_ONE_LAUNCH = "a CPU thread count: on cuda each kernel is one launch over all rays (warp_packet, warp_mesh)"
_EMBREE = ("Embree is a CPU library: not timed on cuda (its hits still give agree_with_embree when embreex is "
           "installed)")
CUDA_SKIPPED = {
    "warp_packet_1thread": _ONE_LAUNCH,
    "warp_packet_2thread": _ONE_LAUNCH,
    "warp_mesh_1thread": _ONE_LAUNCH,
    "packet_2threads_over_1": _ONE_LAUNCH,
    "embree_1thread": _EMBREE,
    "packet_1thread_over_embree": _EMBREE,
}


@wp.kernel
def mesh_query_kernel(
    mesh: wp.uint64,
    origins: wp.array(dtype=wp.vec3),
    dirs: wp.array(dtype=wp.vec3),
    offset: int,
    t_out: wp.array(dtype=float),
):
    i = offset + wp.tid()
    q = wp.mesh_query_ray(mesh, origins[i], dirs[i], 1.0e30)
    t_out[i] = wp.where(q.result, q.t, wp.inf)


def big_scene(seed: int = 0, detail: int = 6):
    """The room with two finely tessellated objects merged into one static mesh: ~100k triangles at
    ``detail`` 6 (each step down divides the tessellation by about 4)."""
    import trimesh

    sc = make_room(seed=seed, n_objects=4, ball_subdivisions=3)
    statue = trimesh.util.concatenate(
        [
            trimesh.creation.icosphere(subdivisions=detail, radius=0.45).apply_translation([-0.6, 0.8, 1.0]),
            trimesh.creation.torus(0.35, 0.1, major_sections=2 ** (detail + 1),
                                   minor_sections=2**detail).apply_translation([0.7, 0.9, 1.2]),
        ]
    )
    sc.add("statue", statue, Material((0.8, 0.7, 0.6)), static=True)
    return sc


def _eye_world_rays(P: int, S: int, seed: int, device: str = "cpu"):
    retina = Retina.log_polar(P, seed=seed)
    eye = NavarroEye()
    rays = rt.eye_rays(retina, eye, S, seed, device)
    T = eye_look_at(EYE_CENTRE, EYE_TARGET)
    o = rays.origins.numpy().astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    d = rays.directions.numpy().astype(np.float64) @ T[:3, :3].T
    keep = rays.weights.numpy() > 0
    # blocked rays stay in place (as dead weight in their packets); give them a valid direction
    d[~keep] = [0.0, 1.0, 0.0]
    return o.astype(np.float32), d.astype(np.float32), retina, eye


def _random_rays(n: int, seed: int):
    rng = np.random.default_rng(seed)
    o = rng.uniform([-2.5, -2.5, 0.2], [2.5, 2.5, 2.7], size=(n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def _embree(V, F):
    try:
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh
    except ImportError:
        return None
    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(V[F], dtype=np.float32))
    return scene


def _embree_t(embree, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Embree's closest-hit distances (inf on a miss)."""
    hit = embree.run(o, d, output=1)
    return np.where(np.asarray(hit["geomID"]) >= 0, np.asarray(hit["tfar"]), np.inf)


def closest_hit_rates(repeats: int = 5, P: int = 14_400, S: int = 16, seed: int = 0, detail: int = 6, log=print,
                      device: str = "cpu") -> dict:
    """Closest-hit rates per ray set and path, on ``device`` ("cpu": the thread variants and Embree;
    "cuda:N": one launch per path, Embree untimed; see the module doc)."""
    cpu = device == "cpu"
    sc = big_scene(seed, detail)
    world = sc.world_mesh()
    V = np.asarray(world.vertices, dtype=np.float32)
    F = np.asarray(world.faces, dtype=np.int32)
    log(f"scene: {len(F):,} triangles")
    sd = rt.scene_data(sc, device, 0)
    mesh = wp.Mesh(points=wp.array(V, dtype=wp.vec3, device=device),
                   indices=wp.array(F.ravel(), dtype=wp.int32, device=device))
    embree = _embree(V, F)
    o_eye, d_eye, *_ = _eye_world_rays(P, S, seed, device)
    sets = {"eye": (o_eye, d_eye), "random": _random_rays(len(o_eye), seed + 1)}
    out = {"triangles": int(len(F)), "rays": {}}
    if not cpu:
        out["device"] = device
    for name, (o, d) in sets.items():
        n = len(o)
        oa, da = wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device)
        t = wp.empty(n, dtype=wp.float32, device=device)
        obj = wp.empty(n, dtype=wp.int32, device=device)
        face = wp.empty(n, dtype=wp.int32, device=device)
        t_mesh = wp.empty(n, dtype=wp.float32, device=device)
        res = {"rays": n}

        # launch_split is one ordinary launch (offset 0) on a CUDA device, whatever ``threads`` says
        def packet(threads):
            _launch.launch_split(closest_hit_kernel, (n + 7) // 8, [sd, oa, da, 0], [t, obj, face], device,
                                 threads=threads, **rt.TRACE_SPLIT)

        def mesh_query():
            _launch.launch_split(mesh_query_kernel, n, [mesh.id, oa, da], [t_mesh], device, threads=1)

        if cpu:
            for th in (1, 2):
                m = median_ms(lambda: packet(th), repeats, warmup=1)
                res[f"warp_packet_{th}thread"] = {**m, "mrays_per_s": n / m["median_ms"] / 1e3}
            m = median_ms(mesh_query, repeats, warmup=1)
            res["warp_mesh_1thread"] = {**m, "mrays_per_s": n / m["median_ms"] / 1e3}
            packet_key, mesh_key = "warp_packet_1thread", "warp_mesh_1thread"
        else:
            packet_key, mesh_key = "warp_packet", "warp_mesh"
            for key, fn in ((packet_key, lambda: packet(None)), (mesh_key, mesh_query)):
                m = median_ms(fn, repeats, warmup=1, device=device)
                res[key] = {**m, "mrays_per_s": n / m["median_ms"] / 1e3}
        # agreement on the hit distance (faces may differ legitimately where a ray meets a shared edge)
        tp = t.numpy()
        res["agree_with_warp_mesh"] = _agree(tp, t_mesh.numpy())
        if embree is None:
            res["embree_1thread"] = "embreex not installed (pip install -e '.[bench]')"
        elif cpu:
            m = median_ms(lambda: embree.run(o, d, output=0), repeats, warmup=1)
            res["embree_1thread"] = {**m, "mrays_per_s": n / m["median_ms"] / 1e3}
            res["packet_1thread_over_embree"] = (
                res["warp_packet_1thread"]["mrays_per_s"] / res["embree_1thread"]["mrays_per_s"]
            )
        else:
            res["embree_1thread"] = CUDA_SKIPPED["embree_1thread"]
        if embree is not None:  # Embree's hits, on the CPU, are the reference on any device
            res["agree_with_embree"] = _agree(tp, _embree_t(embree, o, d))
        if cpu:
            res["packet_2threads_over_1"] = (
                res["warp_packet_2thread"]["mrays_per_s"] / res["warp_packet_1thread"]["mrays_per_s"]
            )
        res["packet_over_warp_mesh"] = res[packet_key]["mrays_per_s"] / res[mesh_key]["mrays_per_s"]
        res["hit_fraction"] = float(np.isfinite(t.numpy()).mean())
        line = ", ".join(f"{k} {v['mrays_per_s']:.2f}" for k, v in res.items() if isinstance(v, dict))
        log(f"{name} rays ({n:,}, {res['hit_fraction']:.0%} hit), Mrays/s: {line}")
        out["rays"][name] = res
    return out


def _agree(t: np.ndarray, t_ref: np.ndarray) -> float:
    """Fraction of rays whose hit distance matches (both miss, or within 1e-4 relative)."""
    both_miss = ~np.isfinite(t) & ~np.isfinite(t_ref)
    with np.errstate(invalid="ignore"):
        close = np.abs(t - t_ref) <= 1e-4 * np.abs(t_ref) + 1e-6
    return float(np.mean(both_miss | close))


def onv_rate(P: int = 14_400, S: int = 16, batch: int = 4, repeats: int = 5, seed: int = 0, log=print,
             device: str = "cpu") -> dict:
    """ONVs per second rendered on ``device`` by :func:`warp_vision.kernels.render.render_onv`, and
    the time to build the eye rays there."""
    retina = Retina.log_polar(P, seed=seed)
    eye = NavarroEye()
    sc = make_room(seed=seed)
    poses = np.repeat(eye_look_at(EYE_CENTRE, EYE_TARGET)[None], batch, axis=0)
    m_eye = median_ms(lambda: rt.eye_rays(retina, eye, S, seed, device), repeats, warmup=1,
                      setup=rt.clear_eye_ray_cache, device=device)
    m = median_ms(lambda: rt.render_onv(sc, retina, eye, poses, S, seed, device), repeats, warmup=1, device=device)
    res = {
        "P": P,
        "S": S,
        "batch": batch,
        "triangles": sc.num_triangles,
        "max_depth": 2,
        "lights": len(sc.lights),
        "render": m,
        "onv_per_s": batch / m["median_ms"] * 1e3,
        "primary_rays_per_s": batch * 3 * P * S / m["median_ms"] * 1e3,
        "eye_rays": m_eye,
    }
    log(f"ONV P={P:,} S={S}: {res['onv_per_s']:.1f} ONV/s (batch {batch}), eye rays {m_eye['median_ms']:.0f} ms")
    return res


def run(repeats: int = 5, P: int = 14_400, S: int = 16, batch: int = 4, log=print, device: str = "cpu") -> dict:
    """Closest-hit rates and the ONV rate on ``device`` ("cpu", "cuda:N")."""
    _launch.init()
    if device != "cpu":
        name = torch.cuda.get_device_name(device)
        log(f"device: {device} ({name}); Embree untimed, no CPU thread variants")
    out = {
        "closest_hit": closest_hit_rates(repeats, P, S, log=log, device=device),
        "onv": onv_rate(P, S, batch, repeats, log=log, device=device),
    }
    if device == "cpu":
        out["threads"] = _launch.cpu_threads()
    else:
        out.update(device=device, device_name=name, skipped=dict(CUDA_SKIPPED))
    return out
