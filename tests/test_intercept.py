"""Interception with one arm: the interception point, the controller's muscle commands, oracle perception."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from warp_vision.body import Body
from warp_vision.nn.arm import ArmNets
from warp_vision.sim.cannon import ARM_REACH, arm_actuators, make_shot, run_shot, sample_shots, shoulder
from warp_vision.sim.intercept import (
    MIN_FRONT,
    REACH_FRACTION,
    arm_interceptor,
    ballistic_path,
    intercept_point,
    intercept_stats,
)

TRAINED_LEFT = Path(__file__).resolve().parents[1] / "runs" / "arm" / "left"


@pytest.fixture(scope="module")
def body():
    return Body()


@pytest.fixture(scope="module")
def untrained():
    torch.manual_seed(0)
    return ArmNets(hidden=32).eval()


class _WildNets:
    """Stand-in nets whose outputs leave [0, 1]: the controller must clip them."""

    def posture(self, angles, velocities=None):
        return torch.full((angles.shape[0], 63), -0.5)

    def voluntary(self, displacement, activations, angles, velocities=None):
        return torch.linspace(-1.0, 2.0, 63).expand(displacement.shape[0], 63)


def test_intercept_point_lies_on_the_predicted_path_within_reach():
    sh = shoulder("left")
    for shot in sample_shots(5, seed=3, split="heldout", side="left"):
        p0, v0 = np.asarray(shot.muzzle), np.asarray(shot.launch_velocity)
        hand = sh + np.array([0.05, -0.375, -0.125])
        for aim in ("plane", "closest", "soonest"):
            hit = intercept_point(p0, v0, sh, hand, aim)
            assert hit is not None, (shot.seed, aim)
            point, tau = hit
            assert np.allclose(point, ballistic_path(p0, v0, [tau])[0], atol=1e-9)
            # the plane crossing: within a path step
            assert np.linalg.norm(point - sh) <= REACH_FRACTION * ARM_REACH + 0.02
            assert point[1] <= sh[1] - MIN_FRONT + 0.02
        # the plane through the shot's target: the path (with gravity) crosses it at the target, at the flight time
        point, tau = intercept_point(p0, v0, sh, hand, "plane", plane_y=shot.target[1])
        assert np.allclose(point, shot.target, atol=1e-6) and tau == pytest.approx(shot.flight_time, abs=1e-6)
    wide = make_shot((1.2, -0.3, 1.0), 10.0)  # 1 m left of the shoulder: nothing within reach
    assert intercept_point(wide.muzzle, wide.launch_velocity, sh, sh + [0, -0.3, 0], "closest") is None


def test_controller_sets_only_its_arm_within_bounds(body, untrained):
    m = body.model
    for nets in (untrained, _WildNets()):
        ctrl = arm_interceptor(body, nets, "left")
        left = set(ctrl.arm.actuators.tolist())
        others = np.array([i for i in range(m.nu) if i not in left])
        assert len(left) == 63 and len(set(arm_actuators(body).tolist()) - left) == 63
        body.reset()
        base = body.data.ctrl.copy()  # the reset's: zero muscles, the pupils' and lenses' set points
        ctrl.ready(body, 0.0)  # the ready posture: the hand where the IK put it
        assert np.linalg.norm(ctrl.arm.hand(body.data) - ctrl.ready_hand) < 0.01
        seen = []

        def watch(b, t, ctrl=ctrl, seen=seen):
            ctrl(b, t)
            seen.append(b.data.ctrl.copy())

        shot = make_shot(ctrl.ready_hand, 9.0)
        run_shot(body, shot, watch, settle=0.05, ready=ctrl.ready)
        c = np.array(seen)
        assert c[:, ctrl.arm.actuators].min() >= 0 and c[:, ctrl.arm.actuators].max() <= 1
        assert np.all(c[:, others] == base[others])  # the other arm, the eyes, neck and intraocular muscles untouched
        assert c[:, ctrl.arm.actuators].max() > 0 and any(p is not None for _, p, _ in ctrl.log)


def test_bad_arguments_raise(body, untrained):
    with pytest.raises(ValueError):
        arm_interceptor(body, untrained, "middle")
    with pytest.raises(ValueError):
        arm_interceptor(body, untrained, "left", perception="telepathy")
    with pytest.raises(ValueError):
        arm_interceptor(body, untrained, "left", perception=3)
    with pytest.raises(ValueError):
        arm_interceptor(body, untrained, "left", aim="anywhere")
    with pytest.raises(ValueError):
        arm_interceptor(body, untrained, "left", gain=0.0)
    with pytest.raises(ValueError):
        intercept_point((0, -2, 1), (0, 5, 0), shoulder("left"), (0.2, -0.3, 1.0), aim="anywhere")
    with pytest.raises(ValueError):
        shoulder("up")


def test_oracle_interception_beats_passive_arms_on_easy_shots(body):
    if not (TRAINED_LEFT / "best.pt").exists():
        pytest.skip(f"needs the trained left arm nets ({TRAINED_LEFT}: python -m warp_vision.train arm --side left)")
    from warp_vision.sim.arm import load_arm

    nets = load_arm(TRAINED_LEFT)
    ready = arm_interceptor(body, nets, "left").ready_hand
    shots = [make_shot(ready, 6.0), make_shot(ready + [0.04, 0.0, 0.04], 7.0)]  # slow, at the ready hand
    oracle = intercept_stats(shots, lambda b: arm_interceptor(b, nets, "left"), body)
    passive = intercept_stats(shots, None, body)
    for o, p in zip(oracle["shots"], passive["shots"]):  # the hanging forearm passes within a few cm of these
        assert o["error"] is None and o["closest"] < 0.02 and o["closest"] < 0.5 * p["closest"], (o, p)
    assert oracle["deflected_fraction"] > passive["deflected_fraction"]


def test_a_ball_fired_at_a_held_hand_is_deflected_and_a_passive_arm_misses_it(body):
    """The body's own least-effort holding activations (the posture net's teacher) keep the hand in the
    ball's path: the shot aimed at the grasp site is deflected by the hand or forearm before the frontal
    plane, with no MuJoCo warning (``body.step`` raises on any). The same shot at the passive, hanging arm
    touches neither hand nor forearm."""
    from warp_vision.sim.arm import Arm, ArmDataConfig, solve_postures

    arm = Arm(body, "left")
    out = solve_postures(arm, ArmDataConfig(postures=8, seed=1), range(6))
    k = int(np.argmin(out["residual"]))
    qpos, act, hand = out["qpos"][k], out["act"][k], out["hand"][k]

    def ready(b, t):
        if t == 0.0:
            b.data.qpos[arm.qadr] = qpos
            b.data.act[arm.actadr] = act
        b.data.ctrl[arm.actuators] = act

    held = run_shot(body, make_shot(hand, 7.0), controller=lambda b, t: ready(b, t + 1.0), settle=0.3, ready=ready)
    assert held.deflected and held.arm_contact in ("hand_left", "forearm_left"), held
    assert held.speed_change > 1.0 and held.before_frontal_plane
    passive = run_shot(body, make_shot(hand, 7.0))
    assert passive.arm_contact is None and not passive.deflected and passive.closest > 0.05, passive


def test_the_offset_oracle_is_the_truth_off_by_its_error_in_a_new_direction_per_shot(body):
    from warp_vision.sim.intercept import OffsetOracle, oracle_perception

    o = OffsetOracle(0.05, seed=3)
    p, v = oracle_perception(body, 0.0)
    q, w = o(body, 0.0)
    assert np.linalg.norm(q - p) == pytest.approx(0.05) and np.array_equal(v, w)
    first = o.offset.copy()
    o.new_shot()
    assert np.linalg.norm(o.offset) == pytest.approx(0.05) and not np.allclose(o.offset, first)
    assert np.allclose(OffsetOracle(0.05, seed=3).offset, first)  # seeded
    assert np.array_equal(OffsetOracle(0.0)(body, 0.0)[0], p)
    for bad in (-0.01, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            OffsetOracle(bad)
