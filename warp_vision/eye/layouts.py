"""Photoreceptor layouts on the hemispherical retina (paper, III.B).

Geometry (docs/ARCHITECTURE.md, "Frames and units"). The retina is the sphere of radius
``RETINA_RADIUS_MM`` (12 mm) about the eyeball centre. A photoreceptor is given by

* its eccentricity ``rho`` [rad]: the angle at the eyeball centre between the fovea (the posterior pole,
  on the optical axis) and the photoreceptor, 0 <= rho <= rho_max <= pi; the arc length from the fovea
  is 12 mm * rho;
* its polar angle ``theta`` [rad] in [0, 2 pi).

Derived positions:

* eye frame (metres, origin at the eyeball centre, +z out of the pupil, +y up, +x = y cross z):
  ``0.012 * (sin rho cos theta, sin rho sin theta, -cos rho)`` (:func:`eye_positions_m`);
* optical frame (mm, origin at the corneal apex, +z into the eye): ``optics.optical_from_eye`` of it;
* the 2D retinal domain of the liNets, the azimuthal-equidistant projection about the fovea:
  ``domain_xy = rho * (cos theta, sin theta)`` [rad], so Euclidean distances there approximate
  great-circle distances on the retina near the fovea and the paper's (rho, theta) domain everywhere.

Two layouts, both plain vectorised numpy, seeded with ``numpy.random.default_rng(seed)`` (the same
seed gives bit-identical output) and returning (rho, theta) in ring order:

* :func:`noisy_log_polar` -- the paper's noisy log-polar layout (density ~ 1 / rho^2 in the retinal
  domain) with a uniformly sampled foveal disk;
* :func:`cone_density_layout` -- density proportional to the human cone density of Curcio et al. (1990)
  (:func:`cone_density_per_mm2`), for up to millions of photoreceptors.

:class:`warp_vision.eye.retina.Retina` holds one layout with all its coordinates.
"""

from __future__ import annotations

import math

import numpy as np

from warp_vision.eye.optics import RETINA_RADIUS_MM

__all__ = [
    "CONE_DENSITY_TABLE",
    "DEFAULT_FOVEA_RADIUS_RAD",
    "RETINA_RADIUS_M",
    "cone_density_layout",
    "cone_density_per_mm2",
    "default_rho_min",
    "eye_positions_m",
    "noisy_log_polar",
]

#: Radius of the retina sphere [m].
RETINA_RADIUS_M = RETINA_RADIUS_MM * 1e-3

#: Default radius of the log-polar layout's uniformly sampled central disk [rad] (1 degree). Inside it
#: the log-polar law 1/rho^2 is replaced by a constant density, as in Schwartz's complex-log model of
#: the retinotopic map, w = log(z + a), whose foveal constant a is 0.3-1 deg (the cortical magnification
#: M(E) ~ 1 / (E + 0.75 deg) of Horton & Hoyt 1991 is nearly flat inside E ~ 0.75 deg). With P = 14,400
#: photoreceptors on a 101 deg retina the spacing at the disk is about 0.045 deg (2.7 arcmin) and ~9.6%
#: of the photoreceptors lie in the central 1 deg, close to V1's share of the visual field there.
DEFAULT_FOVEA_RADIUS_RAD = math.radians(1.0)

#: Human cone density against eccentricity along the retinal surface, Curcio, Sloan, Kalina &
#: Hendrickson (1990), "Human photoreceptor topography", J. Comp. Neurol. 292:497-523. Columns:
#: eccentricity [mm from the foveal centre], density [cones/mm^2]. The peak is the paper's mean peak
#: foveal density (199,000/mm^2); the other rows are the mean of the four principal half-meridians
#: (nasal, temporal, superior, inferior) of the paper's averaged eight-retina data (its Fig. 6 /
#: the published PRtopo tables), rounded to 3 significant figures. It falls by an order of magnitude
#: within 1 mm and levels out at ~4,000/mm^2 in the periphery. Integrated over a 12 mm sphere out to
#: 21 mm (about the Navarro eye's lit retina) it gives 4.9 million cones (Curcio et al.: 4.6 million on
#: average, 4.08-5.29 million).
CONE_DENSITY_TABLE = np.array(
    [
        [0.00, 199000.0],
        [0.05, 151000.0],
        [0.10, 113000.0],
        [0.15, 90200.0],
        [0.20, 71700.0],
        [0.30, 52300.0],
        [0.40, 40700.0],
        [0.50, 33700.0],
        [0.60, 29300.0],
        [0.70, 25000.0],
        [0.80, 21700.0],
        [0.90, 20000.0],
        [1.00, 18700.0],
        [2.00, 11100.0],
        [3.00, 8230.0],
        [4.00, 6740.0],
        [5.00, 5900.0],
        [6.00, 5430.0],
        [7.00, 5150.0],
        [8.00, 4900.0],
        [9.00, 4680.0],
        [10.0, 4450.0],
        [12.0, 4130.0],
        [14.0, 3980.0],
        [16.0, 3900.0],
        [18.0, 4000.0],
    ]
)
CONE_DENSITY_TABLE.flags.writeable = False

_LOG_CONE_DENSITY = np.log(CONE_DENSITY_TABLE[:, 1])

#: Points of the radial quadrature grid used to normalise and invert the cone density.
_QUADRATURE_POINTS = 100_001


# --- validation -----------------------------------------------------------------------------------
#: memory per photoreceptor while a layout is built (polar and 3D positions, Morton sort, temporaries), an
#: upper bound of the log-polar layout's peak (docs/RESULTS.md, "Figures behind the code's constants")
LAYOUT_BYTES_PER_RECEPTOR = 160


def _check_count(P) -> int:
    from warp_vision.resources import require_memory

    if isinstance(P, bool) or not isinstance(P, (int, np.integer)) or P < 1:
        raise ValueError(f"P: expected a positive int (the number of photoreceptors), got {P!r}")
    require_memory(LAYOUT_BYTES_PER_RECEPTOR * int(P), f"a retina of P={int(P):,} photoreceptors",
                   "P, the photoreceptors (--photoreceptors)")
    return int(P)


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative int, got {seed!r}")
    return int(seed)


def _check_angle(name: str, value, low_open: float, high: float) -> float:
    """A finite real number in (low_open, high]."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}: expected a number in ({low_open:g}, {high:g}] rad, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or not low_open < v <= high:
        raise ValueError(f"{name}: expected a number in ({low_open:g}, {high:g}] rad, got {value!r}")
    return v


def _check_noise(noise) -> float:
    if isinstance(noise, bool) or not isinstance(noise, (int, float, np.integer, np.floating)):
        raise ValueError(f"noise: expected a finite number >= 0 (a fraction of the local spacing), got {noise!r}")
    v = float(noise)
    if not math.isfinite(v) or v < 0:
        raise ValueError(f"noise: expected a finite number >= 0 (a fraction of the local spacing), got {noise!r}")
    return v


def _finish(rho: np.ndarray, theta: np.ndarray, rho_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Fold (rho, theta) into 0 <= rho <= rho_max, 0 <= theta < 2 pi (in place; returns the arrays).

    A point pushed through the fovea (rho < 0) comes out on the opposite side; one pushed past rho_max
    is reflected back inside; a clip guards against noise larger than the whole range.
    """
    neg = rho < 0
    rho[neg] = -rho[neg]
    theta[neg] += math.pi
    over = rho > rho_max
    rho[over] = 2.0 * rho_max - rho[over]
    np.clip(rho, 0.0, rho_max, out=rho)
    np.mod(theta, 2.0 * math.pi, out=theta)
    theta[theta >= 2.0 * math.pi] = 0.0  # mod can round up to 2 pi for tiny negative inputs
    return rho, theta


# --- noisy log-polar --------------------------------------------------------------------------------
def default_rho_min(rho_max: float) -> float:
    """The default central-disk radius of :func:`noisy_log_polar` [rad]: 1 deg, or rho_max if smaller."""
    return min(DEFAULT_FOVEA_RADIUS_RAD, float(rho_max))


def _log_polar_counts(P: int, L: float) -> tuple[int, int, int, float]:
    """Ring count N_r, per-ring count K, central-disk count N_c and log step d for P points over a
    log-radius span L = ln(rho_max / rho_min) (see :func:`noisy_log_polar`); N_r K + N_c = P."""
    if L <= 0.0:
        return 0, 0, P, 0.0
    # Continuous solution: P = N_r K + N_c with K = 2 pi / d, N_r = L / d and N_c = K / (e^2d - 1), the
    # innermost ring's density over the disk: ring 0's K points fill the band [rho_min, rho_min e^d]
    # of area pi rho_min^2 (e^2d - 1). For integers, try ring counts near L / d0 and keep the one whose
    # rounded K and remainder N_c deviate least (relative) from isotropy and that disk density.
    d0 = math.sqrt(math.pi * (1.0 + 2.0 * L) / P)
    guess = max(1, round(L / d0))
    best = None
    for rings in range(max(1, guess - 3), min(P, guess + 3) + 1):
        d = L / rings
        per_ring = max(1, min(round(P / (rings + 1.0 / math.expm1(2.0 * d))), P // rings))
        disk = P - rings * per_ring
        ideal_disk = per_ring / math.expm1(2.0 * d)
        error = abs(math.log(per_ring * d / (2.0 * math.pi))) + abs(math.log((disk + 0.5) / (ideal_disk + 0.5)))
        if best is None or error < best[0]:
            best = (error, rings, per_ring, disk, d)
    return best[1:]


def noisy_log_polar(
    P: int,
    rho_max: float,
    seed: int = 0,
    rho_min: float | None = None,
    noise: float = 0.15,
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's noisy log-polar photoreceptor layout (III.B, Fig. 2a,b), foveal disk included.

    Construction, in the (u = ln rho, theta) plane:

    1. N_r rings at u_i = ln rho_min + (i + 1/2) d, i = 0..N_r-1, spanning [rho_min, rho_max] with the
       log step d = ln(rho_max / rho_min) / N_r; K photoreceptors per ring at angular steps 2 pi / K ~ d
       (isotropic sampling: the same spacing rho * d radially and tangentially in the retinal domain,
       so the domain density falls as 1 / (rho d)^2); odd rings are offset by half an angular step.
    2. The central disk rho < rho_min (a log-polar grid would leave a hole at the fovea) is filled with a
       Vogel (sunflower) spiral of N_c points at the innermost ring's density, r_j = rho_min
       sqrt((j + 1/2) / N_c), phi_j = j * golden angle + a seeded phase.
    3. Gaussian noise of standard deviation ``noise`` x the local spacing: on the rings sigma_u = noise d
       and sigma_theta = noise 2 pi / K; in the disk sigma = noise * rho_min sqrt(pi / N_c) per domain
       axis. Points pushed past rho_max are reflected back; through the fovea, to the other side.

    N_r, K and N_c are integers with N_r K + N_c = P exactly, chosen close to the continuous solution
    (K = 2 pi / d, N_c = K / (e^2d - 1) ~ pi / d^2); rounding leaves 2 pi / K and the disk density
    within a few per cent of it for P in the thousands. With rho_min = rho_max everything is the disk.

    Args:
        P:       number of photoreceptors, a positive int.
        rho_max: largest eccentricity [rad], in (0, pi].
        seed:    seeds the noise and the spiral's phase (non-negative int).
        rho_min: radius [rad] of the central disk, in (0, rho_max]; default :func:`default_rho_min`:
                 1 degree (:data:`DEFAULT_FOVEA_RADIUS_RAD`, why: see there) or rho_max if smaller.
        noise:   noise standard deviation as a fraction of the local spacing, >= 0 (0: no noise).

    Returns:
        (rho, theta): [P] float64 eccentricities in [0, rho_max] and [P] float64 polar angles in
        [0, 2 pi), both [rad]; disk first, then ring by ring.

    Raises:
        ValueError: on a bad P, rho_max, rho_min, seed or noise.
    """
    P = _check_count(P)
    rho_max = _check_angle("rho_max", rho_max, 0.0, math.pi)
    seed = _check_seed(seed)
    noise = _check_noise(noise)
    rho_min = default_rho_min(rho_max) if rho_min is None else _check_angle("rho_min", rho_min, 0.0, rho_max)
    rng = np.random.default_rng(seed)

    rings, per_ring, n_disk, d = _log_polar_counts(P, math.log(rho_max / rho_min))

    # Central disk: Vogel spiral.
    j = np.arange(n_disk, dtype=np.float64)
    r = rho_min * np.sqrt((j + 0.5) / max(n_disk, 1))
    phi = j * (math.pi * (3.0 - math.sqrt(5.0))) + rng.uniform(0.0, 2.0 * math.pi)
    x, y = r * np.cos(phi), r * np.sin(phi)
    if n_disk:
        sigma = noise * rho_min * math.sqrt(math.pi / n_disk)
        x += sigma * rng.standard_normal(n_disk)
        y += sigma * rng.standard_normal(n_disk)
    rho_disk, theta_disk = np.hypot(x, y), np.arctan2(y, x)

    # Log-polar rings.
    ring = np.repeat(np.arange(rings, dtype=np.float64), per_ring)
    k = np.tile(np.arange(per_ring, dtype=np.float64), rings)
    step = 2.0 * math.pi / per_ring if per_ring else 0.0
    u = math.log(rho_min) + (ring + 0.5) * d
    theta_ring = (k + 0.5 * (ring % 2)) * step
    n_ring = rings * per_ring
    u += noise * d * rng.standard_normal(n_ring)
    theta_ring += noise * step * rng.standard_normal(n_ring)

    rho = np.concatenate([rho_disk, np.exp(u)])
    theta = np.concatenate([theta_disk, theta_ring])
    return _finish(rho, theta, rho_max)


# --- cone density ------------------------------------------------------------------------------------
def cone_density_per_mm2(eccentricity_mm):
    """Human cone density [cones/mm^2] at an eccentricity [mm along the retina from the foveal centre].

    Piecewise log-linear interpolation of :data:`CONE_DENSITY_TABLE` (Curcio et al. 1990, the mean of the
    four principal meridians): log density is linear in eccentricity between rows, so the density is
    positive, continuous and monotone where the table is. Beyond the last row (18 mm) it stays at
    4,000/mm^2 (Curcio et al. report a flat, slightly rising far periphery).

    Args:
        eccentricity_mm: scalar or array of finite eccentricities >= 0 [mm].

    Returns:
        Density [cones/mm^2]: a float for a scalar, else a float64 array of the same shape.

    Raises:
        ValueError: negative or non-finite eccentricities.
    """
    e = np.asarray(eccentricity_mm, dtype=np.float64)
    if not np.isfinite(e).all() or (e < 0).any():
        raise ValueError(f"eccentricity_mm: expected finite values >= 0 (mm), got {eccentricity_mm!r}")
    dens = np.exp(np.interp(e, CONE_DENSITY_TABLE[:, 0], _LOG_CONE_DENSITY))
    return float(dens) if dens.ndim == 0 else dens


def _cone_radial_profile(P: int, rho_max: float):
    """Quadrature grid for the cone layout: (rho [rad], cumulative count N(rho), ring coordinate I(rho)).

    N(rho) = c * integral_0^rho D(R r) 2 pi R^2 sin r dr, with c chosen so N(rho_max) = P, is the expected
    number of photoreceptors within rho; I(rho) = integral_0^rho R sqrt(c D(R r)) dr counts local
    spacings 1 / sqrt(c D) [mm] along the radius. R = 12 mm.
    """
    R = RETINA_RADIUS_MM
    rho = np.linspace(0.0, rho_max, _QUADRATURE_POINTS)
    dens = cone_density_per_mm2(R * rho)
    dr = rho[1] - rho[0]

    def cumtrapz(f: np.ndarray) -> np.ndarray:
        out = np.empty_like(f)
        out[0] = 0.0
        np.cumsum(0.5 * (f[1:] + f[:-1]) * dr, out=out[1:])
        return out

    count = cumtrapz(dens * (2.0 * math.pi * R * R) * np.sin(rho))
    scale = P / count[-1]
    count *= scale
    count[-1] = P
    ring_coord = cumtrapz(R * np.sqrt(scale * dens))
    return rho, count, ring_coord


def cone_density_layout(
    P: int,
    rho_max: float,
    seed: int = 0,
    noise: float = 0.15,
) -> tuple[np.ndarray, np.ndarray]:
    """Photoreceptors with the human cone density profile (:func:`cone_density_per_mm2`), scaled to P.

    The target density on the 12 mm retina sphere is n(rho) = c D(12 mm * rho) [1/mm^2], with c such that
    integral_0^rho_max n 2 pi R^2 sin(rho) d rho = P (area element R^2 sin rho d rho d theta). It is built
    from rings, without any neighbour search, so it scales to millions of photoreceptors:

    1. the ring coordinate I(rho) = integral R sqrt(n) d rho counts local spacings s = 1 / sqrt(n) along
       the radius; N_r = round(I(rho_max)) rings split [0, rho_max] into bands of equal I (so each band
       is one local spacing wide), and ring k sits at the band's middle in I;
    2. ring k holds the expected count of its band, n_k = round(N(b_k+1)) - round(N(b_k)) with N the
       cumulative expected count (so sum n_k = P exactly); a band one spacing wide has n_k ~ its
       circumference / s, i.e. equal radial and tangential spacing;
    3. the n_k photoreceptors of ring k are spaced 2 pi / n_k apart from a seeded random phase (no
       radial spokes), and get Gaussian noise of ``noise`` x the local spacing: the band width in rho,
       2 pi / n_k in theta. Points pushed past rho_max are reflected back.

    Args:
        P:       number of photoreceptors, a positive int (5,000,000 is about the human cone count).
        rho_max: largest eccentricity [rad] in (0, pi].
        seed:    seeds the ring phases and the noise (non-negative int).
        noise:   noise standard deviation as a fraction of the local spacing, >= 0.

    Returns:
        (rho, theta): [P] float64 eccentricities in [0, rho_max] and polar angles in [0, 2 pi) [rad],
        ring by ring from the fovea out.

    Raises:
        ValueError: on a bad P, rho_max, seed or noise.
    """
    P = _check_count(P)
    rho_max = _check_angle("rho_max", rho_max, 0.0, math.pi)
    seed = _check_seed(seed)
    noise = _check_noise(noise)
    rng = np.random.default_rng(seed)

    grid, count, ring_coord = _cone_radial_profile(P, rho_max)
    rings = max(1, round(float(ring_coord[-1])))
    band = ring_coord[-1] / rings
    bounds = np.interp(np.arange(rings + 1) * band, ring_coord, grid)
    bounds[0], bounds[-1] = 0.0, rho_max
    centres = np.interp((np.arange(rings) + 0.5) * band, ring_coord, grid)
    cum = np.rint(np.interp(bounds, grid, count)).astype(np.int64)
    cum[0], cum[-1] = 0, P
    per_ring = np.diff(cum)  # >= 0: rounding a non-decreasing sequence keeps it non-decreasing

    ring = np.repeat(np.arange(rings, dtype=np.int32), per_ring)
    phase = rng.uniform(0.0, 2.0 * math.pi, size=rings)
    step = 2.0 * math.pi / np.maximum(per_ring, 1)
    width = np.diff(bounds)

    theta = np.arange(P, dtype=np.float64)
    theta -= cum[:-1][ring]  # index within the ring
    theta *= step[ring]
    theta += phase[ring]
    theta += (noise * step)[ring] * rng.standard_normal(P)
    rho = centres[ring]
    rho += (noise * width)[ring] * rng.standard_normal(P)
    return _finish(rho, theta, rho_max)


# --- coordinates ---------------------------------------------------------------------------------------
def eye_positions_m(rho, theta) -> np.ndarray:
    """Photoreceptor positions in the eye frame [m]: 0.012 * (sin rho cos theta, sin rho sin theta, -cos rho).

    Args:
        rho:   [P] eccentricities [rad]; theta: [P] polar angles [rad].

    Returns:
        [P, 3] float64, on the sphere of radius ``RETINA_RADIUS_MM`` / 1000 about the eyeball centre.
    """
    rho = np.asarray(rho, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    s = np.sin(rho)
    out = np.empty(rho.shape + (3,), dtype=np.float64)
    out[..., 0] = s * np.cos(theta)
    out[..., 1] = s * np.sin(theta)
    out[..., 2] = -np.cos(rho)
    out *= RETINA_RADIUS_M
    return out


def _domain_xy(rho: np.ndarray, theta: np.ndarray) -> np.ndarray:
    return np.stack([rho * np.cos(theta), rho * np.sin(theta)], axis=-1)
