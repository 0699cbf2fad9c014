"""The Warp ray tracer against its numpy reference and against optics derived independently."""

import numpy as np
import pytest
import torch
import trimesh

from warp_vision.eye import optics
from warp_vision.eye.optics import EYE_CENTRE_MM, RETINA_RADIUS_MM, NavarroEye
from warp_vision.frames import eye_look_at, look_at, translation
from warp_vision.kernels import render as rt
from warp_vision.kernels.render import reference as ref
from warp_vision.scene import Material, Scene


def retina_points(rho_deg, theta_deg):
    """Optical-frame retina points (mm) at eccentricity rho and polar angle theta (eye frame, deg)."""
    r, t = np.radians(rho_deg), np.radians(theta_deg)
    # eye frame direction (sin r cos t, sin r sin t, -cos r); optical x = -eye x
    return np.stack(
        [-RETINA_RADIUS_MM * np.sin(r) * np.cos(t), RETINA_RADIUS_MM * np.sin(r) * np.sin(t),
         EYE_CENTRE_MM + RETINA_RADIUS_MM * np.cos(r)],
        axis=1,
    )


def small_scene(batch_ball=None):
    sc = Scene(ambient=(0.08, 0.06, 0.05), background=(0.02, 0.03, 0.05))
    sc.add_box("floor", (4, 4, 0.1), translation([0, 1.5, -0.05]), Material((0.5, 0.5, 0.4), reflectivity=0.3),
               static=True)
    sc.add_box("wall", (4, 0.1, 3), translation([0, 3, 1.5]), Material((0.7, 0.3, 0.2), specular=0.2, shininess=8),
               static=True)
    cube = trimesh.creation.box((0.4, 0.4, 0.4))
    cube.visual.vertex_colors = np.tile([40, 200, 90, 255], (len(cube.vertices), 1))
    rot = trimesh.transformations.rotation_matrix(0.5, [0, 0, 1])
    sc.add("cube", cube, Material(vertex_colors=True), translation([0.6, 1.8, 0.2]) @ rot)
    centre = [0.0, 1.0, 1.2] if batch_ball is None else batch_ball
    sc.add_sphere("ball", 0.15, (0, 0, 0), Material((1, 1, 1), specular=0.5, shininess=20, smooth=True), subdivisions=2)
    sc.set_transform("ball", translation(centre))
    sc.add_light((0.5, -0.5, 2.5), intensity=6.0)
    sc.add_light((-1.0, 1.0, 1.5), color=(0.9, 0.8, 0.6), intensity=2.0)
    return sc


EYE_POSE = eye_look_at([0.0, -0.6, 1.1], [0.0, 1.0, 1.0])


# --------------------------------------------------------------------------------------------------
# the eye stage


def test_eye_rays_match_the_float64_optics(device):
    eye = NavarroEye(accommodation_D=2.0, pupil_diameter_mm=5.0)
    rng = np.random.default_rng(0)
    q = retina_points(rng.uniform(0, 102, 200), rng.uniform(0, 360, 200))  # out to the vignetted edge
    S = 4
    rays = rt.eye_rays(q, eye, S, seed=3, device=device)
    O, D, W = ref.eye_rays_ref(q, eye, S, seed=3)
    o = rays.origins.numpy().reshape(O.shape)
    d = rays.directions.numpy().reshape(D.shape)
    w = rays.weights.numpy().reshape(W.shape)
    valid = W > 0
    assert valid.mean() > 0.8 and (~valid).sum() > 0  # some peripheral rays are blocked
    assert np.array_equal(w > 0, valid)
    assert np.abs(o[valid] - O[valid]).max() < 2e-8  # m (float32 at 24 mm: ~2e-6 mm)
    assert np.abs(d[valid] - D[valid]).max() < 2e-6
    np.testing.assert_allclose(w[valid], W[valid], rtol=1e-3)


def test_one_sample_is_the_chief_ray():
    assert np.array_equal(rt.pupil_samples(5, 1, 2.0, seed=1), np.zeros((5, 1, 2)))
    xy = rt.pupil_samples(3, 16, 2.0, seed=1)
    r = np.linalg.norm(xy, axis=-1)
    assert r.max() < 2.0 and r.min() > 0
    # equal-area strata (the concentric map of a 4 x 4 grid): the inner quarter of the disc's area
    # holds a quarter of the samples, and each photoreceptor's pattern has its own rotation
    assert np.sum(r < 1.0) == 3 * 4
    assert not np.allclose(xy[0], xy[1])


# --------------------------------------------------------------------------------------------------
# the scene stage


def random_rays(n, seed=0):
    rng = np.random.default_rng(seed)
    o = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-0.8, -0.4, n), rng.uniform(0.3, 2.0, n)])
    tgt = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(0.5, 3.5, n), rng.uniform(-0.5, 3, n)])
    d = tgt - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def test_closest_hit_matches_brute_force(device):
    sc = small_scene()
    o, d = random_rays(3000)
    t, obj, face = rt.closest_hit(sc, o, d, device=device)
    tr, objr, facer, _, _ = ref.closest_hit_ref(sc, o, d)
    assert np.array_equal(np.isfinite(t), np.isfinite(tr))
    hit = np.isfinite(tr)
    assert hit.mean() > 0.5
    np.testing.assert_allclose(t[hit], tr[hit], rtol=1e-5, atol=1e-6)
    same = (obj == objr) & (face == facer)
    assert same[hit].mean() > 0.995  # ties on shared edges may pick either face


def test_radiance_matches_the_reference(device):
    sc = small_scene()
    o, d = random_rays(1500, seed=1)
    T = look_at([0.3, -1.0, 1.3], [0.0, 1.0, 0.8])
    img = rt.render_camera(sc, T, 40, 30, fov_deg=70.0, device=device).cpu().numpy().reshape(-1, 3)
    # the same pixels' rays, built independently
    ys, xs = np.mgrid[0:30, 0:40]
    th = np.tan(np.radians(35.0))
    px = (2 * (xs + 0.5) / 40 - 1) * th * 40 / 30
    py = (1 - 2 * (ys + 0.5) / 30) * th
    dc = np.stack([px, py, -np.ones_like(px)], -1).reshape(-1, 3)
    dw = dc @ T[:3, :3].T
    L = ref.radiance_ref(sc, np.tile(T[:3, 3], (len(dw), 1)), dw)
    close = np.isclose(img, L, rtol=2e-3, atol=1e-5).all(axis=1)
    assert close.mean() > 0.98  # silhouette and shadow-edge pixels may flip
    assert img.max() > 0.1 and np.std(img) > 0.01  # not a blank image


@pytest.mark.parametrize("max_depth", [0, 2])
def test_onv_matches_the_reference(device, max_depth):
    rng = np.random.default_rng(2)
    q = retina_points(rng.uniform(0, 60, 40), rng.uniform(0, 360, 40))
    eye = NavarroEye(pupil_diameter_mm=4.0)
    sc = small_scene()
    poses = np.stack([EYE_POSE, eye_look_at([0.2, -0.6, 1.0], [0.5, 2.0, 0.3])])
    onv = rt.render_onv(sc, q, eye, poses, samples_per_receptor=4, seed=5, device=device, max_depth=max_depth)
    assert onv.shape == (2, 120) and onv.dtype == torch.float32 and str(onv.device).startswith(device.split(":")[0])
    expect = ref.render_onv_ref(sc, q, eye, poses, 4, seed=5, max_depth=max_depth)
    got = onv.cpu().numpy()
    rel = np.abs(got - expect) / (np.abs(expect) + 1e-3 * expect.max())
    assert np.mean(rel < 2e-3) > 0.97
    assert got.max() > 0


def test_reflections_add_light():
    q = retina_points(np.linspace(30, 60, 20), np.full(20, 90.0))  # upper retina sees the floor
    sc = small_scene()
    eye = NavarroEye()
    a = rt.render_onv(sc, q, eye, EYE_POSE, 1, max_depth=0)
    b = rt.render_onv(sc, q, eye, EYE_POSE, 1, max_depth=2)
    assert not torch.allclose(a, b)


def test_a_scene_packed_once_renders_as_packed_per_call():
    q = retina_points(np.linspace(0, 40, 30), np.linspace(0, 330, 30))
    sc, eye = small_scene(), NavarroEye()
    packed = rt.scene_data(sc)
    for pose in (EYE_POSE, eye_look_at([0.2, -0.6, 1.1], [0.0, 1.0, 1.0])):
        np.testing.assert_array_equal(rt.render_onv(sc, q, eye, pose, 2, packed=packed).numpy(),
                                      rt.render_onv(sc, q, eye, pose, 2).numpy())
    with pytest.raises(ValueError, match="max_depth=0"):
        rt.render_onv(sc, q, eye, EYE_POSE, 2, max_depth=0, packed=packed)
    with pytest.raises(ValueError, match="packed"):
        rt.render_onv(sc, q, eye, EYE_POSE, 2, packed=sc)


def test_per_batch_transforms_equal_separate_renders():
    centres = np.array([[0.0, 1.0, 1.2], [0.3, 1.2, 0.9], [-0.4, 0.8, 1.4]])
    q = retina_points(np.linspace(0, 40, 50), np.linspace(0, 720, 50))
    eye = NavarroEye()
    sc = small_scene()
    sc.set_transform("ball", translation(centres))
    poses = np.repeat(EYE_POSE[None], 3, axis=0)
    together = rt.render_onv(sc, q, eye, poses, 2)
    for b, c in enumerate(centres):
        alone = small_scene(batch_ball=c)
        np.testing.assert_allclose(together[b].numpy(), rt.render_onv(alone, q, eye, EYE_POSE, 2)[0].numpy(), rtol=1e-6,
                                   atol=1e-9)
    assert not torch.allclose(together[0], together[1])


def test_static_merge_changes_nothing():
    q = retina_points(np.linspace(0, 80, 80), np.linspace(0, 1440, 80))
    eye = NavarroEye()
    a = small_scene()
    b = small_scene()
    for o in b.objects:
        o.static = False
    b._version += 1
    np.testing.assert_allclose(
        rt.render_onv(a, q, eye, EYE_POSE, 2).numpy(), rt.render_onv(b, q, eye, EYE_POSE, 2).numpy(), rtol=1e-5,
        atol=1e-9
    )


def test_thread_split_is_bit_identical(monkeypatch):
    rng = np.random.default_rng(4)
    q = retina_points(rng.uniform(0, 90, 3000), rng.uniform(0, 360, 3000))
    eye = NavarroEye()
    sc = small_scene()
    monkeypatch.setenv("WARP_VISION_THREADS", "1")
    rt.clear_eye_ray_cache()
    one = rt.render_onv(sc, q, eye, np.repeat(EYE_POSE[None], 2, 0), 2)
    monkeypatch.setenv("WARP_VISION_THREADS", "2")
    rt.clear_eye_ray_cache()
    two = rt.render_onv(sc, q, eye, np.repeat(EYE_POSE[None], 2, 0), 2)
    assert torch.equal(one, two)


# --------------------------------------------------------------------------------------------------
# physics of the whole eye + scene


def uniform_sky():
    sc = Scene(ambient=(0, 0, 0), background=(1.0, 1.0, 1.0))
    sc.add_sphere("speck", 1e-3, (0.0, 0.0, -100.0))  # far behind the eye: the sky is all it sees
    return sc


def test_irradiance_is_proportional_to_pupil_area():
    q = retina_points(np.linspace(0, 20, 30), np.linspace(0, 700, 30))
    sc = uniform_sky()
    per_area = []
    for D in (2.0, 4.0, 6.0, 8.0):
        eye = NavarroEye(pupil_diameter_mm=D)
        onv = rt.render_onv(sc, q, eye, np.eye(4), samples_per_receptor=16).numpy().reshape(-1, 3)
        per_area.append(onv / eye.pupil_area_mm2)
    per_area = np.array(per_area)
    ratio = per_area / per_area[0]
    assert np.abs(ratio - 1).max() < 0.05
    assert np.all(ratio[-1] < 1.0)  # and slightly less than proportional at 8 mm (aberrations, obliquity)


def test_bright_ball_lights_its_optical_image():
    """A small bright ball 20 degrees to the eye's right: its image is where the float64 optics put it."""
    eye = NavarroEye(pupil_diameter_mm=3.0)
    sc = Scene(ambient=(1.0, 1.0, 1.0), background=(0.0, 0.0, 0.0))
    dist = 2.0
    ang = np.radians(20.0)
    # eye frame: +z forward, +x = y cross z; the eye at the origin, looking along world +z
    ball_eye = np.array([dist * np.sin(ang), 0.0, dist * np.cos(ang)])
    sc.add_sphere("ball", 0.02, ball_eye, Material((1, 1, 1)), subdivisions=3)
    # predicted image: the retina point whose chief ray leaves toward the ball (bisection on eccentricity)
    lo, hi = 0.0, np.radians(40.0)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        o, d, _ = eye.chief_ray(retina_points([np.degrees(mid)], [180.0]))
        de = optics.eye_from_optical_dir(d)[0]
        if np.arctan2(de[0], de[2]) < ang:
            lo = mid
        else:
            hi = mid
    rho_img = np.degrees(lo)
    # a fine patch of photoreceptors around the predicted image, on both sides
    rr, tt = np.meshgrid(np.linspace(rho_img - 2.0, rho_img + 2.0, 41), 180.0 + np.linspace(-4, 4, 31))
    q = retina_points(rr.ravel(), tt.ravel())
    onv = rt.render_onv(sc, q, eye, np.eye(4), samples_per_receptor=16).numpy().reshape(-1, 3)[:, 1]
    assert onv.max() > 0
    lit = onv > 0.5 * onv.max()
    centroid_rho = np.average(rr.ravel()[lit], weights=onv[lit])
    centroid_theta = np.average(tt.ravel()[lit], weights=onv[lit])
    # inverted, on the other side; eccentricity is measured at the eyeball centre, so 20 degrees of
    # field seen from the nodal point (~7.2 mm behind the apex) spans ~20 * (24.0 - 7.2) / 12 degrees
    assert rho_img == pytest.approx(20.0 * (24.0 - 7.2) / 12.0, abs=1.5)
    assert centroid_rho == pytest.approx(rho_img, abs=0.1)
    assert centroid_theta == pytest.approx(180.0, abs=0.3)
    # the ball subtends 1.15 deg: the lit patch spans that, magnified like the eccentricity
    expect = np.degrees(2 * np.arcsin(0.02 / dist)) * (24.0 - 7.2) / 12.0
    assert np.ptp(rr.ravel()[lit]) == pytest.approx(expect, rel=0.2)
    # and a photoreceptor on the other side of the fovea sees nothing
    far = rt.render_onv(sc, retina_points([rho_img], [0.0]), eye, np.eye(4), 16)
    assert far.abs().max() == 0


# --------------------------------------------------------------------------------------------------
# validation


def test_bad_inputs():
    sc = small_scene()
    q = retina_points([0.0, 10.0], [0.0, 0.0])
    eye = NavarroEye()
    with pytest.raises(ValueError, match="eye_poses"):
        rt.render_onv(sc, q, eye, np.eye(3))
    with pytest.raises(ValueError, match="rigid"):
        rt.render_onv(sc, q, eye, np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="retina"):
        rt.render_onv(sc, np.zeros((3, 2)), eye, np.eye(4))
    with pytest.raises(ValueError, match="samples_per_receptor"):
        rt.render_onv(sc, q, eye, np.eye(4), samples_per_receptor=0)
    sc.set_transform("ball", translation(np.zeros((3, 3))))
    with pytest.raises(ValueError, match="batch"):
        rt.render_onv(sc, q, eye, np.repeat(np.eye(4)[None], 2, 0))
    with pytest.raises(ValueError, match="no objects"):
        rt.render_onv(Scene(), q, eye, np.eye(4))
    with pytest.raises(ValueError, match="static"):
        sc.set_transform("floor", translation(np.zeros((2, 3))))
    with pytest.raises(ValueError, match="diffuse"):
        Material(diffuse=(2, 0, 0))
    with pytest.raises(ValueError, match="already exists"):
        sc.add_sphere("ball", 1.0)


def _convergence(o, d):
    """Least-squares point closest to all lines o + t d, and the RMS distance of the lines from it."""
    d = d / np.linalg.norm(d, axis=1, keepdims=True)  # nearly parallel lines: the projectors must be exact
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for oi, di in zip(o, d):
        M = np.eye(3) - np.outer(di, di)
        A += M
        b += M @ oi
    x = np.linalg.solve(A, b)
    dist = [np.linalg.norm((np.eye(3) - np.outer(di, di)) @ (x - oi)) for oi, di in zip(o, d)]
    return x, float(np.sqrt(np.mean(np.square(dist))))


@pytest.mark.parametrize("A", [1.0, 2.0, 4.0])
def test_foveal_rays_converge_at_the_focus_distance(A):
    """A foveal photoreceptor's rays leave the eye converging on the point the eye focuses on (~1/A m)."""
    eye = NavarroEye(accommodation_D=A, pupil_diameter_mm=1.0)  # small: little spherical aberration
    q = retina_points([0.0], [0.0])
    rays = rt.eye_rays(q, eye, 16, seed=1)
    O, D, W = ref.eye_rays_ref(q, eye, 16, seed=1)
    for c in range(3):
        o = rays.origins.numpy().reshape(1, 3, 16, 3)[0, c]
        d = rays.directions.numpy().reshape(1, 3, 16, 3)[0, c]
        x, spot = _convergence(o.astype(np.float64), d.astype(np.float64))
        xr, spot_r = _convergence(O[0, c], D[0, c])
        assert np.linalg.norm(x - xr) < 1e-3 * np.linalg.norm(xr)  # the kernel's focus = the reference's
        assert spot == pytest.approx(spot_r, rel=0.02, abs=1e-6)  # and its spot size
        assert abs(x[0]) < 1e-6 and abs(x[1]) < 1e-6  # on the axis
        assert spot < 0.01 * x[2]  # a tight spot (spherical aberration only)
    # the eye focuses ~1/A metres away (green, near the 589 nm design wavelength), and longitudinal
    # chromatic aberration puts blue's focus nearer than red's by the eye's ~1.2 D
    vergence = [1.0 / _convergence(O[0, c], D[0, c])[0][2] for c in range(3)]  # dioptres, R G B
    assert vergence[1] == pytest.approx(A, abs=0.6)
    assert 1.0 < vergence[2] - vergence[0] < 1.5


def test_radiance_matches_reference_on_random_rays(device):
    sc = small_scene()
    o, d = random_rays(2000, seed=7)
    got = rt.radiance(sc, o, d, device=device).cpu().numpy()
    expect = ref.radiance_ref(sc, o, d)
    close = np.isclose(got, expect, rtol=2e-3, atol=1e-6).all(axis=1)
    assert close.mean() > 0.995


def test_shadows_and_lambert_shading_by_hand():
    """A box hangs under a point light over a grey floor: the floor below it gets only ambient light."""
    albedo, amb, I = 0.5, 0.1, 4.0
    sc = Scene(ambient=(amb, amb, amb))
    sc.add_plane("floor", (10, 10), material=Material((albedo,) * 3), static=True)
    sc.add_box("blocker", (0.4, 0.4, 0.05), translation([0, 0, 1.0]))
    sc.add_light((0.0, 0.0, 2.0), intensity=I)
    o = np.array([[0.0, 0.0, 0.5], [1.5, 0.0, 0.5], [0.1, 0.1, 0.5]])
    d = np.tile([0.0, 0.0, -1.0], (3, 1))
    L = rt.radiance(sc, o, d).numpy()[:, 0]
    assert L[0] == pytest.approx(amb * albedo, rel=1e-5)  # in the shadow
    assert L[2] == pytest.approx(amb * albedo, rel=1e-5)
    r2 = 1.5**2 + 2.0**2
    cos = 2.0 / np.sqrt(r2)
    assert L[1] == pytest.approx(amb * albedo + I / r2 * cos * albedo / np.pi, rel=1e-4)  # lit: Lambert


def test_hidden_objects_are_skipped_per_batch_element():
    q = retina_points(np.linspace(0, 30, 40), np.linspace(0, 720, 40))
    eye = NavarroEye()
    sc = small_scene()
    poses = np.repeat(EYE_POSE[None], 2, 0)
    sc.set_visible("ball", [True, False])
    both = rt.render_onv(sc, q, eye, poses, 2).numpy()
    gone = small_scene()
    gone.objects = [o for o in gone.objects if o.name != "ball"]
    gone._version += 1
    np.testing.assert_allclose(both[1], rt.render_onv(gone, q, eye, EYE_POSE, 2)[0].numpy(), rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(both[0], rt.render_onv(small_scene(), q, eye, EYE_POSE, 2)[0].numpy(), rtol=1e-6,
                               atol=1e-9)
    expect = ref.render_onv_ref(sc, q[:10], eye, poses, 2, seed=0)
    got = rt.render_onv(sc, q[:10], eye, poses, 2).numpy()
    np.testing.assert_allclose(got, expect, rtol=2e-3, atol=1e-6)
    with pytest.raises(ValueError, match="static"):
        sc.set_visible("floor", False)


def test_emission_is_seen_without_light_and_matches_the_reference(device):
    """A glowing ball in a room with no light: its radiance is exactly its emission; with lights the
    kernel still matches the reference."""
    sc = Scene(ambient=(0.0, 0.0, 0.0))
    sc.add_plane("floor", (10, 10), material=Material((0.5, 0.5, 0.5)), static=True)
    sc.add_sphere("glow", 0.3, (0.0, 0.0, 1.0), Material((1, 1, 1), emission=(0.7, 0.4, 0.2), smooth=True))
    o = np.array([[0.0, -2.0, 1.0], [2.0, -2.0, 0.5]])
    d = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    L = rt.radiance(sc, o, d, device=device).cpu().numpy()
    assert np.allclose(L[0], [0.7, 0.4, 0.2], rtol=1e-6)  # the ball glows
    assert np.allclose(L[1], 0.0)  # the floor is dark: emission lights nothing else
    sc2 = small_scene()
    sc2.objects[-1].material.emission = (0.5, 0.5, 0.5)  # the ball (before the scene is first packed)
    o, d = random_rays(1500, seed=3)
    got = rt.radiance(sc2, o, d, device=device).cpu().numpy()
    expect = ref.radiance_ref(sc2, o, d)
    assert np.isclose(got, expect, rtol=2e-3, atol=1e-6).all(axis=1).mean() > 0.995
    with pytest.raises(ValueError, match="emission"):
        Material(emission=(-1.0, 0.0, 0.0))


# --------------------------------------------------------------------------------------------------
# per-batch materials and ambient light

#: the ball's material per batch element: a red matte one, a green glowing one, a blue glossy mirror
BALL = [
    Material((0.9, 0.15, 0.1), smooth=True),
    Material((0.2, 0.8, 0.3), emission=(0.4, 0.9, 0.2), smooth=True),
    Material((0.1, 0.2, 0.9), specular=0.9, shininess=60, reflectivity=0.35, smooth=True),
]
#: the (static) floor's: its reflectivity and albedo change from sample to sample too
FLOOR = [
    Material((0.5, 0.5, 0.4), reflectivity=0.0),
    Material((0.3, 0.6, 0.6), reflectivity=0.5),
    Material((0.8, 0.7, 0.2), specular=0.4, shininess=10, reflectivity=0.2),
]
AMBIENT = np.array([[0.08, 0.06, 0.05], [0.0, 0.0, 0.0], [0.3, 0.2, 0.4]])


def batch_scene():
    sc = small_scene()
    sc.set_material("ball", BALL)
    sc.set_material("floor", FLOOR)
    sc.set_ambient(AMBIENT)
    return sc


def shared_scene(k):
    """The batch scene's element k, as a scene whose materials and ambient light are shared."""
    sc = small_scene()
    sc.set_material("ball", BALL[k])
    sc.set_material("floor", FLOOR[k])
    sc.ambient = AMBIENT[k]
    return sc


def _onv_inputs():
    rng = np.random.default_rng(7)
    # the ball fills the fovea and the near periphery; the rest sees the floor, the wall and the cube
    q = retina_points(np.concatenate([rng.uniform(0, 8, 30), rng.uniform(8, 60, 30)]), rng.uniform(0, 360, 60))
    return q, NavarroEye(pupil_diameter_mm=4.0)


def test_per_batch_materials_match_the_reference_and_shared_renders(device):
    q, eye = _onv_inputs()
    sc = batch_scene()
    assert sc.batch_size() == 3
    poses = np.stack([EYE_POSE, eye_look_at([0.2, -0.6, 1.0], [0.0, 1.0, 1.2]), EYE_POSE])
    got = rt.render_onv(sc, q, eye, poses, samples_per_receptor=4, seed=5, device=device).cpu().numpy()
    expect = ref.render_onv_ref(sc, q, eye, poses, 4, seed=5)
    for b in range(3):  # the tolerances of test_onv_matches_the_reference, per batch element
        rel = np.abs(got[b] - expect[b]) / (np.abs(expect[b]) + 1e-3 * expect[b].max())
        assert np.mean(rel < 2e-3) > 0.97, b
    # each element is its own scene: the same render as a scene whose shared material is material k
    for b in range(3):
        alone = rt.render_onv(shared_scene(b), q, eye, poses[b], 4, seed=5, device=device).cpu().numpy()
        np.testing.assert_allclose(got[b], alone[0], rtol=1e-6, atol=1e-9)
    # ... and the materials matter: elements 0 and 2 share a pose but not a ball, floor or ambient light
    assert np.abs(got[0] - got[2]).max() > 0.2 * got[0].max()


def test_per_batch_materials_in_radiance_and_camera(device):
    sc = batch_scene()
    # straight at the ball's front, lit by the first light: red, glowing green, blue
    front = [rt.radiance(sc, [[0.0, -0.6, 1.2]], [[0.0, 1.0, 0.0]], batch=b, device=device).cpu().numpy()[0]
             for b in range(3)]
    assert front[0][0] > 3 * front[0][1:].max() and front[2][2] > 3 * front[2][:2].max()
    assert front[1][1] > 0.9 and front[1][1] > 2 * front[1][[0, 2]].max()  # its emission alone is (0.4, 0.9, 0.2)
    o, d = random_rays(1500, seed=3)
    T = look_at([0.3, -1.0, 1.3], [0.0, 1.0, 1.0])
    for b in range(3):
        L = rt.radiance(sc, o, d, batch=b, device=device).cpu().numpy()
        assert np.isclose(L, ref.radiance_ref(sc, o, d, b), rtol=2e-3, atol=1e-6).all(axis=1).mean() > 0.995
        alone = rt.radiance(shared_scene(b), o, d, device=device).cpu().numpy()
        np.testing.assert_allclose(L, alone, rtol=1e-6, atol=1e-9)
        img = rt.render_camera(sc, T, 32, 24, batch=b, device=device).cpu().numpy()
        alone = rt.render_camera(shared_scene(b), T, 32, 24, device=device).cpu().numpy()
        np.testing.assert_allclose(img, alone, rtol=1e-6, atol=1e-9)


def test_set_material_takes_effect_without_a_rebuild():
    q, eye = _onv_inputs()
    sc = small_scene()
    before = rt.render_onv(sc, q, eye, EYE_POSE, 2).numpy()
    version, geo = sc._version, next(iter(sc._gpu.values()))
    sc.set_material("ball", BALL[1])  # shared: replaces the ball's material
    sc.set_ambient(AMBIENT[2])
    shared = rt.render_onv(sc, q, eye, EYE_POSE, 2).numpy()
    assert sc._version == version and next(iter(sc._gpu.values())) is geo  # no BVH or geometry rebuild
    assert not np.allclose(shared, before)
    fresh = small_scene()
    fresh.objects[fresh.index("ball")].material = BALL[1]  # before the scene is first packed
    fresh.ambient = AMBIENT[2]
    np.testing.assert_allclose(shared, rt.render_onv(fresh, q, eye, EYE_POSE, 2).numpy(), rtol=1e-6, atol=1e-9)
    sc.set_material("ball", BALL)  # per batch, then shared again
    sc.set_ambient(AMBIENT[[0, 2, 1]])  # element 1: BALL[1] under AMBIENT[2], as just rendered shared
    assert sc.batch_size() == 3 and sc._version == version
    three = rt.render_onv(sc, q, eye, np.repeat(EYE_POSE[None], 3, 0), 2).numpy()
    np.testing.assert_allclose(three[1], shared[0], rtol=1e-6, atol=1e-9)
    assert not np.allclose(three[0], three[1])
    sc.set_material("ball", Material((1, 1, 1), specular=0.5, shininess=20, smooth=True))  # small_scene's own
    sc.set_ambient((0.08, 0.06, 0.05))
    assert sc.objects[sc.index("ball")].batch_materials is None and sc.batch_size() == 1
    np.testing.assert_array_equal(rt.render_onv(sc, q, eye, EYE_POSE, 2).numpy(), before)
    assert sc._version == version and next(iter(sc._gpu.values())) is geo
    # smooth / vertex_colors are how the mesh is shaded: a shared material that changes them repacks
    sc.set_material("ball", Material((1, 1, 1), specular=0.5, shininess=20, smooth=False))
    assert sc._version == version + 1
    flat = rt.render_onv(sc, q, eye, EYE_POSE, 2).numpy()
    fresh = small_scene()
    fresh.objects[fresh.index("ball")].material = Material((1, 1, 1), specular=0.5, shininess=20, smooth=False)
    np.testing.assert_array_equal(flat, rt.render_onv(fresh, q, eye, EYE_POSE, 2).numpy())
    assert not np.array_equal(flat, before)


def test_bad_materials_and_ambient():
    q, eye = _onv_inputs()
    sc = small_scene()
    with pytest.raises(ValueError, match="smooth"):  # the ball is smooth-shaded
        sc.set_material("ball", [Material((1, 0, 0), smooth=True), Material((0, 1, 0))])
    with pytest.raises(ValueError, match="vertex_colors"):  # the cube uses its vertex colours
        sc.set_material("cube", [Material(), Material()])
    with pytest.raises(ValueError, match="empty"):
        sc.set_material("ball", [])
    with pytest.raises(ValueError, match="not a Material"):
        sc.set_material("ball", [BALL[0], (1, 0, 0)])
    with pytest.raises(ValueError, match="Material"):
        sc.set_material("ball", "red")
    with pytest.raises(KeyError):
        sc.set_material("nothing", BALL[0])
    assert sc.objects[sc.index("ball")].batch_materials is None  # the failed calls changed nothing
    for bad, what in [((-0.1, 0, 0), ">= 0"), ((np.nan, 0, 0), "finite"), ((0.1, 0.1), "shape"),
                      (np.zeros((2, 4)), "shape"), (np.zeros((2, 2, 3)), "shape"), (0.1, "shape")]:
        with pytest.raises(ValueError, match=what):
            sc.set_ambient(bad)
        with pytest.raises(ValueError, match=what):
            Scene(ambient=bad)
    np.testing.assert_array_equal(sc.ambient, [0.08, 0.06, 0.05])
    # per-batch things must agree on B, and with the eye poses
    sc.set_material("ball", BALL)  # B = 3
    with pytest.raises(ValueError, match="batch"):
        rt.render_onv(sc, q, eye, np.repeat(EYE_POSE[None], 2, 0))
    with pytest.raises(ValueError, match="batch"):
        rt.render_camera(sc, np.eye(4), 8, 8, batch=3)
    sc.set_ambient(np.full((2, 3), 0.1))
    with pytest.raises(ValueError, match="disagree"):
        sc.batch_size()
    with pytest.raises(ValueError, match="disagree"):
        rt.render_onv(sc, q, eye, np.repeat(EYE_POSE[None], 3, 0))
    sc.set_ambient(np.full((3, 3), 0.1))
    sc.set_transform("ball", np.repeat(np.eye(4)[None], 4, 0))
    with pytest.raises(ValueError, match="disagree"):
        rt.radiance(sc, np.zeros((1, 3)), np.ones((1, 3)))
