"""Interception with one arm: the interception point, the controller's muscle commands, oracle perception."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from warp_vision.body import Body
from warp_vision.nn.arm import ArmNets
from warp_vision.sim.cannon import ARM_REACH, arm_actuators, make_shot, run_shot, sample_shots, shoulder
from warp_vision.sim.intercept import (MIN_FRONT, REACH_FRACTION, arm_interceptor, ballistic_path, intercept_point,
                                       intercept_stats)

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
            assert np.linalg.norm(point - sh) <= REACH_FRACTION * ARM_REACH + 0.02  # the plane crossing: within a path step
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

        def watch(b, t):
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
