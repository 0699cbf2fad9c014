"""``python -m warp_vision.sim intercept``: its arguments, the nets it provides, its figures and frames.

Nothing here simulates a shot in the closed loop or trains a net: the command's runs are minutes long
(docs/RESULTS.md). What needs trained nets skips, with the reason, where they are absent.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from warp_vision.body import SIDES

ROOT = Path(__file__).resolve().parents[1]
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def parsed(monkeypatch, tmp_path):
    """Parse a command line as ``main`` does and return the args ``intercept`` would get (nothing runs)."""
    import warp_vision.sim.cli as cli

    monkeypatch.chdir(tmp_path)
    got = []
    monkeypatch.setattr(cli, "intercept", lambda args: got.append(args))

    def parse(*argv):
        got.clear()
        assert cli.main(["intercept", *argv]) == 0
        return got[0]

    return parse


# --- arguments ---------------------------------------------------------------------------------------
def test_defaults_and_the_shots_they_pick(parsed):
    from warp_vision.sim.intercept_trials import pick_shots

    a = parsed()
    assert (a.side, a.shots, a.shot_seed, a.perception, a.seed) == ("left", None, None, "vision", 0)
    assert a.out == os.path.join("runs", "sim_intercept") and a.video_format == "gif"
    assert a.intraocular == "analytic" and a.ball == "ordinary" and a.no_arms is False and a.perception_error_cm == []
    assert a.frame_every == 2  # 50 frames a second for the cannon ball (the other commands: 25)
    assert [s.seed for s in pick_shots(a)] == [1_000_000]  # the first held-out shot
    a = parsed("--quick", "--shots", "3", "--seed", "5", "--side", "right", "--frame-every", "4")
    assert a.out == os.path.join("runs", "quick", "sim_intercept") and a.frame_every == 4
    shots = pick_shots(a)
    assert [s.seed for s in shots] == [1_000_005, 1_000_006, 1_000_007] and {s.side for s in shots} == {"right"}
    a = parsed("--shot-seed", "42", "--out", "elsewhere", "--video-format", "mp4")
    assert [s.seed for s in pick_shots(a)] == [42] and a.out == "elsewhere"


@pytest.mark.parametrize("argv, words", [
    (["--shots", "0"], "--shots"),
    (["--shots", "-2"], "--shots"),
    (["--shot-seed", "-1"], "--shot-seed"),
    (["--shot-seed", "7", "--shots", "2"], "--shot-seed"),
    (["--seed", "-1"], "--seed"),
    (["--seed", "999999", "--shots", "2"], "--seed"),
    (["--frame-every", "0"], "frame-every"),
    (["--height", "4"], "--height"),
    (["--slow-motion", "0"], "--slow-motion"),
    (["--perception-error-cm", "5"], "--perception-error-cm"),
    (["--shots", "2", "--perception-error-cm", "3", "-1"], "--perception-error-cm"),
    (["--shots", "2", "--perception-error-cm", "nan"], "--perception-error-cm"),
    # run directories of nets the command will not run (they were dropped without a word)
    (["--pupil", "mine"], "--pupil mine: the pupil nets run with --intraocular nets; this command's is analytic"),
    (["--intraocular", "analytic", "--lens", "mine"], "--lens mine: the lens nets run with --intraocular nets"),
    (["--perception", "fixation", "--limb", "mine"], "--limb mine: the limb vision nets run with --perception vision"),
])
def test_bad_input_is_refused_in_one_line_before_any_training(argv, words, tmp_path, monkeypatch, capsys):
    from warp_vision.sim.cli import main

    monkeypatch.chdir(tmp_path)
    try:
        code = main(["intercept", *argv, "--no-progress"])
    except SystemExit as e:  # (a value out of its range is the parser's error: it exits)
        code = e.code
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and words in err[0], err
    assert not (tmp_path / "runs").exists()  # nothing was trained or written


def test_unknown_choices_are_refused_by_the_parser(tmp_path, monkeypatch, capsys):
    from warp_vision.sim.cli import main

    monkeypatch.chdir(tmp_path)
    for argv in (["--perception", "telepathy"], ["--video-format", "avi"], ["--ball", "neon"], ["--side", "up"],
                 ["--side", "up", "--shots", "2"]):
        with pytest.raises(SystemExit) as e:
            main(["intercept", *argv])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: {argv[0]}: expected one of ") and f", got '{argv[1]}' (" in err, err
        assert err.count("\n") == 1, err
    assert not (tmp_path / "runs").exists()


# --- the nets ----------------------------------------------------------------------------------------
def test_the_plan_adds_the_arm_and_both_limb_vision_nets(parsed):
    from warp_vision.sim.build import net_specs
    from warp_vision.sim.intercept_trials import strike_runs

    specs = net_specs(parsed())
    assert [(s.kind, s.eye) for s in specs] == [("foveation", "left"), ("foveation", "right"), ("oculomotor", "left"),
                                                ("oculomotor", "right"), ("arm", "left"), ("limb", "left"),
                                                ("limb", "right")]
    assert [s.run for s in specs[4:]] == [os.path.join("runs", "arm", "left"), os.path.join("runs", "limb", "left"),
                                          os.path.join("runs", "limb", "right")]
    quick = net_specs(parsed("--quick", "--side", "right", "--perception", "oracle"))
    assert [(s.kind, s.eye, s.preset) for s in quick[4:]] == [("arm", "right", "quick")]  # no limb nets with the oracle
    assert quick[4].run == os.path.join("runs", "quick", "arm", "right")
    a = parsed("--quick", "--limb", "L", "--arm", "A")
    assert [s.run for s in net_specs(a)[4:]] == [os.path.join("A", "left"), os.path.join("L", "left"),
                                                 os.path.join("L", "right")]
    assert strike_runs(a) == (os.path.join("A", "left"), {s: os.path.join("L", s) for s in SIDES})
    nets = net_specs(parsed("--intraocular", "nets"))
    assert [s.kind for s in nets] == (["foveation"] * 2 + ["oculomotor"] * 2 + ["pupil"] * 2 + ["lens"] * 2 + ["arm"]
                                      + ["limb"] * 2)


def test_netspec_trains_arms_with_side_and_limb_vision_with_eye(tmp_path):
    from warp_vision.sim.provision import MINUTES, NetSpec, provide, strike_plan

    arm, left, right = strike_plan("left", str(tmp_path / "arm"), str(tmp_path / "limb"))
    assert arm.command() == ["arm", "--preset", "default", "--side", "left", "--out", str(tmp_path / "arm" / "left")]
    assert right.command() == ["limb", "--preset", "default", "--eye", "right", "--out",
                               str(tmp_path / "limb" / "right")]
    assert NetSpec("arm", "right", "r", "quick").command() == ["arm", "--preset", "quick", "--side", "right", "--out",
                                                               "r"]
    assert (arm.what, left.what) == ("left arm's motor nets", "left eye's limb vision net")
    assert NetSpec("oculomotor", "left", "o", "quick").command()[3:5] == ["--eye", "left"]
    assert (MINUTES["arm", "default"], MINUTES["arm", "quick"], MINUTES["limb", "default"], MINUTES["limb", "quick"]) \
        == (6.0, 1.5, 11.0, 2.0)
    assert (arm.minutes(), left.minutes()) == (6.0, 11.0)
    assert [s.kind for s in strike_plan("right", "a", None, quick=True)] == ["arm"]
    with pytest.raises(ValueError, match="side"):
        strike_plan("middle", "a", "l")
    os.makedirs(tmp_path / "limb" / "left")
    (tmp_path / "limb" / "left" / "latest.pt").write_bytes(b"x")  # a stopped run carries on
    assert left.command() == ["limb", "--resume", str(tmp_path / "limb" / "left")]

    calls, lines = [], []

    def fake(cmd):  # "trains" by writing best.pt where the command would, and the summary.json of a final net
        calls.append(cmd)
        out = cmd[cmd.index("--out") + 1] if "--out" in cmd else cmd[cmd.index("--resume") + 1]
        os.makedirs(out, exist_ok=True)
        Path(out, "best.pt").write_bytes(b"net")
        Path(out, "summary.json").write_text("{}")
        return 0

    assert provide([arm, left, right], progress=False, log=lines.append, runner=fake) == [arm, left, right]
    assert [c[3] for c in calls] == ["arm", "limb", "limb"] and all("--no-progress" in c for c in calls)
    assert (
        "about 28 min" in lines[0] and "left arm's motor nets" in lines[1] and "right eye's limb vision net" in lines[3]
    )
    with pytest.raises(SystemExit, match="left arm's motor nets failed"):
        provide(strike_plan("left", str(tmp_path / "arm2"), None), progress=False, log=lambda _m: None,
                runner=lambda cmd: 1)


# --- figures and frames ------------------------------------------------------------------------------
def _fake_results(n=12):
    """intercept_stats' results of three modes on n held-out shots, without simulating any."""
    from warp_vision.sim.cannon import sample_shots
    from warp_vision.sim.intercept import intercept_stats
    from warp_vision.sim.intercept_figures import target_offset

    shots = sample_shots(n, seed=3, split="heldout", side="left")
    rng = np.random.default_rng(0)
    out = {}
    for mode, p in (("vision", 0.6), ("oracle", 0.9), ("passive", 0.15)):
        def runner(shot, p=p):
            hit = bool(rng.uniform() < p)
            return SimpleNamespace(deflected=hit, closest=float(-0.004 if hit else rng.uniform(0.01, 0.4)),
                                   arm_contact="hand_left" if hit else None)

        out[mode] = intercept_stats(shots, runner=runner)
        for row, shot in zip(out[mode]["shots"], shots):
            row["target_offset"] = target_offset(shot)
    return out


def test_the_comparison_figures_are_written(tmp_path):
    from warp_vision.sim.intercept_figures import stats_figures

    results = _fake_results()
    paths = stats_figures(results, str(tmp_path / "figs"))
    assert [os.path.basename(p) for p in paths] == ["success_by_speed.png", "success_by_direction.png",
                                                    "closest_approach.png"]
    for p in paths:
        assert Path(p).read_bytes()[:8] == PNG and os.path.getsize(p) > 5000
    # one shot, one mode (and a shot that failed, at 10 m): still drawn
    one = _fake_results(1)
    one["vision"]["shots"][0].update(closest=10.0, deflected=False)
    assert all(os.path.isfile(p) for p in stats_figures({"vision": one["vision"]}, str(tmp_path / "one")))
    json.dumps(results)  # the results stay JSON-ready with their target offsets


def test_the_target_offset_is_in_the_shoulders_frame():
    from warp_vision.sim.cannon import ENVELOPE, make_shot, sample_shots, shoulder
    from warp_vision.sim.intercept_figures import target_offset

    for side in SIDES:
        s = shoulder(side)
        out = 1.0 if side == "left" else -1.0
        shot = make_shot(s + np.array([out * 0.1, -0.3, -0.2]), 8.0, side=side)
        assert np.allclose(target_offset(shot), [0.1, 0.3, -0.2])
        for sh in sample_shots(5, seed=0, split="heldout", side=side):
            o, f, u = target_offset(sh)
            assert (
                ENVELOPE["outward"][0] <= o <= ENVELOPE["outward"][1]
                and ENVELOPE["forward"][0] <= f <= ENVELOPE["forward"][1]
            )
            assert ENVELOPE["up"][0] <= u <= ENVELOPE["up"][1]


def test_the_hand_ball_distance_figure_is_written(tmp_path):
    from warp_vision.sim.intercept_figures import plot_hand_ball_distance

    t = np.arange(0, 0.4, 0.01)
    trace = {"t": t.tolist(), "true_m": np.abs(0.5 - 2 * t).tolist(), "frame_t": t[::4].tolist(),
             "estimate_m": (np.abs(0.5 - 2 * t[::4]) + 0.02).tolist()}
    p = plot_hand_ball_distance(trace, str(tmp_path / "d.png"), contact_t=0.25, deflected=True, closest_t=0.25,
                                title="x")
    assert Path(p).read_bytes()[:8] == PNG
    trace.update(frame_t=None, estimate_m=None)  # the oracle's: no estimate, no contact
    assert os.path.isfile(plot_hand_ball_distance(trace, str(tmp_path / "o.png"), closest_t=float("nan")))


def test_projection_and_the_strike_frame():
    from warp_vision.frames import look_at
    from warp_vision.sim.intercept_figures import compose_strike_frame, draw_strike
    from warp_vision.sim.video import project

    cam = look_at([0.0, 2.0, 1.0], [0.0, 0.0, 1.0])
    (c, behind, plus_x) = project(cam, 320, 240, 50.0, [[0, 0, 1], [0, 3, 1], [0.2, 0, 1]])
    assert np.allclose(c, (160, 120)) and behind is None
    assert plus_x[0] < 160  # the camera looks along -y: world +x is on the image's left
    img = np.zeros((241, 320, 3), np.uint8)
    # the last: behind the camera
    hand = np.array([[0.1, 0.0, 1.0], [0.05, 0.0, 1.05], [0.0, 0.0, 1.1], [0.0, 3.0, 1.0]])
    out = draw_strike(img, cam, 50.0, hand, ball_path=hand[:2] - 0.1, aim=[0.0, 0.0, 1.0])
    assert out.shape == img.shape and out.any() and not img.any()
    frame = compose_strike_frame(out, np.full((50, 50, 3), 200, np.uint8), "t = 0.100 s\nhand-ball 0.2 m")
    assert frame.dtype == np.uint8 and frame.shape[0] % 2 == 0 and frame.shape[1] % 2 == 0
    assert frame.shape[:2] == (242, 320 + 120)
    with pytest.raises(ValueError):
        compose_strike_frame(np.zeros((4, 8, 3), np.uint8), np.zeros((4, 4, 3), np.uint8), "")


def test_a_shot_result_and_the_time_shares_are_json_ready():
    from warp_vision.sim.cannon import Contact, ShotResult, make_shot, shoulder
    from warp_vision.sim.intercept_trials import result_dict, shot_dict, time_shares

    r = ShotResult(np.bool_(True), {"hand_left": Contact(0.21, "g", (0.1, -0.2, 1.0), 9.5)}, "hand_left", True,
                   np.array([1.0, -2.0, 0.5]), np.float64(-0.003), 0.21, "hand_left", False, False, 0.101, 1.0, 0.3)
    d = json.loads(json.dumps(result_dict(r)))
    assert d["deflected"] is True and d["arm_contact_t"] == 0.21 and d["first_contacts"]["hand_left"]["geom"] == "g"
    assert np.isclose(d["speed_change_m_s"], np.linalg.norm([1.0, -2.0, 0.5]))
    s = shot_dict(make_shot(shoulder("left") + [0.0, -0.3, 0.0], 8.0, seed=1_000_001))
    assert s["split"] == "heldout" and np.allclose(s["target_offset_outward_forward_up_m"], [0, 0.3, 0])
    json.dumps(s)
    sh = time_shares({"render": 2.0, "nets": 1.0, "limb_vision": 0.5, "arm": 0.25, "mujoco": 1.0, "control": 0.25}, 6.0)
    assert np.isclose(sum(sh.values()), 1.0) and np.isclose(sh["other"], 1 / 6)


# --- with trained nets -------------------------------------------------------------------------------
def test_the_trained_limb_vision_nets_read_the_loops_retinas():
    runs = {s: ROOT / "runs" / "limb" / s for s in SIDES}
    missing = [str(r) for r in [*runs.values(), ROOT / "runs" / "foveation_left", ROOT / "runs" / "foveation_right"]
               if not (r / "best.pt").exists()]
    if missing:
        pytest.skip(f"needs trained nets: {', '.join(missing)} (python -m warp_vision.train limb --eye left|right; "
                    "the foveation nets: python -m warp_vision.train --eye left|right)")
    from warp_vision.sim.limb import LimbVision
    from warp_vision.sim.loop import Foveator

    vision = LimbVision({s: str(r) for s, r in runs.items()}, arm="left")
    vision.check_retinas({s: Foveator(str(ROOT / "runs" / f"foveation_{s}")).retina for s in SIDES})
