"""Locally-connected irregular layer (the liNet layer): the Warp kernels of
:mod:`warp_vision.kernels.linet.kernels` as a differentiable torch op.

    y[b, n] = bias[n] + sum_r weight[n, r] * x[b, index[n, r]]        (optionally followed by ReLU)

:func:`locally_connected` validates its arguments, looks up the connectivity's plan (the validated
int32 index and, for grad_x, its CSR transpose: built once per index tensor and cached,
:func:`plan_for`), and runs :func:`forward` and :func:`backward` inside a ``torch.autograd.Function``.
The kernels are gathers, so every launch is split across CPU threads with bit-identical results.

Two kernel families share the maths. With B a multiple of 64 activations are *feature-major*
(``[features, B]`` in memory, handed on as ``[B, features]`` views) and the ``*_fm`` kernels read
each input's 64 batch rows as one vector: one contiguous load, 8-wide SIMD arithmetic, and no index
arithmetic per element. A batch-major x is transposed to that layout first
(:func:`warp_vision.kernels.linet.layout.as_feature_major`) unless it is huge. Other batch sizes use
the batch-major kernels, which take any strides. :mod:`warp_vision.kernels.linet.reference` holds the
plain-torch maths the tests compare against.
"""

from __future__ import annotations

import threading
import weakref
from typing import Any

import numpy as np
import torch
from torch import Tensor

from warp_vision.kernels import launch as _launch
from warp_vision.kernels.linet.kernels import (
    BATCH_BLOCK,
    CONN_BLOCK,
    linet_forward,
    linet_forward_fm,
    linet_grad_bias,
    linet_grad_bias_fm,
    linet_grad_weight,
    linet_grad_weight_fm,
    linet_grad_x,
    linet_grad_x_fm,
)
from warp_vision.kernels.linet.layout import LANES, as_feature_major, feature_major, flat_vectors, warp_array

_FLOATS = (torch.float32, torch.float64)
#: x dtypes read with float32 weights: widened exactly on load, accumulated in float32
_HALVES = (torch.float16, torch.bfloat16)
_INDEX_DTYPES = (torch.int32, torch.int64)


# --------------------------------------------------------------------------------------------------
# Connectivity plan: a private, validated int32 copy of the index and its CSR transpose, cached per
# index tensor and content
# --------------------------------------------------------------------------------------------------


class LinetPlan:
    """Everything the kernels need about one connectivity matrix, on one device.

    source:    [N, R] a private copy of the index as given (its dtype): what a later call's index must
               equal for the plan to serve it
    index:     [N, R] int32, values in [0, in_features): the kernels read this private copy only, so
               writes to the caller's tensor (through torch, numpy or ``.data``) can never make them read
               out of bounds
    t_offsets: [in_features + 1] int32; the connections reading input i are t_entries[t_offsets[i]:t_offsets[i+1]]
    t_entries: [N * R] int32, flat connection ids e = n * R + r, grouped by the input they read
    t_units:   [N * R] int32, the unit n = e // R of each entry of t_entries

    The transposed structure (the last three) is built on first use: only a grad_x needs it, and the
    ONV layer, the largest, never computes one (at 3P = 1.28e7 it would be ~150 MB).
    """

    def __init__(self, source: Tensor, index: Tensor, in_features: int):
        self.source = source
        self.index = index
        self.in_features = in_features
        self._transposed: tuple[Tensor, Tensor, Tensor] | None = None
        self._lock = threading.Lock()

    @property
    def num_units(self) -> int:
        return self.index.shape[0]

    @property
    def receptive_field(self) -> int:
        return self.index.shape[1]

    def transposed(self) -> tuple[Tensor, Tensor, Tensor]:
        """(t_offsets, t_entries, t_units), built once."""
        with self._lock:
            if self._transposed is None:
                flat = self.index.reshape(-1).to(torch.int64)
                # Stable sort keeps the connections of one input in (n, r) order: a deterministic summation order.
                order = torch.sort(flat, stable=True).indices
                counts = torch.bincount(flat, minlength=self.in_features)
                t_offsets = torch.zeros(self.in_features + 1, dtype=torch.int64, device=self.index.device)
                torch.cumsum(counts, 0, out=t_offsets[1:])
                units = torch.div(order, max(1, self.receptive_field), rounding_mode="floor")
                self._transposed = (
                    t_offsets.to(torch.int32), order.to(torch.int32).contiguous(), units.to(torch.int32).contiguous()
                )
            return self._transposed

    @property
    def t_offsets(self) -> Tensor:
        return self.transposed()[0]

    @property
    def t_entries(self) -> Tensor:
        return self.transposed()[1]

    @property
    def t_units(self) -> Tensor:
        return self.transposed()[2]


def build_plan(index: Tensor, in_features: int) -> LinetPlan:
    """Validate ``index`` [N, R] (int32/int64, values in [0, in_features)); its transpose comes on demand."""
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
    source = index.detach().clone(memory_format=torch.contiguous_format)
    return LinetPlan(source, source if source.dtype == torch.int32 else source.to(torch.int32), in_features)


def serves(plan: LinetPlan, index: Tensor, in_features: int) -> bool:
    """Whether ``plan`` was built for ``index``'s current contents over ``in_features`` inputs (one
    comparison of the index with the plan's copy: about 7 ms per 100 MB on this machine's CPU, against
    seconds for the op on an index that large)."""
    return (plan.in_features == in_features and plan.source.dtype == index.dtype
            and plan.source.shape == index.shape and plan.source.device == index.device
            and torch.equal(plan.source, index))


# id(index) -> (weak reference to index, plan). Tensors cannot key a WeakKeyDictionary (their == is
# elementwise), so entries are keyed by id and evicted by a weakref callback; a hit also needs the
# index's content to equal the plan's copy (:func:`serves`), so changes made behind torch's back (a
# numpy array under ``torch.from_numpy``, ``.data``) are seen.
_plan_cache: dict[int, tuple[weakref.ref, LinetPlan]] = {}
_plan_lock = threading.Lock()


def _evict(key: int, cache=_plan_cache, lock=_plan_lock):
    # The cache and lock are bound now: at interpreter exit the module globals may already be gone.
    def callback(_ref):
        with lock:
            cache.pop(key, None)

    return callback


def plan_for(index: Tensor, in_features: int) -> LinetPlan:
    """The cached :class:`LinetPlan` of ``index``; rebuilt (and validated again) whenever the tensor's
    contents differ from the plan's copy, however they were changed."""
    key = id(index)
    with _plan_lock:
        hit = _plan_cache.get(key)
    if hit is not None and hit[0]() is index and serves(hit[1], index, in_features):
        return hit[1]
    plan = build_plan(index, in_features)
    with _plan_lock:
        _plan_cache[key] = (weakref.ref(index, _evict(key)), plan)
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
        if t.dtype not in _FLOATS + _HALVES:
            raise ValueError(f"{name}: expected dtype float32, float64, float16 or bfloat16, got {t.dtype}")
        if t.device.type not in ("cpu", "cuda"):
            raise ValueError(f"{name}: expected a cpu or cuda tensor, got device {t.device}")
    else:
        want = torch.float32 if like.dtype in _HALVES else like.dtype
        if t.dtype != want:
            why = f"float32 weights go with a {like.dtype} x" if like.dtype in _HALVES else "the dtype of x"
            raise ValueError(f"{name}: expected dtype {want} ({why}), got {t.dtype}; convert x (x.to({t.dtype})) "
                             f"or the layer (.to({want}))")
        if t.device != like.device:
            raise ValueError(f"{name}: expected device {like.device} (the device of x), got {t.device}")


#: Fewest threads per CPU slice for the feature-major kernels, whose threads each do a whole row.
FM_MIN_PER_SLICE = 256


def launch_kernel(kernel, dim: int, inputs: list, outputs: list, device: str) -> None:
    """Launch one of the liNet kernels over ``dim`` threads, split across CPU threads as the op does
    (``inputs`` without the trailing ``offset``)."""
    heavy = kernel in (linet_forward_fm, linet_grad_x_fm, linet_grad_weight_fm, linet_grad_bias_fm)
    _launch.launch_split(kernel, dim, inputs, outputs, device,
                         min_per_slice=FM_MIN_PER_SLICE if heavy else _launch.MIN_THREADS_PER_SLICE)


def _blocks(rows: int, block: int) -> int:
    return (rows + block - 1) // block


def forward(x: Tensor, weight: Tensor, bias: Tensor, plan: LinetPlan, relu: bool = False) -> Tensor:
    """Kernel forward: y [B, N] (no autograd). Inputs must already be validated.

    With B a multiple of 64, y is returned feature-major (a [B, N] view of a contiguous [N, B]
    buffer), and a feature-major ``x`` is read by the vectorised kernel; otherwise ``x`` may have any
    strides and y is contiguous.
    """
    B = x.shape[0]
    N = plan.num_units
    dev = _launch.warp_device(x.device)
    if B and B % LANES == 0:
        yT = torch.empty(N, B, dtype=weight.dtype, device=x.device)
        if N and feature_major(x):
            launch_kernel(linet_forward_fm, N,
                          [flat_vectors(x.t()), warp_array(weight.reshape(-1)), warp_array(bias),
                           warp_array(plan.index.reshape(-1)), plan.receptive_field, B // LANES, int(relu)],
                          [flat_vectors(yT)], dev)
        elif N:
            launch_kernel(linet_forward, _blocks(B, BATCH_BLOCK) * N,
                          [warp_array(x), warp_array(weight), warp_array(bias), warp_array(plan.index), int(relu)],
                          [warp_array(yT.t())], dev)
        return yT.t()
    y = torch.empty(B, N, dtype=weight.dtype, device=x.device)
    if B and N:
        launch_kernel(
            linet_forward,
            _blocks(B, BATCH_BLOCK) * N,
            [warp_array(x), warp_array(weight), warp_array(bias), warp_array(plan.index), int(relu)],
            [warp_array(y)],
            dev,
        )
    return y


def backward(
    x: Tensor | None,
    weight: Tensor,
    plan: LinetPlan,
    grad_y: Tensor,
    y: Tensor | None,
    need: tuple[bool, bool, bool],
    x_dtype: torch.dtype | None = None,
) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
    """Kernel vector-Jacobian products (grad_x, grad_weight, grad_bias); ``need`` says which to compute.

    ``grad_y`` [B, N] is the gradient at the layer's output; ``y`` is the fused-ReLU output whose sign
    masks it (None: no activation). ``x`` is needed only for grad_weight. grad_x comes in ``x_dtype``
    (default: grad_y's; float16 or bfloat16 for a half x: accumulated in float32, rounded once).

    When grad_x is needed the masked gradient is materialised once ([B, N], smaller than grad_x) so the
    hot grad_x kernel reads one array; otherwise (the first layer: the ONV needs no gradient, and
    grad_y is then the largest activation gradient of the net) the weight and bias kernels mask on
    the fly and no copy of grad_y is made. With B a multiple of 64 the work is feature-major: grad_y
    is read as [N, B] (transposed once if it arrives batch-major) and grad_x comes out feature-major.
    """
    dev = _launch.warp_device(grad_y.device)
    x_dtype = grad_y.dtype if x_dtype is None else x_dtype
    relu = int(y is not None)
    if relu and need[0]:
        grad_y = torch.ops.aten.threshold_backward(grad_y, y, 0)
        relu = 0
    B, N = grad_y.shape
    R = plan.receptive_field
    if B and B % LANES == 0:
        return _backward_fm(x, weight, plan, grad_y, y if relu else None, need, dev, x_dtype)
    grad_y = grad_y.contiguous()
    g = warp_array(grad_y)
    yy = warp_array(y) if relu else g  # unread when relu == 0
    grad_x = grad_w = grad_b = None
    if need[0]:
        grad_x = torch.empty(B, plan.in_features, dtype=x_dtype, device=grad_y.device)
        if B and plan.in_features:
            launch_kernel(
                linet_grad_x,
                _blocks(B, BATCH_BLOCK) * plan.in_features,
                [g, warp_array(weight.reshape(-1)), warp_array(plan.t_offsets), warp_array(plan.t_entries), R],
                [warp_array(grad_x)],
                dev,
            )
    if need[1]:
        grad_w = torch.zeros(N, R, dtype=grad_y.dtype, device=grad_y.device)
        if B and N and R:
            groups = _blocks(R, CONN_BLOCK)
            launch_kernel(linet_grad_weight, N * groups, [warp_array(x), g, yy, warp_array(plan.index), relu],
                          [warp_array(grad_w)], dev)
    if need[2]:
        grad_b = torch.empty(N, dtype=grad_y.dtype, device=grad_y.device)
        launch_kernel(linet_grad_bias, N, [g, yy, relu], [warp_array(grad_b)], dev)
    return grad_x, grad_w, grad_b


def _backward_fm(x, weight, plan, grad_y, y, need, dev, x_dtype):
    """:func:`backward` for B a multiple of 64: feature-major gradients; y (if given) masks grad_y.

    The feature-major kernels take an already masked gradient (:func:`backward` masks it when grad_x
    is needed): it is materialised here for a feature-major x; for a batch-major x (the ONV layer)
    the batch-major weight and bias kernels mask on the fly instead of copying the net's largest
    activation gradient.
    """
    B, N = grad_y.shape
    R = plan.receptive_field
    if y is not None and feature_major(x):
        grad_y = torch.ops.aten.threshold_backward(grad_y, y, 0)
        y = None
    gT = grad_y.t().contiguous()  # a no-op when grad_y comes from the next liNet layer
    g = flat_vectors(gT)
    chunks = B // LANES
    grad_x = grad_w = grad_b = None
    if need[0]:
        gxT = torch.empty(plan.in_features, B, dtype=x_dtype, device=grad_y.device)
        if N and plan.in_features:
            t_offsets, t_entries, t_units = plan.transposed()
            launch_kernel(linet_grad_x_fm, plan.in_features,
                          [g, warp_array(weight.reshape(-1)), warp_array(t_offsets), warp_array(t_entries),
                           warp_array(t_units), chunks],
                          [flat_vectors(gxT)], dev)
        else:
            gxT.zero_()
        grad_x = gxT.t()
    relu = int(y is not None)
    if need[1]:
        grad_w = torch.empty(N, R, dtype=grad_y.dtype, device=grad_y.device)
    if need[2]:
        grad_b = torch.empty(N, dtype=grad_y.dtype, device=grad_y.device)
    if not N:
        return grad_x, grad_w, grad_b
    if need[1] and R and feature_major(x):
        # the bias gradient comes with the weight gradient (into scratch when it is not wanted)
        gb = grad_b if grad_b is not None else torch.empty(N, dtype=grad_y.dtype, device=grad_y.device)
        launch_kernel(linet_grad_weight_fm, N,
                      [flat_vectors(x.t()), g, warp_array(plan.index.reshape(-1)), R, chunks],
                      [warp_array(grad_w.reshape(-1)), warp_array(gb)], dev)
        return grad_x, grad_w, grad_b
    g_bm = warp_array(gT.t())  # the same memory, seen [B, N] by the batch-major kernels
    y_bm = warp_array(y) if relu else g_bm  # unread when relu == 0
    if need[1] and R:
        launch_kernel(linet_grad_weight, N * _blocks(R, CONN_BLOCK),
                      [warp_array(x), g_bm, y_bm, warp_array(plan.index), relu],
                      [warp_array(grad_w)], dev)
    if need[2]:
        if relu:
            launch_kernel(linet_grad_bias, N, [g_bm, y_bm, relu], [warp_array(grad_b)], dev)
        else:
            launch_kernel(linet_grad_bias_fm, N, [g, chunks], [warp_array(grad_b)], dev)
    return grad_x, grad_w, grad_b


class _LocallyConnectedFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, weight, bias, plan, relu):
        x = as_feature_major(x)  # saved below in the layout the backward kernels read fastest
        y = forward(x, weight, bias, plan, relu)
        ctx.plan = plan
        ctx.relu = relu
        ctx.x_dtype = x.dtype
        # x is needed only for grad_weight; with a fused ReLU the output's sign masks the gradient.
        ctx.save_for_backward(
            x if ctx.needs_input_grad[1] else None, weight, y if relu else None
        )
        return y

    @staticmethod
    def backward(ctx, grad_y):
        x, weight, y = ctx.saved_tensors
        need = tuple(ctx.needs_input_grad[:3])
        grad_x, grad_w, grad_b = backward(x, weight, ctx.plan, grad_y.to(weight.dtype), y, need, ctx.x_dtype)
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
        x:      [B, N_in] float32, float64, float16 or bfloat16, batch-major (contiguous) or
                feature-major (``x.t()`` contiguous, as this op returns y when B is a multiple of 64);
                other strides are copied to contiguous first. A half-precision x (an ONV batch as the
                dataset stores it) is read as it is, widened exactly in the kernels: no float32 copy.
        weight: [N, R] x's dtype (float32 for a half x) and device; one weight per connection, no sharing.
        bias:   [N]    weight's dtype, x's device.
        index:  [N, R] int32 or int64, values in [0, N_in); repeats allowed. A validated private int32
                copy and its CSR transpose are built once per index tensor and cached; every call checks
                that the index still holds the same values (however they were changed) and rebuilds if not.
        relu:   fuse a ReLU into the output (its backward masks by the saved output's sign).
        plan:   a prebuilt :class:`LinetPlan` for ``index`` (skips the cache lookup).

    Returns:
        y: [B, N] in weight's dtype, ``y[b, n] = bias[n] + sum_r weight[n, r] * x[b, index[n, r]]`` (then
        ReLU if asked), accumulated in weight's dtype. grad_x (when x requires one) comes in x's dtype.
        When B is a multiple of 64, y is feature-major: a view of a contiguous [N, B] buffer, so a next
        liNet layer reads each input's batch row as one 64-lane vector (the fast path;
        ``python -m warp_vision.bench linet`` measures both layouts).
        Its gradients with respect to x come out in the same layout. Any torch op accepts such a
        view; call ``.contiguous()`` if something needs batch-major memory.

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
    elif not serves(plan, index, x.shape[1]):
        raise ValueError(
            f"plan: expected a plan for this index ({tuple(index.shape)}, {index.dtype}, its current values) over "
            f"{x.shape[1]} inputs, got one for {tuple(plan.index.shape)} over {plan.in_features} built from other "
            "values"
        )
    if plan.index.device != x.device:
        raise ValueError(f"plan: expected device {x.device} (the device of x), got {plan.index.device}")
    with torch.no_grad():
        for name, t in (("weight", weight), ("bias", bias)):
            # One reduction on the common path: a finite sum means finite elements (NaN and inf
            # propagate); a non-finite sum is checked element-wise (it may be an overflow).
            if not bool(torch.isfinite(t.sum())) and not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name}: expected finite values, got NaN or inf")
    _launch.init()
    if not (x.is_contiguous() or x.t().is_contiguous()):
        x = x.contiguous()
    return _LocallyConnectedFn.apply(x, weight.contiguous(), bias.contiguous(), plan, bool(relu))
