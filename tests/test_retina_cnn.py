"""The CNN on the foveated image: the binning against a dense reference, the augmentations' geometry, the
local read-out, bad inputs, and a training run the simulation can load."""

import dataclasses

import numpy as np
import pytest
import torch

from warp_vision.eye.retina import Retina
from warp_vision.frames import gaze_angles, gaze_directions
from warp_vision.nn.retina_cnn import (
    CONSENSUS_DEG,
    ROTATIONS,
    RetinaCNNFoveationNet,
    consensus_of,
    consensus_transforms,
    native_bfloat16,
    training_autocast,
    transform_matrix,
)


@pytest.fixture(scope="module")
def net():
    angles = Retina.log_polar(3000, seed=1).visual_angles()
    torch.manual_seed(0)
    return RetinaCNNFoveationNet(angles, size=32, channels=4)


def dense_binning(net, k):
    pix, pr, w = net.binning(k)
    m = torch.zeros(net.warp.size ** 2, net.P)
    m.index_put_((pix, pr), w, accumulate=True)
    return m


def test_the_image_is_the_dense_binning_matrix_applied_to_each_channel(net):
    x = torch.randn(3, 3 * net.P)
    for k in (0, 5):
        m = dense_binning(net, k)
        ref = torch.einsum("qp,bpc->bcq", m, x.reshape(3, net.P, 3)).reshape(3, 3, net.warp.size, net.warp.size)
        assert torch.allclose(net.image(x, k), ref, atol=1e-5)
        rows = m.sum(1)
        inside = rows > 0
        assert torch.allclose(rows[inside], torch.ones(int(inside.sum())), atol=1e-5)  # each pixel a weighted mean
        assert inside.float().mean() > 0.6  # black only beyond the retina's rim
    # a transform per group of the batch (training's augmentation in one forward pass)
    ref0 = torch.einsum("qp,bpc->bcq", dense_binning(net, 0),
                        x[:2].reshape(2, net.P, 3)).reshape(2, 3, net.warp.size, net.warp.size)
    ref5 = torch.einsum("qp,bpc->bcq", dense_binning(net, 5),
                        x[2:].reshape(1, net.P, 3)).reshape(1, 3, net.warp.size, net.warp.size)
    assert torch.allclose(net.image(x, [0, 5]), torch.cat([ref0, ref5]), atol=1e-5)


def test_the_views_images_are_one_sparse_product_equal_to_the_dense_and_index_add_references(net):
    """view_images (the consensus's binning: one CSR product for every view) against the dense matrix and
    against the index_add_ of the entries that bench readout times it with; channels_last; a copy of the
    net (whose CSR cache has no storage to copy) rebuilds it."""
    import copy
    import pickle

    from warp_vision.bench.readout import index_add_images

    x = torch.randn(3, 3 * net.P)
    ks = [0, 5, 7]
    n = net.warp.size
    dense = torch.cat([torch.einsum("qp,bpc->bcq", dense_binning(net, k),
                                    x.reshape(3, net.P, 3)).reshape(3, 3, n, n) for k in ks])
    got = net.view_images(x, ks)
    assert got.shape == (9, 3, n, n) and got.is_contiguous(memory_format=torch.channels_last)
    assert torch.allclose(got, dense, atol=1e-5) and torch.allclose(got, index_add_images(net, x, ks), atol=1e-5)
    assert torch.equal(net.image(x, 5), got[3:6])
    assert torch.equal(copy.deepcopy(net).view_images(x, ks), got)
    assert torch.equal(pickle.loads(pickle.dumps(net)).view_images(x, ks), got)  # pickling copies it as it is
    with torch.autocast("cpu", dtype=torch.bfloat16):  # the binning stays float32 under a caller's autocast
        assert torch.equal(net.view_images(x, ks), got)
    with pytest.raises(ValueError, match="onv"):
        net.view_images(x[:, 1:], ks)


@pytest.mark.parametrize("k", [0, 1, 6, 10, 2 * ROTATIONS - 1])
def test_a_spot_appears_where_its_transformed_direction_says(net, k):
    target = torch.tensor([[0.35, -0.2]], dtype=torch.float64)
    spot = (net._dirs @ gaze_directions(target.numpy())[0]) > np.cos(np.radians(4.0))
    x = torch.zeros(1, net.P, 3)
    x[0, torch.as_tensor(spot)] = 1.0
    img = net.image(x.reshape(1, -1), k)[0, 0]
    seen = net.transform_targets(target, k)[0]
    uv = net.warp.dirs_to_uv(gaze_directions(seen.numpy()))
    n = net.warp.size
    col, row = (uv[0] + 1) / 2 * n - 0.5, (1 - uv[1]) / 2 * n - 0.5
    rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    w = img.numpy()
    centroid = (float((w * rr).sum() / w.sum()), float((w * cc).sum() / w.sum()))
    assert abs(centroid[0] - row) < 1.0 and abs(centroid[1] - col) < 1.0


def test_transforms_are_rotations_about_the_axis_and_mirrors():
    assert np.allclose(transform_matrix(0), np.eye(3))
    for k in range(2 * ROTATIONS):
        m = transform_matrix(k)
        assert np.allclose(m @ m.T, np.eye(3)) and np.isclose(np.linalg.det(m), -1.0 if k % 2 else 1.0)
        assert np.allclose(m[:, 2], [0, 0, 1])  # the optical axis stays put


def test_the_read_out_is_the_local_soft_argmax_around_the_peak(net):
    m = net.warp.size // 2
    logits = torch.full((1, m * m), -20.0)
    peak, far = 5 * m + 6, 12 * m + 13
    logits[0, peak] = 10.0
    logits[0, far] = 9.9  # a near-equal peak elsewhere (a lamp) does not pull the estimate
    out = net.read_out(logits)[0].double()
    assert torch.allclose(out, gaze_angles(net.cell_dirs[peak].double()), atol=1e-3)
    logits[0, peak + 1] = 10.0  # two equal neighbours: halfway between them
    mid = gaze_angles((net.cell_dirs[peak] + net.cell_dirs[peak + 1]).double())
    assert torch.allclose(net.read_out(logits)[0].double(), mid, atol=1e-3)


def test_the_heatmap_loss_targets_the_cell_of_the_true_direction(net):
    cell = 9 * (net.warp.size // 2) + 4
    target = gaze_angles(net.cell_dirs[cell : cell + 1].double()).float()
    logits = torch.zeros(1, net.cell_dirs.shape[0])
    uniform = float(net.heatmap_loss(logits, target))
    logits[0, cell] = 20.0
    assert float(net.heatmap_loss(logits, target)) < 1e-6 < uniform


def test_bad_inputs_are_refused(net):
    with pytest.raises(ValueError, match="onv"):
        net(torch.zeros(2, 3 * net.P + 3))
    with pytest.raises(ValueError, match="size"):
        RetinaCNNFoveationNet(gaze_angles(net._dirs), size=40)
    with pytest.raises(ValueError, match="photoreceptor_angles"):
        RetinaCNNFoveationNet(np.full((100, 2), np.nan))
    with pytest.raises(ValueError, match="window"):
        RetinaCNNFoveationNet(gaze_angles(net._dirs), size=32, window=4)


def test_forward_gives_standardised_angles_with_gradients(net):
    x = torch.randn(2, 3 * net.P, requires_grad=True)
    out, logits = net(x, transform=3, with_logits=True)
    assert out.shape == (2, 2) and logits.shape == (2, (net.warp.size // 2) ** 2)
    (out.sum() + logits.logsumexp(1).sum()).backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_consensus_views_are_distinct_turns_alternately_mirrored():
    assert consensus_transforms(1) == [0]
    for n in (2, 8, 16, 48):
        ks = consensus_transforms(n)
        assert len(set(ks)) == n and all(0 <= k < 2 * ROTATIONS for k in ks)
        assert [k % 2 for k in ks] == [i % 2 for i in range(n)]
    assert sorted(consensus_transforms(48)) == list(range(48))
    for bad in (0, 49, 2.0):
        with pytest.raises(ValueError, match="views"):
            consensus_transforms(bad)


def test_the_consensus_averages_the_largest_agreeing_group_and_outvotes_the_rest():
    def dirs(deg):
        return gaze_directions(torch.tensor(np.radians(deg), dtype=torch.float64))

    agree = [[10.0, 0.0], [10.5, 0.3], [9.6, -0.2], [10.2, 0.1], [9.9, 0.4]]  # within 2 deg of each other
    decoy = [[30.0, 5.0], [30.4, 5.2], [29.8, 4.9]]
    # two samples of 8 views: the decoy views first, then the ball's; 5 agreeing views against 3
    d = torch.stack([dirs(decoy + agree), dirs(agree[:1] + decoy + agree[1:])])
    got = np.degrees(consensus_of(d).numpy())
    want = np.degrees(gaze_angles(dirs(agree).sum(0)).numpy())
    assert np.allclose(got, want[None], atol=1e-9)
    # a group of 3 against 2: the 3 decoy views win (the rule counts views, it does not know the ball)
    got = np.degrees(consensus_of(dirs(agree[:2] + decoy)[None]).numpy())[0]
    assert np.allclose(got, np.degrees(gaze_angles(dirs(decoy).sum(0)).numpy()), atol=1e-9)
    # on a tie the first view's group; views further than CONSENSUS_DEG from it are left out
    two = torch.stack([dirs([[0.0, 0.0], [20.0, 0.0]])])
    assert np.allclose(consensus_of(two).numpy(), 0.0, atol=1e-12)
    c = CONSENSUS_DEG
    # the first two tie at 3
    edge = torch.stack([dirs([[0.0, 0.0], [0.95 * c, 0.0], [-0.95 * c, 0.0], [1.05 * c, 0.0]])])
    # 1.05 c is not in view 0's group
    assert np.degrees(float(consensus_of(edge)[0, 0])) == pytest.approx(0.0, abs=1e-9)


def test_eval_mode_reads_out_by_the_consensus_of_views_as_a_plain_reference_does(net):
    import copy

    torch.manual_seed(3)
    m = copy.deepcopy(net).eval()
    m.views = 8
    x = torch.randn(5, 3 * m.P)
    with torch.no_grad():
        ref_dirs = []
        for k in consensus_transforms(8):  # each view read alone, mapped back to the eye frame with numpy
            ang = m.read_out(m.logits(m.image(x, k))).double().numpy()
            ref_dirs.append(gaze_directions(ang) @ transform_matrix(k).T)
        ref = []
        for b in range(len(x)):
            u = np.stack([r[b] / np.linalg.norm(r[b]) for r in ref_dirs])
            near = u @ u.T >= np.cos(np.radians(CONSENSUS_DEG))
            best = int(np.argmax(near.sum(1)))
            ref.append(gaze_angles(u[near[best]].sum(0)))
        ref = np.stack(ref)
        got = m.consensus(x).double().numpy()
        assert np.allclose(got, ref, atol=2e-5)
        assert np.allclose(m.consensus(x, max_images=3).double().numpy(), got, atol=1e-6)  # views in groups: the same
        z = m(x)  # eval mode: the consensus, standardised
        assert torch.allclose(z, (m.consensus(x) - m.target_mean) / m.target_std, atol=1e-6)
        m.views = 1  # one view: the plain read-out
        assert torch.allclose(m(x), (m.read_out(m.logits(m.image(x, 0))) - m.target_mean) / m.target_std)
        m.views = 8
    m.train()  # training reads one (augmented) view
    assert m(x).shape == (5, 2)
    assert torch.allclose(m(x, transform=0).detach(),
                          ((m.read_out(m.logits(m.image(x, 0))) - m.target_mean) / m.target_std).detach(), atol=1e-5)


def test_a_cnn_foveation_run_saves_a_net_the_simulation_can_load(tmp_path, monkeypatch):
    from warp_vision.nn.trained import load_net, read_checkpoint
    from warp_vision.train import foveation
    from warp_vision.train.config import resolve

    cfg = resolve("smoke", {"out": str(tmp_path / "run"), "data_dir": str(tmp_path / "data"), "model": "cnn",
                            "channels": 4, "epochs": 2, "precision": "bfloat16"})
    logs = []
    summary = foveation.run(cfg, progress=False, log=lambda *a: logs.append(" ".join(map(str, a))))
    assert np.isfinite(summary["test_median_deg"])
    assert "training precision: bfloat16 autocast (--precision bfloat16; evaluation float32)" in logs
    assert summary["train_precision"] == "bfloat16"
    # the same command again trains the same net, bit for bit (seeded draws, bfloat16 autocast included)
    foveation.run(dataclasses.replace(cfg, out=str(tmp_path / "again")), progress=False, log=lambda *a: None)
    first, again = (read_checkpoint(tmp_path / d / "best.pt")["model"] for d in ("run", "again"))
    assert first.keys() == again.keys() and all(torch.equal(first[k], again[k]) for k in first)
    model, ck = load_net(tmp_path / "run")
    assert isinstance(model, RetinaCNNFoveationNet) and ck["net"]["onv_dtype"] == "float32"
    assert ck["net"]["views"] == 8 and model.views == 8  # the consensus read-out, from the spec
    assert load_net(tmp_path / "run")[0].views == 8
    spec_before = {k: v for k, v in ck["net"].items() if k != "views"}  # a spec written before views existed
    from warp_vision.nn.trained import build_net as _build
    assert _build(spec_before).views == 8
    # the epochs' validation reads one view; the test (evaluate) the consensus; validate leaves views as it was
    task = foveation.FoveationTask(cfg, log=lambda *a: None)
    task.load((0, 1), progress=False, synthesize=False)
    _, va, _ = task.splits()
    one = task.validate(model, va, ck["norm"], "cpu")
    assert model.views == 8
    model.views = 1
    assert one["median_deg"] == task.evaluate(model, va, ck["norm"], "cpu")["median_deg"]
    model.views = 8
    # evaluate --conditions --views N reads the net with N views and says so
    import json

    from warp_vision.train.conditions import evaluate_conditions

    monkeypatch.chdir(tmp_path)  # the held-out sets are cached under ./runs/datasets
    res = evaluate_conditions([str(tmp_path / "run")], 10, conditions=["glow_dim"], progress=False,
                              log=lambda *a: None, views=2)
    assert list(res) == [f"{tmp_path / 'run'} (views 2)"]
    assert json.loads((tmp_path / "run/conditions.json").read_text())["views"] == 2
    with pytest.raises(ValueError, match="head"):
        resolve("smoke", {"model": "cnn", "head": "linear"}).validate()

    # evaluate --checkpoint latest --views 1: the last epoch's weights, read out from the plain image alone
    from warp_vision.nn.trained import build_net, read_checkpoint
    from warp_vision.train.cli import main as train_main

    latest = read_checkpoint(tmp_path / "run/latest.pt")
    assert latest["epoch"] == 1
    plain = build_net({**latest["net"], "views": 1})
    plain.load_state_dict(latest["model"])
    _, _, te = task.splits()
    want = task.evaluate(plain, te, latest["norm"], "cpu")
    lines = []
    got = foveation.evaluate_run(str(tmp_path / "run"), "test", log=lines.append, checkpoint="latest", views=1)
    assert got["median_deg"] == want["median_deg"] and got["mse"] == want["mse"]
    assert lines[0].startswith(f"{tmp_path / 'run'} (latest.pt, epoch 2; views 1) (test, ")
    assert train_main(["evaluate", str(tmp_path / "run"), "--checkpoint", "latest", "--views", "1"]) == 0
    with pytest.raises(ValueError, match="checkpoint"):
        foveation.evaluate_run(str(tmp_path / "run"), checkpoint="previous")

    # --init: another run (the other eye) starts from these weights; a net of other sizes is refused
    from warp_vision.train.rundir import warm_start

    other = build_net({**ck["net"], "seed": 5})
    assert not torch.equal(other.heat.weight, model.heat.weight)
    warm_start(other, tmp_path / "run")
    assert all(torch.equal(a, b) for a, b in zip(other.state_dict().values(), model.state_dict().values()))
    with pytest.raises(ValueError, match="init"):
        warm_start(build_net({**ck["net"], "channels": 8}), tmp_path / "run")


def test_limb_targets_turn_with_the_image_and_mirrors_swap_the_arms():
    from warp_vision.nn.retina_cnn import RetinaCNNLimbNet

    t = torch.tensor([[0.1, 0.2, 0.3, -0.4, 0.05, 0.6]], dtype=torch.float64)
    assert torch.equal(RetinaCNNLimbNet.transform_targets(t, 0), t)
    turned = RetinaCNNLimbNet.transform_targets(t, 2)  # a turn, no mirror: each arm's vector turned, lengths kept
    assert torch.allclose(turned.reshape(2, 3).norm(dim=1), t.reshape(2, 3).norm(dim=1))
    assert torch.allclose(turned[0, [2, 5]], t[0, [2, 5]]) and not torch.allclose(turned, t)
    mirrored = RetinaCNNLimbNet.transform_targets(t, 1)  # x flipped, and the left arm is now the right one
    assert torch.allclose(mirrored, torch.tensor([[0.4, 0.05, 0.6, -0.1, 0.2, 0.3]], dtype=torch.float64))


def test_a_cnn_limb_run_saves_a_net_the_simulation_can_load(tmp_path):
    from warp_vision.nn.retina_cnn import RetinaCNNLimbNet
    from warp_vision.nn.trained import load_net
    from warp_vision.train import limb
    from warp_vision.train.config import resolve
    from warp_vision.train.config_body import LIMB_PRESETS, LimbTrainConfig

    cfg = resolve("smoke",
                  {"out": str(tmp_path / "run"), "data_dir": str(tmp_path / "data"), "model": "cnn", "channels": 4},
                  LimbTrainConfig, LIMB_PRESETS)
    summary = limb.run(cfg, progress=False, log=lambda *a: None)
    assert np.isfinite(summary["test"]["near_median_cm"]) or summary["test"]["near_pairs"] == 0
    model, ck = load_net(tmp_path / "run")
    assert isinstance(model, RetinaCNNLimbNet) and model(torch.zeros(2, 3 * model.P)).shape == (2, 6)
    with pytest.raises(ValueError, match="model"):
        resolve("smoke", {"model": "conv"}, LimbTrainConfig, LIMB_PRESETS).validate()


def test_a_plateau_at_the_magnified_centre_reads_out_at_its_middle(net):
    """A near ball at the centre spans many cells of equal heat: the angular window takes them all, so
    the estimate is the plateau's middle, not whichever of its cells peaks by a hair."""
    # wider than the plateau
    wide = RetinaCNNFoveationNet(gaze_angles(net._dirs), size=32, channels=4, window=1, window_deg=12.0)
    target = torch.tensor([0.02, -0.03], dtype=torch.float64)  # rad, near the axis
    ang = torch.rad2deg(torch.arccos((wide.cell_dirs.double() @ gaze_directions(target)).clamp(-1, 1)))
    plateau = ang < 5.0
    assert plateau.sum() >= 6
    logits = torch.where(plateau, 5.0, -20.0)[None].float()
    edge = int(torch.where(plateau, ang, -1.0).argmax())  # the plateau's cell farthest from its middle
    logits[0, edge] += 0.01
    out = wide.read_out(logits)[0].double()
    middle = gaze_angles(wide.cell_dirs[plateau].double().sum(0))
    assert torch.allclose(out, middle, atol=1e-3)
    assert torch.rad2deg((out - target).norm()) < 1.5  # about the ball's centre, not its edge cell
    wide.window_deg = 0.0  # the cell window alone: the edge cell wins
    assert torch.allclose(wide.read_out(logits)[0].double(), gaze_angles(wide.cell_dirs[edge].double()), atol=1e-3)


def test_the_ranging_net_sees_the_fovea_finely_and_keeps_distances_under_augmentation():
    from warp_vision.nn.retina_cnn import RANGE_ECC_DEG, RANGE_GATE_DEG, RetinaCNNRangeNet

    angles = Retina.log_polar(400, seed=1).visual_angles()
    net = RetinaCNNRangeNet(angles, size=32, channels=4)
    # the image covers the central RANGE_ECC_DEG only, and the gate leaves room for a near ball's disc
    edge = net.warp.uv_to_dirs(np.array([1.0, 0.0]))
    assert np.degrees(np.arccos(edge[2])) == pytest.approx(RANGE_ECC_DEG) and RANGE_GATE_DEG < RANGE_ECC_DEG - 2
    x = torch.randn(3, 3 * 400, requires_grad=True)
    y = net(x, transform=5)
    assert y.shape == (3, 1)
    y.sum().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all()
    t = torch.log(torch.tensor([[0.5], [2.0]]))
    for k in (0, 7, 2 * ROTATIONS - 1):
        assert torch.equal(RetinaCNNRangeNet.transform_targets(t, k), t)
    with pytest.raises(ValueError):
        net(torch.randn(2, 3 * 399))
    with pytest.raises(ValueError):
        RetinaCNNRangeNet(angles, size=30)


def test_the_training_precision_resolves_per_device_and_refuses_unknown_names():
    assert training_autocast("float32", "cpu") is None
    assert training_autocast("bfloat16", "cpu") is torch.bfloat16
    assert training_autocast("auto", "cpu") is (torch.bfloat16 if native_bfloat16("cpu") else None)
    assert native_bfloat16("meta") is False
    with pytest.raises(ValueError, match="precision"):
        training_autocast("half", "cpu")


def _grads(net, x, t):
    net.zero_grad()
    out, logits = net(x, transform=[0, 3], with_logits=True)
    (out.square().sum() + net.heatmap_loss(logits, t)).backward()
    return out.detach(), logits.detach(), torch.cat([p.grad.flatten() for p in net.parameters()])


def test_bfloat16_training_matches_float32_to_bfloat16_precision_and_inference_stays_float32(device):
    """The reference is the same net in float32: the bfloat16 pass's logits agree with it to bfloat16's
    precision (and differ from it: the autocast did run), its gradients in direction. Their norms differ by
    10-30% on this random 4-channel net: batch norm's and the heat map softmax's gradients are small sums of
    cancelling terms, each rounded to 8 bits (measured; the training run in docs/RESULTS.md is the check that
    matters: the same MSE epoch by epoch). In eval mode the precision is ignored."""
    angles = Retina.log_polar(3000, seed=1).visual_angles()
    torch.manual_seed(0)
    net = RetinaCNNFoveationNet(angles, size=32, channels=4, views=1).to(device).train()
    x = torch.randn(4, 3 * net.P).to(device)
    t = torch.tensor([[0.1, -0.2], [0.3, 0.0], [-0.25, 0.15], [0.0, 0.4]], device=device)
    out32, log32, g32 = _grads(net, x, t)
    net.train_precision = "bfloat16"
    out16, log16, g16 = _grads(net, x, t)
    assert log16.dtype == torch.float32 and out16.dtype == torch.float32
    # the read-out is float32's: the same soft-arg-max of those logits, outside the autocast
    assert torch.equal(out16, (net.read_out(log16) - net.target_mean) / net.target_std)
    assert 0 < (log16 - log32).abs().max() < 0.05 * log32.abs().max()
    assert torch.nn.functional.cosine_similarity(g16, g32, dim=0) > 0.95
    assert 0 < (g16 - g32).norm() < 0.35 * g32.norm()
    net.eval()
    with torch.no_grad():
        a = net(x)
        net.train_precision = "float32"
        assert torch.equal(a, net(x))


def test_the_limb_cnn_trains_in_bfloat16_and_returns_float32(device):
    from warp_vision.nn.retina_cnn import RetinaCNNLimbNet

    angles = Retina.log_polar(3000, seed=1).visual_angles()
    torch.manual_seed(0)
    net = RetinaCNNLimbNet(angles, size=32, channels=4, hidden=8).to(device).train()
    x = torch.randn(4, 3 * net.P).to(device)
    y32 = net(x)
    net.train_precision = "bfloat16"
    y16 = net(x)
    assert y16.dtype == torch.float32 and 0 < (y16 - y32).abs().max() < 0.05 * y32.abs().max() + 0.05


def test_precision_bfloat16_is_the_cnns_alone_and_old_runs_read_as_float32(tmp_path):
    from warp_vision.train.config import asdict, resolve
    from warp_vision.train.config_body import LIMB_PRESETS, LimbTrainConfig
    from warp_vision.train.foveation import FoveationTask
    from warp_vision.train.limb import LimbTask
    from warp_vision.train.rundir import run_config

    with pytest.raises(ValueError, match="precision"):
        resolve("smoke", {"precision": "bfloat16"})  # the smoke preset's liNet
    with pytest.raises(ValueError, match="precision"):
        resolve("smoke", {"precision": "bfloat16", "model": "fc"}, LimbTrainConfig, LIMB_PRESETS)
    with pytest.raises(ValueError, match="precision"):
        resolve("smoke", {"precision": "half", "model": "cnn"})
    assert resolve("smoke", {"precision": "bfloat16", "model": "cnn"}).precision == "bfloat16"
    assert resolve("smoke", {"model": "linet"}).precision == "auto"  # auto: a liNet stays float32
    # a run saved before the field existed trained in float32, and reads so from its checkpoint's config
    for task_cls, cfg in ((FoveationTask, resolve("smoke", {"model": "cnn"})),
                          (LimbTask, resolve("smoke", {"model": "cnn"}, LimbTrainConfig, LIMB_PRESETS))):
        old = {k: v for k, v in asdict(cfg).items() if k != "precision"}
        assert cfg.precision == "auto" and run_config(task_cls, tmp_path, {"config": old}).precision == "float32"


@pytest.mark.parametrize("mode, epoch, plain", [("copies", 2, False), ("no_augment", 0, True),
                                                ("plain_epochs", 1, False), ("plain_epochs", 2, True)])
def test_training_batches_are_turned_and_mirrored_unless_no_augment(monkeypatch, mode, epoch, plain):
    """Each training batch goes through the net in four groups, each binned through a random turn or mirror
    with its targets turned alike; ``--no-augment``, and the last ``--plain-epochs`` epochs, bin every group
    as the plain image, targets as they are."""
    from warp_vision.train import foveation
    from warp_vision.train.config import resolve

    over = {"copies": {}, "no_augment": {"no_augment": True, "views": 1}, "plain_epochs": {"plain_epochs": 1}}[mode]
    cfg = resolve("smoke", {"model": "cnn", **over})
    assert cfg.epochs == 3  # plain_epochs 1: the third epoch (2, 0-based) is the plain image's
    task = foveation.FoveationTask(cfg, log=lambda *a: None)
    task.epoch = epoch
    task.target = torch.tensor([[0.1 * i, -0.05 * i] for i in range(8)])
    task.onv16 = torch.zeros(8, 6)
    monkeypatch.setattr(foveation, "net_input", lambda onv, *a: onv.float())
    seen = {}

    class Spy(torch.nn.Module):
        transform_targets = staticmethod(lambda t, k: t + k)  # a turn that moves every target by k

        def forward(self, x, transform=0, with_logits=False):
            seen["ks"] = transform
            return torch.zeros(len(x), 2, requires_grad=True), torch.zeros(len(x), 4)

        def heatmap_loss(self, logits, true):
            seen["true"] = true
            return torch.zeros(())

    torch.manual_seed(3)
    task.batch_loss(Spy(), torch.arange(8), {"target_mean": torch.zeros(2), "target_std": torch.ones(2)}, "cpu")
    ks = seen["ks"]
    assert len(ks) == 4
    expected = torch.cat([task.target[2 * g : 2 * g + 2] + k for g, k in enumerate(ks)])
    assert torch.equal(seen["true"], expected)
    if plain:
        assert ks == [0, 0, 0, 0] and torch.equal(seen["true"], task.target)
    else:
        assert all(0 <= k < 2 * ROTATIONS for k in ks) and any(k != 0 for k in ks)


def test_no_augment_is_the_cnns_alone():
    from warp_vision.train.config import resolve

    with pytest.raises(ValueError, match="no_augment"):
        resolve("smoke", {"no_augment": True})  # the smoke preset's liNet
    with pytest.raises(ValueError, match="views 1"):
        resolve("smoke", {"model": "cnn", "no_augment": True})  # the consensus reads turned views it never saw
    assert resolve("smoke", {"model": "cnn", "no_augment": True, "views": 1}).no_augment


def test_plain_epochs_are_the_cnns_and_within_the_cap():
    from warp_vision.train.config import resolve

    with pytest.raises(ValueError, match="plain_epochs: the turned"):
        resolve("smoke", {"plain_epochs": 1})  # the smoke preset's liNet
    with pytest.raises(ValueError, match="expected 0 to the 3 epochs"):
        resolve("smoke", {"model": "cnn", "plain_epochs": 4})
    with pytest.raises(ValueError, match="is --no-augment"):
        resolve("smoke", {"model": "cnn", "plain_epochs": 3})
    cfg = resolve("smoke", {"model": "cnn", "plain_epochs": 2})
    assert cfg.plain_epochs == 2 and cfg.views == 8  # the net saw the turned copies first: the consensus stays


def test_the_harness_tells_the_task_its_epoch(tmp_path):
    """``Task.epoch`` is the epoch whose batches ``batch_loss`` is computing (what ``--plain-epochs`` reads)."""
    from warp_vision.train.config import resolve
    from warp_vision.train.harness import Dist, Task, _train_epoch

    seen = []

    class Recorder(Task):
        def batch_loss(self, net, idx, norm, device):
            seen.append(self.epoch)
            loss = (net.weight ** 2).sum()
            return loss, {"loss": float(loss.detach())}

    task = Recorder(resolve("smoke", {"model": "cnn", "batch": 4}), log=lambda *a: None)
    net = torch.nn.Linear(2, 1)
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    for epoch in (0, 2, 1):
        _train_epoch(task, net, net, opt, np.arange(8), epoch, {}, "cpu", Dist("cpu"), False, tmp_path)
    assert seen == [0, 0, 2, 2, 1, 1]
