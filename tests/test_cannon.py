"""The cannon scenario: the ball's contacts with the body, the deflection detector, seeded shots."""

from __future__ import annotations

import numpy as np
import pytest

from warp_vision.body import Body, BodyConfig
from warp_vision.sim.cannon import (
    ARM_REACH,
    ENVELOPE,
    GRAVITY,
    HELDOUT_SEEDS,
    SHOULDER_LEFT,
    SPLITS,
    TRAIN_SEEDS,
    DeflectionDetector,
    arm_actuators,
    geom_parts,
    make_shot,
    part_name,
    run_shot,
    sample_shots,
    shot_from_seed,
    shoulder,
)


@pytest.fixture(scope="module")
def body():
    return Body(BodyConfig(arms=True))


def _ball_velocity(body) -> np.ndarray:
    a = body.model.jnt_dofadr[body.ball_joint]
    return body.data.qvel[a:a + 3].copy()


def _settled_geom(body, name: str) -> np.ndarray:
    """Where geom ``name`` is once the passive arms have settled (as run_shot lets them)."""
    body.reset()
    body.step(1000)
    return body.data.geom_xpos[body.model.geom(name).id].copy()


def test_model_measures_match_the_constants(body):
    body.reset()
    body.step(1000)
    m, d = body.model, body.data
    sh = d.xpos[m.body("humerus_l").id]
    assert np.allclose(sh, SHOULDER_LEFT, atol=0.003)
    assert np.allclose(d.xpos[m.body("humerus_r").id], shoulder("right"), atol=0.003)
    chain = [d.xpos[m.body(n).id] for n in ("humerus_l", "ulna_l", "lunate_l", "3proxph_l")]
    assert sum(np.linalg.norm(b - a) for a, b in zip(chain, chain[1:])) == pytest.approx(ARM_REACH, abs=0.005)
    parts = {part_name(*v) for v in geom_parts(m).values()}
    assert parts == {"torso", "head",
                     *(f"{p}_{s}" for p in ("hand", "forearm", "upper_arm") for s in ("left", "right"))}
    assert len(arm_actuators(body)) == 126  # myo-sim's 63 muscles per arm, no eye, neck or intraocular one


def test_ball_bounces_off_the_torso(body):
    for speed in (6.0, 15.0):
        r = run_shot(body, make_shot((0.0, 0.0, 0.9), speed))  # the chest's centre (its surface is at y ~ 0)
        assert r.arm_contact is None and set(r.first_contacts) == {"torso"}
        assert r.first_contacts["torso"].ball_speed == pytest.approx(speed, rel=0.1)
        assert _ball_velocity(body)[1] < 0  # thrown back toward the cannon
        assert r.ball_end[1] < r.frontal_y and not r.passed  # never behind the back: no tunnelling
        assert not r.deflected


def test_ball_bounces_off_the_head(body):
    r = run_shot(body, make_shot((0.0, 0.0, 1.27), 10.0))  # the face
    assert next(iter(r.first_contacts)) == "head"
    assert r.ball_end[1] < r.frontal_y and not r.passed


def test_a_miss_flies_through_unchanged(body):
    calls = []
    # a shot far left of the body (0.7 m from the shoulder): nothing touches it
    shot = make_shot((0.9, -0.3, 1.0), 10.0)
    r = run_shot(body, shot, controller=lambda b, t: calls.append(t))
    assert r.first_contacts == {} and r.arm_contact is None and not r.deflected
    assert r.passed and not r.landed
    assert np.allclose(_ball_velocity(body), np.asarray(shot.launch_velocity) + GRAVITY * r.duration, atol=1e-9)
    assert r.closest > 0.3  # m from the nearest hand or forearm
    assert len(calls) == round(r.duration / body.model.opt.timestep) and calls[0] == 0.0 and np.all(np.diff(calls) > 0)


def test_forearm_hit_is_a_deflection_before_the_frontal_plane(body):
    forearm = _settled_geom(body, "radius_coll_l")
    shot = make_shot(forearm, 10.0)
    r = run_shot(body, shot)
    assert r.arm_contact in ("forearm_left", "hand_left")
    c = r.first_contacts[r.arm_contact]
    assert c.ball[1] < r.frontal_y and r.before_frontal_plane
    assert r.speed_change > 1.0 and r.deflected
    assert r.closest < 0.005 and r.closest_part == r.arm_contact  # touched: within the contact's 5 mm margin
    assert r.closest_t <= c.t + 1e-9
    # the same touch with the frontal plane put in front of it is no deflection, nor is it under a higher threshold
    r2 = run_shot(body, shot, frontal_y=c.ball[1] - 0.05)
    assert r2.arm_contact == r.arm_contact and not r2.before_frontal_plane and not r2.deflected
    r3 = run_shot(body, shot, threshold=100.0)
    assert r3.arm_contact == r.arm_contact and not r3.deflected


def test_ball_passes_through_without_contacts(body):
    b = Body(BodyConfig(ball_contacts=False))
    r = run_shot(b, make_shot((0.0, 0.0, 0.9), 10.0))
    assert r.first_contacts == {} and r.passed  # the switch: through the chest, as before


def test_shots_are_reproducible_and_splits_disjoint():
    assert sample_shots(5, seed=3) == sample_shots(5, seed=3, split="train")
    assert sample_shots(5, seed=3) != sample_shots(5, seed=4)
    assert TRAIN_SEEDS.stop <= HELDOUT_SEEDS.start  # disjoint ranges
    assert not set(SPLITS["train"][-1000:]) & set(SPLITS["heldout"][:1000])
    last_train = sample_shots(3, seed=len(TRAIN_SEEDS) - 3, split="train")
    held = sample_shots(3, seed=0, split="heldout")
    assert all(s.seed in TRAIN_SEEDS for s in last_train) and all(s.seed in HELDOUT_SEEDS for s in held)
    assert {s.target for s in last_train}.isdisjoint({s.target for s in held})
    assert held[0] == shot_from_seed(HELDOUT_SEEDS[0])


@pytest.mark.parametrize("side", ["left", "right"])
def test_shots_lie_in_the_envelope(side):
    out = 1.0 if side == "left" else -1.0
    for s in sample_shots(100, split="heldout", side=side) + sample_shots(100, side=side):
        off = np.asarray(s.target) - shoulder(side)
        assert ENVELOPE["forward"][0] <= -off[1] <= ENVELOPE["forward"][1]
        assert ENVELOPE["outward"][0] <= out * off[0] <= ENVELOPE["outward"][1]
        assert ENVELOPE["up"][0] <= off[2] <= ENVELOPE["up"][1]
        assert np.linalg.norm(off) <= ENVELOPE["reach_fraction"] * ARM_REACH
        assert ENVELOPE["speed"][0] <= s.speed <= ENVELOPE["speed"][1]
        v, T = np.asarray(s.launch_velocity), s.flight_time
        assert np.linalg.norm(v) == pytest.approx(s.speed)
        assert np.allclose(np.asarray(s.muzzle) + v * T + 0.5 * GRAVITY * T**2, s.target)
        assert 0.15 < T < 0.6 and s.direction @ v == pytest.approx(s.speed)


def test_bad_inputs_are_refused(body):
    for n in (0, -2, 1.5):
        with pytest.raises(ValueError, match="n: expected an integer > 0"):
            sample_shots(n)
    with pytest.raises(ValueError, match="split: expected one of"):
        sample_shots(3, split="test")
    for seed in (-1, len(TRAIN_SEEDS) - 2):
        with pytest.raises(ValueError, match="seed: expected an integer in"):
            sample_shots(3, seed=seed)
    with pytest.raises(ValueError, match="side: expected one of"):
        sample_shots(3, side="middle")
    with pytest.raises(ValueError, match="cannot reach"):
        make_shot((0.0, 0.0, 0.9), 3.0)  # 2.8 m away: 5.3 m/s is the least that gets there
    with pytest.raises(ValueError, match="threshold"):
        DeflectionDetector(body, threshold=0.0)
    with pytest.raises(ValueError, match="muzzle"):
        run_shot(body, make_shot((0.0, 0.0, 0.9), 10.0, muzzle=(1.0, -2.0, 1.0)))

