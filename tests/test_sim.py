"""The MuJoCo body: muscles turn the eyes and head the textbook ways, troubles are reported, the static
inverse holds gazes, the oculomotor net's interface, and the scene follows the body."""

import mujoco
import numpy as np
import pytest
import torch

from warp_vision.body import EYE_MUSCLE_NAMES, NECK_MUSCLE_NAMES, SIDES, Body, BodyConfig, SimulationError
from warp_vision.frames import fick_rotation, gaze_angles, torsion_angle


@pytest.fixture(scope="module")
def body():
    return Body(BodyConfig(arms=False))


def _nasal(side):  # +1 where the eye frame's +x is nasal
    return {"left": -1.0, "right": 1.0}[side]


def _settle(body, side, k, activation=0.5, steps=300):
    body.reset()
    a = np.zeros(6)
    a[k] = activation
    body.set_eye_activations(side, a)
    body.step(steps)
    yaw, pitch = np.degrees(body.gaze_in_head(side))
    # (adduction, elevation, intorsion)
    return yaw * _nasal(side), pitch, np.degrees(body.torsion(side)) * -_nasal(side)


# muscle -> (index into (adduction, elevation, intorsion), sign of its textbook primary action)
PRIMARY = {
    "lateral_rectus": (0, -1),  # abduction
    "medial_rectus": (0, +1),  # adduction
    "superior_rectus": (1, +1),  # elevation
    "inferior_rectus": (1, -1),  # depression
    "superior_oblique": (2, +1),  # intorsion
    "inferior_oblique": (2, -1),  # extorsion
}


@pytest.mark.parametrize("side", SIDES)
@pytest.mark.parametrize("muscle", EYE_MUSCLE_NAMES)
def test_each_extraocular_muscle_turns_the_eye_its_textbook_way(body, side, muscle):
    axis, sign = PRIMARY[muscle]
    moved = np.array(_settle(body, side, EYE_MUSCLE_NAMES.index(muscle)))
    assert sign * moved[axis] > 2.0, f"{muscle} ({side}) moved (adduction, elevation, intorsion) = {moved}"
    assert abs(moved[axis]) == pytest.approx(np.abs(moved).max()) or muscle.endswith("oblique")
    if muscle == "superior_oblique":  # its secondary actions: depression and abduction
        assert moved[1] < -1.0 and moved[0] < 0
    if muscle == "inferior_oblique":  # elevation and abduction
        assert moved[1] > 1.0 and moved[0] < 0


def test_eyes_rest_centred_without_activation(body):
    body.reset()
    body.step(300)
    for s in SIDES:
        assert np.degrees(np.abs(body.gaze_in_head(s))).max() < 0.1


@pytest.mark.parametrize("k", range(len(NECK_MUSCLE_NAMES)))
def test_neck_muscles_turn_the_head(body, k):
    body.reset()
    body.step(500)
    rest = body.neck_angles()
    a = np.zeros(len(NECK_MUSCLE_NAMES))
    a[k] = 0.3
    body.set_neck_activations(a)
    body.step(1000)
    moved = np.degrees(body.neck_angles() - rest)
    j, sign = k // 2, (1 if NECK_MUSCLE_NAMES[k].endswith("pos") else -1)
    assert sign * moved[j] > 0.3, f"{NECK_MUSCLE_NAMES[k]}: neck (yaw, pitch, roll) moved {moved} deg"
    assert abs(moved[j]) == pytest.approx(np.abs(moved).max())


def test_eye_geometry_and_intraocular_state(body):
    body.reset()
    l, r = body.eye_pose("left"), body.eye_pose("right")
    assert np.linalg.norm(l[:3, 3] - r[:3, 3]) == pytest.approx(0.063, abs=1e-6)
    assert np.allclose(l[:3, 2], [0, -1, 0], atol=1e-9)  # the body faces -y; eye +z is the optical axis
    assert body.model.body_mass[body.eye_body["left"]] == pytest.approx(0.0075, rel=0.01)
    body.set_intraocular("left", pupil_mm=6.0, accommodation_D=3.0)
    body.step(200)  # 0.2 s: neither plant has moved yet (latencies 0.22-0.3 s)
    assert body.intraocular("left") == pytest.approx((4.0, 1.0), abs=1e-9)
    body.step(2800)  # 3 s: both have all but converged (dilation's time constant is 0.45 s)
    pupil, acc = body.intraocular("left")
    assert pupil == pytest.approx(6.0, abs=0.05) and acc == pytest.approx(3.0, abs=0.01)
    mirrored = body.data.act[body.model.actuator_actadr[[body.pupil["left"], body.accommodation["left"]]]]
    assert mirrored == pytest.approx([pupil, acc])
    assert body.intraocular("right") == pytest.approx((4.0, 1.0), abs=1e-6)  # the other eye is untouched


def test_instabilities_are_reported(body, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MuJoCo logs the warning to MUJOCO_LOG.TXT in the working directory
    body.reset()
    body.data.qvel[body.model.jnt_dofadr[body.eye_joint["left"]]] = np.nan
    with pytest.raises(SimulationError, match="MuJoCo warned|non-finite"):
        body.step()
    assert (tmp_path / "MUJOCO_LOG.TXT").is_file()  # the warning is MuJoCo's own, logged where it logs
    body.reset()
    body.step()  # a reset body runs again
    with pytest.raises(ValueError, match="eye activations"):
        body.set_eye_activations("left", [2, 0, 0, 0, 0, 0])


def test_deep_penetration_is_reported():
    b = Body(BodyConfig(arms=False, max_penetration=0.005))
    b.set_ball([0.0, 0.0, 0.01])  # 3 cm into the floor
    with pytest.raises(SimulationError, match="penetration"):
        b.step()


def test_set_ball_moves_its_pose_and_the_next_step_sees_it():
    b = Body(BodyConfig(arms=False))
    ball = b.model.jnt_bodyid[b.ball_joint]
    b.set_ball([0.2, -0.8, 1.1], velocity=(0.0, 1.0, 0.0))
    np.testing.assert_allclose(b.data.xpos[ball], [0.2, -0.8, 1.1])  # the poses, before any step
    b.step(10)
    assert b.ball_position()[1] > -0.8  # it flies on from there


def test_fick_torsion_roundtrip():
    R = fick_rotation(0.3, -0.2)
    assert np.allclose(gaze_angles(R[:, 2]), [0.3, -0.2])
    assert torsion_angle(R, 0.3, -0.2) == pytest.approx(0.0, abs=1e-12)


def test_holding_activations_hold_the_gaze(body):
    from warp_vision.sim.oculomotor import eye_holding_activations, settle_gaze

    g = np.radians([[20.0, 0.0], [-20.0, 0.0], [0.0, -15.0]])
    a, res = eye_holding_activations(body, "left", g)
    assert np.all((a >= 0) & (a <= 1)) and res.max() < 1e-5  # N m
    for k in range(len(g)):
        got = settle_gaze(body, "left", a[k])
        assert np.degrees(np.linalg.norm(got - g[k])) < 0.1
        assert abs(np.degrees(body.torsion("left"))) < 0.1
    # the lateral rectus (abduction: +yaw for the left eye) carries the temporal gaze, the medial the nasal
    assert a[0, 0] > a[0, 1] and a[1, 1] > a[1, 0]


def test_extraocular_tendon_paths_are_continuous(body):
    """Over the 38 deg gaze disc no tendon's length jumps between gazes a degree apart: each wraps the
    globe on one side throughout (the obliques once flipped to the far side, 40-47 mm longer, over part of
    the disc, and the superior oblique turned from a depressor into an elevator above 14 deg up)."""
    import mujoco

    from warp_vision.body import EYE_MUSCLE_NAMES
    from warp_vision.sim.oculomotor import eye_qpos

    m, d = body.model, mujoco.MjData(body.model)
    deg = np.arange(-38.0, 38.5, 1.0)
    for side in ("left", "right"):
        ids = [m.tendon(f"{name}_{side}").id for name in EYE_MUSCLE_NAMES]
        length = np.full((len(deg), len(deg), len(ids)), np.nan)
        for a, yaw in enumerate(deg):
            for b, pitch in enumerate(deg):
                if np.hypot(yaw, pitch) <= 38.0:
                    d.qpos[:] = eye_qpos(body, side, np.radians(yaw), np.radians(pitch))
                    mujoco.mj_fwdPosition(m, d)
                    length[a, b] = d.ten_length[ids]
        step = max(np.nanmax(np.abs(np.diff(length, axis=0))), np.nanmax(np.abs(np.diff(length, axis=1))))
        assert step < 0.5e-3, f"{side} eye: a tendon's length jumps {1e3 * step:.1f} mm between neighbouring gazes"


@pytest.mark.parametrize("side", ["left", "right"])
def test_holding_activations_take_the_eye_there_from_the_centre(body, side):
    """The holding activations of a 20 deg gaze in each of eight directions, switched on with the eye
    straight ahead, bring it there (no other equilibrium on the way: upward gazes once stopped 6-8 deg short)."""
    from warp_vision.sim.oculomotor import eye_holding_activations, settle_gaze

    ang = np.radians(np.arange(0, 360, 45))
    g = np.radians(20.0) * np.stack([np.cos(ang), np.sin(ang)], 1)
    a, _ = eye_holding_activations(body, side, g)
    for k in range(len(g)):
        got = settle_gaze(body, side, a[k])
        assert np.degrees(np.linalg.norm(got - g[k])) < 0.5, (side, np.degrees(g[k]), np.degrees(got))


def test_a_saccade_step_settles_fast(body):
    """Stepping the activations from straight ahead to those holding 20 deg brings the eye within 1 deg
    in under 0.12 s of simulated time (a human 20 deg saccade lasts about 0.06 s)."""
    from warp_vision.sim.oculomotor import eye_holding_activations

    a, _ = eye_holding_activations(body, "right", np.radians([[-20.0, 0.0]]))
    body.reset()
    body.set_eye_activations("right", a[0])
    err = []
    for _ in range(200):
        body.step()
        err.append(np.degrees(np.linalg.norm(body.gaze_in_head("right") - np.radians([-20.0, 0.0]))))
    err = np.array(err)
    assert err[119] < 1.0 and err[-1] < 0.1
    assert err[:20].min() > 5  # and it is a movement, not a jump


def test_oculomotor_net_interface():
    from warp_vision.sim.oculomotor import OculomotorNet

    net = OculomotorNet()
    a = torch.rand(5, 6)
    out = net(torch.randn(5, 2), a)
    assert out.shape == (5, 6) and torch.all((out >= 0) & (out <= 1))
    assert torch.equal(net(torch.zeros(5, 2), a), a)  # no change of gaze asks for no change of activations
    with pytest.raises(ValueError, match="change"):
        net(torch.zeros(5, 3), torch.zeros(5, 6))


def test_vergence_distance(body):
    from warp_vision.sim.loop import point_at, vergence_distance

    body.reset()
    assert vergence_distance(body) == np.inf  # parallel gaze lines
    p = point_at(body, 0.0, 0.0, 1.0)
    adr = {s: body.model.jnt_qposadr[body.eye_joint[s]] for s in SIDES}
    for s in SIDES:  # point both eyes at p
        T = body.eye_pose(s)
        d = (T[:3, :3].T @ (p - T[:3, 3]))
        yaw, pitch = gaze_angles(d)
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, fick_rotation(yaw, pitch).reshape(9))
        body.data.qpos[adr[s]:adr[s] + 4] = q
    mujoco.mj_forward(body.model, body.data)
    assert vergence_distance(body) == pytest.approx(1.0, abs=1e-6)


def test_scene_follows_the_body_and_eyes_do_not_see_the_head(body):
    from warp_vision.body import HIDDEN_FROM_EYES
    from warp_vision.sim.loop import body_scene, set_eye_view, sync_scene

    body.reset()
    sc = body_scene(body)
    names = [n for n, _ in sc._mj_bodies]
    assert "mj_head" in names and "mj_eye_left" in names
    a = np.zeros(len(NECK_MUSCLE_NAMES))
    a[0] = 0.4
    body.set_neck_activations(a)
    body.step(300)
    body.set_ball([0.3, -1.0, 1.2])
    sync_scene(sc, body)
    i = sc.index("mj_head")
    assert np.allclose(sc.objects[i].transform[0][:3, :3], body.data.xmat[body.head_body].reshape(3, 3))
    assert np.allclose(sc.objects[sc.index("mj_ball")].transform[0][:3, 3], [0.3, -1.0, 1.2])
    set_eye_view(sc, True)
    assert not any(sc.objects[sc.index(f"mj_{n}")].visible.any() for n in HIDDEN_FROM_EYES if f"mj_{n}" in names)
    set_eye_view(sc, False)
    assert sc.objects[i].visible.all()


def test_the_full_body_builds_from_pip_packages_and_runs():
    """myo-sim's torso scaffold and muscle-driven arms with our head, neck and eyes: it compiles, has every
    actuator, settles under gravity without a MuJoCo warning, and the scene carries its arms."""
    from warp_vision.sim.loop import body_scene

    b = Body(BodyConfig(arms=True))
    m = b.model
    muscles = sum(int(m.actuator_gaintype[i] == mujoco.mjtGain.mjGAIN_MUSCLE) for i in range(m.nu))
    assert muscles == 126 + len(NECK_MUSCLE_NAMES) + 2 * len(EYE_MUSCLE_NAMES)
    b.step(200)  # 0.2 s: the passive arms swing and settle; SimulationError would say why not
    assert 1.2 < b.eye_pose("left")[2, 3] < 1.4  # seated eye height (m)
    names = [n for n, _ in body_scene(b)._mj_bodies]
    assert {"mj_humerus_r", "mj_lunate_l", "mj_head"} <= set(names)


def test_building_the_body_says_nothing_and_leaves_no_mujoco_log(tmp_path, monkeypatch, capfd):
    """myo-sim attaches its arms with an empty prefix; MuJoCo's default handler would print that warning
    and append it to MUJOCO_LOG.TXT in the working directory. The body is built without either, and any
    other MuJoCo warning in that window still reaches the user (as a RuntimeWarning)."""
    from warp_vision.body.spec import EMPTY_PREFIX_WARNING, _without_mujoco_warning

    monkeypatch.chdir(tmp_path)
    Body(BodyConfig(arms=True))
    out, err = capfd.readouterr()
    assert EMPTY_PREFIX_WARNING not in out + err
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert mujoco.get_mju_user_warning() is None  # MuJoCo's own handler is back

    with _without_mujoco_warning(EMPTY_PREFIX_WARNING):
        handler = mujoco.get_mju_user_warning()
        handler(EMPTY_PREFIX_WARNING + " may prevent ...")  # dropped
        with pytest.warns(RuntimeWarning, match="MuJoCo: something else"):
            handler("something else")
