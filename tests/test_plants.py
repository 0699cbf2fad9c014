"""The iris and lens plants: latencies, time constants and ranges against their formulas."""

import math

import numpy as np
import pytest

from warp_vision.eye.plants import LENS_LATENCY_S, LENS_TAU_S, PUPIL_TAU_S, LensPlant, PupilPlant, pupil_latency_s
from warp_vision.eye.pupil import luminance_for_diameter, pupil_diameter_mm


def response(plant, command, duration, dt=0.01):
    plant.command(command)
    t, x = [0.0], [plant.state]
    for _ in range(int(round(duration / dt))):
        x.append(plant.advance(dt))
        t.append(t[-1] + dt)
    return np.array(t), np.array(x)


def onset(t, x, x0, tol=1e-6):
    return t[np.argmax(np.abs(x - x0) > tol)]


def time_to(t, x, x0, x1, frac):
    return float(np.interp(frac, (x - x0) / (x1 - x0), t))


def test_pupil_latency_falls_with_luminance_within_the_human_range():
    lat = pupil_latency_s([1e-3, 1.0, 1e2, 1e5])
    assert lat[1] == pytest.approx(0.25) and lat[2] == pytest.approx(0.20)
    assert lat[0] == pytest.approx(0.30) and lat[3] == pytest.approx(0.20)
    assert np.all(np.diff(pupil_latency_s(np.logspace(-3, 5, 30))) <= 0)
    with pytest.raises(ValueError):
        pupil_latency_s(-1.0)


@pytest.mark.parametrize("d", [2.5, 4.0, 6.0, 7.5])
def test_luminance_for_diameter_inverts_watson_and_yellott(d):
    assert pupil_diameter_mm(luminance_for_diameter(d)) == pytest.approx(d, rel=1e-9)


def test_the_pupil_constricts_faster_than_it_dilates_after_its_latency():
    p = PupilPlant(6.0)
    t, x = response(p, 3.0, 2.0, dt=0.001)
    lat = float(pupil_latency_s(luminance_for_diameter(3.0)))
    assert onset(t, x, 6.0) == pytest.approx(lat, abs=2e-3)
    assert time_to(t, x, 6.0, 3.0, 1 - math.exp(-1)) - lat == pytest.approx(PUPIL_TAU_S["constrict"], rel=0.03)
    q = PupilPlant(3.0)
    t, y = response(q, 6.0, 4.0, dt=0.001)
    lat_d = float(pupil_latency_s(luminance_for_diameter(6.0)))
    assert onset(t, y, 3.0) == pytest.approx(lat_d, abs=2e-3) and lat_d > lat
    assert time_to(t, y, 3.0, 6.0, 1 - math.exp(-1)) - lat_d == pytest.approx(PUPIL_TAU_S["dilate"], rel=0.03)
    assert x[-1] == pytest.approx(3.0, abs=0.01) and y[-1] == pytest.approx(6.0, abs=0.01)


def test_the_lens_latency_time_constant_and_main_sequence():
    peaks = []
    for amp in (1.0, 2.0, 4.0):
        lens = LensPlant(0.5)
        t, x = response(lens, 0.5 + amp, 2.0, dt=0.001)
        assert onset(t, x, 0.5) == pytest.approx(LENS_LATENCY_S, abs=2e-3)
        assert time_to(t, x, 0.5, 0.5 + amp, 1 - math.exp(-1)) - LENS_LATENCY_S == pytest.approx(LENS_TAU_S, rel=0.03)
        peaks.append(np.max(np.diff(x) / 0.001))
    assert peaks[1] / peaks[0] == pytest.approx(2.0, rel=0.02) and peaks[2] / peaks[0] == pytest.approx(4.0, rel=0.02)
    assert peaks[0] == pytest.approx(1.0 / LENS_TAU_S, rel=0.02)


def test_commands_are_clipped_and_bad_ones_refused():
    lens, pupil = LensPlant(), PupilPlant()
    lens.command(15.0)
    pupil.command(0.5)
    for _ in range(300):
        lens.advance(0.01)
        pupil.advance(0.01)
    assert lens.state == pytest.approx(10.0, abs=1e-3) and pupil.state == pytest.approx(2.0, abs=1e-3)
    for bad in (float("nan"), [1.0], True, "3"):
        with pytest.raises(ValueError):
            lens.command(bad)
    with pytest.raises(ValueError):
        pupil.advance(-0.1)
