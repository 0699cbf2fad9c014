"""Navarro eye optics: physics derived independently of the tracer."""

import numpy as np
import pytest

from warp_vision.eye import optics
from warp_vision.eye.optics import EYE_CENTRE_MM, RETINA_RADIUS_MM, RETINA_VERTEX_MM, NavarroEye

FOVEA = np.array([0.0, 0.0, RETINA_VERTEX_MM])


def retina_point(rho_deg, theta_deg=0.0):
    r, t = np.radians(rho_deg), np.radians(theta_deg)
    return np.array(
        [RETINA_RADIUS_MM * np.sin(r) * np.cos(t), RETINA_RADIUS_MM * np.sin(r) * np.sin(t),
         EYE_CENTRE_MM + RETINA_RADIUS_MM * np.cos(r)]
    )


def hand_paraxial():
    """Navarro's relaxed eye at 589 nm from the published table, by reduced-angle y-nu tracing."""
    # (vertex radius, index after, distance to next surface)
    surfaces = [(7.72, 1.3771, 0.55), (6.50, 1.3374, 3.05), (10.2, 1.42, 4.0), (-6.0, 1.336, None)]
    y, nu, n = 1.0, 0.0, 1.0  # a unit-height ray parallel to the axis
    for R, n2, t in surfaces:
        nu = nu - y * (n2 - n) / R
        n = n2
        if t is not None:
            y = y + t * nu / n
    power = -nu / 1.0 * 1000.0  # dioptres (mm -> m)
    back_focal = -y / (nu / n)  # from the lens' back vertex, mm
    return power, back_focal


def test_paraxial_power_of_the_relaxed_eye():
    power, _ = hand_paraxial()
    assert power == pytest.approx(60.4, abs=0.1)
    assert NavarroEye().power_D() == pytest.approx(power, rel=1e-9)


def test_relaxed_eye_focuses_infinity_on_the_retina():
    _, bfd = hand_paraxial()
    lens_back = 0.55 + 3.05 + 4.0
    assert lens_back + bfd == pytest.approx(RETINA_VERTEX_MM, abs=0.02)
    h = np.array([0.02, 0.1, 0.3, 0.6])
    o = np.stack([np.zeros_like(h), h, np.full_like(h, -5.0)], axis=1)
    d = np.tile([0.0, 0.0, 1.0], (len(h), 1))
    p, valid = NavarroEye(pupil_diameter_mm=2.0).trace_to_retina(o, d)
    assert valid.all()
    assert np.abs(p - FOVEA).max() < 2e-3  # a sharp image: spot radius under 2 um


def best_focus_vergence(eye):
    """Object vergence (D) whose near-axis rays land on the fovea (bisection on the ray's landing height)."""

    def height(V):
        z = -1000.0 / V
        o = np.array([[0.0, 0.0, z]])
        d = np.array([[0.0, 0.2, eye.pupil_z_mm - z]])  # a ray through the stop at 0.2 mm
        p, valid = eye.trace_to_retina(o, d)
        assert valid.all()
        return p[0, 1]

    lo, hi = 0.05, 20.0
    assert height(lo) * height(hi) < 0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if height(mid) * height(lo) > 0:
            lo = mid
        else:
            hi = mid
    return lo


@pytest.mark.parametrize("A", [1.0, 2.0, 4.0, 8.0])
def test_accommodation_focuses_at_one_over_A_metres(A):
    V = best_focus_vergence(NavarroEye(accommodation_D=A, pupil_diameter_mm=3.0))
    assert V == pytest.approx(A, rel=0.25)


def test_accommodation_raises_power_monotonically():
    powers = [NavarroEye(accommodation_D=A).power_D() for A in (0, 1, 2, 4, 8)]
    assert np.all(np.diff(powers) > 0.5)


def test_longitudinal_chromatic_aberration():
    e = NavarroEye()
    assert 1.0 < e.power_D(458.0) - e.power_D(633.0) < 2.2  # the human eye's ~1.5 D
    # the refractive index table at its own wavelengths
    assert optics.refractive_indices(543.0) == pytest.approx((1.3777, 1.3391, 1.4222, 1.3377))
    assert optics.refractive_indices(589.0, accommodation_D=2.0)[2] == pytest.approx(1.42 + 9e-5 * 24)


def test_image_is_inverted():
    e = NavarroEye(pupil_diameter_mm=2.0)
    ang = np.radians(10.0)
    # a distant point above (+y) and one to the right (+x): parallel rays through the pupil
    for axis in (0, 1):
        d = np.zeros((3, 3))
        d[:, axis] = -np.sin(ang)
        d[:, 2] = np.cos(ang)
        o = np.zeros((3, 3))
        o[:, axis] = np.sin(ang) / np.cos(ang) * 10.0
        o[:, 2] = -10.0
        o[:, 1 - axis] = [-0.3, 0.0, 0.3]
        p, valid = e.trace_to_retina(o, d)
        assert valid.all()
        assert np.all(p[:, axis] < -2.5)  # 10 degrees -> about 3 mm on the opposite side
        assert np.ptp(p[:, axis]) < 0.01


def test_round_trip_retina_to_world_and_back():
    rng = np.random.default_rng(0)
    e = NavarroEye(accommodation_D=1.5, pupil_diameter_mm=5.0)
    rho = rng.uniform(0, 70, 200)
    th = rng.uniform(0, 360, 200)
    q = np.stack([retina_point(r, t) for r, t in zip(rho, th)])
    rr = np.sqrt(rng.uniform(0, 1, 200)) * e.pupil_radius_mm * 0.999
    a = rng.uniform(0, 2 * np.pi, 200)
    pxy = np.stack([rr * np.cos(a), rr * np.sin(a)], axis=1)
    for wl in (633.0, 458.0):
        o, d, valid = e.trace_to_world(q, pxy, wl)
        assert valid.mean() > 0.95
        assert np.allclose(np.linalg.norm(d[valid], axis=1), 1.0)
        assert np.all(d[valid, 2] < 0)  # out of the eye
        back, ok = e.trace_to_retina(o[valid] + d[valid], -d[valid], wl)
        assert ok.all()
        assert np.abs(back - q[valid]).max() < 1e-8


def test_iris_blocks_rays_outside_the_pupil():
    e = NavarroEye(pupil_diameter_mm=2.0)
    h = np.linspace(0.0, 2.0, 201)
    o = np.stack([np.zeros_like(h), h, np.full_like(h, -5.0)], axis=1)
    p, valid = e.trace_to_retina(o, np.tile([0.0, 0.0, 1.0], (len(h), 1)))
    edge = h[valid].max()
    # the entrance pupil is the stop magnified by the cornea (about 1.13x)
    assert 1.05 < edge < 1.25
    assert np.all(np.isnan(p[~valid]))
    _, _, ok = e.trace_to_world(np.stack([FOVEA, FOVEA]), np.array([[0.9, 0.0], [1.1, 0.0]]))
    assert ok.tolist() == [True, False]


def test_total_internal_reflection_is_invalid():
    d = np.array([[np.sin(np.radians(70)), 0.0, np.cos(np.radians(70))]])
    n = np.array([[0.0, 0.0, -1.0]])
    _, ok = optics.refract(d, n, 1.42 / 1.0)
    assert not ok[0]
    t, ok = optics.refract(d, n, 1.0 / 1.42)
    assert ok[0] and np.sin(np.arccos(t[0, 2])) == pytest.approx(np.sin(np.radians(70)) / 1.42)


def test_irradiance_per_pupil_area_is_nearly_constant():
    """Integrating the ray weights over the stop: irradiance grows with the pupil's area."""
    per_area = []
    for D in (2.0, 4.0, 6.0, 8.0):
        e = NavarroEye(pupil_diameter_mm=D)
        n = 24
        r = np.sqrt((np.arange(n) + 0.5) / n) * e.pupil_radius_mm
        a = 2 * np.pi * (np.arange(n) + 0.5) / n
        R, Ang = np.meshgrid(r, a)
        pxy = np.stack([(R * np.cos(Ang)).ravel(), (R * np.sin(Ang)).ravel()], axis=1)
        *_, w = e.trace_to_world(np.repeat(FOVEA[None], len(pxy), 0), pxy, return_weights=True)
        per_area.append(w.mean())
    per_area = np.array(per_area)
    assert np.abs(per_area / per_area[0] - 1).max() < 0.05
    # the 2 mm value against the paraxial estimate pi (n' sin u')^2 / A_stop, with the entrance pupil
    # 1.13x the stop: E/L = pi (D_ep / 2 f)^2
    f = 1000.0 / NavarroEye().power_D()
    paraxial = np.pi * (1.13 * 1.0 / f) ** 2 / (np.pi * 1.0**2)
    assert per_area[0] == pytest.approx(paraxial, rel=0.05)


def test_field_of_view_limit():
    e = NavarroEye()
    lim = np.degrees(e.retina_eccentricity_limit(167.5))
    assert 90.0 < lim < 110.0
    ang = e.field_angle_deg(np.radians(np.linspace(1, lim * 0.9999, 40)))
    assert np.all(np.isfinite(ang)) and np.all(np.diff(ang) > 0)
    assert ang[-1] <= 83.75 + 1e-6
    assert np.degrees(e.retina_eccentricity_limit(60.0)) < lim


def test_frames_round_trip_and_landmarks():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(10, 3))
    assert np.allclose(optics.optical_from_eye(optics.eye_from_optical(p)), p)
    assert np.allclose(optics.eye_from_optical(FOVEA), [0.0, 0.0, -0.012])
    assert np.allclose(optics.eye_from_optical([0.0, 0.0, 0.0]), [0.0, 0.0, EYE_CENTRE_MM * 1e-3])
    # proper rotation (det +1): x and z flip together
    d = optics.eye_from_optical_dir(np.eye(3))
    assert np.linalg.det(d) == pytest.approx(1.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [({"accommodation_D": -1}, "accommodation_D"), ({"pupil_diameter_mm": 12}, "pupil_diameter_mm"),
     ({"pupil_diameter_mm": float("nan")}, "pupil_diameter_mm")],
)
def test_bad_eye_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        NavarroEye(**kwargs)


def test_bad_rays():
    e = NavarroEye()
    with pytest.raises(ValueError, match="origins_mm"):
        e.trace_to_retina(np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="directions"):
        e.trace_to_retina(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="finite"):
        e.trace_to_retina(np.full((1, 3), np.nan), np.ones((1, 3)))
    with pytest.raises(ValueError, match="pupil_xy_mm"):
        e.trace_to_world(np.zeros((3, 3)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="wavelength_nm"):
        e.surfaces(700.0)
