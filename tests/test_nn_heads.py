"""The foveation net's read-outs: the linear head and the soft-argmax gaze votes."""

import numpy as np
import pytest
import torch

from warp_vision.nn.heads import FoveationNet, foveation_net, log_solid_angle_share, unit_directions


def grid(n=30):
    """n x n inputs on a square, each the position and (here) the visual direction, in radians."""
    g = np.linspace(-0.5, 0.5, n)
    xy = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    return xy, xy.copy()


def test_unit_directions_are_receptive_field_means():
    xy, ang = grid()
    net = foveation_net("linet", xy, layers=2, receptive_field=6, reduction=3, head="softargmax", input_angles=ang)
    dirs = unit_directions(net.backbone, ang)
    assert [tuple(d.shape) for d in dirs] == [(n, 2) for n in net.backbone.layer_sizes]
    idx = net.backbone.layers[1].index.long()
    assert torch.allclose(dirs[2], dirs[1][idx].mean(1))
    assert torch.allclose(net.directions_0.double(), torch.as_tensor(ang))


def test_input_vote_finds_a_bright_spot_and_gradients_reach_everything():
    xy, ang = grid()
    torch.manual_seed(0)
    net = foveation_net("linet", xy, layers=2, receptive_field=6, reduction=3, head="softargmax", input_angles=ang)
    x = torch.full((2, len(xy)), -1.0)
    spots = [(0.2, -0.1), (-0.35, 0.3)]
    for b, c in enumerate(spots):
        near = np.linalg.norm(xy - c, axis=1) < 0.06
        x[b, torch.from_numpy(near)] = 4.0  # a bright disc on a dark field
    _, votes = net.votes(x)
    assert torch.allclose(votes[0], torch.tensor(spots, dtype=torch.float32), atol=0.01)
    # at initialisation the output is that vote, standardised
    net.set_target_norm(torch.tensor([0.1, -0.2]), torch.tensor([0.5, 0.25]))
    out = net(x)
    assert torch.allclose(out * net.target_std + net.target_mean, votes[0], atol=1e-5)
    out.pow(2).sum().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert net.log_temperature.grad[0] != 0


def test_solid_angle_share_balances_a_dense_centre():
    rng = np.random.default_rng(0)
    dense = rng.uniform(-0.1, 0.1, (900, 2))
    sparse = rng.uniform(-1, 1, (900, 2))
    d = torch.from_numpy(np.concatenate([dense, sparse]))
    w = log_solid_angle_share(d).exp()
    assert w[:900].mean() < 0.1 * w[900:].mean()  # a dense unit covers less of the field
    assert torch.isfinite(w).all()


def test_state_dict_round_trip_and_errors():
    xy, ang = grid(12)
    a = foveation_net("linet", xy, layers=2, receptive_field=5, reduction=3, head="softargmax", input_angles=ang,
                      seed=1)
    a.set_target_norm(torch.tensor([0.3, 0.1]), torch.tensor([2.0, 3.0]))
    b = foveation_net("linet", xy, layers=2, receptive_field=5, reduction=3, head="softargmax", input_angles=ang,
                      seed=2)
    b.load_state_dict(a.state_dict())
    x = torch.randn(3, len(xy))
    assert torch.equal(a(x), b(x))
    assert foveation_net("linet", xy, layers=2, receptive_field=5, reduction=3)(x).shape == (3, 2)
    with pytest.raises(ValueError, match="head"):
        foveation_net("fc", xy, layers=2, receptive_field=5, reduction=3, head="softargmax", input_angles=ang)
    with pytest.raises(ValueError, match="input_angles"):
        foveation_net("linet", xy, layers=2, receptive_field=5, reduction=3, head="softargmax")
    with pytest.raises(ValueError, match="input_angles"):
        foveation_net("linet", xy, layers=2, receptive_field=5, reduction=3, head="softargmax", input_angles=ang[:-1])
    with pytest.raises(ValueError, match="head"):
        FoveationNet(a.backbone, head="attention")
    with pytest.raises(ValueError, match="directions"):
        FoveationNet(a.backbone, head="softargmax", directions=[torch.zeros(len(xy), 2)])


def test_the_softargmax_head_votes_alike_on_half_onvs_standardised_in_the_first_layer():
    """A foveation net reading half-precision ONVs (standardised in its first layer) gives what the same
    net gives on the standardised float32 ONVs: the layer-0 vote included."""
    import numpy as np
    import torch

    from warp_vision.eye.retina import Retina
    from warp_vision.nn.trained import build_net, set_input_standardisation

    retina = Retina.log_polar(200, seed=0)
    spec = {"kind": "foveation", "model": "linet", "head": "softargmax", "layers": 2, "receptive_field": 6,
            "reduction": 5, "seed": 0, "photoreceptor_xy": torch.from_numpy(np.asarray(retina.domain_xy, np.float64)),
            "photoreceptor_angles": torch.from_numpy(np.random.default_rng(0).uniform(-1.0, 1.0, (200, 2)))}
    plain = build_net(spec)
    half = build_net({**spec, "onv_dtype": "float16"})
    half.load_state_dict({**plain.state_dict(), **{k: v for k, v in half.state_dict().items() if "input_" in k}})
    norm = {"input_mean": torch.tensor(0.8), "input_std": torch.tensor(0.4)}
    set_input_standardisation(half, norm)
    x = (torch.rand(64, 600, generator=torch.Generator().manual_seed(1)) * 3).half()
    want = plain((x.float() - 0.8) / 0.4)
    got = half(x)
    assert torch.allclose(got, want, rtol=1e-4, atol=1e-4), (got - want).abs().max()
