"""Tests for warp_vision.eye.pupil (Watson & Yellott 2012 unified formula)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from warp_vision.eye.pupil import corneal_flux_density, pupil_diameter_mm, stanley_davies_diameter_mm


def _luminance_for_flux(flux: float, field_deg: float = 60.0, monocular: float = 0.1) -> float:
    """The luminance that gives corneal flux density ``flux`` (written out independently of the module)."""
    area = math.pi * field_deg**2 / 4.0
    return flux / (area * monocular)


def test_dark_limit_is_7_75_mm_at_reference_age():
    assert pupil_diameter_mm(0.0) == pytest.approx(7.75, abs=1e-12)
    assert pupil_diameter_mm(1e-12) == pytest.approx(7.75, abs=1e-3)


def test_bright_limit_tends_to_2_mm():
    assert pupil_diameter_mm(1e12) == pytest.approx(2.0, abs=0.05)
    assert pupil_diameter_mm(1e12) > 2.0


def test_hand_computed_values():
    # F = 846: (F/846)^0.41 = 1, the fraction is 1/3 -> D = 7.75 - 5.75/3.
    lum = _luminance_for_flux(846.0)
    assert pupil_diameter_mm(lum) == pytest.approx(7.75 - 5.75 / 3.0, rel=1e-12)
    # F = 846 * 2^(1/0.41): (F/846)^0.41 = 2, fraction 1/2 -> D = 7.75 - 2.875 = 4.875.
    lum = _luminance_for_flux(846.0 * 2.0 ** (1.0 / 0.41))
    assert pupil_diameter_mm(lum) == pytest.approx(4.875, rel=1e-12)
    # A typical indoor case worked by hand: L = 100 cd/m^2, 60 deg field, one eye:
    # a = pi * 30^2 = 2827.43 deg^2, F = 100 * 2827.43 * 0.1 = 28274.3, F/846 = 33.421,
    # 33.421^0.41 = exp(0.41 * ln 33.421) = exp(0.41 * 3.50918) = exp(1.438764) = 4.21550,
    # fraction = 4.21550 / 6.21550 = 0.678224, D = 7.75 - 5.75 * 0.678224 = 3.85021 mm.
    assert pupil_diameter_mm(100.0) == pytest.approx(3.85021, abs=2e-5)
    assert corneal_flux_density(100.0) == pytest.approx(28274.33, rel=1e-6)
    # Age term at F = 846 for a 60-year-old: D_SD = 5.83333,
    # D = 5.83333 + 31.42 * (0.02132 - 0.009562 * 5.83333) = 5.83333 + 31.42 * (-0.034458) = 4.75065 mm.
    d_sd = 7.75 - 5.75 / 3.0
    expected = d_sd + (60.0 - 28.58) * (0.02132 - 0.009562 * d_sd)
    assert pupil_diameter_mm(_luminance_for_flux(846.0), age_years=60.0) == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(4.75065, abs=1e-4)


def test_monotone_decreasing_in_luminance():
    lum = np.logspace(-6, 8, 200)
    d = pupil_diameter_mm(lum)
    assert isinstance(d, np.ndarray) and d.shape == lum.shape
    assert np.all(np.diff(d) < 0)
    assert np.all((d > 2.0) & (d < 7.75))


def test_vectorised_matches_scalar_and_broadcasts():
    lum = np.array([[0.01, 1.0], [100.0, 1e4]])
    d = pupil_diameter_mm(lum, age_years=45.0, eyes=2)
    assert d.shape == (2, 2)
    for idx in np.ndindex(lum.shape):
        # to 2 ulp: numpy 1.x's array loops and scalar maths may round differently (numpy 2's agree)
        np.testing.assert_array_max_ulp(d[idx], pupil_diameter_mm(float(lum[idx]), age_years=45.0, eyes=2), maxulp=2)
    ages = np.array([20.0, 40.0, 80.0])
    assert pupil_diameter_mm(10.0, age_years=ages).shape == (3,)
    assert isinstance(pupil_diameter_mm(10.0), float)


def test_age_effect_sign():
    # Dark/dim: D_SD > 2.23 mm, older eyes have smaller pupils.
    for lum in (0.001, 1.0, 100.0):
        assert pupil_diameter_mm(lum, age_years=70.0) < pupil_diameter_mm(lum, age_years=28.58)
        assert pupil_diameter_mm(lum, age_years=20.0) > pupil_diameter_mm(lum, age_years=28.58)
    # Extremely bright: D_SD < 0.02132 / 0.009562 = 2.2297 mm, the age term changes sign.
    lum = 1e9
    assert stanley_davies_diameter_mm(corneal_flux_density(lum)) < 0.02132 / 0.009562
    assert pupil_diameter_mm(lum, age_years=70.0) > pupil_diameter_mm(lum, age_years=28.58)


def test_monocular_pupil_larger_than_binocular():
    for lum in (0.01, 1.0, 100.0, 1e4):
        assert pupil_diameter_mm(lum, eyes=1) > pupil_diameter_mm(lum, eyes=2)
    # Binocular = monocular with 10x the luminance (M(2) / M(1) = 10).
    assert pupil_diameter_mm(10.0, eyes=2) == pytest.approx(pupil_diameter_mm(100.0, eyes=1), rel=1e-12)


def test_larger_field_gives_smaller_pupil():
    assert pupil_diameter_mm(10.0, field_deg=10.0) > pupil_diameter_mm(10.0, field_deg=60.0)
    # Doubling the diameter quadruples the area: the same as 4x the luminance.
    assert pupil_diameter_mm(10.0, field_deg=20.0) == pytest.approx(pupil_diameter_mm(40.0, field_deg=10.0), rel=1e-12)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"luminance_cd_m2": -1.0}, "luminance_cd_m2"),
        ({"luminance_cd_m2": float("nan")}, "luminance_cd_m2"),
        ({"luminance_cd_m2": np.array([1.0, np.inf])}, "luminance_cd_m2"),
        ({"luminance_cd_m2": "bright"}, "luminance_cd_m2"),
        ({"luminance_cd_m2": True}, "luminance_cd_m2"),
        ({"luminance_cd_m2": 1.0, "eyes": 3}, "eyes"),
        ({"luminance_cd_m2": 1.0, "eyes": 0}, "eyes"),
        ({"luminance_cd_m2": 1.0, "eyes": 1.0}, "eyes"),
        ({"luminance_cd_m2": 1.0, "field_deg": 0.0}, "field_deg"),
        ({"luminance_cd_m2": 1.0, "field_deg": -5.0}, "field_deg"),
        ({"luminance_cd_m2": 1.0, "field_deg": 400.0}, "field_deg"),
        ({"luminance_cd_m2": 1.0, "age_years": float("nan")}, "age_years"),
        ({"luminance_cd_m2": 1.0, "age_years": -3.0}, "age_years"),
        ({"luminance_cd_m2": 1.0, "age_years": 500.0}, "age_years"),
    ],
)
def test_bad_input_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        pupil_diameter_mm(**kwargs)
