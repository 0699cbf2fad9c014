"""Generator v8: ordinary balls in a family of rooms, lighting over two decades, distractors brighter than
the ball, the body's arms in view; v7 kept by its version; the held-out condition evaluation."""

import json

import numpy as np
import pytest
import torch

from warp_vision.data import foveation as F
from warp_vision.data import foveation_scenes as V
from warp_vision.data.foveation import FoveationDataConfig, render_samples
from warp_vision.frames import gaze_directions

SMALL = dict(photoreceptors=400, samples_per_receptor=1, generator=8)


def params(cfg, i, attempt=0):
    limits = lambda ecc: (F.min_apparent_diameter(cfg, ecc), np.radians(F.MAX_APPARENT_DIAMETER_DEG))  # noqa: E731
    return V.sample_params(cfg, i, attempt, F.BALL_RADII, limits)


def test_v7_stays_reproducible_by_its_version():
    """A v7 config's manifest (and so its dataset's cache key) is what v7 wrote: no v8 fields."""
    v7 = FoveationDataConfig(generator=7, samples=8000)
    m = v7.manifest()
    assert m["generator_version"] == 7 and "rooms" not in m and "condition" not in m and "generator" not in m
    assert v7.key() == "b804806c800c"  # the key v7 gave this config (the default left eye's 8,000 ONVs)
    assert FoveationDataConfig().manifest()["generator_version"] == 7  # still the default (docs/RESULTS.md: why)
    assert FoveationDataConfig(samples=8000, generator=8).key() != v7.key()


@pytest.mark.parametrize("kw, match", [(dict(generator=6), "generator"), (dict(rooms="kitchen", generator=8), "rooms"),
                                       (dict(condition="fog", generator=8), "condition"),
                                       (dict(generator=7, condition="white"), "generators 8 and 9"),
                                       (dict(generator=8, condition="decoy"), "generator 9")])
def test_bad_v8_configs_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        FoveationDataConfig(**kw).validate()


def test_room_families_are_disjoint_and_samples_do_not_depend_on_batching():
    train = [V.room_layout(0, 0, b) for b in range(20)]
    held = [V.room_layout(1, 0, b) for b in range(20)]
    assert not any(np.isclose(a["size"][0], b["size"][0]) and np.isclose(a["size"][1], b["size"][1])
                   for a in train for b in held)
    cfg = FoveationDataConfig(samples=40, **SMALL)
    a, b = params(cfg, 5), params(cfg, 5)
    assert np.array_equal(a["ball"], b["ball"]) and np.array_equal(a["eye_pose"], b["eye_pose"])
    assert not np.array_equal(params(cfg, 5, 1)["ball"], a["ball"])
    # the target is the ball's direction in the eye frame, within the field
    for i in range(12):
        p = params(cfg, i)
        T = p["eye_pose"]
        u = T[:3, :3].T @ (p["ball"] - T[:3, 3])
        u /= np.linalg.norm(u)
        g = gaze_directions(torch.tensor(p["target"][None], dtype=torch.float64))[0].numpy()
        assert np.allclose(u, g, atol=1e-6) and np.degrees(np.arccos(u[2])) <= cfg.max_field_deg + 1e-6
    # rendered alone or in a batch with others: the same ONV
    retina, eye = F.make_retina(cfg), F.make_eye(cfg)
    whole = render_samples(cfg, range(14, 20), None, retina, eye)  # two rooms (blocks 0 and 1)
    part = render_samples(cfg, range(16, 18), None, retina, eye)
    assert np.array_equal(whole["onv"][2:4], part["onv"]) and np.array_equal(whole["target"][2:4], part["target"])


def test_the_mixture_and_the_conditions_follow_their_rules():
    mixed = [params(FoveationDataConfig(**SMALL), i) for i in range(300)]
    share = lambda key: np.mean([p["kind"][key] for p in mixed])  # noqa: E731
    assert 0.08 < share("glow") < 0.25 and 0.2 < share("distractor") < 0.4 and 0.15 < share("arm") < 0.35
    bright = np.array([p["light"]["brightness"] for p in mixed if not p["kind"]["dim"]])
    assert bright.max() / bright.min() > 50  # near two decades
    for p in mixed:
        if not p["kind"]["glow"]:
            assert not p["ball_material"]["emission"].any()
    assert len({tuple(np.round(p["ball_material"]["diffuse"], 3)) for p in mixed}) > 200
    by = {c: [params(FoveationDataConfig(condition=c, rooms="heldout", **SMALL),
                     i) for i in range(30)] for c in V.CONDITIONS[1:]}
    assert all(
        p["kind"]["glow"] and p["kind"]["dim"] and p["ball_material"]["emission"].max() == V.GLOW
        for p in by["glow_dim"]
    )
    for p in by["white"]:
        d = p["ball_material"]["diffuse"]
        assert d.min() >= 0.8 and np.ptp(d) == 0 and not p["ball_material"]["emission"].any()
    for p in by["matte"]:
        d = p["ball_material"]["diffuse"]
        assert p["ball_material"]["specular"] == 0 and np.ptp(d) > 0.1 * d.max()
    for p in by["distractor"]:
        shown = [d for d in p["distractors"].values() if d["visible"]]
        ball = V.ball_radiance(p["light"], p["ball_material"], p["ball"])
        assert all(d["emission"].max() > 1.4 * ball for d in shown)
    assert np.mean([any(d["visible"] for d in p["distractors"].values()) for p in by["distractor"]]) > 0.9
    assert all(p["arm"] is not None for p in by["arm"])


def test_arms_and_distractors_are_in_view_and_the_ball_stays_visible():
    """Hiding the arms (or the distractors) changes the ONV: they are seen; every ball is seen."""
    for cond, names in (("arm", None), ("distractor", V.DISTRACTORS)):
        cfg = FoveationDataConfig(condition=cond, **SMALL)
        retina, eye = F.make_retina(cfg), F.make_eye(cfg)
        ps = [params(cfg, i) for i in range(8)]
        scene = V.make_scene(0, cfg.seed, 0, F.BALL_RADII, with_arms=True)
        V.place(scene, ps)
        from warp_vision.kernels.render import render_onv

        poses = np.stack([p["eye_pose"] for p in ps])
        seen = render_onv(scene, retina, eye, poses, 1).numpy()
        for name in names or [o.name for o in scene.objects if o.name.startswith("arm_")]:
            scene.set_visible(name, False)
        hidden = render_onv(scene, retina, eye, poses, 1).numpy()
        changed = np.abs(seen - hidden).max(axis=1) > 1e-6
        assert changed.mean() >= 0.5, changed
    # rendered datasets redraw hidden balls: every sample's ball is visible
    cfg = FoveationDataConfig(condition="arm", **SMALL)
    ps = [params(cfg, i) for i in range(8)]
    scene = V.make_scene(0, cfg.seed, 0, F.BALL_RADII)
    V.place(scene, ps)
    assert any(F.ball_visible(scene, p, k) for k, p in enumerate(ps))
    data = render_samples(cfg, range(8), None, F.make_retina(cfg), F.make_eye(cfg))
    assert data["meta"].shape == (8, len(F.META_V8)) and (data["meta"][:, 5] == 1).all()


def test_lighting_scales_the_onv_and_per_sample_input_norm_removes_it():
    """Ten times the lamps and ambient light: ten times the ONV; a per-sample normalised net input is unchanged."""
    from warp_vision.kernels.render import render_onv
    from warp_vision.nn.trained import fit_input_norm, net_input

    cfg = FoveationDataConfig(condition="white", **SMALL)
    retina, eye = F.make_retina(cfg), F.make_eye(cfg)
    p = params(cfg, 3)
    q = dict(p, light={**p["light"], "intensity": 10 * p["light"]["intensity"], "ambient": 10 * p["light"]["ambient"]})
    scene = V.make_scene(0, cfg.seed, 0, F.BALL_RADII, with_arms=False)
    V.place(scene, [p, q])
    onv = render_onv(scene, retina, eye, np.stack([p["eye_pose"], q["eye_pose"]]), 1)
    assert torch.allclose(onv[1], 10 * onv[0], rtol=1e-4, atol=1e-7)
    norm = fit_input_norm(onv, np.arange(2), per_sample=True)
    x = net_input(onv, norm, "cpu")
    assert torch.allclose(x[0], x[1], atol=1e-4)
    legacy = fit_input_norm(onv, np.arange(2))
    y = net_input(onv, legacy, "cpu")
    assert not torch.allclose(y[0], y[1], atol=1e-2)


def test_evaluate_conditions_prints_one_table_for_several_runs(tmp_path, capsys):
    from warp_vision.train import foveation
    from warp_vision.train.cli import main as train_main
    from warp_vision.train.config import resolve

    runs = []
    for gen in (7, 8):
        cfg = resolve("smoke",
                      {"out": str(tmp_path / f"v{gen}"), "data_dir": str(tmp_path / f"data{gen}"), "generator": gen,
                       "epochs": 1})
        foveation.run(cfg, progress=False, log=lambda *a: None)
        runs.append(str(tmp_path / f"v{gen}"))
    import os

    cwd = os.getcwd()
    os.chdir(tmp_path)  # the held-out sets are cached under ./runs/datasets
    try:
        assert train_main(["evaluate", *runs, "--conditions", "--samples", "12", "--no-progress"]) == 0
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    for label in ("glowing ball, dim room", "lit white ball", "coloured matte ball", "brighter object", "arm in view",
                  "round decoy", "own test split"):
        assert label in out
    table = [line for line in out.splitlines() if line.startswith("| ")]
    assert len(table) == 1 + len(V.CONDITIONS) and all(line.count("/") >= 2 for line in table[1:])
    for r in runs:
        res = json.loads((tmp_path / r / "conditions.json").read_text())["results"]
        assert set(res) == {"own test split", *V.CONDITIONS[1:]}
        assert all(np.isfinite(v["median_deg"]) and v["p90_deg"] >= v["median_deg"] for v in res.values())
        assert all(0 <= v["over_5deg"] <= 1 for v in res.values())
        assert (tmp_path / r / "figures" / "conditions.png").exists()
    # both runs were measured on the same held-out ONVs
    a = json.loads((tmp_path / runs[0] / "conditions.json").read_text())["results"]
    b = json.loads((tmp_path / runs[1] / "conditions.json").read_text())["results"]
    assert all(a[c]["dataset"] == b[c]["dataset"] for c in V.CONDITIONS[1:])
    assert train_main(["evaluate", runs[0], "--conditions", "--samples", "2"]) != 0
    assert "samples: expected at least 10" in capsys.readouterr().err
    assert train_main(["evaluate", runs[0], "--conditions", "--views", "8", "--samples", "12"]) != 0  # a liNet
    assert "only the retina CNN" in capsys.readouterr().err
    assert train_main(["evaluate", runs[0], "--conditions", "--views", "0"]) != 0
    assert "views" in capsys.readouterr().err
    assert train_main(["evaluate", runs[0], "--views", "8"]) != 0  # its own split: still a liNet
    assert "only the retina CNN" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train_main(["evaluate", *runs, "--agreement", "--views", "8"])
    assert "not with --agreement" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train_main(["evaluate", *runs, "--agreement", "--checkpoint", "latest"])
    assert "reads the best checkpoint" in capsys.readouterr().err
    # --checkpoint latest: the last epoch's weights (here the run's only epoch), beside the best's files
    os.chdir(tmp_path)
    try:
        assert train_main(["evaluate", runs[1], "--conditions", "--samples", "12", "--checkpoint", "latest",
                           "--no-progress"]) == 0
    finally:
        os.chdir(cwd)
    assert f"{runs[1]} (latest.pt, epoch 1)" in capsys.readouterr().out
    latest = json.loads((tmp_path / runs[1] / "conditions_latest.json").read_text())
    assert latest["checkpoint"] == "latest" and latest["epoch"] == 1
    # one epoch: the same net
    assert latest["results"] == json.loads((tmp_path / runs[1] / "conditions.json").read_text())["results"]
    assert (tmp_path / runs[1] / "figures" / "conditions_latest.png").exists()


def test_furniture_shape_names_each_piece_of_a_room():
    from warp_vision.scene.room import furniture_shape, make_room

    room = make_room(n_objects=5, seed=3)
    pieces = [o for o in room.objects if o.name.startswith("object_")]
    assert len(pieces) == 5
    for o in pieces:  # a box has 8 corners; a cylinder is round
        assert (len(o.mesh.vertices) == 8) == (furniture_shape(o.name) == "box"), o.name
    assert [furniture_shape(o.name) for o in pieces] == ["box", "cylinder", "box", "cylinder", "box"]
    assert (
        F._landed_class("object_1") == "furniture: cylinder"
        and F._landed_class("wall_north") == "wall, floor or ceiling"
    )
    assert [F._landed_class(n) for n in ("decoy_barrel", "decoy_drum",
                                         "decoy_plate")] == ["decoy: barrel", "decoy: drum", "decoy: plate"]
    for bad in ("wall_north", "object_", "object_x"):
        with pytest.raises(ValueError, match="furniture"):
            furniture_shape(bad)
