"""The pupil nets: their data, their interface, their training run, and the pupil in the closed loop."""

import numpy as np
import pytest
import torch

from warp_vision.body import SIDES, Body, BodyConfig


def _retina_xy(P=300, seed=0):
    rng = np.random.default_rng(seed)
    r = np.sqrt(rng.uniform(0, 1, P)) * 0.8
    a = rng.uniform(0, 2 * np.pi, P)
    return np.stack([r * np.cos(a), r * np.sin(a)], 1)


def test_region_log_means_match_a_plain_reference():
    from warp_vision.nn.intraocular import LOG_FLOOR, RegionLogMeans, retina_regions

    xy = _retina_xy()
    pool = RegionLogMeans(xy, rings=3, sectors=4)
    onv = torch.rand(5, 3 * len(xy), dtype=torch.float64).float() * 10 ** torch.linspace(-3, 2, 5)[:, None]
    got = pool(onv).view(5, 13, 3)
    region = retina_regions(xy, 3, 4)
    x = onv.double().numpy().reshape(5, -1, 3)
    for r in range(12):
        np.testing.assert_allclose(got[:, r].numpy(), np.log10(x[:, region == r].mean(1) + LOG_FLOOR), rtol=1e-5,
                                   atol=1e-5)
    np.testing.assert_allclose(got[:, 12].numpy(), np.log10(x.mean(1) + LOG_FLOOR), rtol=1e-5, atol=1e-5)
    counts = np.bincount(region, minlength=12).reshape(3, 4).sum(1)
    assert counts.max() - counts.min() <= 1  # rings of equal photoreceptor counts


def test_the_pupil_net_refuses_bad_inputs_and_answers_within_the_iris_range():
    from warp_vision.nn.intraocular import PupilNet

    net = PupilNet(_retina_xy(), hidden=4)
    onv = torch.rand(3, 900)
    out = net(onv, torch.tensor([2.0, 4.0, 8.0]))
    assert out.shape == (3,) and ((out > 2) & (out < 8)).all()
    for bad, match in [((torch.rand(3, 899), [4.0] * 3), r"\[B, 900\]"), ((torch.rand(900), [4.0]), r"\[B, 900\]"),
                       ((-torch.rand(3, 900), [4.0] * 3), ">= 0"),
                       ((torch.full((3, 900), float("nan")), [4.0] * 3), "finite"),
                       ((onv, [4.0, 4.0]), "one diameter per ONV"), ((onv, [4.0, 0.0, 4.0]), r"\(0, 10\]"),
                       ((onv, [4.0, 11.0, 4.0]), r"\(0, 10\]")]:
        with pytest.raises(ValueError, match=match):
            net(bad[0], torch.tensor(bad[1]))


def test_pupil_samples_carry_the_luminance_their_exposure_gives_them():
    from warp_vision.data.foveation import make_retina
    from warp_vision.data.intraocular import PUPIL_GRID_MM, PupilDataConfig, render_pupil_samples
    from warp_vision.eye.pupil import adapting_luminance

    cfg = PupilDataConfig(samples=40, photoreceptors=300, samples_per_receptor=1, luminance_decades=4.0)
    retina = make_retina(cfg.scene_config())
    d = render_pupil_samples(cfg, range(14, 20), retina)  # across a room block's edge (16)
    lum = adapting_luminance(d["onv"].astype(np.float64).mean(1) * d["exposure"], d["pupil"])
    np.testing.assert_allclose(lum, d["luminance"], rtol=1e-4)
    assert set(d["pupil"].tolist()) <= set(PUPIL_GRID_MM)
    assert d["pupil"][0] == d["pupil"][1] and np.all((d["luminance"] > 75.17e-2) & (d["luminance"] < 75.17e2))
    again = render_pupil_samples(cfg, [17], retina)  # a sample does not depend on its batch
    np.testing.assert_array_equal(again["onv"][0], d["onv"][3])
    assert again["exposure"][0] == d["exposure"][3]
    shuffled = render_pupil_samples(cfg, [18, 14, 17, 15], retina)  # rows in the order asked, across blocks
    for k in d:
        np.testing.assert_array_equal(shuffled[k], d[k][[4, 0, 3, 1]])
    with pytest.raises(ValueError, match=r"luminance_decades: expected decades in \(0, 8\], got 0"):  # (not "0 to 8")
        PupilDataConfig(luminance_decades=0).validate()
    with pytest.raises(ValueError, match="rooms"):
        PupilDataConfig(rooms="elsewhere").validate()


def test_a_smoke_pupil_run_trains_and_measures_held_out_rooms(tmp_path):
    from warp_vision.sim.loop import load_pupil
    from warp_vision.train.config import resolve
    from warp_vision.train.config_intraocular import PUPIL_PRESETS, PupilTrainConfig
    from warp_vision.train.pupil import run

    cfg = resolve("smoke", {"out": str(tmp_path / "run"), "data_dir": str(tmp_path / "data")}, PupilTrainConfig,
                  PUPIL_PRESETS)
    summary = run(cfg, progress=False, log=lambda *_a, **_k: None)
    held = summary["heldout"]
    assert set(held) >= {"median_error_mm", "p90_error_mm", "median_relative_error", "within_5pct"}
    assert np.isfinite(held["median_error_mm"]) and held["median_error_mm"] >= 0
    assert (tmp_path / "run" / "figures" / "pupil.png").exists()
    net = load_pupil(str(tmp_path / "run"))
    assert net(torch.rand(2, 3 * cfg.photoreceptors), torch.tensor([3.0, 5.0])).shape == (2,)
    from warp_vision.sim.loop import Foveator, load_lens

    with pytest.raises(ValueError, match="expected a lens run"):
        load_lens(str(tmp_path / "run"))
    with pytest.raises(
        ValueError, match=r"expected a foveation run \(python -m warp_vision.train\); it holds a net of kind 'pupil'"
    ):
        Foveator(str(tmp_path / "run"))
    with pytest.raises(ValueError, match="pupil_mm"):
        load_pupil(str(tmp_path / "run"))(torch.rand(2, 3 * cfg.photoreceptors), torch.tensor([3.0]))


# --- the pupil in the closed loop ----------------------------------------------------------------------


class _ConstantPupilNet:
    def __init__(self, mm):
        self.mm, self.calls = mm, 0

    def __call__(self, onv, pupil_mm):
        self.calls += 1
        assert onv.shape[0] == 1 and pupil_mm.shape == (1,)
        return torch.tensor([self.mm])


@pytest.fixture(scope="module")
def bare_body():
    return Body(BodyConfig(arms=False))


def _loop(body, **kw):
    from test_loop import _HoldingOculomotor, _OracleFoveator

    from warp_vision.sim.loop import VisuomotorLoop

    return VisuomotorLoop(body, {s: _OracleFoveator(body, s) for s in SIDES},
                          {s: _HoldingOculomotor(body, s) for s in SIDES}, **kw)


def test_a_light_step_in_the_loop_settles_on_the_teachers_steady_state(bare_body):
    from warp_vision.eye.plants import PUPIL_LATENCY_S
    from warp_vision.sim.scenarios import light_steps

    res = light_steps(_loop(bare_body), phases=((1.5, 1.0), (1.5, 100.0)), progress=False)
    tr = res["traces"]
    for st in res["steps"]:
        assert st["direction"] == "constrict" and st["log_units"] == 2.0
        assert st["end_relative_error"] < 0.05 and st["settle_s"] is not None and st["settle_s"] < 1.5
        # the iris waits its latency (and at most one visual frame of 40 ms) before it moves
        assert PUPIL_LATENCY_S[0] <= st["latency_s"] <= PUPIL_LATENCY_S[1] + 0.05
        assert st["steady_state_mm"] < st["from_mm"] - 0.5
    assert tr["light"][0] == 1.0 and tr["light"][-1] == 100.0


def test_the_loop_commands_the_pupil_from_its_nets(bare_body):
    from warp_vision.sim.loop import VisuomotorLoop
    from warp_vision.sim.scenarios import light_steps

    nets = {s: _ConstantPupilNet(6.0) for s in SIDES}
    res = light_steps(_loop(bare_body, pupil_nets=nets), phases=((2.5, 1.0),), progress=False)
    assert nets["left"].calls >= 150 // 4
    assert abs(res["traces"]["pupil_left"][-1] - 6.0) < 0.05  # the net's command, not the teacher's
    assert abs(res["traces"]["teacher_left"][-1] - 6.0) > 1.0
    with pytest.raises(ValueError, match="pupil_nets"):
        VisuomotorLoop(bare_body, {}, {}, pupil_nets={"left": nets["left"]})


# --- the lens --------------------------------------------------------------------------------------------


def test_textured_cards_face_forward_with_a_seeded_pattern():
    from warp_vision.scene.textures import ALBEDO_RANGE, card_pattern, textured_card

    card = textured_card(0.3, 32, 5)
    assert np.allclose(card.face_normals[:, 2], 1.0) and np.allclose(card.bounds, [[-0.15, -0.15, 0], [0.15, 0.15, 0]])
    p = card_pattern(32, 5)
    assert p.min() >= 0 and p.max() <= 1 and p.std() > 0.1
    assert ALBEDO_RANGE[0] * 0.85 <= p.min() and p.max() <= ALBEDO_RANGE[1] * 1.15
    np.testing.assert_array_equal(p, card_pattern(32, 5))
    assert not np.array_equal(p, card_pattern(32, 6))
    with pytest.raises(ValueError, match="textured_card"):
        textured_card(0.0, 32, 5)


def test_band_energies_match_a_plain_reference():
    """Band-pass energies and channel correlations against a direct numpy computation: each band is the
    mean over one neighbourhood minus the mean over the next (the photoreceptor itself first)."""
    from scipy.spatial import cKDTree

    from warp_vision.nn.intraocular import CHANNEL_PAIRS, BandEnergies

    xy = _retina_xy(200)
    ks = (3, 7, 12)
    be = BandEnergies(xy, neighbourhoods=ks, rings=2)
    assert be.features == 3 * 6 * 2
    x = torch.rand(4, 200, 3, dtype=torch.float64).float() + 0.1
    got = be(x).view(4, 3, 6, 2).numpy()  # [B, band, 3 energies + 3 correlations, ring]
    _d, nbr = cKDTree(xy).query(xy, 13)
    rho = np.hypot(*xy.T)
    ring = (rho > np.median(rho)).astype(int)
    xn = x.double().numpy() / x.double().numpy().mean(1, keepdims=True)
    levels = [xn] + [xn[:, nbr[:, 1:k + 1]].mean(2) for k in ks]
    for bi in range(len(ks)):
        band = levels[bi] - levels[bi + 1]
        for r in range(2):
            b = band[:, ring == r]
            e = (b ** 2).mean(1)  # [B, 3]
            np.testing.assert_allclose(got[:, bi, :3, r], np.log10(e + 1e-8), rtol=1e-4, atol=1e-4)
            for c, (i, j) in enumerate(CHANNEL_PAIRS):
                corr = (b[..., i] * b[..., j]).mean(1) / np.sqrt(e[:, i] * e[:, j])
                np.testing.assert_allclose(got[:, bi, 3 + c, r], corr, rtol=1e-4, atol=1e-4)
    # a channel blurred (smoothed) relative to the others loses fine energy and its correlation with them
    y = x.clone()
    y[..., 2] = torch.from_numpy(levels[2][..., 2]).float()
    f = be(y).view(4, 3, 6, 2).numpy()
    assert (f[:, 0, 2] < got[:, 0, 2] - 0.3).all()
    with pytest.raises(ValueError, match="neighbourhoods"):
        BandEnergies(xy, neighbourhoods=(6, 3))


def test_the_lens_net_refuses_bad_inputs():
    from warp_vision.nn.intraocular import LensNet

    xy = _retina_xy(300)
    net = LensNet(xy, np.arange(100), 300, hidden=4)
    assert net(torch.rand(2, 900), torch.tensor([3.0, 4.0])).shape == (2,)
    assert net(torch.rand(2, 300), torch.tensor([3.0, 4.0]), central_only=True).shape == (2,)
    with pytest.raises(ValueError, match="samples_per_receptor"):
        LensNet(xy, np.arange(100), 300, samples_per_receptor=0)
    with pytest.raises(ValueError, match=r"\[B, 900\]"):
        net(torch.rand(2, 300), torch.tensor([3.0, 4.0]))
    with pytest.raises(ValueError, match="one diameter per ONV"):
        net(torch.rand(2, 900), torch.tensor([3.0]))
    with pytest.raises(ValueError, match="onv and pupil_mm"):
        net()
    with pytest.raises(ValueError, match="central"):
        LensNet(xy, np.arange(250, 310), 300)


def test_the_lens_holds_on_an_image_without_contrast():
    """A uniform field (a glowing ball filling the fovea) carries no defocus cue: the loop's lens command
    holds instead of following the net's meaningless estimate."""
    from warp_vision.nn.intraocular import LensNet
    from warp_vision.sim.loop import _lens_command

    net = LensNet(_retina_xy(300), np.arange(100), 300, hidden=4)
    textured, uniform = torch.rand(1, 900) + 0.1, torch.full((1, 900), 0.3)
    c_tex = float(net.contrast(net.raw_features(textured, torch.tensor([4.0])))[0])
    c_uni = float(net.contrast(net.raw_features(uniform, torch.tensor([4.0])))[0])
    assert c_uni < -7 < c_tex
    net.contrast_floor.fill_(c_tex - 1.0)
    def central(onv):  # the loop renders the net's field only
        return onv.view(1, 300, 3)[:, :100].reshape(1, 300)

    assert _lens_command(net, central(uniform), 2.0, 4.0, hold=1.5) == (1.5, None)
    cmd, d = _lens_command(net, central(textured), 2.0, 4.0, hold=1.5)
    assert d is not None and cmd == pytest.approx(2.0 - d)


def test_lens_samples_fill_the_central_field_with_a_card_at_the_stated_defocus():
    from warp_vision.data.foveation import FoveationDataConfig, make_retina
    from warp_vision.data.intraocular import LensDataConfig, central_photoreceptors, render_lens_samples

    cfg = LensDataConfig(samples=40, photoreceptors=1000, samples_per_receptor=1, card_vertices=48)
    retina = make_retina(FoveationDataConfig(photoreceptors=1000))
    central = central_photoreceptors(retina, cfg.central_deg)
    pos = np.asarray(retina.positions_optical_mm)[central]
    d = render_lens_samples(cfg, range(12, 20), pos)
    np.testing.assert_allclose(d["defocus"], d["accommodation"] - 1.0 / d["distance"], atol=1e-5)
    assert np.all(np.abs(d["defocus"]) <= cfg.defocus_range_D + 1e-6)
    assert np.all((d["distance"] >= 0.2) & (d["distance"] <= 5.0))
    onv = d["onv"].astype(np.float32).reshape(len(d["onv"]), -1, 3)
    assert (onv.sum(2) > 0).all()  # every central photoreceptor sees the card (the background is black)
    again = render_lens_samples(cfg, [13], pos)
    np.testing.assert_array_equal(again["onv"][0], d["onv"][1])


def test_a_smoke_lens_run_trains_and_measures_held_out_cards(tmp_path, monkeypatch):
    from warp_vision.sim.loop import load_lens
    from warp_vision.train import lens
    from warp_vision.train.config import resolve
    from warp_vision.train.config_intraocular import LENS_PRESETS, LensTrainConfig
    from warp_vision.train.lens import run

    monkeypatch.setattr(lens, "CALIBRATE_MIN_SAMPLES", 1)  # the smoke set is too small for the real threshold

    cfg = resolve("smoke", {"out": str(tmp_path / "run"), "data_dir": str(tmp_path / "data")}, LensTrainConfig,
                  LENS_PRESETS)
    said = []
    summary = run(cfg, progress=False, log=lambda *a, **_k: said.append(" ".join(map(str, a))))
    assert {"median_error_D", "p90_error_D", "sign_correct_above_0.5D"} <= set(summary["heldout"])
    assert (tmp_path / "run" / "figures" / "lens.png").exists()
    assert any(line.startswith("lens net's bias near focus (D) at accommodations 0: ") for line in said), said
    net = load_lens(str(tmp_path / "run"))
    assert net(torch.rand(2, 3 * cfg.photoreceptors), torch.tensor([3.0, 5.0])).shape == (2,)
    # the bias table fitted after training travels in best.pt, and the summary scores the calibrated estimate
    assert summary["bias_D"] == pytest.approx(net.bias_D.tolist()) and any(b != 0 for b in summary["bias_D"])
    assert {"median_error_D", "sign_correct_above_0.5D"} <= set(summary["heldout_calibrated"])


def test_a_bias_table_with_nothing_to_fit_says_so():
    # a smoke-sized run logged "bias near focus (D) at accommodations 0: +0.000, 1: +0.000, ...", a table of
    # zeros that read as a perfectly calibrated net
    from types import SimpleNamespace

    from warp_vision.nn.intraocular import LENS_BIAS_KNOTS_D
    from warp_vision.train.lens import LensTask

    said = []
    true = torch.tensor([3.0, -2.0, 0.1])  # one sample near focus: fewer than a knot needs
    task = SimpleNamespace(_predict=lambda model, data, ids, device: (true + 0.2, true), log=said.append,
                           data={"accommodation": torch.tensor([1.0, 2.0, 3.0])})
    model = SimpleNamespace(bias_D=torch.ones(len(LENS_BIAS_KNOTS_D)))
    assert LensTask.calibrate(task, model, [0, 1, 2], "cpu")
    assert torch.all(model.bias_D == 0)
    assert said == ["lens net's bias near focus: not fitted, no accommodation has 20 training samples within 0.6 D "
                    "of focus; none is subtracted"]


def test_the_lens_bias_table_is_the_median_error_near_focus():
    from warp_vision.nn.intraocular import LENS_BIAS_KNOTS_D
    from warp_vision.train.lens import fit_bias

    rng = np.random.default_rng(0)
    acc = rng.uniform(0, 4, 20000)
    true = rng.uniform(-2, 2, len(acc))
    bias = 0.05 * acc - 0.1  # the net reads 0.1 D short at the far point, 0.1 D long at 4 D
    pred = true + bias + rng.normal(0, 0.02, len(acc))
    pred[np.abs(true) > 0.6] += 1.0  # errors far from focus do not enter the table
    table = fit_bias(pred, true, acc)
    inside = LENS_BIAS_KNOTS_D <= 4.0
    np.testing.assert_allclose(table[inside], 0.05 * LENS_BIAS_KNOTS_D[inside] - 0.1, atol=0.01)
    # held flat
    np.testing.assert_allclose(table[LENS_BIAS_KNOTS_D > 4.5], table[LENS_BIAS_KNOTS_D == 4.0][0], atol=1e-12)
    assert np.all(fit_bias(pred, true + 5.0, acc) == 0.0)  # nothing near focus: no correction
    with pytest.raises(ValueError, match="as many"):
        fit_bias(pred, true[:-1], acc)


def test_the_lens_net_subtracts_its_bias_at_the_lens_state():
    from warp_vision.nn.intraocular import LENS_BIAS_KNOTS_D, LensNet

    net = LensNet(_retina_xy(300), np.arange(100), 300, hidden=4)
    old = {k: v for k, v in net.state_dict().items() if k != "bias_D"}
    net.load_state_dict(old)  # a checkpoint from before the calibration: no correction
    assert torch.equal(net.calibrated(torch.tensor([0.3]), 2.0), torch.tensor([0.3]))
    net.bias_D.copy_(torch.as_tensor(0.1 * LENS_BIAS_KNOTS_D))
    out = net.calibrated(torch.tensor([0.3, 0.3]), [2.0, 2.25])
    np.testing.assert_allclose(out.numpy(), [0.3 - 0.2, 0.3 - 0.225], atol=1e-6)
    with pytest.raises(ValueError, match="accommodation_D"):
        net.calibrated(torch.tensor([0.3]), float("nan"))


def test_focus_summary_counts_the_steps_in_focus_by_the_goal():
    from warp_vision.sim.scenarios import focus_summary

    def step(to, t, end):
        return {"from_m": 2.0 if to < 1 else 0.33, "to_m": to, "in_focus_s": t, "end_defocus_D": end}

    runs = [[step(0.33, 1.0, -0.1), step(2.0, 0.8, 0.05)], [step(0.33, None, -0.3), step(2.0, 1.3, 0.2)]]
    f = focus_summary(runs, goal_s=1.2)
    assert f["near"]["steps"] == 2 and f["near"]["in_focus_within_goal"] == 1 and f["near"]["median_in_focus_s"] is None
    assert f["far"]["in_focus_within_goal"] == 1 and f["far"]["median_in_focus_s"] == pytest.approx(1.05)
    assert f["near"]["median_abs_end_defocus_D"] == pytest.approx(0.2)


class _OracleLensNet:
    """A lens net's interface (raw_features, contrast above its floor, head) answering the true defocus
    of the rendered state: the accommodation the frame was rendered at minus the card's vergence from
    the eye."""

    contrast_floor = torch.tensor(-np.inf)
    samples_per_receptor = 1

    def __init__(self, loop, side):
        self.loop, self.side = loop, side
        self.P = len(loop.fov[side].retina.positions_optical_mm)
        self.central = torch.arange(0, self.P, 10)

    def raw_features(self, onv, pupil_mm, central_only=False):
        assert central_only and onv.shape == (1, 3 * len(self.central))
        return torch.zeros(len(onv), 1)

    def contrast(self, raw):
        return torch.zeros(len(raw))

    def calibrated(self, defocus, accommodation_D):
        return defocus

    def head(self, raw):
        loop, s = self.loop, self.side
        acc = loop._optics[s][0]
        centre = loop.fov[s].target()
        return torch.tensor([acc - 1.0 / np.linalg.norm(centre - loop.body.eye_pose(s)[:3, 3])])


def test_a_focus_step_in_the_loop_comes_into_focus(bare_body):
    from warp_vision.eye.plants import LENS_LATENCY_S
    from warp_vision.sim.scenarios import FOCUS_TOLERANCE_D, focus_steps

    for lens in ("vergence", "nets"):
        loop = _loop(bare_body)
        if lens == "nets":
            loop.lens_nets = {s: _OracleLensNet(loop, s) for s in SIDES}
            loop.optics_step_d = 0.1
        res = focus_steps(loop, phases=((1.0, 2.0), (1.5, 1.0 / 3.0)), progress=False, card_vertices=48)
        for st in res["steps"]:
            assert st["in_focus_s"] is not None and st["in_focus_s"] < 1.2, (lens, st)
            assert abs(st["end_defocus_D"]) < FOCUS_TOLERANCE_D
            assert st["latency_s"] >= LENS_LATENCY_S - 0.01  # the lens waits its latency
        assert len(res["snapshots"]) >= 1 and sum(o.name.startswith("focus_card") for o in loop.scene.objects) == 2


class _ConstantLensNet(_OracleLensNet):
    """Reads the same defocus whatever the image."""

    def __init__(self, loop, side, defocus):
        super().__init__(loop, side)
        self.defocus = defocus

    def head(self, raw):
        return torch.tensor([self.defocus])


def test_accommodation_is_yoked_to_the_mean_of_both_eyes_readings(bare_body):
    """Both lenses take one command, the mean of the vergences the two eyes' nets read (the consensual
    response); unyoked, each eye follows its own net."""
    for yoked in (True, False):
        loop = _loop(bare_body)
        loop.lens_nets = {"left": _ConstantLensNet(loop, "left", 0.3), "right": _ConstantLensNet(loop, "right", -0.1)}
        loop.yoked_lens = yoked
        loop.reset()
        loop.step()  # the first period is a frame
        acc = {s: loop._optics[s][0] for s in SIDES}
        read = {"left": acc["left"] - 0.3, "right": acc["right"] + 0.1}
        for s in SIDES:
            want = (read["left"] + read["right"]) / 2 if yoked else read[s]
            assert loop._lens_command[s] == pytest.approx(want), (yoked, s)
