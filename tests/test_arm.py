"""The arm task: postures the body holds by itself, the posture and voluntary nets, and their training run."""

import json

import mujoco
import numpy as np
import pytest
import torch

from warp_vision.body import Body
from warp_vision.nn.arm import ArmNets, PostureNet, VoluntaryNet
from warp_vision.nn.trained import load_net
from warp_vision.sim.arm import FRONT_M, Arm, ArmDataConfig, hold_start, reach_pairs, run_arm, solve_postures
from warp_vision.train.cli import TASKS, _task_parser
from warp_vision.train.cli import main as train_main


@pytest.fixture(scope="module")
def left_arm():
    return Arm(Body(), "left")


def test_sampled_postures_put_the_hand_in_front_and_keep_the_couplings(left_arm):
    arm, m = left_arm, left_arm.model
    cfg = ArmDataConfig(postures=8, seed=1)
    d = mujoco.MjData(m)
    q = cfg.sample_posture(arm, 3, d)
    assert np.array_equal(q, cfg.sample_posture(arm, 3, d))  # sample k is a function of (seed, side, k)
    d.qpos[:] = q
    mujoco.mj_forward(m, d)
    assert FRONT_M[0] <= arm.shoulder(d)[1] - arm.hand(d)[1] <= FRONT_M[1]
    assert not arm.touching(d)
    # MuJoCo's own equality residuals vanish: the coupled joints sit where the polynomials put them
    eq = d.efc_type[: d.nefc] == mujoco.mjtConstraint.mjCNSTR_EQUALITY
    assert np.abs(d.efc_pos[: d.nefc][eq]).max() < 1e-9
    assert len(arm.actuators) == 63 and len(arm.independent) == 27


def test_holding_activations_hold_a_sampled_posture(left_arm):
    """The solved activations hold a posture with the hand in front: the hand moves less than 2 cm in 0.3 s,
    where the passive arm (no activation) drops far more."""
    arm, body = left_arm, left_arm.body
    out = solve_postures(arm, ArmDataConfig(postures=8, seed=1), range(6))
    k = int(np.argmin(out["residual"]))
    assert out["residual"][k] < 0.05 and 0 <= out["act"].min() and out["act"].max() <= 1
    hold_start(body, arm, out["qpos"][k], out["act"][k])
    held = np.linalg.norm(run_arm(body, arm, (0.3,))[0] - out["hand"][k])
    hold_start(body, arm, out["qpos"][k], np.zeros(63))
    passive = np.linalg.norm(run_arm(body, arm, (0.3,))[0] - out["hand"][k])
    assert held < 0.02 and passive > 0.05, (held, passive)
    # the stored torque balance is the solve's: A a = b up to the residual
    res = np.linalg.norm(out["torque_A"][k] @ out["act"][k] - out["torque_b"][k])
    assert abs(res - out["residual"][k]) < 1e-3


def test_reach_pairs_move_by_the_least_joint_motion():
    rng = np.random.default_rng(0)
    angles = rng.uniform(-1, 1, size=(2500, 7))
    hand = angles[:, :3] * 0.25  # a 0.5 m cube
    idx = np.arange(2000)
    i, j = reach_pairs(idx, 4000, rng, hand, angles)
    assert set(i) <= set(idx) and set(j) <= set(idx)
    stay = np.mean(i == j)
    assert 0.07 < stay < 0.2, stay  # a tenth hold still; a move never picks the start itself otherwise
    step = np.linalg.norm(hand[j] - hand[i], axis=1)
    assert np.mean((step > 0) & (step < 0.08)) > 0.2 and np.mean(step > 0.15) > 0.3  # corrections and reaches
    # of the candidates near the goal, the one nearest the start in joint space: nearer than a random one
    move = i != j
    assert np.median(np.linalg.norm(angles[j[move]] - angles[i[move]], axis=1)) < 0.8 * np.median(
        np.linalg.norm(angles[rng.choice(idx, move.sum())] - angles[i[move]], axis=1))


def test_nets_reject_bad_inputs_and_stay_in_range():
    torch.manual_seed(0)
    nets = ArmNets(hidden=32)
    a = torch.rand(5, 63)
    q = torch.zeros(5, 7)
    d = 0.3 * torch.randn(5, 3)
    v = torch.randn(5, 7)
    out = nets.voluntary(d, a, q, v)
    assert out.shape == (5, 63) and out.min() >= 0 and out.max() <= 1
    assert torch.equal(nets.voluntary(d, a, q), nets.voluntary(d, a, q, torch.zeros(5, 7)))  # no velocities: at rest
    assert torch.equal(nets(d, a, q, v), out)
    p = nets.posture(q, v)
    assert p.shape == (5, 63) and 0 < p.min() and p.max() < 1
    bad = [
        lambda: nets.voluntary(d[:, :2], a, q),  # displacement not 3D
        lambda: nets.voluntary(d, a[:, :60], q),  # 60 activations
        lambda: nets.voluntary(d, a, q[:4]),  # batch sizes differ
        lambda: nets.voluntary(d, a + 1.5, q),  # activations outside [0, 1]
        lambda: nets.voluntary(d.clone().fill_(float("nan")), a, q),  # not finite
        lambda: nets.voluntary(d[0], a[0], q[0]),  # unbatched
        lambda: nets.posture(torch.full((2, 7), float("inf"))),
        lambda: nets.posture(torch.zeros(2, 6)),
        lambda: nets.posture(q, v[:, :6]),  # velocities of 6 joints
        lambda: nets.voluntary(d, a, q, v[:3]),  # velocities of another batch
        lambda: PostureNet()(np.zeros((2, 7))),  # not a tensor
    ]
    for call in bad:
        with pytest.raises(ValueError):
            call()
    assert isinstance(nets.voluntary, VoluntaryNet)


def test_the_cli_lists_the_arm_task():
    assert "arm" in TASKS
    a = _task_parser("arm").parse_args(["--side", "right", "--preset", "smoke"])
    assert a.side == "right" and a.preset == "smoke"
    assert train_main(["arm", "--preset", "smoke", "--side", "middle", "--no-progress"]) == 2  # refused in one line


def test_smoke_run_trains_evaluates_and_writes_its_summary(tmp_path):
    run = tmp_path / "left"
    argv = ["arm", "--preset", "smoke", "--out", str(run), "--data-dir", str(tmp_path / "data"), "--no-progress"]
    assert train_main(argv) == 0
    s = json.loads((run / "summary.json").read_text())
    assert s["task"] == "arm" and s["side"] == "left" and s["postures"] == 40
    for k in ("reach_closed_loop_error_300ms_median_m", "reach_open_loop_error_600ms_p90_m",
              "reach_teacher_hold_error_600ms_median_m", "reach_teacher_feedback_error_300ms_median_m",
              "hold_posture_net_drift_1000ms_median_m", "hold_teacher_drift_300ms_median_m"):
        assert k in s
    assert s["hold_teacher_drift_300ms_median_m"] < 0.05  # the teacher holds the held-out postures
    net, ck = load_net(run)
    assert isinstance(net, ArmNets) and ck["net"]["side"] == "left"
    assert train_main(["evaluate", str(run)]) == 0


def test_demanded_torque_is_a_saturating_spring_and_a_damper():
    from warp_vision.sim.arm import SATURATION_RAD, STIFFNESS, demanded_torque

    z = np.zeros(7)
    assert np.array_equal(demanded_torque(z, z), np.zeros(27))
    t = demanded_torque(np.r_[0.01, 5.0, -5.0, 0, 0, 0, 0], np.r_[0, 0, 0, 1.0, 0, 0, 0])
    assert t[0] == pytest.approx(STIFFNESS * 0.01, rel=1e-3)  # a spring for small moves
    assert t[1] == pytest.approx(STIFFNESS * SATURATION_RAD, rel=1e-3) and t[2] == -t[1]  # saturating
    assert t[3] < 0 and np.all(t[7:] == 0)  # a damper; the fingers asked for nothing
    tt = demanded_torque(torch.ones(2, 7), torch.zeros(2, 7), xp=torch)
    assert tt.shape == (2, 27) and np.allclose(tt[0].numpy(), demanded_torque(np.ones(7), z), atol=1e-5)
