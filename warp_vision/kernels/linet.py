"""Locally-connected irregular layer (the liNet layer): Warp forward and backward kernels in torch autograd.

    y[b, n] = bias[n] + sum_r weight[n, r] * x[b, index[n, r]]        (optionally followed by ReLU)

Every kernel here is a *gather*: each Warp thread writes only its own output element, so launches are
deterministic and can be split across CPU threads (``kernels.launch.launch_split``). The gradient with
respect to ``x`` is a gather over the transposed connectivity, a CSR structure built once per index
tensor and cached (:func:`plan_for`). No ``[B, N, R]`` intermediate is ever formed.

The backward passes are written by hand: Warp's automatic adjoints are not trusted for loops whose
trip count is not a compile-time constant (DESIGN.md). ``linet_ref.py`` holds the plain-torch maths
the tests compare against.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import warp as wp
from torch import Tensor

from warp_vision.kernels import launch as _launch

wp.set_module_options({"enable_backward": False})

_FLOATS = (torch.float32, torch.float64)
_INDEX_DTYPES = (torch.int32, torch.int64)


# --------------------------------------------------------------------------------------------------
# Kernels (1D launches over flattened outputs; ``offset`` is the first thread of a split launch)
# --------------------------------------------------------------------------------------------------


#: Batch rows one forward / grad_x thread handles: eight independent accumulators hide the latency
#: of the strided gathers (measured 5x faster than one row per thread on the CPU backend).
#: The kernels spell it as the literal 8: keep the two in step.
BATCH_BLOCK = 8
#: Connections one grad_weight thread handles (one load of the upstream gradient serves four products).
CONN_BLOCK = 4


@wp.kernel
def linet_forward(
    x: wp.array2d(dtype=Any),
    weight: wp.array2d(dtype=Any),
    bias: wp.array(dtype=Any),
    index: wp.array2d(dtype=wp.int32),
    relu: int,
    offset: int,
    y_out: wp.array2d(dtype=Any),
):
    """y_out[b, n] = (ReLU of) bias[n] + sum_r weight[n, r] * x[b, index[n, r]].

    Thread t = blk * N + n computes rows b = 8 blk .. 8 blk + 7 of unit n (rows past B read row
    B - 1 and are never stored). The constant-length loops over the 8 rows are unrolled by Warp.
    """
    t = offset + wp.tid()
    num_units = weight.shape[0]
    blk = t // num_units
    n = t - blk * num_units
    last = x.shape[0] - 1
    b0 = blk * 8
    acc = wp.vector(bias[n], length=8)
    for r in range(weight.shape[1]):
        i = index[n, r]
        w = weight[n, r]
        for k in range(8):
            acc[k] += w * x[wp.min(b0 + k, last), i]
    for k in range(8):
        if b0 + k <= last:
            v = acc[k]
            if relu != 0 and v < y_out.dtype(0.0):
                v = y_out.dtype(0.0)  # not wp.max: NaN must stay NaN, as in torch.relu
            y_out[b0 + k, n] = v


@wp.kernel
def linet_grad_x(
    grad_y: wp.array2d(dtype=Any),
    weight_flat: wp.array(dtype=Any),
    t_offsets: wp.array(dtype=wp.int32),
    t_entries: wp.array(dtype=wp.int32),
    receptive_field: int,
    offset: int,
    grad_x_out: wp.array2d(dtype=Any),
):
    """grad_x[b, i] = sum over connections e = n * R + r that read input i of weight[e] * grad_y[b, n].

    ``t_offsets``/``t_entries`` are the CSR transpose of the index matrix. Thread t = blk * N_in + i
    computes rows b = 8 blk .. 8 blk + 7 (clamped as in the forward kernel).
    """
    t = offset + wp.tid()
    num_in = grad_x_out.shape[1]
    blk = t // num_in
    i = t - blk * num_in
    last = grad_y.shape[0] - 1
    b0 = blk * 8
    acc = wp.vector(grad_x_out.dtype(0.0), length=8)
    for k in range(t_offsets[i], t_offsets[i + 1]):
        e = t_entries[k]
        n = e // receptive_field
        w = weight_flat[e]
        for j in range(8):
            acc[j] += w * grad_y[wp.min(b0 + j, last), n]
    for j in range(8):
        if b0 + j <= last:
            grad_x_out[b0 + j, i] = acc[j]


@wp.func
def _masked(g: Any, y: Any, relu: int):
    """The upstream gradient g, zeroed where a fused ReLU clamped the output y to zero."""
    if relu != 0 and y <= type(y)(0.0):
        return type(y)(0.0)
    return g


@wp.kernel
def linet_grad_weight(
    x: wp.array2d(dtype=Any),
    grad_y: wp.array2d(dtype=Any),
    y: wp.array2d(dtype=Any),
    index: wp.array2d(dtype=wp.int32),
    relu: int,
    offset: int,
    grad_weight_out: wp.array2d(dtype=Any),
):
    """grad_weight[n, r] = sum_b g[b, n] * x[b, index[n, r]], g = grad_y masked by y > 0 if ``relu``.

    Thread t = n * ceil(R / 4) + q computes connections r = 4 q .. 4 q + 3 of unit n (clamped to
    R - 1, never stored past it).
    """
    t = offset + wp.tid()
    R = index.shape[1]
    groups = (R + 3) // 4
    n = t // groups
    r0 = (t - n * groups) * 4
    cols = wp.vector(index[n, r0], length=4)
    for k in range(1, 4):
        cols[k] = index[n, wp.min(r0 + k, R - 1)]
    acc = wp.vector(grad_weight_out.dtype(0.0), length=4)
    for b in range(x.shape[0]):
        g = _masked(grad_y[b, n], y[b, n], relu)
        for k in range(4):
            acc[k] += g * x[b, cols[k]]
    for k in range(4):
        if r0 + k < R:
            grad_weight_out[n, r0 + k] = acc[k]


@wp.kernel
def linet_grad_bias(
    grad_y: wp.array2d(dtype=Any),
    y: wp.array2d(dtype=Any),
    relu: int,
    offset: int,
    grad_bias_out: wp.array(dtype=Any),
):
    """grad_bias[n] = sum_b g[b, n], g = grad_y masked by y > 0 if ``relu``; thread t = n."""
    n = offset + wp.tid()
    acc = grad_bias_out.dtype(0.0)
    for b in range(grad_y.shape[0]):
        acc += _masked(grad_y[b, n], y[b, n], relu)
    grad_bias_out[n] = acc


def _overload_all() -> None:
    for wdt in (wp.float32, wp.float64):
        a1, a2 = wp.array(dtype=wdt), wp.array2d(dtype=wdt)
        i1, i2 = wp.array(dtype=wp.int32), wp.array2d(dtype=wp.int32)
        wp.overload(linet_forward, [a2, a2, a1, i2, int, int, a2])
        wp.overload(linet_grad_x, [a2, a1, i1, i1, int, int, a2])
        wp.overload(linet_grad_weight, [a2, a2, a2, i2, int, int, a2])
        wp.overload(linet_grad_bias, [a2, a2, int, int, a1])


_overload_all()


# --------------------------------------------------------------------------------------------------
# Connectivity plan: validated int32 index and its CSR transpose, cached per index tensor
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LinetPlan:
    """Everything the kernels need about one connectivity matrix, on one device.

    index:     [N, R] int32, values in [0, in_features)
    t_offsets: [in_features + 1] int32; the connections reading input i are t_entries[t_offsets[i]:t_offsets[i+1]]
    t_entries: [N * R] int32, flat connection ids e = n * R + r, grouped by the input they read
    """

    index: Tensor
    t_offsets: Tensor
    t_entries: Tensor
    in_features: int

    @property
    def num_units(self) -> int:
        return self.index.shape[0]

    @property
    def receptive_field(self) -> int:
        return self.index.shape[1]


def build_plan(index: Tensor, in_features: int) -> LinetPlan:
    """Validate ``index`` [N, R] (int32/int64, values in [0, in_features)) and build its transpose."""
    if not isinstance(index, Tensor):
        raise ValueError(f"index: expected a torch.Tensor, got {type(index).__name__}")
    if index.dim() != 2:
        raise ValueError(f"index: expected shape [N, R], got rank {index.dim()} shape {tuple(index.shape)}")
    if index.dtype not in _INDEX_DTYPES:
        raise ValueError(f"index: expected dtype int32 or int64, got {index.dtype}")
    if not isinstance(in_features, (int, np.integer)) or in_features < 1:
        raise ValueError(f"in_features: expected a positive int, got {in_features!r}")
    in_features = int(in_features)
    if in_features >= 2**31 or index.numel() >= 2**31:
        raise ValueError(
            f"index: sizes must fit int32 (in_features={in_features}, N*R={index.numel()}), got larger"
        )
    if index.numel():
        lo, hi = int(index.min()), int(index.max())
        if lo < 0 or hi >= in_features:
            raise ValueError(
                f"index: expected values in [0, {in_features}) (in_features={in_features}), "
                f"got values in [{lo}, {hi}]"
            )
    idx32 = index.to(torch.int32).contiguous()
    flat = idx32.reshape(-1).to(torch.int64)
    # Stable sort keeps the connections of one input in (n, r) order: a deterministic summation order.
    order = torch.sort(flat, stable=True).indices
    counts = torch.bincount(flat, minlength=in_features)
    t_offsets = torch.zeros(in_features + 1, dtype=torch.int64, device=index.device)
    torch.cumsum(counts, 0, out=t_offsets[1:])
    return LinetPlan(idx32, t_offsets.to(torch.int32), order.to(torch.int32).contiguous(), in_features)


# id(index) -> (weak reference to index, index._version, in_features, plan). Tensors cannot key a
# WeakKeyDictionary (their == is elementwise), so entries are keyed by id and evicted by a weakref callback.
_plan_cache: dict[int, tuple[weakref.ref, int, int, LinetPlan]] = {}
_plan_lock = threading.Lock()


def _evict(key: int, cache=_plan_cache, lock=_plan_lock):
    # The cache and lock are bound now: at interpreter exit the module globals may already be gone.
    def callback(_ref):
        with lock:
            cache.pop(key, None)

    return callback


def plan_for(index: Tensor, in_features: int) -> LinetPlan:
    """The cached :class:`LinetPlan` of ``index``; rebuilt when the tensor is modified in place."""
    key = id(index)
    with _plan_lock:
        hit = _plan_cache.get(key)
    if hit is not None and hit[0]() is index and hit[1] == index._version and hit[2] == in_features:
        return hit[3]
    plan = build_plan(index, in_features)
    with _plan_lock:
        _plan_cache[key] = (weakref.ref(index, _evict(key)), index._version, in_features, plan)
    return plan


# --------------------------------------------------------------------------------------------------
# Host functions
# --------------------------------------------------------------------------------------------------


def _check_tensor(name: str, t: Any, rank: int, like: Tensor | None = None) -> None:
    if not isinstance(t, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if t.dim() != rank:
        raise ValueError(f"{name}: expected rank {rank}, got rank {t.dim()} shape {tuple(t.shape)}")
    if like is None:
        if t.dtype not in _FLOATS:
            raise ValueError(f"{name}: expected dtype float32 or float64, got {t.dtype}")
        if t.device.type not in ("cpu", "cuda"):
            raise ValueError(f"{name}: expected a cpu or cuda tensor, got device {t.device}")
    else:
        if t.dtype != like.dtype:
            raise ValueError(f"{name}: expected dtype {like.dtype} (the dtype of x), got {t.dtype}")
        if t.device != like.device:
            raise ValueError(f"{name}: expected device {like.device} (the device of x), got {t.device}")


def _wp(t: Tensor) -> wp.array:
    return wp.from_torch(t, requires_grad=False)


def _split(kernel, dim: int, inputs: list, outputs: list, device: str) -> None:
    _launch.launch_split(kernel, dim, inputs, outputs, device)


def _blocks(rows: int, block: int) -> int:
    return (rows + block - 1) // block


def forward(x: Tensor, weight: Tensor, bias: Tensor, plan: LinetPlan, relu: bool = False) -> Tensor:
    """Kernel forward: y [B, N] (no autograd). Inputs must already be validated and contiguous."""
    B = x.shape[0]
    N = plan.num_units
    y = torch.empty(B, N, dtype=x.dtype, device=x.device)
    if B and N:
        _split(
            linet_forward,
            _blocks(B, BATCH_BLOCK) * N,
            [_wp(x), _wp(weight), _wp(bias), _wp(plan.index), int(relu)],
            [_wp(y)],
            _launch.warp_device(x.device),
        )
    return y


def backward(
    x: Tensor | None,
    weight: Tensor,
    plan: LinetPlan,
    grad_y: Tensor,
    y: Tensor | None,
    need: tuple[bool, bool, bool],
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """Kernel vector-Jacobian products (grad_x, grad_weight, grad_bias); ``need`` says which to compute.

    ``grad_y`` [B, N] is the gradient at the layer's output; ``y`` is the fused-ReLU output whose sign
    masks it (None: no activation). ``x`` is needed only for grad_weight.

    When grad_x is needed the masked gradient is materialised once ([B, N], smaller than grad_x) so the
    hot grad_x kernel reads one array; otherwise (the first layer: the ONV needs no gradient, and
    grad_y is then the largest activation gradient of the net) the weight and bias kernels mask on
    the fly and no copy of grad_y is made.
    """
    dev = _launch.warp_device(grad_y.device)
    relu = int(y is not None)
    if relu and need[0]:
        grad_y = torch.ops.aten.threshold_backward(grad_y, y, 0)
        relu = 0
    g = _wp(grad_y)
    yy = _wp(y) if relu else g  # unread when relu == 0
    B, N = grad_y.shape
    R = plan.receptive_field
    grad_x = grad_w = grad_b = None
    if need[0]:
        grad_x = torch.empty(B, plan.in_features, dtype=grad_y.dtype, device=grad_y.device)
        if B and plan.in_features:
            _split(
                linet_grad_x,
                _blocks(B, BATCH_BLOCK) * plan.in_features,
                [g, _wp(weight.reshape(-1)), _wp(plan.t_offsets), _wp(plan.t_entries), R],
                [_wp(grad_x)],
                dev,
            )
    if need[1]:
        grad_w = torch.zeros(N, R, dtype=grad_y.dtype, device=grad_y.device)
        if B and N and R:
            groups = _blocks(R, CONN_BLOCK)
            _split(linet_grad_weight, N * groups, [_wp(x), g, yy, _wp(plan.index), relu], [_wp(grad_w)], dev)
    if need[2]:
        grad_b = torch.empty(N, dtype=grad_y.dtype, device=grad_y.device)
        _split(linet_grad_bias, N, [g, yy, relu], [_wp(grad_b)], dev)
    return grad_x, grad_w, grad_b


class _LocallyConnectedFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weight, bias, plan, relu):
        y = forward(x, weight, bias, plan, relu)
        ctx.plan = plan
        ctx.relu = relu
        # x is needed only for grad_weight; with a fused ReLU the output's sign masks the gradient.
        ctx.save_for_backward(
            x if ctx.needs_input_grad[1] else None, weight, y if relu else None
        )
        return y

    @staticmethod
    def backward(ctx, grad_y):
        x, weight, y = ctx.saved_tensors
        need = tuple(ctx.needs_input_grad[:3])
        grad_x, grad_w, grad_b = backward(x, weight, ctx.plan, grad_y.contiguous(), y, need)
        return grad_x, grad_w, grad_b, None, None


def locally_connected(
    x: Tensor,
    weight: Tensor,
    bias: Tensor,
    index: Tensor,
    *,
    relu: bool = False,
    plan: LinetPlan | None = None,
) -> Tensor:
    """The locally-connected irregular layer, differentiable in ``x``, ``weight`` and ``bias``.

    Args:
        x:      [B, N_in] float32 or float64 (made contiguous if it is not).
        weight: [N, R] same dtype and device as x; one weight per connection, no sharing.
        bias:   [N]    same dtype and device as x.
        index:  [N, R] int32 or int64, values in [0, N_in); repeats allowed. Its validated int32 copy
                and CSR transpose are built once per index tensor (and per in-place modification) and cached.
        relu:   fuse a ReLU into the output (its backward masks by the saved output's sign).
        plan:   a prebuilt :class:`LinetPlan` for ``index`` (skips the cache lookup).

    Returns:
        y: [B, N], ``y[b, n] = bias[n] + sum_r weight[n, r] * x[b, index[n, r]]`` (then ReLU if asked).

    Raises:
        ValueError: on a wrong rank, shape, dtype or device, an out-of-range index, or non-finite
        weight or bias, naming the argument, what was expected and what came.
    """
    _check_tensor("x", x, 2)
    _check_tensor("weight", weight, 2, like=x)
    _check_tensor("bias", bias, 1, like=x)
    if not isinstance(index, Tensor):
        raise ValueError(f"index: expected a torch.Tensor, got {type(index).__name__}")
    if index.device != x.device:
        raise ValueError(f"index: expected device {x.device} (the device of x), got {index.device}")
    if tuple(index.shape) != tuple(weight.shape):
        raise ValueError(
            f"index: expected shape {tuple(weight.shape)} (the shape of weight, [N, R]), got {tuple(index.shape)}"
        )
    if bias.shape[0] != weight.shape[0]:
        raise ValueError(f"bias: expected shape ({weight.shape[0]},) (N = weight.shape[0]), got {tuple(bias.shape)}")
    if plan is None:
        plan = plan_for(index, x.shape[1])
    elif plan.in_features != x.shape[1] or tuple(plan.index.shape) != tuple(index.shape):
        raise ValueError(
            f"plan: expected a plan for index {tuple(index.shape)} over {x.shape[1]} inputs, "
            f"got one for {tuple(plan.index.shape)} over {plan.in_features}"
        )
    if plan.index.device != x.device:
        raise ValueError(f"plan: expected device {x.device} (the device of x), got {plan.index.device}")
    with torch.no_grad():
        if not bool(torch.isfinite(weight).all()):
            raise ValueError("weight: expected finite values, got NaN or inf")
        if not bool(torch.isfinite(bias).all()):
            raise ValueError("bias: expected finite values, got NaN or inf")
    _launch.init()
    return _LocallyConnectedFn.apply(x.contiguous(), weight.contiguous(), bias.contiguous(), plan, bool(relu))
