"""The Navarro (1985) accommodating schematic eye, traced exactly in float64 numpy.

Frames and units (docs/ARCHITECTURE.md): everything in this module is in millimetres in the *optical
frame* (origin at the corneal apex, +z pointing into the eye, +y up, +x = y cross z). The eye frame used
by the rest of the package (metres, origin at the eyeball centre, +z out of the pupil) is reached only
through :func:`eye_from_optical` / :func:`optical_from_eye` and their direction variants.

Surfaces are conicoids of revolution with vertex ``z0``, vertex radius ``R`` and conic constant ``Q``::

    x^2 + y^2 + (1 + Q) s^2 - 2 R s = 0,    s = z - z0,

whose vertex sheet is the sag ``s = r^2 / (R (1 + sqrt(1 - (1 + Q) r^2 / R^2)))``. Rays are refracted
with the vector form of Snell's law; total internal reflection, missing a surface, leaving its aperture
or hitting the iris makes a ray invalid.

The Warp ray tracer (:mod:`warp_vision.kernels.render`) implements the same optics in float32 and is
tested against this module.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

# --- frames ---------------------------------------------------------------------------------------
EYE_CENTRE_MM = 12.00398
"""Distance of the eyeball centre (the retina sphere's centre, the rotation centre) behind the apex."""
RETINA_RADIUS_MM = 12.0
RETINA_VERTEX_MM = 24.00398
"""Axial length: apex to retina vertex (the fovea), the same for every accommodation."""


def eye_from_optical(points_mm: np.ndarray) -> np.ndarray:
    """Optical-frame points [..., 3] (mm) -> eye-frame points [..., 3] (m).

    The two frames differ by a half turn about y (x and z flip), a shift of ``EYE_CENTRE_MM`` and the
    unit change; the same function is its own inverse up to that shift and scale.
    """
    p = np.asarray(points_mm, dtype=np.float64)
    out = np.empty_like(p)
    out[..., 0] = -p[..., 0] * 1e-3
    out[..., 1] = p[..., 1] * 1e-3
    out[..., 2] = (EYE_CENTRE_MM - p[..., 2]) * 1e-3
    return out


def optical_from_eye(points_m: np.ndarray) -> np.ndarray:
    """Eye-frame points [..., 3] (m) -> optical-frame points [..., 3] (mm)."""
    p = np.asarray(points_m, dtype=np.float64)
    out = np.empty_like(p)
    out[..., 0] = -p[..., 0] * 1e3
    out[..., 1] = p[..., 1] * 1e3
    out[..., 2] = EYE_CENTRE_MM - p[..., 2] * 1e3
    return out


def eye_from_optical_dir(directions: np.ndarray) -> np.ndarray:
    """Directions [..., 3] in the optical frame -> the eye frame (unitless; x and z flip)."""
    d = np.array(directions, dtype=np.float64, copy=True)
    d[..., 0] *= -1.0
    d[..., 2] *= -1.0
    return d


# --- media ----------------------------------------------------------------------------------------
_WAVELENGTHS_NM = np.array([458.0, 543.0, 589.0, 633.0])
# columns: cornea, aqueous, lens (relaxed), vitreous; rows follow _WAVELENGTHS_NM (Navarro 1985)
_INDICES = np.array(
    [
        [1.3828, 1.3445, 1.4292, 1.3428],
        [1.3777, 1.3391, 1.4222, 1.3377],
        [1.3771, 1.3374, 1.4200, 1.3360],
        [1.3747, 1.3360, 1.4183, 1.3347],
    ]
)
CHANNEL_WAVELENGTHS_NM = (633.0, 543.0, 458.0)
"""The wavelengths of the R, G and B channels (the ONV's 3 values per photoreceptor)."""


def refractive_indices(wavelength_nm: float, accommodation_D: float = 0.0) -> tuple[float, float, float, float]:
    """(cornea, aqueous, lens, vitreous) indices at ``wavelength_nm`` (458 to 633 nm).

    Navarro's values at 458, 543, 589 and 633 nm, interpolated piecewise-linearly in 1/lambda^2 (the
    Cauchy variable) between them. The lens index rises with accommodation by 9e-5 (10 A + A^2).
    """
    wl = float(wavelength_nm)
    if not (_WAVELENGTHS_NM[0] <= wl <= _WAVELENGTHS_NM[-1]):
        raise ValueError(f"wavelength_nm: expected 458 to 633 nm (the tabulated range), got {wavelength_nm}")
    x = 1.0 / wl**2
    xs = 1.0 / _WAVELENGTHS_NM[::-1] ** 2  # increasing
    n = [float(np.interp(x, xs, _INDICES[::-1, k])) for k in range(4)]
    A = float(accommodation_D)
    n[2] += 9e-5 * (10.0 * A + A * A)
    return n[0], n[1], n[2], n[3]


# --- surfaces -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Surface:
    """One refracting conicoid: vertex at ``z0`` mm, vertex radius ``R`` mm, conic ``Q``.

    ``n_front`` / ``n_back`` are the indices in front of (smaller z) and behind the surface;
    ``semi_diameter`` (mm) is the clear aperture radius (beyond it the ray is blocked).
    """

    name: str
    z0: float
    R: float
    Q: float
    n_front: float
    n_back: float
    semi_diameter: float


def sag(r: np.ndarray, R: float, Q: float) -> np.ndarray:
    """Sag s(r) (mm) of a conicoid's vertex sheet at radial distance r (mm)."""
    r = np.asarray(r, dtype=np.float64)
    return r * r / (R * (1.0 + np.sqrt(1.0 - (1.0 + Q) * r * r / (R * R))))


def _intersect_conic(o, d, s: Surface, valid):
    """Closest forward hit of rays o + t d with the vertex sheet of ``s`` inside its aperture.

    Returns (points [N,3], unit normals [N,3] (pointing to +z at the vertex), valid [N]).
    """
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return _intersect_conic_impl(o, d, s, valid)


def _intersect_conic_impl(o, d, s: Surface, valid):
    k = 1.0 + s.Q
    oz = o[:, 2] - s.z0
    a = d[:, 0] ** 2 + d[:, 1] ** 2 + k * d[:, 2] ** 2
    b = 2.0 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] + k * oz * d[:, 2] - s.R * d[:, 2])
    c = o[:, 0] ** 2 + o[:, 1] ** 2 + k * oz * oz - 2.0 * s.R * oz
    eps = 1e-12
    best = np.full(len(o), np.inf)
    lin = np.abs(a) < eps
    disc = b * b - 4.0 * a * c
    sq = np.sqrt(np.where(disc >= 0.0, disc, 0.0))
    roots = [
        np.where(lin, -c / np.where(b == 0, eps, b), (-b - sq) / (2.0 * np.where(lin, 1.0, a))),
        np.where(lin, np.inf, (-b + sq) / (2.0 * np.where(lin, 1.0, a))),
    ]
    for t in roots:
        p = o + t[:, None] * d
        ps = p[:, 2] - s.z0
        r2 = p[:, 0] ** 2 + p[:, 1] ** 2
        ok = (
            (t > 1e-9)
            & np.isfinite(t)
            & (lin | (disc >= 0.0))
            & ((k * ps - s.R) * s.R < 0.0)  # the vertex sheet, not the conic's far sheet
            & (r2 <= s.semi_diameter**2)
        )
        best = np.where(ok & (t < best), t, best)
    hit = valid & np.isfinite(best)
    t = np.where(hit, best, 0.0)
    p = o + t[:, None] * d
    n = np.stack([-p[:, 0], -p[:, 1], s.R - k * (p[:, 2] - s.z0)], axis=1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return p, n, hit


def refract(d: np.ndarray, n: np.ndarray, eta: np.ndarray | float):
    """Vector Snell: unit directions d [N,3] through unit normals n [N,3], eta = n1 / n2.

    Returns (refracted unit directions [N,3], ok [N]) where ok is False on total internal reflection.
    The normal's orientation does not matter.
    """
    cos_i = -np.sum(d * n, axis=1)
    n = np.where((cos_i < 0.0)[:, None], -n, n)
    cos_i = np.abs(cos_i)
    eta = np.asarray(eta, dtype=np.float64)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    ok = k >= 0.0
    t = eta[..., None] * d + (eta * cos_i - np.sqrt(np.where(ok, k, 0.0)))[:, None] * n
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, ok


def _normalize(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _check_rays(name_o, o, name_d, d):
    o = np.asarray(o, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    if o.ndim != 2 or o.shape[1] != 3:
        raise ValueError(f"{name_o}: expected shape [N, 3], got {o.shape}")
    if d.shape != o.shape:
        raise ValueError(f"{name_d}: expected shape [{len(o)}, 3], got {d.shape}")
    for name, a in ((name_o, o), (name_d, d)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return o, d


def _number(name: str, value, low: float, high: float, unit: str) -> float:
    """``value`` as a float in [low, high], or a ValueError naming ``name`` (None, strings, NaN, inf, out of range)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if isinstance(value, bool) or not np.isfinite(v) or not low <= v <= high:
        raise ValueError(f"{name}: expected {low:g} to {high:g} {unit}, got {value!r}")
    return v


class NavarroEye:
    """Navarro's (1985) accommodating wide-angle schematic eye.

    accommodation_D: lens accommodation A in dioptres (0 = relaxed, focused at infinity), 0 to 10.
    pupil_diameter_mm: entrance aperture (the iris) diameter, 1 to 9 mm; the stop is a flat disc at
        the lens' front vertex.
    cornea_semi_diameter_mm, lens_semi_diameter_mm: clear apertures (the limbus; the lens equator).
    """

    def __init__(
        self,
        accommodation_D: float = 0.0,
        pupil_diameter_mm: float = 4.0,
        cornea_semi_diameter_mm: float = 6.0,
        lens_semi_diameter_mm: float = 4.5,
    ):
        A = _number("accommodation_D", accommodation_D, 0.0, 10.0, "dioptres")
        D = _number("pupil_diameter_mm", pupil_diameter_mm, 1.0, 9.0, "mm")
        self.accommodation_D = A
        self.pupil_diameter_mm = D
        self.cornea_semi_diameter_mm = _number("cornea_semi_diameter_mm", cornea_semi_diameter_mm, 1.0, 12.0, "mm")
        self.lens_semi_diameter_mm = _number("lens_semi_diameter_mm", lens_semi_diameter_mm, 1.0, 12.0, "mm")
        L = np.log(A + 1.0)
        self.pupil_z_mm = 0.55 + 3.05 - 0.05 * L
        """z of the stop plane (= the lens front vertex), mm."""
        self.lens_thickness_mm = 4.0 + 0.1 * L
        self._lens_front = (10.2 - 1.75 * L, -3.1316 - 0.34 * L)
        self._lens_back = (-6.0 + 0.2294 * L, -1.0 - 0.125 * L)

    def __repr__(self) -> str:
        return f"NavarroEye(accommodation_D={self.accommodation_D:g}, pupil_diameter_mm={self.pupil_diameter_mm:g})"

    @property
    def pupil_radius_mm(self) -> float:
        return 0.5 * self.pupil_diameter_mm

    @property
    def pupil_area_mm2(self) -> float:
        return np.pi * self.pupil_radius_mm**2

    def surfaces(self, wavelength_nm: float = 589.0) -> list[Surface]:
        """The four refracting surfaces, front to back, with the media's indices at ``wavelength_nm``."""
        nc, na, nl, nv = refractive_indices(wavelength_nm, self.accommodation_D)
        zl = self.pupil_z_mm
        cs, ls = self.cornea_semi_diameter_mm, self.lens_semi_diameter_mm
        return [
            Surface("cornea_front", 0.0, 7.72, -0.26, 1.0, nc, cs),
            Surface("cornea_back", 0.55, 6.50, 0.0, nc, na, cs),
            Surface("lens_front", zl, *self._lens_front, na, nl, ls),
            Surface("lens_back", zl + self.lens_thickness_mm, *self._lens_back, nl, nv, ls),
        ]

    # --- paraxial optics ----------------------------------------------------------------------
    def system_matrix(self, wavelength_nm: float = 589.0) -> np.ndarray:
        """Paraxial ray-transfer matrix (reduced angles n*u) from the cornea's vertex to the lens' back vertex."""
        M = np.eye(2)
        z = 0.0
        for s in self.surfaces(wavelength_nm):
            M = np.array([[1.0, (s.z0 - z) / s.n_front], [0.0, 1.0]]) @ M  # transfer in the front medium
            M = np.array([[1.0, 0.0], [-(s.n_back - s.n_front) / s.R, 1.0]]) @ M
            z = s.z0
        return M

    def power_D(self, wavelength_nm: float = 589.0) -> float:
        """Paraxial power of the whole eye in dioptres (the relaxed Navarro eye: about 60.4 D)."""
        return -self.system_matrix(wavelength_nm)[1, 0] * 1000.0

    # --- exact ray tracing --------------------------------------------------------------------
    def trace_to_retina(self, origins_mm, directions, wavelength_nm: float = 589.0):
        """Trace rays from the air in front of the cornea to the retina.

        origins_mm: [N, 3] mm, optical frame, in front of the cornea; directions: [N, 3] (normalised
        here), pointing into the eye (+z). Returns (points_mm [N, 3] on the retina sphere,
        valid [N] bool); invalid rays (blocked by the iris or a surface's aperture, totally internally
        reflected, or missing a surface) have NaN points.
        """
        o, d = _check_rays("origins_mm", origins_mm, "directions", directions)
        d = _normalize(d)
        valid = np.ones(len(o), dtype=bool)
        s = self.surfaces(wavelength_nm)
        for surf in s[:2]:
            o, n, valid = _intersect_conic(o, d, surf, valid)
            d, ok = refract(d, n, surf.n_front / surf.n_back)
            valid &= ok
        # the stop
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.pupil_z_mm - o[:, 2]) / d[:, 2]
        p = o + t[:, None] * d
        valid &= (d[:, 2] > 0) & (t >= -1e-9) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= self.pupil_radius_mm**2)
        for surf in s[2:]:
            o, n, valid = _intersect_conic(o, d, surf, valid)
            d, ok = refract(d, n, surf.n_front / surf.n_back)
            valid &= ok
        pts, valid = _hit_retina(o, d, valid)
        pts[~valid] = np.nan
        return pts, valid

    def _retina_to_stop(self, q, aim_xy, wavelength_nm, clip: bool = True):
        """From retina points q [N,3] toward aim points on the lens-back vertex plane, out to the stop.

        Returns (stop points [N,3], directions in the aqueous [N,3], valid [N]). With ``clip`` False
        the lens surfaces continue past their apertures (the aiming's Newton steps use that).
        """
        s = self.surfaces(wavelength_nm)
        if not clip:
            s = [replace(x, semi_diameter=np.inf) for x in s]
        z_aim = s[3].z0
        a = np.concatenate([aim_xy, np.full((len(q), 1), z_aim)], axis=1)
        d = _normalize(a - q)
        o = q
        valid = np.ones(len(q), dtype=bool)
        for surf in (s[3], s[2]):
            o, n, valid = _intersect_conic(o, d, surf, valid)
            d, ok = refract(d, n, surf.n_back / surf.n_front)
            valid &= ok
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.pupil_z_mm - o[:, 2]) / d[:, 2]
        valid &= d[:, 2] < 0
        return o + t[:, None] * d, d, valid

    def _aim(self, q, pxy, wavelength_nm, tol_mm=1e-10, max_iter=30):
        """Newton's method on the aim point (lens-back vertex plane) so that the ray from retina point q
        passes through stop point pxy. Returns (aim [N,2], Jacobian d stop / d aim [N,2,2], converged [N])."""
        N = len(q)
        z_aim = self.surfaces(wavelength_nm)[3].z0
        # initial guess: the straight line from q through the pupil point
        f = (z_aim - q[:, 2]) / (self.pupil_z_mm - q[:, 2])
        aim = q[:, :2] + (pxy - q[:, :2]) * f[:, None]
        h = 1e-6
        converged = np.zeros(N, dtype=bool)
        J = np.zeros((N, 2, 2))
        for _ in range(max_iter):
            p0, _, ok0 = self._retina_to_stop(q, aim, wavelength_nm, clip=False)
            err = p0[:, :2] - pxy
            for j in range(2):
                da = np.zeros(2)
                da[j] = h
                pp, _, okp = self._retina_to_stop(q, aim + da, wavelength_nm, clip=False)
                pm, _, okm = self._retina_to_stop(q, aim - da, wavelength_nm, clip=False)
                J[:, :, j] = (pp[:, :2] - pm[:, :2]) / (2 * h)
                ok0 &= okp & okm
            converged = ok0 & (np.max(np.abs(err), axis=1) < tol_mm)
            if np.all(converged | ~ok0):
                break
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            det = np.where(ok0 & (np.abs(det) > 1e-30), det, 1.0)
            step0 = (J[:, 1, 1] * err[:, 0] - J[:, 0, 1] * err[:, 1]) / det
            step1 = (-J[:, 1, 0] * err[:, 0] + J[:, 0, 0] * err[:, 1]) / det
            move = ok0 & ~converged
            aim[move, 0] -= step0[move]
            aim[move, 1] -= step1[move]
        return aim, J, converged

    def trace_path(self, retina_mm, pupil_xy_mm, wavelength_nm: float = 589.0, world_length_mm: float = 10.0):
        """The polyline of each ray of :meth:`trace_to_world`, for drawings: [N, 7, 3] mm (optical frame).

        Points: retina, lens back, lens front, stop, cornea back, cornea front, and ``world_length_mm``
        further out into the world. Rows of invalid rays are NaN.
        """
        q = np.asarray(retina_mm, dtype=np.float64)
        pxy = np.asarray(pupil_xy_mm, dtype=np.float64)
        s = self.surfaces(wavelength_nm)
        aim, _, converged = self._aim(q, pxy, wavelength_nm)
        pts = [q]
        d = _normalize(np.concatenate([aim, np.full((len(q), 1), s[3].z0)], axis=1) - q)
        o, valid = q, converged.copy()
        for surf in (s[3], s[2]):
            o, n, valid = _intersect_conic(o, d, surf, valid)
            d, ok = refract(d, n, surf.n_back / surf.n_front)
            valid &= ok
            pts.append(o)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.pupil_z_mm - o[:, 2]) / d[:, 2]
        pts.append(o + t[:, None] * d)
        for surf in (s[1], s[0]):
            o, n, valid = _intersect_conic(o, d, surf, valid)
            d, ok = refract(d, n, surf.n_back / surf.n_front)
            valid &= ok
            pts.append(o)
        pts.append(o + world_length_mm * d)
        path = np.stack(pts, axis=1)
        path[~valid] = np.nan
        return path

    def trace_to_world(
        self,
        retina_mm,
        pupil_xy_mm,
        wavelength_nm: float = 589.0,
        return_weights: bool = False,
        tol_mm: float = 1e-10,
        max_iter: int = 30,
    ):
        """Trace from retina points through given points of the stop, out of the cornea into the air.

        retina_mm: [N, 3] mm on the retina sphere (optical frame); pupil_xy_mm: [N, 2] mm, points of
        the stop plane (inside the pupil for valid rays). The direction leaving the retina is found
        by Newton's method on the aim point (exact ray aiming through the lens).

        Returns (origins_mm [N, 3] on the cornea's front surface, directions [N, 3] unit, pointing
        out of the eye into the world, valid [N] bool). With ``return_weights`` also
        ``weights [N]`` in sr/mm^2: the irradiance the retina point gets per unit radiance and per
        unit stop area around that pupil point, ``n_vitreous^2 cos(theta_retina) d(omega)/dA_pupil``
        (radiance scales with n^2 across the media). Integrating it over the pupil gives the
        retinal irradiance per unit scene radiance.
        """
        q = np.asarray(retina_mm, dtype=np.float64)
        pxy = np.asarray(pupil_xy_mm, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 3:
            raise ValueError(f"retina_mm: expected shape [N, 3], got {q.shape}")
        if pxy.shape != (len(q), 2):
            raise ValueError(f"pupil_xy_mm: expected shape [{len(q)}, 2], got {pxy.shape}")
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(pxy))):
            raise ValueError("retina_mm, pupil_xy_mm: expected finite values, got NaN or inf")
        N = len(q)
        s = self.surfaces(wavelength_nm)
        z_aim = s[3].z0
        aim, J, converged = self._aim(q, pxy, wavelength_nm, tol_mm, max_iter)
        p, d, valid = self._retina_to_stop(q, aim, wavelength_nm)
        valid &= converged & (pxy[:, 0] ** 2 + pxy[:, 1] ** 2 <= self.pupil_radius_mm**2 * (1 + 1e-12))
        o = p
        for surf in (s[1], s[0]):
            o, n, valid = _intersect_conic(o, d, surf, valid)
            d, ok = refract(d, n, surf.n_back / surf.n_front)
            valid &= ok
        o[~valid] = np.nan
        d[~valid] = np.nan
        if not return_weights:
            return o, d, valid
        # solid angle per unit aim-plane area, times the cosines, over |d stop / d aim|
        v = np.concatenate([aim, np.full((N, 1), z_aim)], axis=1) - q
        dist = np.linalg.norm(v, axis=1)
        u = v / dist[:, None]
        domega_daim = np.abs(u[:, 2]) / dist**2
        normal_in = _normalize(np.array([0.0, 0.0, EYE_CENTRE_MM]) - q)  # retina normal, into the eye
        cos_r = np.abs(np.sum(u * normal_in, axis=1))
        det = np.abs(J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0])
        nv = s[3].n_back
        w = np.where(valid, nv * nv * cos_r * domega_daim / np.where(det > 0, det, np.inf), 0.0)
        return o, d, valid, w

    def chief_ray(self, retina_mm, wavelength_nm: float = 589.0):
        """Rays from retina points [N, 3] through the pupil centre: (origins_mm, directions, valid)."""
        q = np.asarray(retina_mm, dtype=np.float64)
        return self.trace_to_world(q, np.zeros((len(q), 2)), wavelength_nm)

    def field_angle_deg(self, eccentricity_rad, wavelength_nm: float = 589.0) -> np.ndarray:
        """World angle (deg, from the optical axis) seen by retina points at these eccentricities.

        The eccentricity is the angle at the eyeball centre from the fovea; NaN where the chief
        ray is blocked.
        """
        rho = np.atleast_1d(np.asarray(eccentricity_rad, dtype=np.float64))
        q = np.stack(
            [RETINA_RADIUS_MM * np.sin(rho), np.zeros_like(rho), EYE_CENTRE_MM + RETINA_RADIUS_MM * np.cos(rho)],
            axis=1,
        )
        _, d, valid = self.chief_ray(q, wavelength_nm)
        ang = np.degrees(np.arccos(np.clip(-d[:, 2], -1.0, 1.0)))
        return np.where(valid, ang, np.nan)

    def retina_eccentricity_limit(self, fov_deg: float = 167.5, wavelength_nm: float = 589.0) -> float:
        """The largest retinal eccentricity (rad) that sees the field within ``fov_deg`` / 2 of the axis.

        Photoreceptors beyond it either look outside the field of view or get no light at all
        (their chief ray through the pupil is blocked), so layouts stop there.
        """
        if not 0.0 < fov_deg < 180.0:
            raise ValueError(f"fov_deg: expected degrees in (0, 180), got {fov_deg}")
        rho = np.linspace(1e-3, np.radians(150.0), 1500)
        ang = self.field_angle_deg(rho, wavelength_nm)
        ok = np.isfinite(ang) & (ang <= 0.5 * fov_deg)
        # the field angle grows with eccentricity: the limit is the first failure
        first_bad = int(np.argmin(ok)) if not ok.all() else len(rho)
        if first_bad == 0:
            raise ValueError("no retinal eccentricity receives light for this eye")
        lo, hi = rho[first_bad - 1], rho[min(first_bad, len(rho) - 1)]
        for _ in range(50):  # bisection to 1e-15 rad
            mid = 0.5 * (lo + hi)
            a = self.field_angle_deg(mid, wavelength_nm)[0]
            if np.isfinite(a) and a <= 0.5 * fov_deg:
                lo = mid
            else:
                hi = mid
        return float(lo)


def _hit_retina(o, d, valid):
    """Hit of rays (inside the eye) with the retina sphere: the forward root from inside."""
    c = np.array([0.0, 0.0, EYE_CENTRE_MM])
    oc = o - c
    b = np.sum(oc * d, axis=1)
    cc = np.sum(oc * oc, axis=1) - RETINA_RADIUS_MM**2
    disc = b * b - cc
    t = -b + np.sqrt(np.where(disc >= 0, disc, 0.0))
    valid = valid & (disc >= 0) & (t > 0)
    return o + t[:, None] * d, valid
