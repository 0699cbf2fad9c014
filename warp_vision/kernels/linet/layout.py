"""Feature-major activations for the liNet kernels: 64-lane vectors and the transposes into them.

With a batch B that is a multiple of 64, the liNet op keeps activations *feature-major*: ``[features,
B]`` in memory, handed on as ``[B, features]`` views (``t.t()`` contiguous). A Warp array element is
then a vector of 64 batch rows, so the kernels in ``kernels/linet/kernels.py`` gather one input's rows with
one contiguous load. This module holds that layout: the vector types, the zero-copy views of a tensor
as vector arrays, and the transpose of a batch-major x (an ONV batch) into it. The tests compare the
transposes with torch's ``x.t()``.
"""

from __future__ import annotations

from typing import Any

import torch
import warp as wp
from torch import Tensor

from warp_vision.kernels import launch as _launch

wp.set_module_options({"enable_backward": False})

#: Batch rows in one feature-major vector. The kernels here and in kernels.py spell it as the literal 64.
LANES = 64

#: The 64-lane vector type of each scalar type, for feature-major arrays.
VEC_TYPES = {t: wp.types.vector(length=LANES, dtype=t) for t in (wp.float32, wp.float64, wp.float16, wp.bfloat16)}


@wp.kernel
def transpose_rows(x: wp.array2d(dtype=Any), offset: int, xT_out: wp.array2d(dtype=Any)):
    """xT_out[f, c] = (x[64 c, f], ..., x[64 c + 63, f]): a batch-major x to 64-lane feature-major.

    Thread t = c * F + f gathers one column of a 64-row block: the 64 cache lines it reads serve the
    next 15 threads (features f + 1 ...) too, and its output is one contiguous 64-lane store.
    """
    t = offset + wp.tid()
    F = x.shape[1]
    c = t // F
    f = t - c * F
    v = xT_out.dtype(x.dtype(0.0))
    for k in range(64):
        v[k] = x[c * 64 + k, f]
    xT_out[f, c] = v


# An 8 x 8 block transpose in native code, for 4-byte (float32) and 2-byte (float16, bfloat16: moved as
# int16 bits) elements: the kernel language has no lane shuffles, and the scalar gather above moves one
# element per load. With AVX2 (Warp compiles CPU kernels with -march=native) the block is eight 32- (or
# 16-) byte loads, 24 shuffles and eight stores; elsewhere (CUDA, other CPUs, the ragged last block) it
# is a plain loop, and on the CPU it beats both transpose_rows and torch's x.t().contiguous().
def _tile8_snippet(elem: str) -> str:
    """The native 8 x 8 block transpose for elements of C type ``elem`` (4 or 2 bytes): eight rows of 8
    loaded, shuffled (the same three interleaving stages for any element size) and stored."""
    rowbytes = {"float": 32, "short": 16}[elem]
    return _TILE8_TEMPLATE.replace("ELEM", elem).replace("ROWBYTES", str(rowbytes))


_TILE8_TEMPLATE = r"""
    const ELEM* src = (const ELEM*)x.data;
    ELEM* dst = (ELEM*)out.data;
#if defined(__AVX2__) && !defined(__CUDA_ARCH__)
    if (f0 + 8 <= F) {
        typedef ELEM v8 __attribute__((ext_vector_type(8)));
        const ELEM* s = src + (size_t)k0 * F + f0;
        ELEM* d = dst + (size_t)f0 * B + k0;
        v8 r0, r1, r2, r3, r4, r5, r6, r7;
        __builtin_memcpy(&r0, s, ROWBYTES); __builtin_memcpy(&r1, s + (size_t)F, ROWBYTES);
        __builtin_memcpy(&r2, s + 2 * (size_t)F, ROWBYTES); __builtin_memcpy(&r3, s + 3 * (size_t)F, ROWBYTES);
        __builtin_memcpy(&r4, s + 4 * (size_t)F, ROWBYTES); __builtin_memcpy(&r5, s + 5 * (size_t)F, ROWBYTES);
        __builtin_memcpy(&r6, s + 6 * (size_t)F, ROWBYTES); __builtin_memcpy(&r7, s + 7 * (size_t)F, ROWBYTES);
        // interleave pairs of rows, then pairs of pairs, then the 128-bit halves
        v8 t0 = __builtin_shufflevector(r0, r1, 0, 8, 1, 9, 4, 12, 5, 13);
        v8 t1 = __builtin_shufflevector(r0, r1, 2, 10, 3, 11, 6, 14, 7, 15);
        v8 t2 = __builtin_shufflevector(r2, r3, 0, 8, 1, 9, 4, 12, 5, 13);
        v8 t3 = __builtin_shufflevector(r2, r3, 2, 10, 3, 11, 6, 14, 7, 15);
        v8 t4 = __builtin_shufflevector(r4, r5, 0, 8, 1, 9, 4, 12, 5, 13);
        v8 t5 = __builtin_shufflevector(r4, r5, 2, 10, 3, 11, 6, 14, 7, 15);
        v8 t6 = __builtin_shufflevector(r6, r7, 0, 8, 1, 9, 4, 12, 5, 13);
        v8 t7 = __builtin_shufflevector(r6, r7, 2, 10, 3, 11, 6, 14, 7, 15);
        v8 u0 = __builtin_shufflevector(t0, t2, 0, 1, 8, 9, 4, 5, 12, 13);
        v8 u1 = __builtin_shufflevector(t0, t2, 2, 3, 10, 11, 6, 7, 14, 15);
        v8 u2 = __builtin_shufflevector(t1, t3, 0, 1, 8, 9, 4, 5, 12, 13);
        v8 u3 = __builtin_shufflevector(t1, t3, 2, 3, 10, 11, 6, 7, 14, 15);
        v8 u4 = __builtin_shufflevector(t4, t6, 0, 1, 8, 9, 4, 5, 12, 13);
        v8 u5 = __builtin_shufflevector(t4, t6, 2, 3, 10, 11, 6, 7, 14, 15);
        v8 u6 = __builtin_shufflevector(t5, t7, 0, 1, 8, 9, 4, 5, 12, 13);
        v8 u7 = __builtin_shufflevector(t5, t7, 2, 3, 10, 11, 6, 7, 14, 15);
        v8 o0 = __builtin_shufflevector(u0, u4, 0, 1, 2, 3, 8, 9, 10, 11);
        v8 o1 = __builtin_shufflevector(u1, u5, 0, 1, 2, 3, 8, 9, 10, 11);
        v8 o2 = __builtin_shufflevector(u2, u6, 0, 1, 2, 3, 8, 9, 10, 11);
        v8 o3 = __builtin_shufflevector(u3, u7, 0, 1, 2, 3, 8, 9, 10, 11);
        v8 o4 = __builtin_shufflevector(u0, u4, 4, 5, 6, 7, 12, 13, 14, 15);
        v8 o5 = __builtin_shufflevector(u1, u5, 4, 5, 6, 7, 12, 13, 14, 15);
        v8 o6 = __builtin_shufflevector(u2, u6, 4, 5, 6, 7, 12, 13, 14, 15);
        v8 o7 = __builtin_shufflevector(u3, u7, 4, 5, 6, 7, 12, 13, 14, 15);
        __builtin_memcpy(d, &o0, ROWBYTES); __builtin_memcpy(d + (size_t)B, &o1, ROWBYTES);
        __builtin_memcpy(d + 2 * (size_t)B, &o2, ROWBYTES); __builtin_memcpy(d + 3 * (size_t)B, &o3, ROWBYTES);
        __builtin_memcpy(d + 4 * (size_t)B, &o4, ROWBYTES); __builtin_memcpy(d + 5 * (size_t)B, &o5, ROWBYTES);
        __builtin_memcpy(d + 6 * (size_t)B, &o6, ROWBYTES); __builtin_memcpy(d + 7 * (size_t)B, &o7, ROWBYTES);
        return;
    }
#endif
    for (int a = 0; a < 8 && f0 + a < F; ++a)
        for (int c = 0; c < 8; ++c)
            dst[(size_t)(f0 + a) * B + k0 + c] = src[(size_t)(k0 + c) * F + f0 + a];
"""
_TILE8_SNIPPET = _tile8_snippet("float")


@wp.func_native(_TILE8_SNIPPET)
def _transpose_tile8(x: wp.array(dtype=wp.float32), F: int, B: int, k0: int, f0: int, out: wp.array(dtype=wp.float32)):
    """out[f0 + a, k0 + c] = x[k0 + c, f0 + a] for a, c in 0..7 (a < F - f0); x [B, F] and out
    [F, B] contiguous, flattened."""
    ...


@wp.kernel
def transpose_tiles(x: wp.array(dtype=wp.float32), F: int, B: int, offset: int, out: wp.array(dtype=wp.float32)):
    """out = x.t() for a contiguous float32 x [B, F] (B a multiple of 8), flattened: thread t is the
    8 x 8 block of features 8 (t // (B / 8)) .. + 7 and rows 8 (t % (B / 8)) .. + 7, so one
    thread after another fill a block of eight whole output rows."""
    t = offset + wp.tid()
    row_blocks = B // 8
    fb = t // row_blocks
    _transpose_tile8(x, F, B, (t - fb * row_blocks) * 8, fb * 8, out)


@wp.func_native(_tile8_snippet("short"))
def _transpose_tile8_16(x: wp.array(dtype=wp.int16), F: int, B: int, k0: int, f0: int, out: wp.array(dtype=wp.int16)):
    """:func:`_transpose_tile8` for 2-byte elements."""
    ...


@wp.kernel
def transpose_tiles_16(x: wp.array(dtype=wp.int16), F: int, B: int, offset: int, out: wp.array(dtype=wp.int16)):
    """:func:`transpose_tiles` for a 2-byte x (float16 or bfloat16 seen as int16 bits)."""
    t = offset + wp.tid()
    row_blocks = B // 8
    fb = t // row_blocks
    _transpose_tile8_16(x, F, B, (t - fb * row_blocks) * 8, fb * 8, out)


for _wdt in (wp.float32, wp.float64, wp.float16, wp.bfloat16):
    wp.overload(transpose_rows, [wp.array2d(dtype=_wdt), int, wp.array2d(dtype=VEC_TYPES[_wdt])])


def warp_array(t: Tensor) -> wp.array:
    """``t`` as a Warp array of its own shape and dtype (zero-copy, no gradient)."""
    return wp.from_torch(t, requires_grad=False)


def feature_major(t: Tensor) -> bool:
    """Whether the [B, F] tensor ``t`` is a view of a contiguous [F, B] buffer (``t.t()`` contiguous)
    with B a positive multiple of 64: the layout the vectorised kernels read and write."""
    return t.dim() == 2 and t.shape[0] > 0 and t.shape[0] % LANES == 0 and t.t().is_contiguous()


def _vec(tT: Tensor) -> wp.array:
    """A contiguous [F, B] tensor as a Warp [F, B / 64] array of 64-lane vectors (zero-copy)."""
    F, B = tT.shape
    return wp.from_torch(tT.view(F, B // LANES, LANES), dtype=VEC_TYPES[wp.dtype_from_torch(tT.dtype)],
                         requires_grad=False)


def flat_vectors(tT: Tensor) -> wp.array:
    """A contiguous [F, B] tensor as a flat Warp array of F * B / 64 64-lane vectors (zero-copy):
    the vectors of feature f are elements f * (B / 64) ... f * (B / 64) + B / 64 - 1."""
    return wp.from_torch(tT.view(-1, LANES), dtype=VEC_TYPES[wp.dtype_from_torch(tT.dtype)], requires_grad=False)


#: A batch-major x up to this size (B a multiple of 64) is copied to feature-major for the vectorised
#: kernels (the copy is what backward saves); a larger one is read in place by the batch-major
#: kernels, so a huge ONV batch is never held twice.
TRANSPOSE_MAX_BYTES = 256 * 2**20


def as_feature_major(x: Tensor) -> Tensor:
    """``x`` [B, F] in the layout the kernels read fastest: x itself if it is feature-major or B is
    not a multiple of 64 or it is larger than :data:`TRANSPOSE_MAX_BYTES`; else a feature-major copy
    in x's dtype (one Warp transpose launch: 8 x 8 blocks for float32, float16 and bfloat16, 64-row
    gathers for float64)."""
    B, F = x.shape
    if feature_major(x) or B % LANES or not F or x.numel() * x.element_size() > TRANSPOSE_MAX_BYTES:
        return x
    _launch.init()
    xT = torch.empty(F, B, dtype=x.dtype, device=x.device)
    dev = _launch.warp_device(x.device)
    if x.dtype == torch.float32:
        _launch.launch_split(transpose_tiles, (F + 7) // 8 * (B // 8), [warp_array(x.reshape(-1)), F, B],
                             [warp_array(xT.reshape(-1))], dev)
    elif x.element_size() == 2:
        _launch.launch_split(transpose_tiles_16, (F + 7) // 8 * (B // 8),
                             [warp_array(x.reshape(-1).view(torch.int16)), F, B],
                             [warp_array(xT.reshape(-1).view(torch.int16))], dev)
    else:
        _launch.launch_split(transpose_rows, (B // LANES) * F, [warp_array(x)], [_vec(xT)], dev)
    return xT.t()
