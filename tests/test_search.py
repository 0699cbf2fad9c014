"""Active search (warp_vision.sim.search): inhibition of return in the world, both eyes agreeing, the search
cycle on a scripted trial, the candidates of the retina CNN, and the foveal verification net's interface."""

from pathlib import Path

import numpy as np
import pytest
import torch

from warp_vision.body import SIDES, Body, BodyConfig


@pytest.fixture(scope="module")
def bare_body():
    return Body(BodyConfig(arms=False))


class _ScriptedFoveator:
    """A foveation net whose candidates are the true directions of given world points, in the given order
    (the first scores highest), as seen from its eye; a small retina so rendering costs little."""

    def __init__(self, body, side, points):
        from warp_vision.data.foveation import FoveationDataConfig, make_eye, make_retina

        cfg = FoveationDataConfig(photoreceptors=300, samples_per_receptor=1, eye=side)
        self.retina, self.trained_eye, self.samples_per_receptor = make_retina(cfg), make_eye(cfg), 1
        self.body, self.side, self.points = body, side, points

    def candidates(self, onv, k=4, min_sep_deg=4.0):
        from warp_vision.sim.loop import true_direction

        pts = self.points() if callable(self.points) else self.points
        d = np.full((k, 2), np.nan)
        s = np.zeros(k)
        for i, p in enumerate(pts[:k]):
            d[i], s[i] = true_direction(self.body, self.side, p), 1.0 - 0.1 * i
        return d, s

    def __call__(self, onv):
        return self.candidates(onv)[0][:1]


class _OracleVerifier:
    """Accepts when the ball lies within 2.5 deg of the eye's axis; its offset is the ball's true direction."""

    def __init__(self, body, side):
        self.body, self.side, self.calls = body, side, 0

    def __call__(self, onv):
        from warp_vision.sim.loop import gaze_error_deg, true_direction

        self.calls += 1
        p = self.body.ball_position()
        return gaze_error_deg(self.body, self.side, p) <= 2.5, 1.0, true_direction(self.body, self.side, p)


def _holding_oculomotor(body):
    from test_loop import _HoldingOculomotor

    return {s: _HoldingOculomotor(body, s) for s in SIDES}


def test_inhibition_of_return_holds_a_rejected_point_after_the_head_turns(bare_body):
    """A rejected point is kept in the world: after the head has turned 20 deg it is still suppressed (from
    either eye), a point 10 deg away is not, and the memory ends after IOR_S."""
    import mujoco

    from warp_vision.sim.loop import point_at
    from warp_vision.sim.search import IOR_S, ActiveSearch

    body = bare_body
    body.reset()
    search = ActiveSearch()
    rejected = point_at(body, 15.0, 0.0, 1.5)
    search.inhibit(rejected, now=0.0)
    q = body.data.qpos
    q[body.model.jnt_qposadr[body.neck_joints[0]]] = np.radians(20.0)  # the head turns toward it
    mujoco.mj_forward(body.model, body.data)
    assert search.inhibited(body, rejected, now=0.5)
    assert search.inhibited(body, rejected + np.array([0.0, 0.0, 0.02]), now=0.5)  # within IOR_DEG
    other = point_at(body, -10.0, 0.0, 1.5)  # (head-relative: 10 deg the other way)
    assert not search.inhibited(body, other, now=0.5)
    assert not search.inhibited(body, rejected, now=IOR_S + 0.01)  # forgotten
    body.reset()


def test_two_eyes_that_disagree_produce_no_fixation(bare_body):
    """Each eye proposes a different object: the rays do not meet, no pair forms, the search holds the gaze
    (the loop's eyes stay where they were); when both propose the same object, it becomes the target."""
    from warp_vision.sim.loop import VisuomotorLoop, gaze_error_deg, point_at
    from warp_vision.sim.search import ActiveSearch, pairs

    body = bare_body
    body.reset()
    body.model.opt.gravity[:] = 0
    a, b = point_at(body, 15.0, 5.0, 1.2), point_at(body, -12.0, -4.0, 1.6)
    fov = {"left": _ScriptedFoveator(body, "left", [a]), "right": _ScriptedFoveator(body, "right", [b])}
    assert pairs(body, {s: fov[s].candidates(None) for s in SIDES}) == []
    search = ActiveSearch({s: _OracleVerifier(body, s) for s in SIDES})
    loop = VisuomotorLoop(body, fov, _holding_oculomotor(body), perception="search", search=search)
    for _ in range(30):
        body.set_ball(a)
        loop.step()
    assert search.log == [] and search.s.target is None
    assert min(gaze_error_deg(body, s, a) for s in SIDES) > 10 and min(gaze_error_deg(body, s, b) for s in SIDES) > 10
    fov["right"].points = [a]  # now both see a
    for _ in range(40):
        body.set_ball(a)
        loop.step()
    assert search.log[0][1] == "target" and max(gaze_error_deg(body, s, a) for s in SIDES) < 1.0
    body.model.opt.gravity[2] = -9.81
    body.reset()


def test_a_decoy_nearer_the_gaze_is_rejected_and_the_search_ends_on_the_ball(bare_body):
    """The scripted trial: a decoy 8 deg from the gaze scores above the ball at 25 deg. The eyes go to the
    decoy first, its verification rejects it, it is inhibited, and the eyes go on to the ball, are accepted
    and stay there; the single-answer loop (its net's first candidate: the decoy) stays on the decoy."""
    from warp_vision.sim.loop import VisuomotorLoop, gaze_error_deg, point_at
    from warp_vision.sim.scenarios import run_scenario
    from warp_vision.sim.search import ActiveSearch

    body = bare_body
    body.reset()
    body.model.opt.gravity[:] = 0
    decoy, ball = point_at(body, 8.0, 2.0, 1.3), point_at(body, -20.0, 15.0, 1.0)
    fov = {s: _ScriptedFoveator(body, s, [decoy, ball]) for s in SIDES}
    search = ActiveSearch({s: _OracleVerifier(body, s) for s in SIDES})
    loop = VisuomotorLoop(body, fov, _holding_oculomotor(body), perception="search", search=search)
    tr = run_scenario(loop, 1.0, ball=lambda _t: ball, progress=False)
    kinds = [k for _, k, _ in search.log]
    assert kinds[:4] == ["target", "reject", "target", "accept"], kinds
    assert np.linalg.norm(search.log[1][2] - decoy) < 0.05 and np.linalg.norm(search.log[3][2] - ball) < 0.05
    assert max(tr["error_left"][-20:].max(), tr["error_right"][-20:].max()) < 1.0
    single = VisuomotorLoop(body, fov, _holding_oculomotor(body))
    single.reset()
    run_scenario(single, 0.6, ball=lambda _t: ball, progress=False)
    assert max(gaze_error_deg(body, s, decoy) for s in SIDES) < 1.0  # the single answer is held by the decoy
    body.model.opt.gravity[2] = -9.81
    body.reset()


def test_the_loop_refuses_a_search_without_its_mode(bare_body):
    from warp_vision.sim.loop import VisuomotorLoop
    from warp_vision.sim.search import ActiveSearch

    fov = {s: _ScriptedFoveator(bare_body, s, []) for s in SIDES}
    with pytest.raises(ValueError, match="search"):
        VisuomotorLoop(bare_body, fov, {}, perception="search")
    with pytest.raises(ValueError, match="search"):
        VisuomotorLoop(bare_body, fov, {}, perception="nets", search=ActiveSearch())
    with pytest.raises(ValueError, match="verifiers"):
        ActiveSearch({"left": None})


def test_pair_point_needs_rays_that_meet_at_a_plausible_distance():
    from warp_vision.sim.search import pair_point

    o1, o2 = np.array([-0.03, 0.0, 0.0]), np.array([0.03, 0.0, 0.0])
    p = np.array([0.1, 0.2, 1.5])
    u = lambda o: (p - o) / np.linalg.norm(p - o)  # noqa: E731
    assert np.allclose(pair_point(o1, u(o1), o2, u(o2)), p, atol=1e-9)
    off = u(o2) + np.array([0.0, 0.05, 0.0])  # 3 deg apart at 1.5 m: 8 cm, beyond the tolerance
    assert pair_point(o1, u(o1), o2, off / np.linalg.norm(off)) is None
    behind = -u(o1)
    assert pair_point(o1, behind, o2, -u(o2)) is None  # the point behind the eyes


# --- the candidates ------------------------------------------------------------------------------------


def test_retina_cnn_candidates_are_separated_peaks_with_the_strongest_first():
    from warp_vision.frames import gaze_directions
    from warp_vision.nn.retina_cnn import RetinaCNNFoveationNet

    rng = np.random.default_rng(0)
    angles = np.radians(rng.uniform(-40, 40, size=(400, 2)))
    torch.manual_seed(0)
    net = RetinaCNNFoveationNet(angles, size=32, channels=4, views=1).eval()
    x = torch.randn(2, 3 * 400)
    dirs, scores = net.candidates(x, k=4, min_sep_deg=6.0)
    assert dirs.shape == (2, 4, 2) and scores.shape == (2, 4)
    with torch.no_grad():
        single = net.read_out(net.logits(net.image(x, 0)))
    assert torch.allclose(dirs[:, 0], single, atol=1e-6)  # the first is the map's own answer
    for b in range(2):
        d = gaze_directions(dirs[b].double().numpy())
        cos = d @ d.T
        assert (cos[np.triu_indices(4, 1)] < np.cos(np.radians(6.0)) + 1e-3).all()  # separated peaks
        assert ((scores[b] >= 0) & (scores[b] <= 1)).all()
    with pytest.raises(ValueError, match="k"):
        net.candidates(x, k=0)


# --- the verification net's interface ------------------------------------------------------------------


def test_the_verifier_rejects_bad_inputs_and_reads_its_field_out_of_the_onv():
    from warp_vision.nn.verify import FovealVerifier

    rng = np.random.default_rng(1)
    P = 200
    angles = np.radians(rng.uniform(-5, 5, size=(P, 2)))
    xy = rng.uniform(-0.1, 0.1, size=(P, 2))
    central = np.arange(0, P, 2)
    for model in ("cnn", "linet"):
        net = FovealVerifier(model, central, angles, xy, central_deg=6.0, channels=4, image_size=32, layers=2).eval()
        assert net.N == 100
        with torch.no_grad():
            out = net(torch.randn(3, 300))
            ok, prob, off = net.verdict(torch.randn(3, 300))
        assert out.shape == (3, 3) and ok.dtype == torch.bool and prob.shape == (3,) and off.shape == (3, 2)
        with pytest.raises(ValueError, match="central field"):
            net(torch.randn(3, 3 * P))  # a whole ONV, not its central field
        with pytest.raises(ValueError, match="central field"):
            net(torch.randn(300))
        onv = torch.arange(3 * P, dtype=torch.float32)[None]
        f = net.field(onv)
        assert f.shape == (1, 300) and torch.equal(f[0, :6], torch.tensor([0.0, 1, 2, 6, 7, 8]))
    with pytest.raises(ValueError, match="model"):
        FovealVerifier("fc", central, angles, xy, 6.0)
    with pytest.raises(ValueError, match="central"):
        FovealVerifier("cnn", np.arange(8), angles, xy, 6.0)


def test_a_verifier_refuses_another_kind_of_run_and_a_bad_onv(finished):
    from warp_vision.sim.search import Verifier

    with pytest.raises(ValueError, match="expected a verify run"):
        Verifier(str(finished), eye="left")


def test_verify_training_writes_per_class_false_accepts_and_its_threshold(tmp_path):
    """The smoke preset end to end: a summary with the held-out ROC area, the threshold fitted into best.pt,
    false accepts per look-alike class; the net loads as the loop's Verifier for its eye only."""
    import json

    from warp_vision.data.verification import CLASSES
    from warp_vision.sim.search import Verifier
    from warp_vision.train import verify as V
    from warp_vision.train.config_verify import VERIFY_PRESETS, VerifyTrainConfig

    out = tmp_path / "verify_left"
    cfg = VerifyTrainConfig(preset="smoke", **VERIFY_PRESETS["smoke"], out=str(out), data_dir=str(tmp_path / "data"))
    V.run(cfg, progress=False, log=lambda _m: None)
    s = json.loads((out / "summary.json").read_text())
    assert s["task"] == "verify" and set(s["heldout"]["false_accepts"]) <= set(CLASSES[1:])
    assert np.isfinite(s["threshold"]) and (out / "figures" / "verify_roc.png").exists()
    v = Verifier(str(out), eye="left")
    assert float(v.model.threshold) == pytest.approx(s["threshold"])
    ok, p, off = v(torch.rand(1, 3 * 1000))
    assert isinstance(ok, bool) and 0 <= p <= 1 and off.shape == (2,)
    with pytest.raises(ValueError, match="one ONV"):
        v(torch.rand(2, 3 * 1000))
    with pytest.raises(ValueError, match="right"):
        Verifier(str(out), eye="right")


def test_verification_samples_do_not_depend_on_batching():
    from warp_vision.data.foveation import make_retina
    from warp_vision.data.verification import CLASSES, VerifyDataConfig, central_photoreceptors, render_verify_samples

    cfg = VerifyDataConfig(samples=16, photoreceptors=400, samples_per_receptor=1)
    r = make_retina(cfg.scene_config())
    pos = np.ascontiguousarray(np.asarray(r.positions_optical_mm)[central_photoreceptors(r, cfg.central_deg)])
    whole = render_verify_samples(cfg, range(8), pos)
    parts = [render_verify_samples(cfg, range(a, b), pos) for a, b in ((0, 3), (3, 8))]
    for k in ("label", "cls", "offset", "ball_ecc_deg"):
        assert np.array_equal(whole[k], np.concatenate([p[k] for p in parts])), k
    assert np.allclose(whole["onv"].astype(np.float32), np.concatenate([p["onv"] for p in parts]).astype(np.float32),
                       rtol=1e-2, atol=1e-6)
    labels = whole["label"] > 0.5
    assert np.all(whole["ball_ecc_deg"][labels] <= 2.5) and set(whole["cls"]) <= set(range(len(CLASSES)))
    with pytest.raises(ValueError, match="max_offset_deg"):
        VerifyDataConfig(max_offset_deg=9.0).validate()


def test_the_trials_are_seeded_disjoint_and_scored(bare_body, tmp_path):
    """Held-out and training trials come from disjoint seed ranges and rooms; run_all runs a trial under the
    search (scripted candidates: a decoy's face, then the ball; verification by the true ball) and under the
    single answer, scores both, and draws the scanpath and summary figures."""
    from warp_vision.sim import search_report as R
    from warp_vision.sim import search_trials as T
    from warp_vision.sim.loop import VisuomotorLoop

    held, train = T.trial_seeds(8, split="heldout"), T.trial_seeds(8, split="train")
    assert not set(held) & set(train)
    assert {T.sample_trial(s).room_seed for s in held}.isdisjoint({T.sample_trial(s).room_seed for s in train})
    assert T.sample_trial(held[3]).ball == T.sample_trial(held[3]).ball  # reproducible
    with pytest.raises(ValueError, match="trials"):
        T.trial_seeds(0)
    trial = next(T.sample_trial(s) for s in T.trial_seeds(50) if T.sample_trial(s).decoy is not None)
    body = bare_body
    body.reset()

    def seen():  # the decoy's face first (the face toward the eyes), then the ball
        from warp_vision.data.foveation_decoys import DECOYS

        T_dec = loop.scene.objects[loop.scene.index(trial.decoy["name"])].transform[0]
        face = T_dec[:3, 3] - T_dec[:3, 2] * DECOYS[trial.decoy["name"]][1] / 2
        return [face, body.ball_position()]

    fov = {s: _ScriptedFoveator(body, s, seen) for s in SIDES}
    loop = VisuomotorLoop(body, fov, _holding_oculomotor(body), ball="ordinary")
    report = R.run_all(loop, [trial], {s: _OracleVerifier(body, s) for s in SIDES}, scanpaths=1, out=str(tmp_path))
    s, n = report["modes"]["search"], report["modes"]["nets"]
    assert s["trials"][0]["found"], s["trials"][0]["events"]
    assert [e[1] for e in s["trials"][0]["events"]][:2] == ["target", "reject"]
    assert not n["trials"][0]["found"] and n["summary"]["found_share"] == 0.0
    assert "decoy" in s["trials"][0]["look_alikes"] and report["search_cost"]["frame_ms"] > 0
    assert (tmp_path / "figures" / f"scanpath_{trial.seed}.png").exists()
    assert Path(R.summary_figure(report, str(tmp_path / "figures" / "search.png"))).stat().st_size > 0
    lines = R.report_lines(report)
    assert any("active search" in ln and "1/1 trials" in ln for ln in lines), lines
    body.reset()


def test_a_trial_whose_physics_fails_counts_as_a_miss_with_its_error(monkeypatch):
    """run_all scores a trial that raises SimulationError as not found, names the error, and goes on."""
    from warp_vision.body import SimulationError
    from warp_vision.sim import search_report as R
    from warp_vision.sim import search_trials as T

    def boom(*_a, **_k):
        raise SimulationError("t=0.2 s: contact penetration 22.0 mm (limit 20 mm)")

    monkeypatch.setattr(T, "run_trial", boom)
    monkeypatch.setattr(R, "_trial_scene", lambda *_a: None)

    class _Loop:
        body = None

    report = R.run_all(_Loop(), [T.sample_trial(T.trial_seeds(1)[0])], None, progress=False)
    s = report["modes"]["search"]["summary"]
    assert s["found"] == 0 and s["simulation_errors"] == 1
    assert "penetration" in report["modes"]["nets"]["trials"][0]["error"]
