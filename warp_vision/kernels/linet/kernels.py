"""The liNet layer's Warp kernels: forward and hand-written backward of the locally-connected op.

    y[b, n] = bias[n] + sum_r weight[n, r] * x[b, index[n, r]]        (optionally followed by ReLU)

Every kernel here is a *gather*: each Warp thread writes only its own output element, so launches are
deterministic and can be split across CPU threads (:func:`warp_vision.kernels.launch.launch_split`).
All are 1D launches over flattened outputs whose last input, ``offset``, is the first thread of a split
launch. The gradient with respect to ``x`` is a gather over the transposed connectivity (the CSR
arrays of :class:`warp_vision.kernels.linet.op.LinetPlan`). No ``[B, N, R]`` intermediate is ever formed.

Two families share that maths: the batch-major kernels (``linet_forward``, ``linet_grad_x``,
``linet_grad_weight``, ``linet_grad_bias``), which take 2D arrays of any strides and 8 batch rows per
thread, and the feature-major ``*_fm`` kernels, which read each input's 64 batch rows as one vector
(:mod:`warp_vision.kernels.linet.layout`). The backward kernels are written by hand and Warp's automatic
adjoints are off (``enable_backward``): the adjoint of a loop whose trip count is a runtime value is not
reliable, and that of a gather is a scatter a split launch cannot run (docs/ARCHITECTURE.md, Conventions,
"Warp's adjoints are off"). :mod:`warp_vision.kernels.linet.op` chooses and launches them.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warp_vision.kernels.linet.layout import VEC_TYPES

wp.set_module_options({"enable_backward": False})


#: Batch rows one forward / grad_x thread handles: eight independent accumulators hide the latency
#: of the strided gathers (far faster than one row per thread on the CPU backend).
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
            acc[k] += w * weight.dtype(x[wp.min(b0 + k, last), i])  # a half x widens exactly
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
    acc = wp.vector(weight_flat.dtype(0.0), length=8)
    for k in range(t_offsets[i], t_offsets[i + 1]):
        e = t_entries[k]
        n = e // receptive_field
        w = weight_flat[e]
        for j in range(8):
            acc[j] += w * grad_y[wp.min(b0 + j, last), n]
    for j in range(8):
        if b0 + j <= last:
            grad_x_out[b0 + j, i] = grad_x_out.dtype(acc[j])  # rounded once to x's dtype


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
            acc[k] += g * grad_weight_out.dtype(x[b, cols[k]])
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


# Feature-major kernels: activations stored as [features, B] (``y.t()`` contiguous), B a multiple of 64
# (the layout, its vector types and transposes: kernels/linet/layout.py).
# One array element is a vector of 64 batch rows, so a gathered input row is one contiguous 256-byte
# (float32) load with no per-element index arithmetic, and the arithmetic compiles to 8-wide SIMD on
# the CPU (faster than 8-row vectors with eight accumulators per thread).


@wp.func
def _relu_lanes(v: Any):
    """Component-wise ReLU of a vector; NaN stays NaN, as in torch.relu."""
    out = v
    for k in range(64):
        if v[k] < type(v[k])(0.0):
            out[k] = type(v[k])(0.0)
    return out


@wp.func
def _lane_sum(v: Any):
    """Sum of a 64-lane vector by halving (each step independent lane adds: SIMD, not a serial chain)."""
    h = v
    for k in range(32):
        h[k] = h[k] + h[k + 32]
    for k in range(16):
        h[k] = h[k] + h[k + 16]
    for k in range(8):
        h[k] = h[k] + h[k + 8]
    for k in range(4):
        h[k] = h[k] + h[k + 4]
    return (h[0] + h[2]) + (h[1] + h[3])


@wp.kernel
def linet_forward_fm(
    xT: wp.array(dtype=Any),
    weight: wp.array(dtype=Any),
    bias: wp.array(dtype=Any),
    index: wp.array(dtype=wp.int32),
    receptive_field: int,
    chunks: int,
    relu: int,
    offset: int,
    yT_out: wp.array(dtype=Any),
):
    """yT_out[n, c] = (ReLU of) bias[n] + sum_r weight[n, r] * xT[index[n, r], c]; c a vector of 64 rows.

    Every array is flat (1D): ``xT`` and ``yT_out`` hold ``chunks`` = B / 64 vectors per feature,
    ``weight`` and ``index`` are [N, R] flattened. Flat arrays cost one address computation per
    access (2D arrays add a stride multiply and a negative-index wrap per dimension), and the while
    loops are leaner than range()'s runtime-step iterator. Thread t = n loops over the row's vectors (no integer
    division per thread: on the CPU a division costs more than a unit's 20 vector FMAs).
    """
    n = offset + wp.tid()
    e0 = n * receptive_field
    for c in range(chunks):
        acc = yT_out.dtype(bias[n])
        e = e0
        while e < e0 + receptive_field:  # a while loop: leaner than range()'s runtime-step iterator
            acc += weight[e] * yT_out.dtype(xT[index[e] * chunks + c])  # a half x widens exactly
            e += 1
        if relu != 0:
            acc = _relu_lanes(acc)
        yT_out[n * chunks + c] = acc


@wp.kernel
def linet_grad_x_fm(
    gT: wp.array(dtype=Any),
    weight: wp.array(dtype=Any),
    t_offsets: wp.array(dtype=wp.int32),
    t_entries: wp.array(dtype=wp.int32),
    t_units: wp.array(dtype=wp.int32),
    chunks: int,
    offset: int,
    gxT_out: wp.array(dtype=Any),
):
    """gxT_out[i, c] = sum over connections e = n * R + r reading input i of weight[e] * gT[n, c].

    Feature-major twin of :func:`linet_grad_x` on flat arrays (as :func:`linet_forward_fm`);
    thread t = i. ``t_units`` holds each transposed connection's unit n (= e // R, precomputed:
    no division in the loop).
    """
    i = offset + wp.tid()
    k0 = t_offsets[i]
    k1 = t_offsets[i + 1]
    for c in range(chunks):
        acc = gT.dtype(weight.dtype(0.0))
        k = k0
        while k < k1:
            acc += weight[t_entries[k]] * gT[t_units[k] * chunks + c]
            k += 1
        gxT_out[i * chunks + c] = gxT_out.dtype(acc)  # rounded once to x's dtype


@wp.kernel
def linet_grad_weight_fm(
    xT: wp.array(dtype=Any),
    gT: wp.array(dtype=Any),
    index: wp.array(dtype=wp.int32),
    receptive_field: int,
    chunks: int,
    offset: int,
    grad_weight_out: wp.array(dtype=Any),
    grad_bias_out: wp.array(dtype=Any),
):
    """grad_weight[n, r] = sum_b g[b, n] x[b, index[n, r]] and grad_bias[n] = sum_b g[b, n] (g already
    masked); feature-major, flat arrays (``grad_weight_out`` is [N, R] flattened).

    Thread t = n: the bias sum first (the row of g is then in cache), then for each connection
    lane-wise products accumulated over the row's vectors and the lanes summed. Fusing the bias
    saves a launch and a pass over g.
    """
    n = offset + wp.tid()
    bacc = gT.dtype(grad_bias_out.dtype(0.0))
    for c in range(chunks):
        bacc += gT[n * chunks + c]
    grad_bias_out[n] = _lane_sum(bacc)
    e = n * receptive_field
    while e < (n + 1) * receptive_field:
        i = index[e] * chunks
        acc = gT.dtype(grad_weight_out.dtype(0.0))
        for c in range(chunks):
            acc += wp.cw_mul(gT[n * chunks + c], gT.dtype(xT[i + c]))
        grad_weight_out[e] = _lane_sum(acc)
        e += 1


@wp.kernel
def linet_grad_bias_fm(
    gT: wp.array(dtype=Any),
    chunks: int,
    offset: int,
    grad_bias_out: wp.array(dtype=Any),
):
    """grad_bias[n] = sum_b g[b, n] (g already masked); feature-major, flat; thread t = n. For a
    frozen weight: otherwise :func:`linet_grad_weight_fm` computes it."""
    n = offset + wp.tid()
    acc = gT.dtype(grad_bias_out.dtype(0.0))
    for c in range(chunks):
        acc += gT[n * chunks + c]
    grad_bias_out[n] = _lane_sum(acc)


#: the dtypes x may have with float32 weights: float32 itself, and the half types the kernels widen on load
HALF_TYPES = (wp.float16, wp.bfloat16)


def _overload(xdt, wdt) -> None:
    """The kernels for an x of ``xdt`` with weights, bias, y and the gradients of ``wdt`` (grad_x: ``xdt``)."""
    x2, a1, a2 = wp.array2d(dtype=xdt), wp.array(dtype=wdt), wp.array2d(dtype=wdt)
    i1, i2 = wp.array(dtype=wp.int32), wp.array2d(dtype=wp.int32)
    wp.overload(linet_forward, [x2, a2, a1, i2, int, int, a2])
    wp.overload(linet_grad_x, [a2, a1, i1, i1, int, int, x2])
    wp.overload(linet_grad_weight, [x2, a2, a2, i2, int, int, a2])
    xv, v1 = wp.array(dtype=VEC_TYPES[xdt]), wp.array(dtype=VEC_TYPES[wdt])
    wp.overload(linet_forward_fm, [xv, a1, a1, i1, int, int, int, int, v1])
    wp.overload(linet_grad_x_fm, [v1, a1, i1, i1, i1, int, int, xv])
    wp.overload(linet_grad_weight_fm, [xv, v1, i1, int, int, int, a1, a1])
    if xdt == wdt:
        wp.overload(linet_grad_bias, [a2, a2, int, int, a1])
        wp.overload(linet_grad_bias_fm, [v1, int, int, a1])


def _overload_all() -> None:
    for wdt in (wp.float32, wp.float64):
        _overload(wdt, wdt)
    for hdt in HALF_TYPES:
        _overload(hdt, wp.float32)


_overload_all()
