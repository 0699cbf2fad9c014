"""Stage 1 of the ONV renderer: the rays each photoreceptor casts through the eye, in Warp.

For every photoreceptor p, colour channel c and pupil sample s, ``eye_rays_kernel`` finds the ray from
the photoreceptor through the s-th point of the pupil, refracted out through the lens and the cornea
with channel c's refractive indices: exact conic surfaces and vector Snell in float32, the same maths
as :class:`warp_vision.eye.optics.NavarroEye` (float64, the reference the tests compare with). The
direction leaving the retina is found by Newton's method on its aim point (ray aiming through the lens).

Each ray carries the irradiance weight ``A_pupil / S * n_v^2 cos(theta_retina) d(omega)/dA_pupil`` (sr),
so a photoreceptor's value, the weighted sum of its rays' radiances, is its irradiance: it grows with
the pupil's area and a blocked ray carries nothing. The rays depend only on the retina and the eye's
state (accommodation, pupil), not on the scene, so :func:`eye_rays` caches them.

Ray k = (p * 3 + c) * S + s; rays are in the eye frame (m, docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import warp as wp

from warp_vision.eye.optics import CHANNEL_WAVELENGTHS_NM, EYE_CENTRE_MM, NavarroEye
from warp_vision.kernels import launch as _launch

wp.set_module_options({"enable_backward": False})

#: Most Newton iterations of the ray aiming through the lens (it converges quadratically: usually 2-3)
AIM_ITERATIONS = wp.constant(8)
#: Central-difference step (mm) for the aiming Jacobian
AIM_STEP_MM = wp.constant(0.01)
#: Newton stops once the ray passes this close (mm) to its pupil point (float32 noise is ~1e-6 mm)
AIM_CONVERGED_MM = wp.constant(4e-6)
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
    o: wp.vec3, d: wp.vec3, surf: wp.array3d(dtype=float), c: int, j: int, backwards: int, clip: int
):
    """Hit surface j of channel c and refract (front->back medium, or back->front if ``backwards``);
    with ``clip`` 0 the surface continues past its aperture (for the aiming's derivatives)."""
    semi = surf[c, j, 5]
    if clip == 0:
        semi = 1.0e30
    ok, t, n = conic_hit(o, d, surf[c, j, 0], surf[c, j, 1], surf[c, j, 2], semi)
    p = o + t * d
    eta = surf[c, j, 3] / surf[c, j, 4]
    if backwards != 0:
        eta = surf[c, j, 4] / surf[c, j, 3]
    ok2, d2 = refract_dir(d, n, eta)
    return ok and ok2, p, d2


@wp.func
def retina_to_stop(q: wp.vec3, aim: wp.vec2, surf: wp.array3d(dtype=float), c: int, pupil_z: float, clip: int):
    """From retina point q toward ``aim`` on the lens-back vertex plane, out through the lens to the stop.

    Returns (ok, point on the stop plane, direction in the aqueous). The Newton iterations run with
    ``clip`` 0 (apertures ignored: the map is smooth there); the final ray is checked with ``clip`` 1.
    """
    d = wp.normalize(wp.vec3(aim[0], aim[1], surf[c, 3, 0]) - q)
    ok1, p1, d1 = through_surface(q, d, surf, c, 3, 1, clip)
    ok2, p2, d2 = through_surface(p1, d1, surf, c, 2, 1, clip)
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
        ok0, s0, d0 = retina_to_stop(q, aim, surf, c, pupil_z, 0)
        okx1, sx1, dx1 = retina_to_stop(q, aim + wp.vec2(h, 0.0), surf, c, pupil_z, 0)
        okx0, sx0, dx0 = retina_to_stop(q, aim - wp.vec2(h, 0.0), surf, c, pupil_z, 0)
        oky1, sy1, dy1 = retina_to_stop(q, aim + wp.vec2(0.0, h), surf, c, pupil_z, 0)
        oky0, sy0, dy0 = retina_to_stop(q, aim - wp.vec2(0.0, h), surf, c, pupil_z, 0)
        ok = ok0 and okx1 and okx0 and oky1 and oky0
        if not ok:
            break
        j00 = (sx1[0] - sx0[0]) / (2.0 * h)
        j10 = (sx1[1] - sx0[1]) / (2.0 * h)
        j01 = (sy1[0] - sy0[0]) / (2.0 * h)
        j11 = (sy1[1] - sy0[1]) / (2.0 * h)
        ex = s0[0] - target[0]
        ey = s0[1] - target[1]
        if it == AIM_ITERATIONS or wp.max(wp.abs(ex), wp.abs(ey)) < AIM_CONVERGED_MM:
            break  # converged: the Jacobian (for the weight) is the one at this aim
        det = j00 * j11 - j01 * j10
        if det == 0.0:
            ok = False
            break
        aim = aim - wp.vec2((j11 * ex - j01 * ey) / det, (-j10 * ex + j00 * ey) / det)
    w = float(0.0)
    o = wp.vec3(0.0)
    dout = wp.vec3(0.0, 0.0, 1.0)
    if ok:
        okf, sp, dd = retina_to_stop(q, aim, surf, c, pupil_z, 1)
        miss = wp.length(wp.vec2(sp[0] - target[0], sp[1] - target[1]))
        inside = target[0] * target[0] + target[1] * target[1] <= pupil_r * pupil_r
        ok1, p1, d1 = through_surface(sp, dd, surf, c, 1, 1, 1)
        ok2, p2, d2 = through_surface(p1, d1, surf, c, 0, 1, 1)
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
#: The cache keeps the most recently used ray sets within this many bytes (at least one): the closed loop's
#: two eyes visit a dozen or so (accommodation, pupil) states in its experiments, each set costing about
#: 0.17 s to aim at P = 14,400, S = 4 (4.8 MB); with 8 entries they evicted each other.
_EYE_CACHE_BYTES = 256 * 2**20


def _ray_bytes(r: EyeRays) -> int:
    return r.P * 3 * r.S * 28  # origin and direction (vec3) and weight (float32) per ray


def clear_eye_ray_cache() -> None:
    """Forget every cached :class:`EyeRays`: the next :func:`eye_rays` call traces its rays afresh
    (benchmarks time that; tests compare fresh traces)."""
    with _eye_cache_lock:
        _eye_cache.clear()


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
        [[[s.z0, s.R, s.Q, s.n_front, s.n_back,
           s.semi_diameter] for s in eye.surfaces(wl)] for wl in CHANNEL_WAVELENGTHS_NM],
        dtype=np.float32,
    )


#: memory per ray bundle (photoreceptor x pupil sample) while the eye's rays are built: 3 channels of
#: origin, direction and weight (84 B) and the pupil samples with their temporaries, an upper bound of the
#: peak (docs/RESULTS.md, "Figures behind the code's constants")
EYE_RAYS_BYTES_PER_SAMPLE = 160


def eye_rays_bytes(P: int, samples_per_receptor: int) -> int:
    """An estimate of the memory :func:`eye_rays` needs for P photoreceptors and S samples each."""
    return EYE_RAYS_BYTES_PER_SAMPLE * int(P) * int(samples_per_receptor)


def _check_samples(S) -> int:
    if isinstance(S, bool) or not isinstance(S, (int, np.integer)) or S < 1:
        raise ValueError(f"samples_per_receptor: expected a positive int, got {S!r}")
    return int(S)


def eye_rays(retina, eye: NavarroEye, samples_per_receptor: int = 16, seed: int = 0, device: str = "cpu") -> EyeRays:
    """The rays each photoreceptor casts into the world through ``eye`` (cached; see the module doc).
    Sizes whose rays would not fit in the memory available are refused (ValueError) before allocating."""
    from warp_vision.resources import require_memory

    _launch.init()
    pos = _retina_positions(retina)
    S = _check_samples(samples_per_receptor)
    require_memory(eye_rays_bytes(len(pos), S), f"the eye's rays (P={len(pos):,}, S={S:,})",
                   "samples_per_receptor or the photoreceptors")
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
        chunks_per_thread=16,  # rays differ in cost (Newton steps, blocked rays): balance the workers
    )
    with _eye_cache_lock:
        _eye_cache[key] = out
        while len(_eye_cache) > 1 and sum(_ray_bytes(r) for r in _eye_cache.values()) > _EYE_CACHE_BYTES:
            _eye_cache.popitem(last=False)
    return out
