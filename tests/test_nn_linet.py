"""warp_vision.nn.linet: LocallyConnected, the LiNet backbone, the FC baseline, parameter counts; and
the receptive-field figure of warp_vision.viz."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from warp_vision.kernels.linet.reference import locally_connected_ref
from warp_vision.nn import (
    FullyConnected,
    LiNet,
    LocallyConnected,
    build_connectivity,
    fc_param_count,
    linet_param_count,
    onv_positions,
    receptive_field_radius,
)
from warp_vision.viz import plot_receptive_fields


def foveated_positions(num: int, seed: int = 0) -> np.ndarray:
    """[num, 2] log-uniform eccentricity in [0.01, 1], uniform angle: density ~ 1/rho^2."""
    rng = np.random.default_rng(seed)
    rho = np.exp(rng.uniform(math.log(0.01), 0.0, num))
    theta = rng.uniform(0.0, 2 * math.pi, num)
    return np.stack([rho * np.cos(theta), rho * np.sin(theta)], axis=1)


@pytest.fixture(scope="module")
def in_pos() -> np.ndarray:
    return onv_positions(foveated_positions(400))  # N_0 = 1200


def reference_forward(net: LiNet, x: torch.Tensor) -> torch.Tensor:
    """The liNet, composed by hand from the plain-torch reference layer and its buffers/parameters."""
    for layer in net.layers:
        x = torch.relu(locally_connected_ref(x, layer.weight, layer.bias, layer.index))
    return x


# ---------------------------------------------------------------------------------------------------
# LocallyConnected
# ---------------------------------------------------------------------------------------------------


def test_locally_connected_buffers_init_and_forward():
    torch.manual_seed(0)
    index = np.array([[0, 3, 4], [1, 2, 2], [4, 0, 1], [3, 3, 3]])
    layer = LocallyConnected(index, in_features=5, relu=False, dtype=torch.float64)
    assert dict(layer.named_buffers()).keys() == {"index"}
    assert {n for n, _ in layer.named_parameters()} == {"weight", "bias"}
    assert layer.index.dtype == torch.int32 and layer.weight.shape == (4, 3) and layer.bias.shape == (4,)
    assert (layer.out_features, layer.receptive_field, layer.in_features) == (4, 3, 5)
    assert torch.all(layer.bias == 0)
    assert "receptive_field=3" in repr(layer) and "relu=False" in repr(layer)
    with torch.no_grad():
        layer.weight.copy_(torch.tensor([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.5], [0.0, 1.0, -2.0], [1.0, 1.0, 1.0]]))
        layer.bias.copy_(torch.tensor([0.5, 0.0, -1.0, 2.0]))
    x = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0]], dtype=torch.float64)
    # By hand: 0.5+1+8+15 = 24.5; -2+1.5+1.5 = 1; -1+0+1-4 = -4; 2+4+4+4 = 14
    torch.testing.assert_close(layer(x), torch.tensor([[24.5, 1.0, -4.0, 14.0]], dtype=torch.float64))
    layer.relu = True
    torch.testing.assert_close(layer(x), torch.tensor([[24.5, 1.0, 0.0, 14.0]], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"x: expected shape \[B, 5\], got \(1, 6\)"):
        layer(torch.ones(1, 6, dtype=torch.float64))
    # a numpy batch was "expected shape [B, 5], got ndarray"
    with pytest.raises(ValueError,
                       match=r"x: expected a torch tensor \[B, 5\], got a ndarray \(torch.from_numpy\(x\)\)"):
        layer(np.ones((1, 5)))


def test_locally_connected_he_init_and_seeded_reset():
    index = np.random.default_rng(0).integers(0, 100, size=(4000, 8))
    layer = LocallyConnected(index, in_features=100)
    std = float(layer.weight.detach().std())
    # He: std = sqrt(2 / R) = 0.5; 32000 samples give a relative standard error of ~0.4 %.
    assert abs(std - 0.5) < 0.02
    a = LocallyConnected(index, 100)
    b = LocallyConnected(index, 100)
    a.reset_parameters(torch.Generator().manual_seed(5))
    b.reset_parameters(torch.Generator().manual_seed(5))
    assert torch.equal(a.weight, b.weight)
    assert LocallyConnected(torch.tensor(index, dtype=torch.int32), 100).index.dtype == torch.int32


@pytest.mark.parametrize(
    "args, match",
    [
        ((np.array([[0, 5]]), 5), "index"),  # out of range
        ((np.array([[-1, 0]]), 5), "index"),
        ((np.array([0, 1]), 5), "index"),  # not [N, R]
        ((np.array([[0.0, 1.0]]), 5), "index"),  # float
        ((np.array([[0, 1]]), 0), "in_features"),
    ],
)
def test_locally_connected_value_errors(args, match):
    with pytest.raises(ValueError, match=match):
        LocallyConnected(*args)
    with pytest.raises(ValueError, match="dtype"):
        LocallyConnected(np.array([[0, 1]]), 5, dtype=torch.int32)


# ---------------------------------------------------------------------------------------------------
# LiNet
# ---------------------------------------------------------------------------------------------------


def test_linet_attributes_and_buffers(in_pos):
    net = LiNet(in_pos, layers=3, receptive_field=[10, 8, 6], reduction=5, seed=0)
    assert net.layer_sizes == [1200, 240, 48, 9]
    assert net.receptive_fields == [10, 8, 6]
    assert (net.in_features, net.out_features) == (1200, 9)
    assert all(layer.relu for layer in net.layers)
    conns = build_connectivity(in_pos, 3, [10, 8, 6], 5, seed=0)
    for h, (layer, c) in enumerate(zip(net.layers, conns), start=1):
        np.testing.assert_array_equal(layer.index.numpy(), c.index)
        np.testing.assert_array_equal(net.layer_positions(h).numpy(), c.positions.astype(np.float32))
    np.testing.assert_array_equal(net.layer_positions(0).numpy(), in_pos.astype(np.float32))  # kept in float32
    keys = set(net.state_dict())
    assert {f"positions_{h}" for h in range(4)} | {f"layers.{h}.index" for h in range(3)} <= keys
    with pytest.raises(ValueError, match="h"):
        net.layer_positions(4)


def test_linet_forward_matches_reference(in_pos, device):
    torch.manual_seed(0)
    net = LiNet(in_pos, layers=3, receptive_field=10, reduction=5, seed=0).to(device)
    x = torch.rand(5, net.in_features, device=device)  # irradiance-like: non-negative
    y = net(x)
    assert y.shape == (5, net.out_features) and y.dtype == torch.float32
    assert (y > 0).any()  # not all units dead, or the comparison would be vacuous
    torch.testing.assert_close(y, reference_forward(net, x), rtol=1e-5, atol=1e-6)
    net64 = net.double()
    torch.testing.assert_close(net64(x.double()), reference_forward(net64, x.double()), rtol=1e-12, atol=1e-12)


def test_linet_gradients_flow_and_match_reference(in_pos, device):
    torch.manual_seed(1)
    net = LiNet(in_pos, layers=3, receptive_field=10, reduction=5, seed=0).to(device).double()
    x = torch.rand(4, net.in_features, device=device, dtype=torch.float64, requires_grad=True)
    (net(x) ** 2).sum().backward()
    grads = [p.grad.clone() for p in net.parameters()]
    gx = x.grad.clone()
    for p, g in zip(net.parameters(), grads):
        assert g is not None and torch.isfinite(g).all() and (g != 0).any(), p.shape
    net.zero_grad()
    x.grad = None
    (reference_forward(net, x) ** 2).sum().backward()
    for p, g in zip(net.parameters(), grads):
        torch.testing.assert_close(g, p.grad, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(gx, x.grad, rtol=1e-10, atol=1e-12)


def test_linet_state_dict_round_trip(in_pos):
    torch.manual_seed(0)
    src = LiNet(in_pos, layers=3, receptive_field=10, reduction=5, seed=0)
    x = torch.rand(3, src.in_features)
    y_src = src(x)

    same = LiNet(in_pos, layers=3, receptive_field=10, reduction=5, seed=0)  # other random weights
    assert not torch.equal(same(x), y_src)
    same.load_state_dict(src.state_dict())
    assert torch.equal(same(x), y_src)

    # A different connectivity seed: loading must restore the index buffers (and positions), and the
    # kernels' cached plan of the old index must not be reused.
    other = LiNet(in_pos, layers=3, receptive_field=10, reduction=5, seed=7)
    y_before = other(x)  # populates the plan cache with the seed-7 connectivity
    assert not torch.equal(other.layers[0].index, src.layers[0].index)
    other.load_state_dict(src.state_dict())
    for a, b in zip(other.state_dict().values(), src.state_dict().values()):
        assert torch.equal(a, b)
    assert torch.equal(other(x), y_src) and not torch.equal(y_before, y_src)
    np.testing.assert_array_equal(other.connectivity()[1].index, src.connectivity()[1].index)


def test_linet_value_errors(in_pos):
    with pytest.raises(ValueError, match="receptive_field"):
        LiNet(in_pos, layers=4, receptive_field=20, reduction=5)  # N_3 = 9 < R_4 = 20
    with pytest.raises(ValueError, match="in_positions"):
        LiNet(np.zeros((100, 3)))


# ---------------------------------------------------------------------------------------------------
# Fully-connected baseline and parameter counts
# ---------------------------------------------------------------------------------------------------


def test_fully_connected_sizes_and_forward():
    torch.manual_seed(0)
    fc = FullyConnected(30, [12, 4])
    assert (fc.in_features, fc.out_features, fc.layer_sizes) == (30, 4, [30, 12, 4])
    assert [tuple(layer.weight.shape) for layer in fc.layers] == [(12, 30), (4, 12)]
    assert all(torch.all(layer.bias == 0) for layer in fc.layers)
    x = torch.rand(2, 30)
    ref = torch.relu(fc.layers[1](torch.relu(fc.layers[0](x))))
    torch.testing.assert_close(fc(x), ref)
    with pytest.raises(ValueError, match="hidden"):
        FullyConnected(30, [])
    with pytest.raises(ValueError, match="hidden"):
        FullyConnected(30, [12, 0])


def test_param_counts_by_hand():
    sizes = [1000, 200, 40, 8, 1]
    # liNet, R = 5: (200 + 40 + 8 + 1) * (5 + 1) = 249 * 6 = 1494
    assert linet_param_count(sizes, 5) == 1494
    assert linet_param_count(sizes, [5, 5, 5, 5]) == 1494
    # FC: 1000*200+200 + 200*40+40 + 40*8+8 + 8*1+1 = 200200 + 8040 + 328 + 9 = 208577
    assert fc_param_count(sizes) == 208577


def test_module_param_counts_match_formulas():
    net = LiNet(foveated_positions(1000, seed=4), layers=4, receptive_field=5, reduction=5)
    assert net.layer_sizes == [1000, 200, 40, 8, 1]
    assert net.num_parameters() == linet_param_count(net.layer_sizes, 5) == 1494
    fc = FullyConnected.like(net)
    assert fc.layer_sizes == net.layer_sizes
    assert fc.num_parameters() == fc_param_count(net.layer_sizes) == 208577


# ---------------------------------------------------------------------------------------------------
# Figure
# ---------------------------------------------------------------------------------------------------


def test_plot_receptive_fields(in_pos):
    net = LiNet(in_pos, layers=2, receptive_field=10, reduction=5, seed=0)
    fig = plot_receptive_fields(net, layer=1, units=12)
    assert isinstance(fig, Figure)
    (ax,) = fig.axes
    circles = [p for p in ax.patches if isinstance(p, Circle)]
    assert len(circles) == 12
    assert ax.get_xlabel() and ax.get_ylabel() and ax.get_title()
    assert ax.get_aspect() == 1.0
    # A circle's radius is its unit's receptive-field radius, centred at the unit.
    conns = net.connectivity()
    # the net's float32 positions
    radius = receptive_field_radius(in_pos.astype(np.float32).astype(np.float64), conns[0])
    unit_of = {tuple(p): n for n, p in enumerate(conns[0].positions)}
    for c in circles:
        n = unit_of[tuple(c.center)]
        assert c.radius == pytest.approx(radius[n], rel=1e-12)

    # A connectivity list, explicit units, layer 2 (its previous positions are layer 1's).
    fig2 = plot_receptive_fields(conns, layer=2, units=[0, 5, 9])
    assert len(fig2.axes[0].patches) == 3
    with pytest.raises(ValueError, match="in_positions"):
        plot_receptive_fields(conns, layer=1)
    with pytest.raises(ValueError, match="layer"):
        plot_receptive_fields(net, layer=3)


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_a_folded_standardisation_reads_half_inputs_as_the_float32_path_does(half):
    """The first layer standardising in its weights (half-precision ONVs) computes what it computes on a
    standardised float32 copy, up to float32 rounding; its gradients reach weight and bias alike."""
    from warp_vision.nn.linet import LocallyConnected

    g = torch.Generator().manual_seed(0)
    index = torch.randint(0, 300, (60, 9), generator=g)
    plain = LocallyConnected(index, 300, relu=True)
    folded = LocallyConnected(index, 300, relu=True)
    folded.load_state_dict(plain.state_dict())
    folded.fold_input_standardisation()
    mean, std = torch.tensor(0.7), torch.tensor(0.3)
    folded.input_mean.copy_(mean)
    folded.input_std.copy_(std)
    x = (torch.rand(64, 300, generator=g) * 3).to(half)
    want = plain((x.float() - mean) / std)
    got = folded(x)
    scale = plain.bias.abs() + (x.float()[:, index].abs() / std + mean / std) @ torch.ones(9) * plain.weight.abs().max()
    assert got.dtype == torch.float32 and ((got - want).abs() <= 1e-5 * scale + 1e-6).all()
    got.sum().backward()
    want.sum().backward()
    assert torch.allclose(folded.weight.grad, plain.weight.grad, rtol=1e-4, atol=1e-5)
    assert torch.allclose(folded.bias.grad, plain.bias.grad, rtol=1e-5, atol=1e-6)
    assert {"input_mean", "input_std"} <= set(folded.state_dict())
