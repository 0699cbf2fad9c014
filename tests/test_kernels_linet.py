"""The locally-connected Warp kernels against the plain-torch reference (kernels/linet/reference.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from warp_vision.kernels import launch
from warp_vision.kernels.linet import locally_connected
from warp_vision.kernels.linet.layout import feature_major
from warp_vision.kernels.linet.op import LinetPlan, build_plan, plan_for
from warp_vision.kernels.linet.reference import locally_connected_backward_ref, locally_connected_ref

# Each output is a sum of R + 1 products. The kernel and the reference sum in different orders, so
# they agree to a few ulps of the *absolute* sum: |a - b| <= RTOL * (sum of |terms|).
RTOL = {torch.float32: 1e-5, torch.float64: 1e-12}


def make_case(B, n_in, N, R, dtype, device, seed=0, unread=0, index_dtype=torch.int64):
    """Random x, weight, bias and an index with repeats (and ``unread`` inputs nothing reads)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, n_in, generator=g, dtype=torch.float64).to(dtype)
    w = torch.randn(N, R, generator=g, dtype=torch.float64).to(dtype)
    b = torch.randn(N, generator=g, dtype=torch.float64).to(dtype)
    readable = max(1, n_in - unread)
    index = torch.randint(0, readable, (N, R), generator=g)
    if N and R >= 2:
        index[0, 1] = index[0, 0]  # a repeat within one receptive field
    return x.to(device), w.to(device), b.to(device), index.to(index_dtype).to(device)


def abs_bound_forward(x, w, b, index):
    """Elementwise sum of |terms| of each output, for the summation-order tolerance."""
    xa = x.abs().double()
    return b.abs().double() + (xa[:, index.long()] * w.abs().double()).sum(-1)


def assert_close_abs(got, want, scale, dtype, what):
    err = (got.double() - want.double()).abs()
    bound = RTOL[dtype] * (scale + 1e-30)
    worst = (err / bound).max().item() if err.numel() else 0.0
    assert worst <= 1.0, f"{what}: error {err.max().item():.3e} exceeds tolerance (worst ratio {worst:.2f})"


def check_against_reference(
    B, n_in, N, R, dtype, device, relu=False, seed=0, unread=0, index_dtype=torch.int64, feature_major_x=False
):
    x, w, b, index = make_case(B, n_in, N, R, dtype, device, seed, unread, index_dtype)
    if feature_major_x:  # the same values, stored [n_in, B] as one liNet layer hands them to the next
        x = x.t().contiguous().t()
    x.requires_grad_(True)
    w.requires_grad_(True)
    b.requires_grad_(True)
    y = locally_connected(x, w, b, index, relu=relu)
    with torch.no_grad():
        pre = locally_connected_ref(x.double(), w.double(), b.double(), index)
        y_ref = torch.relu(pre) if relu else pre
    assert y.shape == (B, N) and y.dtype == dtype and y.device == x.device
    # B a multiple of 64: y comes out feature-major (the vectorised layout), else batch-major
    assert feature_major(y) if B % 64 == 0 else y.is_contiguous()
    assert_close_abs(y, y_ref, abs_bound_forward(x, w, b, index), dtype, "forward")

    gy = torch.randn(B, N, generator=torch.Generator().manual_seed(seed + 1), dtype=torch.float64).to(dtype).to(device)
    gx, gw, gb = torch.autograd.grad(y, (x, w, b), gy)
    gpre = gy.double() * (pre > 0) if relu else gy.double()
    gx_ref, gw_ref, gb_ref = locally_connected_backward_ref(x.double(), w.double(), index, gpre)
    ga = gpre.abs()
    gx_scale = torch.zeros(B, n_in, dtype=torch.float64, device=x.device)
    gx_scale.index_add_(1, index.long().reshape(-1), (ga[:, :, None] * w.abs().double()[None]).reshape(B, -1))
    assert_close_abs(gx, gx_ref, gx_scale, dtype, "grad_x")
    gw_scale = (ga[:, :, None] * x.abs().double()[:, index.long()]).sum(0)
    assert_close_abs(gw, gw_ref, gw_scale, dtype, "grad_weight")
    assert_close_abs(gb, gb_ref, ga.sum(0), dtype, "grad_bias")
    if unread:
        assert torch.all(gx[:, n_in - unread :] == 0), "inputs that nothing reads must get zero gradient"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize(
    "B,n_in,N,R",
    [
        (1, 1, 1, 1),  # tiny
        (3, 7, 5, 3),  # B and R not multiples of the kernels' blocks
        (8, 40, 12, 4),
        (13, 300, 61, 9),
        (9, 2000, 400, 20),
    ],
)
def test_matches_reference(B, n_in, N, R, dtype, relu, device):
    check_against_reference(B, n_in, N, R, dtype, device, relu=relu, unread=min(3, n_in - 1))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize("feature_major_x", [False, True])
@pytest.mark.parametrize("B,n_in,N,R", [(64, 1, 1, 1), (64, 300, 61, 9), (128, 2000, 400, 20), (192, 50, 70, 3)])
def test_feature_major_path_matches_reference(B, n_in, N, R, dtype, relu, feature_major_x, device):
    # B a multiple of 64: the 64-lane kernels (feature-major x) or the batch-major forward writing a
    # feature-major y, and the feature-major backward kernels
    check_against_reference(
        B, n_in, N, R, dtype, device, relu=relu, unread=min(3, n_in - 1), feature_major_x=feature_major_x
    )


#: unit roundoff of the half types (half the spacing of numbers near 1) and their smallest subnormal:
#: rounding a float32 to them moves it by at most u * |value| + tiny / 2
HALF_ROUNDING = {torch.float16: (2.0**-11, 2.0**-24), torch.bfloat16: (2.0**-8, 2.0**-133)}


@pytest.mark.parametrize("x_dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize("layout", ["batch_major", "feature_major"])
@pytest.mark.parametrize("B,n_in,N,R", [(3, 7, 5, 3), (13, 300, 61, 9), (64, 300, 61, 9), (128, 2000, 400, 20)])
def test_half_precision_x_matches_reference(B, n_in, N, R, x_dtype, relu, layout, device):
    """A float16 or bfloat16 x with float32 weights. The kernels widen x exactly, so y and grad_weight
    differ from the exact (float64) values only by float32 summation order (the float32 tolerance);
    grad_x, summed in float32 and rounded once to x's dtype, by that plus the rounding: u |grad_x| + tiny."""
    x, w, b, index = make_case(B, n_in, N, R, torch.float32, device, seed=3, unread=2)
    x = x.to(x_dtype)
    if layout == "feature_major":
        x = x.t().contiguous().t()
    x.requires_grad_(True)
    w.requires_grad_(True)
    b.requires_grad_(True)
    y = locally_connected(x, w, b, index, relu=relu)
    assert y.dtype == torch.float32
    xd = x.detach().double()
    with torch.no_grad():
        pre = locally_connected_ref(xd, w.double(), b.double(), index)
        y_ref = torch.relu(pre) if relu else pre
    assert_close_abs(y, y_ref, abs_bound_forward(xd, w, b, index), torch.float32, "forward")
    gy = torch.randn(B, N, generator=torch.Generator().manual_seed(4), dtype=torch.float64).float().to(device)
    gx, gw, gb = torch.autograd.grad(y, (x, w, b), gy)
    assert gx.dtype == x_dtype and gw.dtype == gb.dtype == torch.float32
    gpre = gy.double() * (pre > 0) if relu else gy.double()
    gx_ref, gw_ref, gb_ref = locally_connected_backward_ref(xd, w.double(), index, gpre)
    ga = gpre.abs()
    gx_scale = torch.zeros(B, n_in, dtype=torch.float64, device=x.device)
    gx_scale.index_add_(1, index.long().reshape(-1), (ga[:, :, None] * w.abs().double()[None]).reshape(B, -1))
    u, tiny = HALF_ROUNDING[x_dtype]
    summed = RTOL[torch.float32] * (gx_scale + 1e-30)
    bound = summed + u * (gx_ref.abs() + summed) + tiny
    err = (gx.double() - gx_ref).abs()
    assert (err <= bound).all(), f"grad_x: worst error / bound {(err / bound).max().item():.2f}"
    assert_close_abs(gw, gw_ref, (ga[:, :, None] * xd.abs()[:, index.long()]).sum(0), torch.float32, "grad_weight")
    assert_close_abs(gb, gb_ref, ga.sum(0), torch.float32, "grad_bias")
    assert torch.all(gx[:, n_in - 2:] == 0)


def test_a_half_x_needing_no_gradient_gets_none_computed(monkeypatch):
    """The first layer's ONV needs no gradient: no grad_x kernel runs for it (as for float32)."""
    import warp_vision.kernels.linet.op as op

    x, w, b, index = make_case(64, 300, 61, 9, torch.float32, "cpu")
    launched = []
    real = op.launch_kernel
    monkeypatch.setattr(op, "launch_kernel", lambda k, *a, **kw: launched.append(k.key) or real(k, *a, **kw))
    w.requires_grad_(True)
    locally_connected(x.half(), w, b, index).sum().backward()
    assert launched and not [k for k in launched if "grad_x" in k]


def test_feature_major_chain_matches_reference(device):
    # Two fused-ReLU layers and a torch head: the liNet's data path, gradients through all of it
    g = torch.Generator().manual_seed(11)
    x = torch.randn(64, 500, generator=g, dtype=torch.float64).to(device).requires_grad_(True)
    i1 = torch.randint(0, 500, (120, 9), generator=g).to(device)
    i2 = torch.randint(0, 120, (30, 7), generator=g).to(device)
    params = [torch.randn(*s, generator=g, dtype=torch.float64).to(device).requires_grad_(True)
              for s in ((120, 9), (120,), (30, 7), (30,), (3, 30))]
    w1, b1, w2, b2, head = params

    def net(layer):
        h = layer(x, w1, b1, i1, True)
        return (layer(h, w2, b2, i2, True) @ head.t()).square().sum()

    got = torch.autograd.grad(net(lambda *a: locally_connected(*a[:4], relu=a[4])), [x, *params])
    want = torch.autograd.grad(net(lambda *a: torch.relu(locally_connected_ref(*a[:4]))), [x, *params])
    for a, c in zip(got, want):
        assert torch.allclose(a, c, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("index_dtype", [torch.int32, torch.int64])
def test_large_layer_matches_reference(index_dtype, device):
    # ~1e5 units in, 2e4 out: large enough that CPU launches are split across threads.
    check_against_reference(4, 100_000, 20_000, 5, torch.float32, device, index_dtype=index_dtype, unread=7)


@pytest.mark.parametrize("B,feature_major_x", [(3, False), (64, False), (64, True)])
def test_gradcheck_float64(B, feature_major_x, device):
    x, w, b, index = make_case(B, 11, 6, 4, torch.float64, device, seed=3)
    if feature_major_x:
        x = x.t().contiguous().t()
    for relu in (False, True):
        inputs = tuple(t.clone().requires_grad_(True) for t in (x, w, b))
        assert torch.autograd.gradcheck(
            lambda x_, w_, b_, relu=relu: locally_connected(x_, w_, b_, index, relu=relu), inputs, eps=1e-6, atol=1e-8
        )


@settings(max_examples=30, deadline=None)
@given(
    B=st.integers(1, 20),
    n_in=st.integers(1, 60),
    N=st.integers(1, 40),
    R=st.integers(1, 12),
    relu=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_hypothesis_shapes(B, n_in, N, R, relu, seed):
    check_against_reference(B, n_in, N, R, torch.float32, "cpu", relu=relu, seed=seed)


@pytest.mark.parametrize("B", [11, 64])
def test_split_launch_is_bit_identical_to_one_thread(B, monkeypatch):
    x, w, b, index = make_case(B, 30_000, 9_000, 7, torch.float32, "cpu", seed=5)
    for t in (x, w, b):
        t.requires_grad_(True)
    outs = []
    for threads in ("1", "2", "3"):
        monkeypatch.setenv("WARP_VISION_THREADS", threads)
        y = locally_connected(x, w, b, index, relu=True)
        grads = torch.autograd.grad(y, (x, w, b), torch.ones_like(y))
        outs.append((y, *grads))
    for other in outs[1:]:
        for a, c in zip(outs[0], other):
            assert torch.equal(a, c)


def test_only_requested_gradients_are_computed():
    x, w, b, index = make_case(4, 50, 10, 3, torch.float32, "cpu")
    w.requires_grad_(True)
    y = locally_connected(x, w, b, index)
    y.sum().backward()
    assert x.grad is None and b.grad is None and w.grad is not None


@pytest.mark.parametrize("feature_major_x", [False, True])
@pytest.mark.parametrize("wants", [(True, False, False), (False, True, False), (False, False, True),
                                   (False, True, True), (True, True, False), (True, False, True)])
def test_any_subset_of_gradients_matches_reference(wants, feature_major_x, device):
    # B = 128: the feature-major kernels; a frozen bias (the weight kernel's fused bias sum goes to
    # scratch) and a frozen weight (the bias-only kernel) must leave the other gradients right.
    B, n_in, N, R = 128, 300, 61, 9
    x, w, b, index = make_case(B, n_in, N, R, torch.float64, device, seed=3)
    if feature_major_x:
        x = x.t().contiguous().t()
    leaves = [t.requires_grad_(want) for t, want in zip((x, w, b), wants)]
    y = locally_connected(x, w, b, index)
    gy = torch.randn(B, N, generator=torch.Generator().manual_seed(4), dtype=torch.float64).to(device)
    got = torch.autograd.grad(y, [t for t in leaves if t.requires_grad], gy)
    want = locally_connected_backward_ref(x.detach(), w.detach(), index, gy)
    assert len(got) == sum(wants)
    for g, ref in zip(got, [r for r, wanted in zip(want, wants) if wanted]):
        torch.testing.assert_close(g, ref, rtol=1e-10, atol=1e-10)


def test_non_contiguous_input_is_accepted():
    x, w, b, index = make_case(6, 40, 10, 3, torch.float32, "cpu")
    xt = x.t().contiguous().t()  # same values, column-major
    assert not xt.is_contiguous()
    assert torch.equal(locally_connected(xt, w, b, index), locally_connected(x, w, b, index))


def test_empty_batch():
    x, w, b, index = make_case(0, 40, 10, 3, torch.float32, "cpu")
    w.requires_grad_(True)
    y = locally_connected(x, w, b, index)
    assert y.shape == (0, 10)
    y.sum().backward()
    assert torch.equal(w.grad, torch.zeros_like(w))


def test_plan_transpose_lists_every_connection_once():
    index = torch.tensor([[2, 2, 0], [1, 2, 4]])
    plan = build_plan(index, in_features=6)
    assert isinstance(plan, LinetPlan)
    offs = plan.t_offsets.tolist()
    ents = plan.t_entries.tolist()
    assert offs == [0, 1, 2, 5, 5, 6, 6]  # input 3 and 5 are read by nothing
    for i in range(6):
        for e in ents[offs[i] : offs[i + 1]]:
            assert index.reshape(-1)[e] == i
    assert sorted(ents) == list(range(6))


def test_plan_cache_follows_in_place_changes():
    x, w, b, index = make_case(2, 20, 5, 3, torch.float32, "cpu")
    p1 = plan_for(index, 20)
    assert plan_for(index, 20) is p1
    y1 = locally_connected(x, w, b, index)
    index[0, 0] = (index[0, 0] + 1) % 20  # in-place edit bumps the version: the plan is rebuilt
    assert plan_for(index, 20) is not p1
    y2 = locally_connected(x, w, b, index)
    assert not torch.equal(y1[:, 0], y2[:, 0]) or x[:, index[0, 0]].eq(x[:, (index[0, 0] - 1) % 20]).all()
    assert torch.allclose(y2, locally_connected_ref(x, w, b, index), atol=1e-5)


@pytest.mark.parametrize("how", ["numpy", "data"])
@pytest.mark.parametrize("dtype", [torch.int64, torch.int32])
def test_plan_cache_sees_changes_made_behind_torchs_back(how, dtype):
    """Writes through the numpy array under ``torch.from_numpy`` or through ``.data`` do not bump the
    tensor's version: the op still answers for the new values, and an out-of-range value is refused."""
    x, w, b, index = make_case(64, 40, 8, 4, torch.float32, "cpu")
    arr = index.numpy().astype(np.int64 if dtype == torch.int64 else np.int32)
    idx = torch.from_numpy(arr)
    view = arr if how == "numpy" else idx.data.numpy()
    locally_connected(x, w, b, idx)  # caches a plan
    view[:] = (view + 7) % 40
    assert torch.allclose(locally_connected(x, w, b, idx), locally_connected_ref(x, w, b, idx.long()), atol=1e-5)
    view[0, 0] = 40  # out of range
    with pytest.raises(ValueError, match=r"index: expected values in \[0, 40\)"):
        locally_connected(x, w, b, idx)


def test_a_plan_for_other_values_is_refused():
    x, w, b, index = make_case(2, 20, 5, 3, torch.float32, "cpu")
    plan = build_plan(index, 20)
    other = index.clone()
    other[0, 0] = (other[0, 0] + 1) % 20
    with pytest.raises(ValueError, match="plan: expected a plan for this index"):
        locally_connected(x, w, b, other, plan=plan)


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda a: a.update(x=a["x"][0]), "x: expected rank 2"),
        (lambda a: a.update(x=a["x"].to(torch.int32)), "x: expected dtype float32, float64, float16 or bfloat16"),
        (lambda a: a.update(x=a["x"].half(), weight=a["weight"].half()),
         r"weight: expected dtype torch.float32 \(float32 weights go with a torch.float16 x\)"),
        (lambda a: a.update(weight=a["weight"].double()),
         r"weight: expected dtype torch.float32 \(the dtype of x\), got "
                                                          r"torch.float64; convert x \(x.to\(torch.float64\)\) or the "
                                                          r"layer \(.to\(torch.float32\)\)"),
        (lambda a: a.update(bias=a["bias"].double()), "bias: expected dtype torch.float32"),
        (lambda a: a.update(weight=a["weight"][:, :2]), r"index: expected shape \(10, 2\)"),
        (lambda a: a.update(bias=a["bias"][:4]), r"bias: expected shape \(10,\)"),
        (lambda a: a.update(index=a["index"].float()), "index: expected dtype int32 or int64"),
        (lambda a: a.update(index=a["index"] + 40), r"index: expected values in \[0, 40\)"),
        (lambda a: a["index"].__setitem__((3, 1), -1), r"got values in \[-1,"),
        (lambda a: a["weight"].__setitem__((2, 2), float("nan")), "weight: expected finite values"),
        (lambda a: a["bias"].__setitem__(1, float("inf")), "bias: expected finite values"),
        (lambda a: a.update(index=a["index"].numpy()), "index: expected a torch.Tensor"),
        (lambda a: a.update(x=a["x"].numpy()), "x: expected a torch.Tensor"),
    ],
)
def test_bad_input_raises_value_error(mutate, match):
    x, w, b, index = make_case(3, 40, 10, 3, torch.float32, "cpu")
    args = {"x": x, "weight": w, "bias": b, "index": index}
    mutate(args)
    with pytest.raises(ValueError, match=match):
        locally_connected(args["x"], args["weight"], args["bias"], args["index"])


def test_mismatched_device_raises(cuda_device):
    x, w, b, index = make_case(3, 40, 10, 3, torch.float32, "cpu")
    with pytest.raises(ValueError, match="weight: expected device"):
        locally_connected(x, w.to(cuda_device), b, index)


def test_slices_cover_the_range_once():
    for total, parts in [(10, 3), (7, 7), (5, 9), (100_001, 2)]:
        sl = launch.slices(total, parts)
        covered = np.concatenate([np.arange(s, s + n) for s, n in sl])
        assert np.array_equal(covered, np.arange(total))
        assert len(sl) <= parts


@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize("B", [10, 64])
def test_first_layer_gradients_without_grad_x(relu, B, device):
    # x (an ONV) needs no gradient: the weight and bias kernels then mask the ReLU on the fly.
    x, w, b, index = make_case(B, 500, 120, 7, torch.float64, device, seed=9)
    w.requires_grad_(True)
    b.requires_grad_(True)
    y = locally_connected(x, w, b, index, relu=relu)
    gy = torch.randn(y.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64).to(device)
    gw, gb = torch.autograd.grad(y, (w, b), gy)
    pre = locally_connected_ref(x, w.detach(), b.detach(), index)
    gpre = gy * (pre > 0) if relu else gy
    _, gw_ref, gb_ref = locally_connected_backward_ref(x, w.detach(), index, gpre)
    assert torch.allclose(gw, gw_ref, rtol=1e-12, atol=1e-12)
    assert torch.allclose(gb, gb_ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("B", [9, 64])
def test_fused_relu_propagates_nan_like_torch(B):
    g = torch.Generator().manual_seed(3)
    x = torch.randn(B, 30, generator=g)
    x[2, 5] = float("nan")
    w = torch.randn(12, 4, generator=g)
    b = torch.randn(12, generator=g)
    idx = torch.randint(0, 30, (12, 4), generator=g)
    y = locally_connected(x, w, b, idx, relu=True)
    ref = torch.relu(locally_connected_ref(x, w, b, idx))
    assert torch.equal(torch.isnan(y), torch.isnan(ref)) and torch.isnan(y).any()
    assert torch.allclose(y.nan_to_num(), ref.nan_to_num(), atol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
@pytest.mark.parametrize("B,F", [(64, 1), (64, 37), (128, 1000), (192, 16), (64, 8)])
def test_transpose_kernel_matches_torch(B, F, dtype, device):
    from warp_vision.kernels.linet.layout import as_feature_major

    x = torch.randn(B, F, generator=torch.Generator().manual_seed(B + F), dtype=dtype).to(device)
    xt = as_feature_major(x)
    assert feature_major(xt) and torch.equal(xt, x)
    # a copy in the other layout (a single feature is already both layouts)
    assert (xt is x) if F == 1 else (xt.data_ptr() != x.data_ptr())
    assert as_feature_major(xt) is xt  # already feature-major: no copy
    odd = x[:63]
    assert as_feature_major(odd) is odd  # B not a multiple of 64: left batch-major


@pytest.mark.parametrize("relu", [False, True])
def test_huge_batch_major_input_is_read_in_place(relu, device, monkeypatch):
    # Above TRANSPOSE_MAX_BYTES a batch-major x is not copied: the batch-major kernels read it and
    # write a feature-major y, and the backward mixes the two families.
    from warp_vision.kernels.linet import layout

    monkeypatch.setattr(layout, "TRANSPOSE_MAX_BYTES", 0)
    assert layout.as_feature_major(torch.zeros(64, 10)).is_contiguous()
    check_against_reference(64, 700, 90, 11, torch.float64, device, relu=relu, unread=2)
    check_against_reference(128, 300, 61, 9, torch.float32, device, relu=relu)
