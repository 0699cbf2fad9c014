"""Tests for warp_vision.eye.layouts and warp_vision.eye.retina: photoreceptor layouts and the Retina container."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from matplotlib.figure import Figure

from warp_vision.eye.layouts import (
    CONE_DENSITY_TABLE,
    cone_density_layout,
    cone_density_per_mm2,
    noisy_log_polar,
)
from warp_vision.eye.retina import Retina
from warp_vision.frames import morton_order

RHO_MAX = 1.7  # rad: about the Navarro eye's lit retina for a 167.5 deg field
R_MM = 12.0  # retina radius, written out here independently of the module


class StubEye:
    """Stands in for NavarroEye: a fixed retina eccentricity limit, recording the fields of view asked for."""

    def __init__(self, limit: float = RHO_MAX):
        self.limit = limit
        self.asked: list[float] = []

    def retina_eccentricity_limit(self, fov_deg: float = 167.5) -> float:
        self.asked.append(fov_deg)
        return self.limit

    def __repr__(self) -> str:
        return f"StubEye({self.limit})"


LAYOUTS = {"log_polar": noisy_log_polar, "cone_density": cone_density_layout}


# --- layouts ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", sorted(LAYOUTS))
@pytest.mark.parametrize("P", [1, 7, 100, 14400])
def test_exact_count_and_ranges(layout, P):
    rho, theta = LAYOUTS[layout](P, RHO_MAX, seed=3)
    assert rho.shape == (P,) and theta.shape == (P,)
    assert rho.dtype == np.float64 and theta.dtype == np.float64
    assert np.all((rho >= 0.0) & (rho <= RHO_MAX))
    assert np.all((theta >= 0.0) & (theta < 2.0 * math.pi))


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_large_noise_stays_in_range(layout):
    rho, theta = LAYOUTS[layout](5000, 0.5, seed=1, noise=3.0)
    assert len(rho) == 5000
    assert np.all((rho >= 0.0) & (rho <= 0.5)) and np.all((theta >= 0.0) & (theta < 2.0 * math.pi))


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_same_seed_identical_different_seed_differs(layout):
    a = LAYOUTS[layout](3000, RHO_MAX, seed=5)
    b = LAYOUTS[layout](3000, RHO_MAX, seed=5)
    c = LAYOUTS[layout](3000, RHO_MAX, seed=6)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0]) and not np.array_equal(a[1], c[1])


def test_log_polar_noiseless_structure():
    rho_min = 0.02
    rho, theta = noisy_log_polar(14400, RHO_MAX, seed=0, rho_min=rho_min, noise=0.0)
    ring_rho = rho[rho > rho_min]
    radii, counts = np.unique(np.round(ring_rho, 12), return_counts=True)
    assert len(set(counts.tolist())) == 1  # the same K on every ring
    K = int(counts[0])
    log_steps = np.diff(np.log(radii))
    assert np.allclose(log_steps, log_steps[0])
    # Isotropic: the angular step 2 pi / K equals the log step between rings (within rounding of K).
    assert 2.0 * math.pi / K == pytest.approx(log_steps[0], rel=0.03)
    # Rings span [rho_min, rho_max] with half a step at each end.
    assert math.log(radii[0] / rho_min) == pytest.approx(log_steps[0] / 2.0, rel=1e-6)
    assert math.log(RHO_MAX / radii[-1]) == pytest.approx(log_steps[0] / 2.0, rel=1e-6)
    # The central disk is filled (no hole at the fovea) at about the innermost ring's density.
    inner = (rho <= rho_min).sum()
    ring0_density = K / (math.pi * rho_min**2 * (math.exp(2.0 * log_steps[0]) - 1.0))
    assert inner / (math.pi * rho_min**2) == pytest.approx(ring0_density, rel=0.03)
    assert rho.min() < 0.1 * rho_min


def test_log_polar_density_falls_as_inverse_square():
    P = 14400
    rho, _ = noisy_log_polar(P, RHO_MAX, seed=2)
    rho_min = math.radians(1.0)  # the documented default
    # Annuli of one octave each, inside the log-polar part (clear of rho_min and rho_max).
    edges = rho_min * 2.0 ** np.arange(1, 6)  # 2, 4, 8, 16, 32 deg
    counts = np.histogram(rho, bins=edges)[0]
    # 1/rho^2 density (in the retinal domain) puts the same number in every octave.
    assert counts.min() / counts.max() > 0.93
    # Density in each annulus against its mean radius: log-log slope -2.
    density = counts / (math.pi * (edges[1:] ** 2 - edges[:-1] ** 2))
    mid = np.sqrt(edges[1:] * edges[:-1])
    slope = np.polyfit(np.log(mid), np.log(density), 1)[0]
    assert slope == pytest.approx(-2.0, abs=0.05)
    # And the absolute level: N(annulus) = 2 pi / d^2 * ln 2 with P = pi (1 + 2 ln(rho_max/rho_min)) / d^2.
    L = math.log(RHO_MAX / rho_min)
    expected = P * 2.0 * math.log(2.0) / (1.0 + 2.0 * L)
    assert counts.mean() == pytest.approx(expected, rel=0.05)


def test_log_polar_rho_min_argument():
    rho, _ = noisy_log_polar(5000, 1.0, seed=0, rho_min=0.1, noise=0.0)
    disk = rho < 0.1
    # Outside the disk the counts per octave are equal; inside, the density is uniform.
    assert 0 < disk.sum() < 5000
    r = rho[disk]
    assert (r < 0.05).sum() / disk.sum() == pytest.approx(0.25, abs=0.03)
    # rho_min = rho_max: all a uniform disk.
    rho, _ = noisy_log_polar(4000, 0.3, seed=0, rho_min=0.3, noise=0.0)
    assert len(rho) == 4000 and (rho < 0.15).mean() == pytest.approx(0.25, abs=0.01)


# --- cone density --------------------------------------------------------------------------------------
def test_cone_density_fit_values():
    assert cone_density_per_mm2(0.0) == pytest.approx(199000.0)
    # Table rows are reproduced exactly; between rows the interpolation is log-linear.
    for ecc, dens in CONE_DENSITY_TABLE:
        assert cone_density_per_mm2(ecc) == pytest.approx(dens, rel=1e-12)
    mid = cone_density_per_mm2(1.5)
    assert mid == pytest.approx(math.sqrt(18700.0 * 11100.0), rel=1e-12)
    # Curcio et al. 1990: an order of magnitude below the peak by 1 mm; ~4,000-5,000 in the periphery.
    assert 8.0 < cone_density_per_mm2(0.0) / cone_density_per_mm2(1.0) < 14.0
    far = cone_density_per_mm2(np.array([10.0, 14.0, 18.0, 20.0, 25.0]))
    assert np.all((far > 3500.0) & (far < 5000.0))
    e = np.linspace(0.0, 16.0, 2000)
    assert np.all(np.diff(cone_density_per_mm2(e)) < 0)
    assert isinstance(cone_density_per_mm2(1.0), float)
    assert cone_density_per_mm2(np.zeros((2, 3))).shape == (2, 3)


def test_cone_density_total_count_matches_curcio():
    # The human retina holds 4.08-5.29 million cones (Curcio et al. 1990); integrate over a 12 mm sphere
    # out to 21 mm along the surface.
    rho = np.linspace(0.0, 21.0 / R_MM, 400001)
    f = cone_density_per_mm2(R_MM * rho) * 2.0 * math.pi * R_MM**2 * np.sin(rho)
    total = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(rho)))
    assert 4.08e6 < total < 5.29e6


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), np.array([1.0, -2.0])])
def test_cone_density_bad_input(bad):
    with pytest.raises(ValueError, match="eccentricity_mm"):
        cone_density_per_mm2(bad)


def test_cone_layout_density_matches_fit():
    P = 300_000
    rho, _ = cone_density_layout(P, RHO_MAX, seed=4)
    # Normalisation by an independent quadrature: expected count in [a, b] = P * I(a, b) / I(0, rho_max).
    grid = np.linspace(0.0, RHO_MAX, 400001)
    f = cone_density_per_mm2(R_MM * grid) * np.sin(grid)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(grid))])
    scale = P / cum[-1]
    for a_mm, b_mm in [(0.0, 0.1), (0.1, 0.3), (0.4, 1.0), (1.5, 4.0), (6.0, 12.0), (14.0, 20.0)]:
        a, b = a_mm / R_MM, b_mm / R_MM
        count = int(((rho >= a) & (rho < b)).sum())
        area_mm2 = 2.0 * math.pi * R_MM**2 * (math.cos(a) - math.cos(b))
        expected_count = scale * (np.interp(b, grid, cum) - np.interp(a, grid, cum))
        assert count == pytest.approx(expected_count, rel=0.15), (a_mm, b_mm)
        # The same as densities against the fit at the annulus (its area-weighted mean).
        empirical = count / area_mm2
        fitted = expected_count / area_mm2
        assert empirical == pytest.approx(fitted, rel=0.15)
    # The foveal peak is far denser than the periphery, as the fit says (ratio ~ 199000 / 4000).
    fovea = ((rho < 0.1 / R_MM).sum()) / (2.0 * math.pi * R_MM**2 * (1.0 - math.cos(0.1 / R_MM)))
    periphery = ((rho > 14.0 / R_MM) & (rho < 20.0 / R_MM)).sum() / (
        2.0 * math.pi * R_MM**2 * (math.cos(14.0 / R_MM) - math.cos(20.0 / R_MM))
    )
    assert 25.0 < fovea / periphery < 50.0


def test_cone_layout_five_million():
    P = 5_000_000
    retina = Retina.cone_density(P, seed=0, eye=StubEye())
    assert retina.P == P
    assert retina.rho.min() >= 0.0 and retina.rho.max() <= RHO_MAX
    norms = np.linalg.norm(retina.positions_eye_m[::997], axis=1)
    assert np.allclose(norms, R_MM * 1e-3, rtol=1e-12)
    # The fovea is resolved: about the expected number of cones within 50 um of its centre.
    grid = np.linspace(0.0, RHO_MAX, 200001)
    f = cone_density_per_mm2(R_MM * grid) * np.sin(grid)
    total = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(grid)))
    r = 0.05 / R_MM
    inner = grid <= r
    part = float(np.sum(0.5 * (f[inner][1:] + f[inner][:-1]) * np.diff(grid[inner])))
    assert (retina.rho < r).sum() == pytest.approx(P * part / total, rel=0.05)


# --- the Retina container ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def retina() -> Retina:
    return Retina.log_polar(14400, seed=0, eye=StubEye())


def test_constructors_use_the_eye_limit():
    eye = StubEye(1.2)
    r = Retina.log_polar(500, seed=1, eye=eye, fov_deg=120.0)
    assert eye.asked == [120.0]
    assert r.rho_max == 1.2 and r.rho.max() <= 1.2 and r.layout == "log_polar" and r.seed == 1
    assert r.params["rho_min"] == pytest.approx(math.radians(1.0)) and r.params["eye"] == "StubEye(1.2)"
    c = Retina.cone_density(500, seed=2, eye=eye, noise=0.0)
    assert c.rho_max == 1.2 and c.layout == "cone_density" and c.params["noise"] == 0.0
    with pytest.raises(ValueError, match="layout_kwargs"):
        Retina.log_polar(100, eye=eye, colour="red")
    with pytest.raises(ValueError, match="layout_kwargs"):
        Retina.cone_density(100, eye=eye, rho_min=0.1)


def test_default_eye_is_navarro():
    from warp_vision.eye.optics import NavarroEye

    r = Retina.log_polar(200, seed=0)
    assert r.rho_max == NavarroEye().retina_eccentricity_limit(167.5)
    assert 1.2 < r.rho_max < math.pi


def test_positions_consistent(retina):
    P = retina.P
    assert P == 14400
    eye = retina.positions_eye_m
    assert np.allclose(np.linalg.norm(eye, axis=1), 0.012, rtol=1e-12)
    # Recompute eccentricity and polar angle from the eye-frame points: the fovea is at (0, 0, -0.012).
    rho = np.arccos(np.clip(-eye[:, 2] / 0.012, -1.0, 1.0))
    assert np.allclose(rho, retina.rho, atol=1e-7)
    off_axis = retina.rho > 1e-6
    theta = np.mod(np.arctan2(eye[:, 1], eye[:, 0]), 2.0 * math.pi)
    dtheta = np.angle(np.exp(1j * (theta - retina.theta)))
    assert np.allclose(dtheta[off_axis], 0.0, atol=1e-8)
    # Domain = azimuthal-equidistant projection: |xy| = rho, direction = theta.
    xy = retina.domain_xy
    assert np.allclose(np.hypot(xy[:, 0], xy[:, 1]), rho, atol=1e-7)
    assert np.allclose(xy[:, 0], retina.rho * np.cos(retina.theta))
    assert np.allclose(xy[:, 1], retina.rho * np.sin(retina.theta))
    # Optical frame (mm, apex origin, +z into the eye): x flips, z = 12.00398 - 1000 z_eye.
    opt = retina.positions_optical_mm
    assert np.allclose(opt[:, 0], -1000.0 * eye[:, 0], atol=1e-12)
    assert np.allclose(opt[:, 1], 1000.0 * eye[:, 1], atol=1e-12)
    assert np.allclose(opt[:, 2], 12.00398 - 1000.0 * eye[:, 2], atol=1e-12)
    # Centre of the sphere at z = 12.00398 mm in the optical frame; the fovea at 24.00398 mm.
    assert np.allclose(np.linalg.norm(opt - [0.0, 0.0, 12.00398], axis=1), 12.0, rtol=1e-12)
    fovea = Retina.from_polar([0.0], [0.0], seed=0, layout="one", rho_max=0.1)
    assert np.allclose(fovea.positions_optical_mm, [[0.0, 0.0, 24.00398]], atol=1e-12)
    assert np.allclose(fovea.positions_eye_m, [[0.0, 0.0, -0.012]], atol=1e-15)
    # Inward normals point at the eyeball centre.
    n = retina.inward_normals_eye
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0) and np.allclose(n * 0.012, -eye)


def test_retina_same_seed_bit_identical():
    a = Retina.cone_density(2000, seed=9, eye=StubEye())
    b = Retina.cone_density(2000, seed=9, eye=StubEye())
    c = Retina.cone_density(2000, seed=10, eye=StubEye())
    for name in ("rho", "theta", "domain_xy", "positions_eye_m", "positions_optical_mm"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert not np.array_equal(getattr(a, name), getattr(c, name)), name


def test_morton_order_applied(retina):
    xy = retina.domain_xy
    assert np.array_equal(morton_order(xy), np.arange(retina.P))
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1).mean()
    shuffled = xy[np.random.default_rng(0).permutation(retina.P)]
    random_step = np.linalg.norm(np.diff(shuffled, axis=0), axis=1).mean()
    assert step < 0.05 * random_step
    # Same for the cone layout, and from_polar(morton=False) keeps the given order.
    c = Retina.cone_density(5000, seed=0, eye=StubEye())
    assert np.array_equal(morton_order(c.domain_xy), np.arange(5000))
    rho, theta = cone_density_layout(5000, RHO_MAX, seed=0)
    kept = Retina.from_polar(rho, theta, seed=0, layout="x", rho_max=RHO_MAX, morton=False)
    assert np.array_equal(kept.rho, rho)


def test_local_spacing_grows_with_eccentricity(retina):
    s = retina.local_spacing_rad()
    assert s.shape == (retina.P,) and np.all(s > 0)
    assert np.median(s[retina.rho > 0.5]) > 10.0 * np.median(s[retina.rho < 0.02])


def test_save_load_round_trip(retina, tmp_path):
    path = tmp_path / "retina.npz"
    retina.save(path)
    assert sorted(os.listdir(tmp_path)) == ["retina.npz"]  # no temporary file left behind
    loaded = Retina.load(path)
    for name in ("rho", "theta", "domain_xy", "positions_eye_m", "positions_optical_mm"):
        assert np.array_equal(getattr(loaded, name), getattr(retina, name)), name
    assert loaded.seed == retina.seed and loaded.layout == retina.layout and loaded.rho_max == retina.rho_max
    assert loaded.params == retina.params
    # Overwrite in place.
    other = Retina.cone_density(300, seed=1, eye=StubEye())
    other.save(str(path))
    assert Retina.load(str(path)).P == 300


def _write_npz(path, **entries):
    with open(path, "wb") as f:
        np.savez(f, **entries)


def _valid_entries(retina):
    return dict(
        format_version=np.int64(1),
        rho=retina.rho,
        theta=retina.theta,
        seed=np.int64(0),
        layout=np.str_("log_polar"),
        rho_max=np.float64(retina.rho_max),
        params_json=np.str_("{}"),
    )


@pytest.mark.parametrize(
    "change, match",
    [
        ({"rho": None}, "missing entries \\['rho'\\]"),
        ({"format_version": np.int64(99)}, "format_version"),
        ({"rho_max": np.float64(0.01)}, "rho"),
        ({"rho_max": np.float64(-1.0)}, "rho_max"),
        ({"rho": "nan"}, "finite"),
        ({"theta": "short"}, "same shape"),
        ({"rho": "int"}, "'rho' expected a float64"),
        ({"params_json": np.str_("{not json")}, "params_json"),
        ({"params_json": np.str_("[1, 2]")}, "params_json"),
        ({"seed": np.float64(1.5)}, "'seed'"),
        ({"seed": np.int64(-1)}, "seed"),
        ({"layout": np.int64(3)}, "'layout'"),
    ],
)
def test_load_rejects_bad_content(retina, tmp_path, change, match):
    entries = _valid_entries(retina)
    for key, value in change.items():
        if value is None:
            del entries[key]
        elif value == "nan":
            bad = entries[key].copy()
            bad[3] = np.nan
            entries[key] = bad
        elif value == "short":
            entries[key] = entries[key][:-1]
        elif value == "int":
            entries[key] = np.zeros(retina.P, dtype=np.int64)
        else:
            entries[key] = value
    path = tmp_path / "bad.npz"
    _write_npz(path, **entries)
    with pytest.raises(ValueError, match=match):
        Retina.load(path)


def test_load_rejects_non_archives(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file at all")
    with pytest.raises(ValueError, match="junk.npz"):
        Retina.load(junk)
    single = tmp_path / "single.npy"
    np.save(single, np.zeros(3))
    with pytest.raises(ValueError, match="single.npy"):
        Retina.load(single)
    with pytest.raises(FileNotFoundError):
        Retina.load(tmp_path / "absent.npz")


def test_load_names_an_archive_whose_headers_are_damaged(retina, tmp_path, unclose_npz_headers):
    # numpy's tokenize.TokenError came through as it was
    path = tmp_path / "damaged.npz"
    retina.save(path)
    unclose_npz_headers(path)
    with pytest.raises(ValueError, match="damaged.npz: not a readable Retina"):
        Retina.load(path)


def test_plot_returns_figure_with_two_axes(retina):
    from warp_vision.viz import plot_retina_layout

    fig = plot_retina_layout(retina)
    assert isinstance(fig, Figure) and len(fig.axes) == 2
    full, zoom = fig.axes
    assert full.get_aspect() == 1.0 and zoom.get_aspect() == 1.0
    # All photoreceptors drawn in the left panel, in degrees.
    offsets = full.collections[0].get_offsets()
    assert len(offsets) == retina.P
    assert np.allclose(np.asarray(offsets), np.degrees(retina.domain_xy))
    assert zoom.get_xlim()[1] < 5.0  # the zoom is on the fovea (degrees)
    # One axes given: only the full layout, drawn on it.
    single = Figure()
    ax = single.add_subplot()
    assert plot_retina_layout(retina, ax=ax) is single and len(single.axes) == 1


# --- validation ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", sorted(LAYOUTS))
@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"P": 0}, "P"),
        ({"P": -5}, "P"),
        ({"P": 10.0}, "P"),
        ({"P": True}, "P"),
        ({"P": "100"}, "P"),
        ({"rho_max": 0.0}, "rho_max"),
        ({"rho_max": -1.0}, "rho_max"),
        ({"rho_max": 3.5}, "rho_max"),
        ({"rho_max": float("nan")}, "rho_max"),
        ({"seed": -1}, "seed"),
        ({"seed": 1.5}, "seed"),
        ({"noise": -0.1}, "noise"),
        ({"noise": float("inf")}, "noise"),
    ],
)
def test_layout_bad_arguments(layout, kwargs, match):
    args = {"P": 100, "rho_max": 1.0, "seed": 0} | kwargs
    with pytest.raises(ValueError, match=match):
        LAYOUTS[layout](**args)


@pytest.mark.parametrize("rho_min", [0.0, -0.1, 1.5, float("nan")])
def test_log_polar_bad_rho_min(rho_min):
    with pytest.raises(ValueError, match="rho_min"):
        noisy_log_polar(100, 1.0, seed=0, rho_min=rho_min)


def test_from_polar_bad_arguments():
    with pytest.raises(ValueError, match="rho, theta"):
        Retina.from_polar([0.1, 0.2], [0.0], seed=0, layout="x", rho_max=1.0)
    with pytest.raises(ValueError, match="rho, theta"):
        Retina.from_polar([], [], seed=0, layout="x", rho_max=1.0)
    with pytest.raises(ValueError, match="rho"):
        Retina.from_polar([0.1, 1.5], [0.0, 0.0], seed=0, layout="x", rho_max=1.0)
    with pytest.raises(ValueError, match="rho"):
        Retina.from_polar([-0.1, 0.5], [0.0, 0.0], seed=0, layout="x", rho_max=1.0)
    with pytest.raises(ValueError, match="finite"):
        Retina.from_polar([0.1, 0.2], [0.0, np.inf], seed=0, layout="x", rho_max=1.0)
    with pytest.raises(ValueError, match="rho_max"):
        Retina.from_polar([0.1], [0.0], seed=0, layout="x", rho_max=4.0)
    with pytest.raises(ValueError, match="layout"):
        Retina.from_polar([0.1], [0.0], seed=0, layout="", rho_max=1.0)
    with pytest.raises(ValueError, match="seed"):
        Retina.from_polar([0.1], [0.0], seed=-2, layout="x", rho_max=1.0)
    with pytest.raises(ValueError, match="params"):
        Retina.from_polar([0.1], [0.0], seed=0, layout="x", rho_max=1.0, params={"f": object()})
    with pytest.raises(ValueError, match="P"):
        Retina.log_polar(0, eye=StubEye())


def test_visual_angles_follow_the_inverted_image():
    """The fovea sees straight ahead; a photoreceptor on the retina's +x side sees the field's -x side
    (the image is inverted), at the field angle the optics give; the targets' (yaw, pitch) convention."""
    from warp_vision.eye.optics import NavarroEye
    from warp_vision.eye.retina import Retina

    eye = NavarroEye()
    rho = np.radians([0.0, 20.0, 20.0, 40.0])
    theta = np.radians([0.0, 0.0, 90.0, 180.0])
    r = Retina.from_polar(rho, theta, seed=0, layout="test", rho_max=1.0, morton=False)
    a = np.degrees(r.visual_angles(eye))
    F20, F40 = eye.field_angle_deg(np.radians([20.0, 40.0]))
    assert np.allclose(a[0], 0.0, atol=1e-6)
    assert a[1][0] == pytest.approx(-F20, rel=1e-6) and abs(a[1][1]) < 1e-6  # +x retina -> looks toward -x
    assert a[2][1] == pytest.approx(-F20, rel=1e-6) and abs(a[2][0]) < 1e-6  # +y retina -> looks down
    assert a[3][0] == pytest.approx(F40, rel=1e-6)
