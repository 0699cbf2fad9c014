"""Active face recognition: anny identities, face ONVs, the AFR net and its training, end to end on a few
identities and poses. The first anny model build in a fresh environment takes a few minutes (anny
caches it under ~/.cache/anny); everything else here takes seconds."""

import json

import numpy as np
import pytest
import torch

from warp_vision.data import faces as FA
from warp_vision.train import faces as TF
from warp_vision.train.cli import main as train_main
from warp_vision.train.config import FACE_PRESETS, FaceTrainConfig, resolve


@pytest.fixture(scope="module")
def ids(tmp_path_factory):
    path = tmp_path_factory.mktemp("ids") / "identities.npz"
    return FA.load_identities(3, seed=0, cache=path, progress=False, log=lambda *a: None), path


@pytest.fixture(scope="module")
def smoke_data(tmp_path_factory, ids):
    d = tmp_path_factory.mktemp("facedata")
    cfg = face_smoke(d / "unused", d, ids[1])
    FA.synthesize(d, cfg.data_config(), progress=False, log=lambda *a: None, identities_path=ids[1])
    return d


def face_smoke(out, data, cache, **kw):
    return resolve("smoke", {"out": str(out), "data_dir": str(data), "identities_cache": str(cache), **kw},
                   FaceTrainConfig, FACE_PRESETS)


def test_identities_are_distinct_coloured_heads(ids):
    ids, path = ids
    assert ids.vertices.shape[0] == 3 and ids.vertices.shape[2] == 3 and ids.faces.max() < ids.vertices.shape[1]
    assert np.isfinite(ids.vertices).all() and ids.colours.min() >= 0 and ids.colours.max() <= 1
    # a head: about 15 to 30 cm tall and 12 to 22 cm wide
    ext = ids.vertices.max(1) - ids.vertices.min(1)
    assert np.all((ext[:, 2] > 0.15) & (ext[:, 2] < 0.35) & (ext[:, 0] > 0.12) & (ext[:, 0] < 0.25)), ext
    # distinct shapes (RMS vertex distance to the nearest other identity, mm) and distinct skin tones
    assert ids.nearest_neighbour_mm().min() > 2.0
    skin = ids.params[:, [ids.param_names.index(f"skin_{c}") for c in "rgb"]]
    assert np.abs(skin[:, None] - skin[None]).sum(-1)[np.triu_indices(3, 1)].min() > 1e-3
    # the face centre lies in front of the pivot (the face looks toward -y), between the eyes and the chin
    assert np.all(ids.face_centre[:, 1] < ids.pivot[:, 1] - 0.03)
    # lips redder than the skin around them
    lips = ids.colours[0][:, 0] / np.maximum(ids.colours[0][:, 1], 1e-3)
    assert lips.max() > 1.3 * np.median(lips)
    # the cache round-trips, and a cache of more identities serves fewer
    again = FA.load_identities(2, seed=0, cache=path, progress=False, log=lambda *a: None)
    assert np.array_equal(again.vertices, ids.vertices[:2])
    assert np.allclose(again.colours, ids.colours[:2], atol=1e-3)


def test_identity_i_does_not_depend_on_the_set_size(ids):
    one = FA.build_identities(1, seed=0, progress=False)
    assert np.allclose(one.vertices[0], ids[0].vertices[0], atol=1e-6)
    other = FA.build_identities(1, seed=1, progress=False)
    assert not np.allclose(other.vertices[0], ids[0].vertices[0], atol=1e-3)


def test_pose_grid_and_labels():
    cfg = FA.FaceDataConfig(identities=50)
    v = cfg.pose_values()
    assert len(v) == 30 and v[0] == -29 and v[-1] == 29 and np.allclose(np.diff(v), 2)
    assert cfg.samples == 45_000 and cfg.poses == 900
    assert len(FA.FaceDataConfig(pose_step_deg=4).pose_values()) == 15
    assert cfg.sample_labels(0) == (0, -29.0, -29.0)
    assert cfg.sample_labels(1) == (0, -29.0, -27.0)
    assert cfg.sample_labels(30) == (0, -27.0, -29.0)
    assert cfg.sample_labels(900 + 31) == (1, -27.0, -27.0)
    with pytest.raises(ValueError, match="distance_m"):
        FA.FaceDataConfig(distance_m=10).validate()
    with pytest.raises(ValueError, match="pose_step_deg"):
        FA.FaceDataConfig(pose_step_deg=0).validate()


def test_head_pose_and_fixation(ids):
    ids = ids[0]
    cfg = FA.FaceDataConfig(identities=3)
    c0 = ids.face_centre[0]
    for yaw, pitch in [(0, 0), (20, 0), (0, 20), (-25, 15)]:
        T = FA.head_pose(ids, 0, yaw, pitch)
        assert np.allclose(T[:3, :3] @ ids.pivot[0] + T[:3, 3], ids.pivot[0])  # turns about its pivot
        c = T[:3, :3] @ c0 + T[:3, 3]
        E = FA.eye_pose(cfg, ids, 0, T)
        axis = E[:3, 2]
        to_c = c - E[:3, 3]
        assert np.linalg.norm(np.cross(axis, to_c / np.linalg.norm(to_c))) < 1e-9  # the eye fixates the centre
        if yaw > 0:
            assert c[0] > c0[0] + 0.01  # positive yaw turns the face toward +x (its left)
        if pitch > 0:
            assert c[2] > c0[2] + 0.005  # positive pitch lifts the face
    E = FA.eye_pose(cfg, ids, 0, np.eye(4))
    assert np.isclose(np.linalg.norm(c0 - E[:3, 3]), cfg.distance_m)


def test_face_onvs_differ_by_identity_and_pose_and_reproduce(ids):
    ids = ids[0]
    cfg = FA.FaceDataConfig(identities=3, photoreceptors=900, samples_per_receptor=2, pose_step_deg=20.0)
    retina, eye, scene = FA.make_retina(cfg), FA.make_eye(cfg), FA.make_scene(ids)
    n = cfg.poses
    centre = (len(cfg.pose_values()) ** 2) // 2
    idx = [centre, n + centre, 2 * n + centre, 0, centre]
    r = FA.render_samples(cfg, idx, ids, scene, retina, eye)
    assert r["onv"].shape == (5, 3 * 900) and r["onv"].dtype == np.float16
    assert list(r["identity"]) == [0, 1, 2, 0, 0]
    onv = r["onv"].astype(np.float32)
    assert np.array_equal(onv[0], onv[4])  # the same sample renders the same ONV
    base = np.abs(onv[0]).mean()
    for k in (1, 2, 3):  # other identities, another pose
        assert np.abs(onv[k] - onv[0]).mean() > 0.02 * base
    # the face, not the backdrop, fills the fovea: hiding the head changes the central photoreceptors
    for i in range(3):
        scene.set_visible(f"head_{i}", False)
        scene.set_transform(f"head_{i}", np.eye(4))
    from warp_vision.kernels.render import render_onv

    empty = render_onv(scene, retina, eye, FA.eye_pose(cfg, ids, 0, np.eye(4))[None], 2).numpy()[0]
    central = np.repeat(retina.rho < np.radians(5), 3)
    assert np.abs(empty[central] - onv[0][central]).mean() > 0.2 * np.abs(onv[0][central]).mean()


def test_afr_net_heads_and_gradients():
    from warp_vision.nn.connectivity import onv_positions
    from warp_vision.nn.heads import afr_net

    rng = np.random.default_rng(0)
    pos = onv_positions(rng.uniform(-1, 1, (200, 2)))
    for model in ("linet", "fc"):
        net = afr_net(pos, identities=5, layers=3, receptive_field=6, reduction=2, model=model)
        logits, z = net(torch.randn(4, 600))
        assert logits.shape == (4, 5) and z.shape == (4, 2)
        (logits.sum() + z.sum()).backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())
        net.set_pose_norm([2.0, -3.0], [10.0, 5.0])  # (yaw, pitch) mean and std in degrees
        assert torch.allclose(net.pose_degrees(torch.tensor([[0.0, 0.0], [1.0, -2.0]])),
                              torch.tensor([[2.0, -3.0], [12.0, -13.0]]))
    with pytest.raises(ValueError, match="identities"):
        afr_net(pos, identities=1)


def test_shuffled_labels_permute_only_the_training_split():
    ident = torch.arange(20)
    pose = torch.stack([ident.float(), -ident.float()], 1)
    tr = np.arange(5, 20)
    a, b = TF.shuffled_labels(ident, pose, tr, seed=0)
    assert torch.equal(a[:5], ident[:5]) and sorted(a[5:].tolist()) == list(range(5, 20))
    assert not torch.equal(a[5:], ident[5:])
    assert torch.equal(b[:, 0].long(), a)  # identity and pose move together


def test_faces_smoke_end_to_end_and_resume(tmp_path, ids, smoke_data, capsys):
    cfg = face_smoke(tmp_path / "a", smoke_data, ids[1])
    summary = TF.run(cfg, progress=False, log=lambda *a: None)
    run = tmp_path / "a"
    for name in ("config.json", "latest.pt", "best.pt", "metrics.jsonl", "summary.json", "figures/loss_curves.png",
                 "figures/confusion_matrix.png", "figures/retina_grid.png", "figures/pose_error.png"):
        assert (run / name).exists(), name
    assert summary["epochs"] == 3 and 0 <= summary["test_accuracy"] <= 1 and np.isfinite(summary["test_pose_mae_deg"])
    assert summary["identity_nearest_neighbour_mm"]["min"] > 2.0
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    # best.pt is written exactly at the epochs that reach both the best validation MSE and accuracy
    for k, r in enumerate(rows):
        both = r["val_mse"] <= min(x["val_mse"] for x in rows[: k + 1]) and \
            r["val_accuracy"] >= max(x["val_accuracy"] for x in rows[: k + 1])
        assert r["saved_best"] == both
    best = torch.load(run / "best.pt", weights_only=True)
    assert best["epoch"] + 1 == max(r["epoch"] for r in rows if r["saved_best"])
    # the saved net carries its pose scale: pose_degrees turns its standardised outputs into the labels' degrees
    for k in ("pose_mean", "pose_std"):
        assert torch.equal(best["model"][k], best["norm"][k].float()), k
    assert float(best["norm"]["pose_std"].min()) > 1.0  # degrees, not the untrained net's 1s
    assert train_main(["evaluate", str(run)]) == 0
    assert "identity accuracy" in capsys.readouterr().out
    # resume after epoch 1 equals the uninterrupted run
    cfg_b = face_smoke(tmp_path / "b", smoke_data, ids[1])
    assert TF.run(cfg_b, progress=False, log=lambda *a: None, stop_after_epoch=1) == {"interrupted": True}
    resumed = TF.run(resume=str(tmp_path / "b"), progress=False, log=lambda *a: None)
    a = torch.load(run / "latest.pt", weights_only=True)
    b = torch.load(tmp_path / "b/latest.pt", weights_only=True)
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert resumed["test_accuracy"] == summary["test_accuracy"]
    # resume with the epochs already done as the new cap: ends the run now, evaluated, with figures
    cfg_d = face_smoke(tmp_path / "d", smoke_data, ids[1])
    TF.run(cfg_d, progress=False, log=lambda *a: None, stop_after_epoch=1)
    assert not (tmp_path / "d/summary.json").exists()
    assert train_main(["faces", "--resume", str(tmp_path / "d"), "--epochs", "1", "--no-progress"]) == 0
    ended = json.loads((tmp_path / "d/summary.json").read_text())
    assert ended["epochs"] == 1 and ended["stopped"] == "max epochs"
    assert json.loads((tmp_path / "d/config.json").read_text())["epochs"] == 1
    assert (tmp_path / "d/figures/confusion_matrix.png").exists()
    with pytest.raises(ValueError, match="epochs"):
        TF.run(face_smoke(tmp_path / "e", smoke_data, ids[1]), progress=False, epochs=2)
    # bad input is refused with a message
    assert train_main(["faces", "--preset", "smoke", "--identities", "1", "--out", str(tmp_path / "c")]) == 2


def test_a_file_that_is_not_an_identity_cache_is_refused_by_name_and_left_alone(tmp_path, unclose_npz_headers):
    # --identities-cache README.md read as numpy's "pickled (object) data" error; a damaged header as
    # numpy's tokenize.TokenError
    for name, content in (("notes.md", b"# notes\n"), ("empty.npz", b""), ("other.npz", None),
                          ("damaged.npz", "damaged")):
        f = tmp_path / name
        if content is None or content == "damaged":
            np.savez(f, vertices=np.zeros(3))
            if content == "damaged":
                unclose_npz_headers(f)
        else:
            f.write_bytes(content)
        before = f.read_bytes()
        with pytest.raises(ValueError, match=f"{name}: not a cache of face identities"):
            FA.load_identities(2, 0, f, progress=False, log=lambda *a: None)
        assert f.read_bytes() == before


def test_a_cache_of_another_identity_seed_is_refused_not_used(ids):
    # an explicit --identities-cache of seed 0's heads gave a seed-1 dataset seed 0's identities, without a word
    _, path = ids
    assert FA.FaceIdentities.load(path).seed == 0 and FA.FaceIdentities.load(path).subset(2).seed == 0
    before = path.read_bytes()
    with pytest.raises(ValueError, match="holds identity seed 0's identities, not seed 1's"):
        FA.load_identities(3, seed=1, cache=path, progress=False, log=lambda *a: None)
    assert path.read_bytes() == before
    assert len(FA.load_identities(2, seed=0, cache=path, progress=False, log=lambda *a: None)) == 2
