"""Light-adapted pupil diameter from luminance: the unified formula of Watson & Yellott (2012).

Watson, A. B. & Yellott, J. I. (2012). A unified formula for light-adapted pupil size. Journal of Vision
12(10):12, 1-16. The formula combines luminance, the size of the adapting field, the observer's age and
whether one or both eyes are adapted:

1. effective corneal flux density   F = L * a * M(e)                       [cd m^-2 deg^2]
   L = luminance of the adapting field [cd/m^2], a = its area [deg^2] (a circular field of diameter d
   degrees has a = pi d^2 / 4), M(e) = the monocular effect: M(1) = 0.1 (one eye adapted),
   M(2) = 1 (both eyes).
2. Stanley & Davies (1995), applied to F:
   D_SD(F) = 7.75 - 5.75 * (F/846)^0.41 / ((F/846)^0.41 + 2)                [mm]
   It falls from 7.75 mm (F -> 0) towards 2 mm (F -> infinity); at F = 846 it is 7.75 - 5.75/3.
3. the age correction, with the reference age y0 = 28.58 years:
   D_U = D_SD + (y - y0) * (0.02132 - 0.009562 * D_SD)                        [mm]
   Older eyes have smaller pupils in the dark (D_SD > 0.02132 / 0.009562 = 2.23 mm) and very slightly
   larger ones in the brightest light. Watson & Yellott fitted it over ages 20-83; outside that range the
   formula is an extrapolation.

Plain numpy; vectorised over every argument (they broadcast against each other).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "LUMINANCE_CALIBRATION",
    "adapting_luminance",
    "luminance_for_diameter",
    "MONOCULAR_EFFECT",
    "REFERENCE_AGE_YEARS",
    "corneal_flux_density",
    "pupil_diameter_mm",
    "stanley_davies_diameter_mm",
]

#: y0 of the unified formula [years]: at this age the age term vanishes (D_U = D_SD).
REFERENCE_AGE_YEARS = 28.58

#: M(e): the monocular effect for e = 1 (one eye adapted) and e = 2 (both eyes adapted).
MONOCULAR_EFFECT = {1: 0.1, 2: 1.0}

#: Stanley & Davies (1995) constants: the flux density scale [cd m^-2 deg^2] and the exponent.
_SD_FLUX_SCALE = 846.0
_SD_EXPONENT = 0.41


def _check_real(name: str, value, *, allow_zero: bool, upper: float | None = None) -> np.ndarray:
    """``value`` as a float64 array of finite numbers >= 0 (> 0 unless ``allow_zero``), <= ``upper``."""
    if isinstance(value, bool) or (isinstance(value, np.ndarray) and value.dtype == bool):
        raise ValueError(f"{name}: expected real numbers, got a boolean {value!r}")
    arr = np.asarray(value)
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(f"{name}: expected real numbers, got {value!r} (dtype {arr.dtype})")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: expected finite values, got {int((~np.isfinite(arr)).sum())} NaN/inf entries")
    low = 0.0
    if allow_zero:
        bad = arr < low
        what = ">= 0"
    else:
        bad = arr <= low
        what = "> 0"
    if upper is not None:
        bad = bad | (arr > upper)
        what += f" and <= {upper:g}"
    if bad.any():
        raise ValueError(f"{name}: expected values {what}, got {arr[bad].reshape(-1)[:5].tolist()} (first offending)")
    return arr


def _check_eyes(eyes) -> int:
    if isinstance(eyes, bool) or not isinstance(eyes, (int, np.integer)) or int(eyes) not in MONOCULAR_EFFECT:
        raise ValueError(f"eyes: expected 1 (one eye adapted) or 2 (both eyes), got {eyes!r}")
    return int(eyes)


def corneal_flux_density(luminance_cd_m2, field_deg=60.0, eyes: int = 1):
    """The effective corneal flux density F = L * a * M(e) of Watson & Yellott (2012).

    Args:
        luminance_cd_m2: L, the adapting field's luminance [cd/m^2], >= 0; scalar or array.
        field_deg:       the adapting field's diameter [deg of visual angle], > 0 and <= 360 (a circular
                         field: area a = pi * (field_deg / 2)^2 [deg^2]); broadcasts with the luminance.
        eyes:            e, how many eyes see the field: 1 (M = 0.1) or 2 (M = 1).

    Returns:
        F [cd m^-2 deg^2]: a float for scalar inputs, else a float64 array of the broadcast shape.

    Raises:
        ValueError: negative, NaN or infinite luminance; a non-positive, non-finite or > 360 deg field;
            eyes not in {1, 2}.
    """
    lum = _check_real("luminance_cd_m2", luminance_cd_m2, allow_zero=True)
    field = _check_real("field_deg", field_deg, allow_zero=False, upper=360.0)
    e = _check_eyes(eyes)
    area_deg2 = math.pi * (field / 2.0) ** 2
    flux = lum * area_deg2 * MONOCULAR_EFFECT[e]
    return float(flux) if flux.ndim == 0 else flux


def stanley_davies_diameter_mm(flux_density):
    """Stanley & Davies (1995) pupil diameter [mm] from the corneal flux density F [cd m^-2 deg^2] (>= 0).

    D_SD = 7.75 - 5.75 * (F/846)^0.41 / ((F/846)^0.41 + 2); 7.75 mm at F = 0, decreasing towards 2 mm.
    Returns a float for a scalar input, else a float64 array.
    """
    flux = _check_real("flux_density", flux_density, allow_zero=True)
    s = (flux / _SD_FLUX_SCALE) ** _SD_EXPONENT
    d = 7.75 - 5.75 * (s / (s + 2.0))
    return float(d) if d.ndim == 0 else d


def pupil_diameter_mm(
    luminance_cd_m2,
    field_deg=60.0,
    age_years=REFERENCE_AGE_YEARS,
    eyes: int = 1,
):
    """Light-adapted pupil diameter by the Watson & Yellott (2012) unified formula.

    D_U = D_SD(F) + (y - y0) * (0.02132 - 0.009562 * D_SD(F)), with F = L * a * M(e) (module docstring).
    The default is the simulated human's case: one eye adapted (e = 1), age y = y0 = 28.58 years (no age
    term), a 60 deg diameter adapting field.

    Args:
        luminance_cd_m2: L, the adapting field's luminance [cd/m^2], >= 0; scalar or array (the result
                         is vectorised over it).
        field_deg:       the adapting field's diameter [deg of visual angle], in (0, 360]; its area is
                         a = pi * (field_deg / 2)^2 [deg^2].
        age_years:       y, the observer's age [years], in (0, 120]; the fit covers 20-83 years.
        eyes:            e, how many eyes are adapted: 1 (monocular, M = 0.1) or 2 (binocular, M = 1).

    All numeric arguments broadcast against each other.

    Returns:
        Pupil diameter [mm] (the entrance pupil, as the fitted studies report it): a float when every
        argument is a scalar, else a float64 ndarray of the broadcast shape. 7.75 mm in the dark at
        age y0; it decreases monotonically with luminance.

    Raises:
        ValueError: negative, NaN or infinite luminance; a field outside (0, 360] deg; an age outside
            (0, 120] years or not finite; eyes not in {1, 2}; non-numeric input.
    """
    flux = np.asarray(corneal_flux_density(luminance_cd_m2, field_deg, eyes))
    age = _check_real("age_years", age_years, allow_zero=False, upper=120.0)
    d_sd = np.asarray(stanley_davies_diameter_mm(flux))
    d = d_sd + (age - REFERENCE_AGE_YEARS) * (0.02132 - 0.009562 * d_sd)
    return float(d) if d.ndim == 0 else d


def luminance_for_diameter(diameter_mm, field_deg=60.0, eyes: int = 1):
    """The luminance (cd/m^2) whose light-adapted pupil (:func:`pupil_diameter_mm` at the reference age)
    is ``diameter_mm``: Stanley & Davies inverted in closed form. Diameters are clipped into the formula's
    open range (2, 7.75) mm, so 2 mm and below give a very bright, 7.75 mm and above a very dim luminance."""
    d = _check_real("diameter_mm", diameter_mm, allow_zero=False)
    k = np.clip((7.75 - d) / 5.75, 1e-9, 1 - 1e-9)  # s / (s + 2)
    s = 2.0 * k / (1.0 - k)
    flux = _SD_FLUX_SCALE * s ** (1.0 / _SD_EXPONENT)
    field = _check_real("field_deg", field_deg, allow_zero=False, upper=360.0)
    lum = flux / (np.pi * field**2 / 4.0 * MONOCULAR_EFFECT[_check_eyes(eyes)])
    return float(lum) if lum.ndim == 0 else lum


#: The renderer's radiance in photometric units: the adapting luminance (cd/m^2) of a scene whose ONV,
#: seen through a pupil of D mm, has a mean irradiance (over every photoreceptor and channel) of m is
#: ``LUMINANCE_CALIBRATION * m / D**2`` (the irradiance grows with the pupil's area). The constant is set
#: once so that the foveation training room (data generator v7, seen through its 4 mm pupil; mean
#: irradiance 0.00279 over the default left dataset) is the luminance whose Watson & Yellott pupil is
#: those 4 mm: 75.2 cd/m^2 * 16 mm^2 / 0.00279 = 4.31e5. A loop whose pupil follows this law keeps the
#: foveation nets' ONVs as bright as the ones they were trained on.
LUMINANCE_CALIBRATION = 4.31e5


def adapting_luminance(onv_mean, pupil_mm):
    """The adapting luminance (cd/m^2) of a scene whose ONV, seen through a ``pupil_mm`` pupil, has mean
    irradiance ``onv_mean`` (:data:`LUMINANCE_CALIBRATION`). Vectorised; both must be > 0."""
    m = _check_real("onv_mean", onv_mean, allow_zero=False)
    d = _check_real("pupil_mm", pupil_mm, allow_zero=False)
    lum = LUMINANCE_CALIBRATION * m / d**2
    return float(lum) if lum.ndim == 0 else lum
