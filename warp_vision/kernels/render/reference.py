"""Plain numpy reference for the ONV renderer (:mod:`warp_vision.kernels.render`): brute-force triangles,
float64, written for clarity.

The eye part reuses :class:`warp_vision.eye.optics.NavarroEye` (exact float64 tracing); the scene part
tests every ray against every triangle (Moller-Trumbore) and shades with the same Phong model, shadow
rays and mirror recursion as the kernels, with each batch element's transforms, visibility, lights,
materials and ambient light. Use it on small scenes and few photoreceptors only.

Barycentrics follow Warp's convention: a hit at ``u * v0 + v * v1 + (1 - u - v) * v2``.
"""

from __future__ import annotations

import numpy as np

from warp_vision.eye import optics
from warp_vision.eye.optics import CHANNEL_WAVELENGTHS_NM, NavarroEye
from warp_vision.kernels.render.eye_rays import pupil_samples
from warp_vision.kernels.render.shade import RAY_EPSILON_M


def eye_rays_ref(retina_mm: np.ndarray, eye: NavarroEye, samples_per_receptor: int, seed: int = 0):
    """Eye-frame rays (m) of each photoreceptor, channel and pupil sample.

    Returns (origins [P, 3, S, 3], directions [P, 3, S, 3], weights [P, 3, S] sr); blocked rays have
    weight 0 (and NaN geometry).
    """
    q = np.asarray(retina_mm, dtype=np.float64)
    P, S = len(q), int(samples_per_receptor)
    pxy = pupil_samples(P, S, eye.pupil_radius_mm, seed)  # [P, S, 2]
    O = np.zeros((P, 3, S, 3))
    D = np.zeros((P, 3, S, 3))
    W = np.zeros((P, 3, S))
    for c, wl in enumerate(CHANNEL_WAVELENGTHS_NM):
        o, d, valid, w = eye.trace_to_world(np.repeat(q, S, axis=0), pxy.reshape(-1, 2), wl, return_weights=True)
        O[:, c] = optics.eye_from_optical(o).reshape(P, S, 3)
        D[:, c] = optics.eye_from_optical_dir(d).reshape(P, S, 3)
        W[:, c] = (w * eye.pupil_area_mm2 / S).reshape(P, S)
    return O, D, W


def intersect_triangles(o, d, v0, v1, v2, t_max=np.inf):
    """Closest hit of rays [N, 3] with triangles [F, 3] each: (t [N] (inf on a miss), face [N] (-1), u, v)."""
    e1 = v1 - v0
    e2 = v2 - v0
    N = len(o)
    best_t = np.full(N, np.inf)
    best_f = np.full(N, -1)
    best_u = np.zeros(N)
    best_v = np.zeros(N)
    t_max = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (N,))
    chunk = max(1, 2_000_000 // max(1, len(v0)))
    for s in range(0, N, chunk):
        oo, dd = o[s : s + chunk, None, :], d[s : s + chunk, None, :]
        pvec = np.cross(dd, e2[None])
        det = np.sum(e1[None] * pvec, axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tvec = oo - v0[None]
            b1 = np.sum(tvec * pvec, axis=-1) * inv
            qvec = np.cross(tvec, e1[None])
            b2 = np.sum(dd * qvec, axis=-1) * inv
            t = np.sum(e2[None] * qvec, axis=-1) * inv
            ok = (
                (np.abs(det) > 1e-20)
                & (b1 >= 0)
                & (b2 >= 0)
                & (b1 + b2 <= 1)
                & (t >= 0)
                & (t < t_max[s : s + chunk, None])
            )
        t = np.where(ok, t, np.inf)
        f = np.argmin(t, axis=1)
        rows = np.arange(len(f))
        tt = t[rows, f]
        hit = np.isfinite(tt)
        best_t[s : s + chunk] = tt
        best_f[s : s + chunk] = np.where(hit, f, -1)
        bb1, bb2 = b1[rows, f], b2[rows, f]
        best_u[s : s + chunk] = np.where(hit, 1.0 - bb1 - bb2, 0.0)
        best_v[s : s + chunk] = np.where(hit, bb1, 0.0)
    return best_t, best_f, best_u, best_v


def _transform(obj, batch):
    T = obj.transform
    return T[batch if T.shape[0] > 1 else 0]


def closest_hit_ref(scene, origins, directions, batch: int = 0, t_max=np.inf):
    """Closest hit over the scene's objects in the world frame.

    Returns (t [N] m (inf on a miss), object [N] (-1), face [N] (-1), u [N], v [N]).
    """
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    N = len(o)
    best = (np.full(N, np.inf), np.full(N, -1), np.full(N, -1), np.zeros(N), np.zeros(N))
    for i, ob in enumerate(scene.objects):
        if not ob.visible[batch if len(ob.visible) > 1 else 0]:
            continue
        V = np.asarray(ob.mesh.vertices, dtype=np.float64)
        V = V @ _transform(ob, batch)[:3, :3].T + _transform(ob, batch)[:3, 3]
        F = np.asarray(ob.mesh.faces)
        t, f, u, v = intersect_triangles(o, d, V[F[:, 0]], V[F[:, 1]], V[F[:, 2]], t_max)
        closer = t < best[0]
        best = (
            np.where(closer, t, best[0]),
            np.where(closer, i, best[1]),
            np.where(closer, f, best[2]),
            np.where(closer, u, best[3]),
            np.where(closer, v, best[4]),
        )
    return best


def _lights(scene, batch):
    out = []
    for li in scene.lights:
        pos = np.atleast_2d(li.position)
        col = np.atleast_2d(li.color)
        inten = np.atleast_1d(li.intensity)
        pick = lambda a: a[batch if len(a) > 1 else 0]  # noqa: E731
        out.append((pick(pos), pick(col) * pick(inten)))
    return out


def radiance_ref(scene, origins, directions, batch: int = 0, max_depth: int = 2) -> np.ndarray:
    """RGB radiance [N, 3] along world rays: Phong with shadow rays, mirror recursion to ``max_depth``."""
    o = np.asarray(origins, dtype=np.float64).copy()
    d = np.asarray(directions, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    N = len(o)
    result = np.zeros((N, 3))
    throughput = np.ones((N, 3))
    alive = np.ones(N, dtype=bool)
    lights = _lights(scene, batch)
    for _ in range(max_depth + 1):
        if not alive.any():
            break
        idx = np.nonzero(alive)[0]
        t, obj, face, u, v = closest_hit_ref(scene, o[idx], d[idx], batch)
        miss = obj < 0
        result[idx[miss]] += throughput[idx[miss]] * scene.background
        alive[idx[miss]] = False
        hit_idx = idx[~miss]
        if len(hit_idx) == 0:
            break
        t, obj, face, u, v = t[~miss], obj[~miss], face[~miss], u[~miss], v[~miss]
        dd = d[hit_idx]
        p = o[hit_idx] + t[:, None] * dd
        n = np.zeros((len(hit_idx), 3))
        base = np.zeros((len(hit_idx), 3))
        ks, shin, refl = np.zeros(len(hit_idx)), np.ones(len(hit_idx)), np.zeros(len(hit_idx))
        emit = np.zeros((len(hit_idx), 3))
        for i, ob in enumerate(scene.objects):
            m = obj == i
            if not m.any():
                continue
            T = _transform(ob, batch)
            F = np.asarray(ob.mesh.faces)[face[m]]
            V = np.asarray(ob.mesh.vertices, dtype=np.float64)
            w = np.stack([u[m], v[m], 1.0 - u[m] - v[m]], axis=1)
            mat = ob.material_for(batch)  # smooth / vertex_colors agree with ob.material's
            if mat.smooth:
                VN = np.asarray(ob.mesh.vertex_normals, dtype=np.float64)
                nl = np.einsum("nk,nkj->nj", w, VN[F])
                nl /= np.linalg.norm(nl, axis=1, keepdims=True)
            else:
                nl = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
                nl /= np.linalg.norm(nl, axis=1, keepdims=True)
            n[m] = nl @ T[:3, :3].T
            vc = getattr(ob.mesh.visual, "vertex_colors", None) if mat.vertex_colors else None
            if vc is not None and len(vc) == len(V):
                base[m] = np.einsum("nk,nkj->nj", w, np.asarray(vc[:, :3], dtype=np.float64)[F] / 255.0)
            else:
                base[m] = mat.diffuse
            ks[m], shin[m], refl[m] = mat.specular, mat.shininess, mat.reflectivity
            emit[m] = mat.emission
        flip = np.sum(n * dd, axis=1) > 0
        n[flip] *= -1
        amb = np.atleast_2d(scene.ambient)
        local = amb[batch if len(amb) > 1 else 0][None] * base + emit
        p_off = p + RAY_EPSILON_M * n
        for lpos, lrad in lights:
            lv = lpos[None] - p_off
            dist = np.linalg.norm(lv, axis=1)
            l = lv / dist[:, None]
            ndl = np.sum(n * l, axis=1)
            lit = ndl > 0
            if lit.any():
                ts, *_ = closest_hit_ref(scene, p_off[lit], l[lit], batch, t_max=dist[lit])
                lit[np.nonzero(lit)[0][np.isfinite(ts)]] = False
            E = lrad[None] / (dist**2)[:, None]
            shade = base * (ndl / np.pi)[:, None]
            r = 2 * ndl[:, None] * n - l
            rv = np.maximum(-np.sum(r * dd, axis=1), 0.0)
            shade = shade + np.where(ks > 0, ks * rv**shin / np.pi, 0.0)[:, None]
            local += np.where(lit[:, None], E * shade, 0.0)
        result[hit_idx] += throughput[hit_idx] * local * (1 - refl)[:, None]
        throughput[hit_idx] *= refl[:, None]
        alive[hit_idx] = refl > 0
        d[hit_idx] = dd - 2 * np.sum(dd * n, axis=1)[:, None] * n
        o[hit_idx] = p_off
    return result


def render_onv_ref(scene, retina_mm, eye: NavarroEye, eye_poses, samples_per_receptor: int = 1, seed: int = 0,
                   max_depth: int = 2):
    """The ONV [B, 3P] by the references above (float64)."""
    O, D, W = eye_rays_ref(retina_mm, eye, samples_per_receptor, seed)
    T = np.asarray(eye_poses, dtype=np.float64).reshape(-1, 4, 4)
    P, S = W.shape[0], W.shape[2]
    out = np.zeros((len(T), P, 3))
    ok = W > 0
    for b, Tb in enumerate(T):
        o = O[ok] @ Tb[:3, :3].T + Tb[:3, 3]
        d = D[ok] @ Tb[:3, :3].T
        L = radiance_ref(scene, o, d, b, max_depth)
        chan = np.nonzero(ok)[1]
        contrib = np.zeros((P, 3, S))
        contrib[ok] = W[ok] * L[np.arange(len(L)), chan]
        out[b] = contrib.sum(axis=2)
    return out.reshape(len(T), 3 * P)
