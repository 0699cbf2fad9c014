"""The weight-shared convolution on the irregular retina: stencils, shapes, shared weights, the read-out."""

import numpy as np
import pytest
import torch

from warp_vision.eye.retina import Retina
from warp_vision.nn.retina_conv import (
    STENCIL,
    RetinaConv,
    RetinaConvFoveationNet,
    channel_plan,
    site_counts,
    stencil_layers,
)


@pytest.fixture(scope="module")
def retina():
    return Retina.log_polar(1600, seed=1)


def test_stencils_sit_on_the_site_and_its_compass_points(retina):
    xy = np.asarray(retina.domain_xy, np.float64)
    plan = stencil_layers(xy, 3, 4, seed=0)
    prev = xy
    for p in plan:
        st = p["stencil"]
        assert st.shape == (len(p["sites"]), STENCIL) and np.array_equal(st[:, 0], p["sites"])
        assert len(p["sites"]) == len(prev) // 4 and len(np.unique(p["sites"])) == len(p["sites"])
        # the 8 points lie around the site, roughly at the compass directions, in order
        d = prev[st[:, 1:]] - prev[st[:, :1]]
        ang = np.degrees(np.arctan2(d[..., 1], d[..., 0])) % 360
        want = np.arange(0, 360, 45)
        err = np.abs((ang - want + 180) % 360 - 180)
        assert np.median(err) < 25
        prev = prev[p["sites"]]
    # the stencil shrinks toward the fovea with the photoreceptor spacing
    d1 = np.linalg.norm(xy[plan[0]["stencil"][:, 1]] - xy[plan[0]["stencil"][:, 0]], axis=1)
    ecc = np.linalg.norm(xy[plan[0]["sites"]], axis=1)
    assert np.median(d1[ecc < np.percentile(ecc, 20)]) < 0.5 * np.median(d1[ecc > np.percentile(ecc, 80)])
    assert np.array_equal(stencil_layers(xy, 3, 4, seed=0)[2]["stencil"], plan[2]["stencil"])
    with pytest.raises(ValueError, match="stride"):
        stencil_layers(xy, 2, 1)
    with pytest.raises(ValueError, match="no sites"):
        stencil_layers(xy, 9, 4)
    assert site_counts(len(xy), 3, 4) == [len(xy)] + [len(p["sites"]) for p in plan]  # the configs' first check


def test_weights_are_shared_and_the_read_out_votes_for_a_direction(retina):
    torch.manual_seed(0)
    xy = np.asarray(retina.domain_xy, np.float64)
    net = RetinaConvFoveationNet(RetinaConv(xy, layers=3, stride=4, channels=4), xy)  # any finite directions
    b = net.backbone
    assert b.channels == channel_plan(4, 3) == [4, 8, 16]
    # parameters do not grow with the retina: one 3 x 3 x C kernel per output channel and layer
    assert sum(c.weight.numel() for c in b.convs) == 9 * (3 * 4 + 4 * 8 + 8 * 16)
    x = torch.randn(5, 3 * retina.P)
    net.eval()  # batch norm from its running statistics: a unit depends on its own stencil only
    maps = b(x)
    assert [tuple(m.shape) for m in maps] == [(5, n, c) for n, c in zip(b.layer_sites[1:], b.channels)]
    # a unit's response is its stencil's inputs through the shared kernel: recompute one by hand
    st = b.stencil_1[7]
    g = x.reshape(5, retina.P, 3)[:, st].reshape(5, -1)
    assert torch.allclose(maps[0][:, 7], torch.relu(b.norms[0](g @ b.convs[0].weight.T + b.convs[0].bias)), atol=1e-5)
    net.train()
    out = net(x)
    assert out.shape == (5, 2) and torch.isfinite(out).all()
    out.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())
    # every vote is a convex combination of its sites' directions
    for v in net.votes(x):
        assert (v.abs().max(0).values <= torch.as_tensor(np.abs(xy).max(0), dtype=torch.float32) + 1e-5).all()
    # the heat-map loss falls when each layer's saliency peaks on the site of the true direction
    target = net.directions_0[5:6].clone()
    flat = [torch.zeros(1, len(getattr(net, f"directions_{k}"))) for k in range(len(net.voting))]
    peaked = [f.clone() for f in flat]
    for k, f in enumerate(peaked):
        f[0, torch.cdist(target, getattr(net, f"directions_{k}")).argmin()] = 8.0
    assert net.heatmap_loss(peaked, target) < 0.1 * net.heatmap_loss(flat, target)
    with pytest.raises(ValueError, match="onv"):
        net(torch.randn(2, 3 * retina.P + 1))
    with pytest.raises(ValueError, match="photoreceptor_angles"):
        RetinaConvFoveationNet(b, np.zeros((3, 2)))


def test_a_conv_foveation_run_saves_a_net_the_simulation_can_load(tmp_path):
    from warp_vision.nn.trained import load_net
    from warp_vision.train import foveation
    from warp_vision.train.config import resolve

    cfg = resolve("smoke", {"out": str(tmp_path / "run"), "data_dir": str(tmp_path / "data"), "model": "conv",
                            "reduction": 4, "layers": 2, "channels": 4, "epochs": 2})
    summary = foveation.run(cfg, progress=False, log=lambda *a: None)
    assert np.isfinite(summary["test_median_deg"])
    model, ck = load_net(tmp_path / "run")
    assert isinstance(model, RetinaConvFoveationNet) and ck["net"]["onv_dtype"] == "float32"
    with pytest.raises(ValueError, match="head"):
        resolve("smoke", {"model": "conv", "head": "linear"}).validate()
