"""Generator v9: v8's scenes plus decoys (cylinders seen end-on, such as a cannon's muzzle), each v9 sample
v8's with decoys added; the "decoy" held-out condition; the demo's gaze-error summary."""

import numpy as np
import pytest

from warp_vision.data import foveation as F
from warp_vision.data import foveation_decoys as D
from warp_vision.data import foveation_scenes as V
from warp_vision.data.foveation import FoveationDataConfig, render_samples

SMALL = dict(photoreceptors=400, samples_per_receptor=1)


def params(cfg, i, attempt=0):
    limits = lambda ecc: (F.min_apparent_diameter(cfg, ecc), np.radians(F.MAX_APPARENT_DIAMETER_DEG))  # noqa: E731
    p = V.sample_params(cfg, i, attempt, F.BALL_RADII, limits)
    return D.add_decoys(cfg, p, i, attempt) if cfg.generator >= 9 else p


def shown(p):
    return [n for n, d in p["decoys"].items() if d["visible"]]


def test_a_v9_sample_is_the_v8_sample_with_decoys():
    v8, v9 = FoveationDataConfig(generator=8, **SMALL), FoveationDataConfig(generator=9, **SMALL)
    assert v9.manifest()["generator_version"] == 9 and v9.key() != v8.key()
    for i in range(60):
        a, b = params(v8, i), params(v9, i)
        assert np.array_equal(a["target"], b["target"]) and np.array_equal(a["ball"], b["ball"])
        assert np.array_equal(a["meta"], b["meta"][:-1]) and len(b["meta"]) == len(F.META_V9)
        assert b["meta"][-1] == bool(shown(b))


def test_decoys_follow_their_rules():
    mixed = [params(FoveationDataConfig(generator=9, **SMALL), i) for i in range(300)]
    share = np.mean([bool(shown(p)) for p in mixed])
    assert 0.15 < share < 0.4, share
    assert not any(shown(p) for p in mixed if p["kind"]["dim"])  # v7's condition stays v7's
    decoy = [params(FoveationDataConfig(generator=9, condition="decoy", rooms="heldout", **SMALL),
                    i) for i in range(80)]
    assert np.mean([bool(shown(p)) for p in decoy]) > 0.95
    for c in ("white", "arm", "glow_dim"):
        assert not any(shown(params(FoveationDataConfig(generator=9, condition=c, **SMALL), i)) for i in range(20))
    end_on, ratios = [], []
    for p in decoy:
        eye = p["eye_pose"][:3, 3]
        d_ball = np.linalg.norm(p["ball"] - eye)
        a_ball = np.arcsin(p["radius"] / d_ball)
        for n in shown(p):
            T = p["decoys"][n]["pose"]
            r, length = D.DECOYS[n]
            axis = T[:3, 2]
            face = T[:3, 3] - axis * length / 2
            u = (face - eye) / np.linalg.norm(face - eye)
            ratios.append(np.arctan(r / np.linalg.norm(face - eye)) / a_ball)
            end_on.append(np.degrees(np.arccos(np.clip(abs(axis @ u), -1, 1))) <= D.END_ON_TILT_DEG + 1e-6)
            assert V._in_room(face, p["room"]["size"], 0.0) and V._in_room(face + axis * length, p["room"]["size"], 0.0)
            # never in front of the ball: wholly behind it, or off its disc
            assert not D._in_front_of_ball(T[:3, 3], np.hypot(r, length / 2), eye, (p["ball"] - eye) / d_ball, d_ball,
                                           p["radius"], a_ball)
    ratios = np.array(ratios)
    assert ratios.min() > D.APPARENT_RATIO[0] - 0.02 and ratios.max() < D.APPARENT_RATIO[1] + 0.02
    assert 0.6 < np.mean(end_on) <= 0.95


def test_decoys_are_rendered_in_sight_and_the_ball_stays_visible():
    cfg = FoveationDataConfig(generator=9, condition="decoy", rooms="heldout", samples=8, **SMALL)
    retina, eye = F.make_retina(cfg), F.make_eye(cfg)
    data = render_samples(cfg, range(8), None, retina, eye)
    assert data["meta"].shape == (8, len(F.META_V9)) and (data["meta"][:, -1] == 1).all()
    # hiding the decoys changes the ONVs: they are seen
    from warp_vision.kernels.render import render_onv

    ps = [params(cfg, i) for i in range(8)]
    scene = V.make_scene(V.ROOM_FAMILIES["heldout"], cfg.seed, 0, F.BALL_RADII, with_arms=False)
    D.add_decoy_objects(scene)
    V.place(scene, ps)
    D.place_decoys(scene, ps)
    assert all(F.ball_visible(scene, p, k) for k, p in enumerate(ps) if D.decoy_in_sight(scene, p, k))
    poses = np.stack([p["eye_pose"] for p in ps])
    seen = render_onv(scene, retina, eye, poses, 1).numpy()
    for n in D.DECOYS:
        scene.set_visible(n, False)
    hidden = render_onv(scene, retina, eye, poses, 1).numpy()
    assert (np.abs(seen - hidden).max(axis=1) > 1e-6).mean() >= 0.5


def test_the_training_presets_use_v9():
    from warp_vision.train.conditions import condition_config
    from warp_vision.train.config import resolve

    for preset in ("quick", "default", "paper"):
        assert resolve(preset, {}).generator == 9
    data = resolve("default", {}).data_config()
    assert condition_config(data, "decoy", 10).generator == 9
    assert condition_config(data, "white", 10).generator == 8  # the other held-out sets stay v8's (same ONVs)


def test_flight_error_summary():
    from warp_vision.sim.demo import flight_error_summary

    t = np.linspace(0, 0.8, 81)
    err = np.where(t < 0.3, 20.0, 1.0)
    s = flight_error_summary(t, err)
    assert s["median"] == 1.0 and s["share_over_5deg"] == pytest.approx(30 / 81)
    assert s["at_0.2_s"] == 20.0 and s["at_0.4_s"] == 1.0
    with pytest.raises(ValueError, match="lengths"):
        flight_error_summary(t, err[:-1])


def test_ball_signal_renders_the_dataset_s_onvs_and_measures_each_ball():
    """ball_signal re-renders the samples as the dataset has them (the same ONVs), counts the
    photoreceptors that see each ball, and tells what a direction from the eye reaches first."""
    from warp_vision.frames import gaze_angles, gaze_directions

    cfg = FoveationDataConfig(generator=9, samples=18, photoreceptors=3000, samples_per_receptor=1)
    retina, eye = F.make_retina(cfg), F.make_eye(cfg)
    idx = [17, 0, 3, 16, 1, 6, 2, 4]  # out of order, two rooms: the results follow the order given
    data = render_samples(cfg, idx, None, retina, eye)
    targets = data["target"].astype(np.float64)
    sig = F.ball_signal(cfg, idx, retina, eye, directions=targets, with_onv=True)
    assert np.array_equal(sig["onv"].astype(np.float16), data["onv"])
    assert (sig["receptors"] > 0).mean() >= 0.75 and np.isfinite(sig["contrast"]).all() and (sig["contrast"] >= 0).all()
    assert (sig["receptors"] == 0).sum() == (sig["contrast"] == 0).sum()
    assert (sig["landed_on"] == "ball").mean() >= 0.75  # the centre of a partly hidden ball may be behind something
    # the way back: from the eye away from the ball reaches something else
    away = gaze_angles(-gaze_directions(targets))
    again = F.ball_signal(cfg, idx[::-1], retina, eye, directions=away[::-1], with_onv=True,
                          chance_directions=targets[::-1])
    assert np.array_equal(again["receptors"], sig["receptors"][::-1]) and np.array_equal(again["onv"], sig["onv"][::-1])
    assert not (again["landed_on"] == "ball").any() and set(again["landed_on"]) <= set(F.LANDED_ON)
    assert np.array_equal(again["chance_landed_on"], sig["landed_on"][::-1])  # chance directions are followed alike
    with pytest.raises(ValueError, match="chance_directions"):
        F.ball_signal(cfg, [0, 1], retina, eye, chance_directions=targets[:1])
    assert "landed_on" not in F.ball_signal(cfg, [0], retina, eye) and "onv" not in F.ball_signal(cfg, [0], retina, eye)


def test_a_glowing_ball_stands_out_more_than_a_matte_one():
    sizes = dict(samples=12, photoreceptors=3000, samples_per_receptor=1, rooms="heldout")
    contrast = {}
    for condition in ("glow_dim", "matte"):
        cfg = FoveationDataConfig(generator=8, condition=condition, **sizes)
        sig = F.ball_signal(cfg, range(12), F.make_retina(cfg), F.make_eye(cfg))
        contrast[condition] = np.median(sig["contrast"][sig["receptors"] > 0])
    assert contrast["glow_dim"] > 5 * contrast["matte"] and contrast["matte"] > 0.02


def test_ball_signal_refuses_what_it_cannot_measure():
    cfg = FoveationDataConfig(generator=9, samples=4, **SMALL)
    retina, eye = F.make_retina(cfg), F.make_eye(cfg)
    with pytest.raises(ValueError, match="v8 and v9"):
        F.ball_signal(FoveationDataConfig(generator=7, samples=4, **SMALL), [0], retina, eye)
    with pytest.raises(ValueError, match="distinct"):
        F.ball_signal(cfg, [1, 1], retina, eye)
    with pytest.raises(ValueError, match="directions"):
        F.ball_signal(cfg, [0, 1], retina, eye, directions=np.zeros((3, 2)))
