"""The limb vision nets: their samples' geometry, the rendered dataset, the training task, the errors
they are judged by, and the ballistic fit the interception reads them through."""

import json

import numpy as np
import pytest
import torch

from warp_vision.sim.cannon import GRAVITY
from warp_vision.sim.limb import (
    META,
    NEAR_M,
    SIDES,
    LimbDataConfig,
    Poser,
    dataset_fields,
    fit_ballistic,
    render_samples,
    sample_params,
)
from warp_vision.sim.limb_errors import discrepancy_errors
from warp_vision.train.cli import main as train_main


@pytest.fixture(scope="module")
def poser():
    return Poser()


def test_a_sample_is_reproducible_and_its_target_is_ball_minus_hand_in_the_eye_frame(poser):
    cfg = LimbDataConfig(samples=8)
    a, b = sample_params(cfg, 3, poser), sample_params(cfg, 3, poser)
    assert np.array_equal(a["target"], b["target"]) and np.array_equal(a["eye_pose"], b["eye_pose"])
    assert not np.array_equal(sample_params(cfg, 4, poser)["target"], a["target"])
    R, centre = a["eye_pose"][:3, :3], a["eye_pose"][:3, 3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9)
    for k, s in enumerate(SIDES):
        assert np.allclose(a["target"][3 * k:3 * k + 3], R.T @ (a["ball"] - a["hands"][s]), atol=1e-9)
    # the eye looks at the ball, off by the sample's tracking error
    ball = R.T @ (a["ball"] - centre)
    off = np.degrees(np.arccos(ball[2] / np.linalg.norm(ball)))
    assert off == pytest.approx(a["err_deg"], rel=1e-3, abs=1e-3) and 0 <= a["err_deg"] <= 25  # yaw and pitch of it


def test_balls_lie_near_a_hand_or_on_a_shot_and_in_front_of_the_body(poser):
    from warp_vision.sim.cannon import SHOULDER_LEFT

    cfg = LimbDataConfig(samples=40)
    ps = [sample_params(cfg, i, poser) for i in range(40)]
    near = [p for p in ps if not p["on_path"]]
    assert 0 < len(near) < 40
    for p in near:
        assert min(np.linalg.norm(p["ball"] - h) for h in p["hands"].values()) <= NEAR_M + 1e-9
    for p in ps:
        assert (
            p["ball"][1] < SHOULDER_LEFT[1] and min(np.linalg.norm(p["ball"] - h) for h in p["hands"].values()) > 0.05
        )
    assert {round(p["light"], 6) for p in ps}.__len__() > 30 and all(10 ** -0.5 <= p["light"] <= 10 ** 0.5 for p in ps)


def test_rendered_samples_fill_the_fields_and_keep_to_one_room(poser):
    from warp_vision.data.foveation import make_retina

    cfg = LimbDataConfig(samples=8, photoreceptors=400, samples_per_receptor=1, chunk_size=4)
    retina = make_retina(cfg.foveation_config())
    out = render_samples(cfg, [0, 1], poser, retina)
    fields = dataset_fields(cfg)
    for k, (shape, dtype) in fields.items():
        assert out[k].shape == (2, *shape) and out[k].dtype == np.dtype(dtype), k
    assert np.isfinite(out["onv"].astype(np.float32)).all() and out["onv"].astype(np.float32).max() > 0
    assert np.allclose(out["target"][1], sample_params(cfg, 1, poser)["target"], atol=1e-6)
    distance = np.linalg.norm(out["target"][0, :3])
    assert out["meta"][0, META.index("ball_hand_left_m")] == pytest.approx(distance, rel=1e-5)
    with pytest.raises(ValueError, match="one chunk"):
        render_samples(cfg, [3, 4], poser, retina)


@pytest.mark.parametrize("bad", [dict(eye="middle"), dict(samples=0), dict(rooms="attic"), dict(shots="test"),
                                 dict(ball="red")])
def test_bad_dataset_configs_are_refused(bad):
    with pytest.raises(ValueError):
        LimbDataConfig(**bad).validate()


def test_the_ball_is_part_of_the_dataset_and_the_glowing_datasets_keep_their_keys():
    ordinary, glowing = LimbDataConfig(), LimbDataConfig(ball="glowing")
    assert ordinary.ball == "ordinary" and ordinary.key() != glowing.key()
    assert "ball" not in glowing.manifest()  # as the glowing-ball datasets were recorded before the choice
    assert glowing.key() == "c912248a91d0"  # the left eye's default glowing-ball dataset, as it was cached
    for cfg in (ordinary, glowing):
        assert LimbDataConfig.from_manifest(cfg.manifest()) == cfg


def test_the_errors_count_near_pairs_and_relative_error():
    true = np.array([[0.1, 0, 0, 2.0, 0, 0], [0, 0.3, 0, 0, 0, 0.5]])
    pred = true + np.array([[0.01, 0, 0, 0.5, 0, 0], [0, 0.03, 0, 0, 0, 0.1]])
    e = discrepancy_errors(pred, true)
    assert e["near_pairs"] == 3  # the 2 m pair is not near
    assert e["near_median_cm"] == pytest.approx(3.0) and e["near_median_relative"] == pytest.approx(0.1)
    assert e["by_distance"]["1-2 m"]["pairs"] == 0 and e["by_distance"]["0-0.2 m"]["median_cm"] == pytest.approx(1.0)


def test_the_ballistic_fit_recovers_a_thrown_ball_and_weights_its_observations():
    p0, v0 = np.array([0.3, -2.0, 1.2]), np.array([0.5, 8.0, 2.0])
    ts = np.linspace(0.0, 0.2, 6)
    obs = p0 + v0 * ts[:, None] + 0.5 * GRAVITY * ts[:, None] ** 2
    p, v = fit_ballistic(ts, obs, np.ones(6), 0.25)
    assert np.allclose(p, p0 + v0 * 0.25 + 0.5 * GRAVITY * 0.25 ** 2, atol=1e-9)
    assert np.allclose(v, v0 + GRAVITY * 0.25, atol=1e-9)
    bad = obs.copy()
    bad[0] += 1.0  # one wild observation, nearly weightless
    p2, _ = fit_ballistic(ts, bad, np.r_[1e-9, np.ones(5)], 0.25)
    assert np.allclose(p2, p, atol=1e-6)
    one = fit_ballistic([0.1], obs[:1], [1.0], 0.3)
    assert np.array_equal(one[0], obs[0]) and np.array_equal(one[1], np.zeros(3))


def test_the_validation_gate_keeps_a_decoy_out_of_the_fit_and_extrapolates_a_lost_ball():
    from warp_vision.sim.limb import GATE_RELOCK, BallisticPerception

    p0, v0 = np.array([1.2, -2.6, 0.9]), np.array([-2.0, 7.0, 2.5])
    path = lambda t: p0 + v0 * t + 0.5 * GRAVITY * t**2  # noqa: E731
    muzzle = p0.copy()
    hand = np.array([0.3, 0.2, 1.0])
    bp = BallisticPerception("left")
    ts = np.arange(0.0, 0.40, 0.02)
    for t in ts[:10]:  # the ball, seen for 0.2 s
        bp._add(t, path(t), hand, {})
    for t in ts[10:]:  # then the eyes fixate the muzzle (a static decoy) to the end
        bp._add(t, muzzle, hand, {})
    assert len(bp.rejected) == len(ts) - 10 and len(bp.log) == len(ts)  # never relocked onto a standing decoy
    p, v = bp(None, 0.36)  # the path extrapolated from the ball's observations, not at rest at the muzzle
    assert np.allclose(p, path(0.36), atol=1e-6) and np.allclose(v, v0 + GRAVITY * 0.36, atol=1e-6)
    # without the gate the decoy would have pulled the fit toward the muzzle
    last = [(t, q) for t, q, _, _ in bp.log if t >= 0.36 - 0.25]
    ungated, _ = fit_ballistic([t for t, _ in last], [q for _, q in last], np.ones(len(last)), 0.36)
    assert np.linalg.norm(ungated - path(0.36)) > 1.0
    # a moving path of its own, seen GATE_RELOCK frames running, replaces a wrong first track
    bp = BallisticPerception("left")
    for t in ts[:5]:
        bp._add(t, muzzle + np.array([0.0, 0.0, 1.0]) + 0.01 * t, hand, {})  # a wrong start, nearly still
    for t in ts[5:5 + GATE_RELOCK]:
        bp._add(t, path(t), hand, {})
    p, _ = bp(None, ts[5 + GATE_RELOCK])
    assert np.allclose(p, path(ts[5 + GATE_RELOCK]), atol=1e-6) and len(bp.rejected) == GATE_RELOCK - 1


def test_smoke_run_trains_and_reports_held_out_errors(tmp_path):
    from warp_vision.nn.trained import load_net

    run = tmp_path / "left"
    argv = ["limb", "--preset", "smoke", "--out", str(run), "--data-dir", str(tmp_path / "data" / "limb-smoke"),
            "--no-progress"]
    assert train_main(argv) == 0
    s = json.loads((run / "summary.json").read_text())
    for split in ("test", "heldout"):
        assert {"near_median_cm", "near_p90_cm", "near_median_relative", "by_distance"} <= set(s[split])
    assert np.isfinite(s["heldout"]["all_median_cm"]) and (run / "figures" / "limb_errors.png").exists()
    net, ck = load_net(run)
    assert ck["net"]["kind"] == "limb" and ck["data"]["eye"] == "left"
    x = torch.rand(2, 3 * 400, dtype=torch.float16)
    assert net(x.float() if ck["net"]["onv_dtype"] == "float32" else x).shape == (2, 6)
    # refused in one line
    assert train_main(["limb", "--preset", "smoke", "--near-weight-m", "0", "--no-progress"]) == 2


def test_the_gaze_lines_cross_at_the_ball_and_fixation_vision_sees_it_there():
    from types import SimpleNamespace

    from warp_vision.frames import gaze_angles, look_rotation
    from warp_vision.sim.limb import MAX_DEPTH_M, FixationVision, nearest_to_rays

    ball = np.array([0.1, -0.8, 1.3])
    eyes = {"left": np.array([0.032, -0.09, 1.55]), "right": np.array([-0.032, -0.09, 1.55])}
    u = {s: (ball - o) / np.linalg.norm(ball - o) for s, o in eyes.items()}
    assert np.allclose(nearest_to_rays(eyes["left"], u["left"], eyes["right"], u["right"]), ball, atol=1e-9)
    # parallel gaze lines: the depth is capped; a ray pointing away is cut at its origin
    far = nearest_to_rays(eyes["left"], u["left"], eyes["right"], u["left"])
    assert np.linalg.norm(far - eyes["left"]) <= MAX_DEPTH_M + 0.1
    assert np.allclose(nearest_to_rays(eyes["left"], -u["left"], eyes["left"], -u["left"], 2.0),
                       eyes["left"] - 2.0 * u["left"])
    # each eye off the ball by a few degrees: the foveation nets' estimates say by how much
    poses, est = {}, {}
    for s, o in eyes.items():
        R = look_rotation(u[s] + np.array([0.05, 0.0, 0.03]), up=(0.0, 0.0, 1.0))
        poses[s] = np.eye(4)
        poses[s][:3, :3], poses[s][:3, 3] = R, o
        est[s] = gaze_angles(R.T @ u[s])
    fx = FixationVision("left")
    assert fx(None, 0.0) is None  # nothing seen yet: the interceptor holds
    assert fx.observe(SimpleNamespace(estimate=None), poses, np.zeros(3), 0.0) is None
    p = fx.observe(SimpleNamespace(estimate=est), poses, ball + [0.0, 0.0, -0.3], 0.01)
    assert np.allclose(p, ball, atol=1e-6) and np.allclose(fx(None, 0.01)[0], ball, atol=1e-6)
    fx.reset()
    assert fx(None, 0.02) is None and len(fx.log) == 1
    with pytest.raises(ValueError):
        FixationVision("middle")


def test_range_errors_are_relative_absolute_and_split_by_distance_and_hand():
    from warp_vision.sim.limb_errors import range_errors

    true = np.log([0.5, 1.5, 3.0, 0.8])
    pred = true + np.log([1.1, 0.98, 1.02, 1.0])
    e = range_errors(pred, true, hand_m=np.array([0.3, 0.9, 2.0, 0.1]))
    assert e["depth_n"] == 4 and e["depth_median_relative"] == pytest.approx(0.02)
    assert e["depth_bias_relative"] == pytest.approx(0.01)
    assert e["near_hand"]["n"] == 2 and e["near_hand"]["median_cm"] == pytest.approx(2.5)  # 5 cm and 0 cm
    assert e["by_distance"]["2-4 m"]["n"] == 1 and e["by_distance"]["2-4 m"]["median_cm"] == pytest.approx(6.0)
    assert e["by_distance"]["1-2 m"]["median_relative"] == pytest.approx(0.02)


def test_smoke_ranging_run_trains_on_balls_near_the_line_of_sight(tmp_path):
    from warp_vision.nn.retina_cnn import RANGE_GATE_DEG
    from warp_vision.nn.trained import load_net
    from warp_vision.train.config_body import LimbTrainConfig
    from warp_vision.train.limb import LimbTask

    run = tmp_path / "left"
    argv = ["limb", "--preset", "smoke", "--model", "range", "--out", str(run),
            "--data-dir", str(tmp_path / "data" / "limb-smoke"), "--no-progress"]
    assert train_main(argv) == 0
    s = json.loads((run / "summary.json").read_text())
    for split in ("test", "heldout"):
        assert {"depth_median_relative", "depth_p90_relative", "near_hand", "by_distance"} <= set(s[split])
    assert 0 < s["heldout_samples_in_gate"] <= 16 and (run / "figures" / "range_errors.png").exists()
    net, ck = load_net(run)
    assert ck["net"]["model"] == "range" and ck["net"]["onv_dtype"] == "float32"
    assert net(torch.rand(3, 3 * 400)).shape == (3, 1)
    # the splits hold only the balls within the gate, and the target is the log distance
    task = LimbTask(LimbTrainConfig(**json.loads((run / "config.json").read_text())))
    task.load((0, 1), progress=False, synthesize=False)
    ids = np.concatenate(task.splits())
    assert len(ids) and (task.meta[ids, 3].numpy() < RANGE_GATE_DEG).all()
    assert torch.allclose(task.target[:, 0], torch.log(task.meta[:, 0]))
    # a foveation run cannot be a ranging net: its --model does not offer it (it did, and validation refused it)
    with pytest.raises(SystemExit) as e:
        train_main(["--preset", "smoke", "--model", "range", "--no-progress"])
    assert e.value.code == 2


def test_limb_vision_with_ranging_nets_puts_the_ball_along_the_seen_direction(tmp_path):
    from types import SimpleNamespace

    from warp_vision.frames import gaze_angles, look_rotation
    from warp_vision.nn.retina_cnn import RANGE_GATE_DEG
    from warp_vision.sim.limb import LimbVision

    for eye in SIDES:
        assert train_main(["limb", "--preset", "smoke", "--model", "range", "--eye", eye, "--epochs", "1",
                           "--out", str(tmp_path / eye), "--data-dir", str(tmp_path / "data" / eye),
                           "--no-progress"]) == 0
    lv = LimbVision({s: str(tmp_path / s) for s in SIDES}, "left")
    assert lv.ranging
    lv.check_ball("ordinary")  # the default: the loop's ordinary ball
    with pytest.raises(ValueError, match="learnt the ordinary ball, the loop shows the glowing"):
        lv.check_ball("glowing")
    onv = {s: torch.rand(1, 3 * 400) for s in SIDES}
    dist = {s: lv.distance(onv[s], s) for s in SIDES}
    assert all(np.isfinite(d) and d > 0 for d in dist.values())
    with pytest.raises(ValueError):
        lv.discrepancy(onv)
    poses = {}
    for s, x in (("left", 0.032), ("right", -0.032)):
        poses[s] = np.eye(4)
        poses[s][:3, :3], poses[s][:3, 3] = look_rotation([0.0, -1.0, 0.1], up=(0.0, 0.0, 1.0)), [x, -0.09, 1.55]
    inside = gaze_angles(np.array([np.sin(np.radians(2.0)), 0.0, np.cos(np.radians(2.0))]))
    outside = gaze_angles(np.array([np.sin(np.radians(RANGE_GATE_DEG + 1)), 0.0,
                                    np.cos(np.radians(RANGE_GATE_DEG + 1))]))
    loop = SimpleNamespace(onv=onv, estimate={"left": inside, "right": outside})
    hand = np.array([0.2, -0.4, 1.0])
    p = lv.observe(loop, poses, hand, 0.04)
    u = poses["left"][:3, :3] @ np.array([np.sin(np.radians(2.0)), 0.0, np.cos(np.radians(2.0))])
    assert np.allclose(p, poses["left"][:3, 3] + dist["left"] * u, atol=1e-6)  # the right eye is outside its gate
    t, est, per_eye, h = lv.log[-1]
    assert set(per_eye) == {"left"} and np.array_equal(h, hand)
    loop.estimate = {"left": outside, "right": outside}
    assert lv.observe(loop, poses, hand, 0.08) is None  # no eye sees the ball near its line of sight
    # the ONV-only and the ranging nets do not mix
    assert train_main(["limb", "--preset", "smoke", "--epochs", "1", "--out", str(tmp_path / "linet"),
                       "--data-dir", str(tmp_path / "data" / "right"), "--eye", "right", "--no-progress"]) == 0
    with pytest.raises(ValueError, match="ranging"):
        LimbVision({"left": str(tmp_path / "left"), "right": str(tmp_path / "linet")}, "left")


def test_frame_errors_compare_each_observation_with_the_ballistic_ball():
    from warp_vision.sim.cannon import shot_from_seed
    from warp_vision.sim.intercept import ballistic_path
    from warp_vision.sim.limb_errors import frame_error_summary, frame_errors

    shot = shot_from_seed(1_000_000)
    hand = np.array([0.2, -0.3, 1.0])
    log = []
    for t in (0.04, 0.08, 0.12, 0.16):
        ball = ballistic_path(shot.muzzle, shot.launch_velocity, [t])[0]
        log.append((t, ball + [0.0, 0.0, 0.05], {}, hand))
    rows = frame_errors(log, shot, until=0.13)
    assert len(rows) == 3 and all(r[1] == pytest.approx(0.05) for r in rows)
    s = frame_error_summary(rows + [(0.3, 0.01, 0.0)])
    assert s["all"]["frames"] == 4 and s["near"]["frames"] == 1 and s["near"]["median_cm"] == pytest.approx(1.0)
    assert s["all"]["median_cm"] == pytest.approx(5.0)
