"""Plain-torch reference of the locally-connected irregular layer, written for clarity, not speed.

    y[b, n] = bias[n] + sum_r weight[n, r] * x[b, index[n, r]]

Tests and benchmarks compare :mod:`warp_vision.kernels.linet.op` against these functions. A
half-precision x (float16, bfloat16) goes with float32 weights: it is widened (exactly) to the weights'
dtype, the sums are taken there, and grad_x is rounded to x's dtype at the end, as the op does.
"""

from __future__ import annotations

import torch
from torch import Tensor


def locally_connected_ref(x: Tensor, weight: Tensor, bias: Tensor, index: Tensor) -> Tensor:
    """Forward: x [B, N_in], weight [N, R], bias [N], index [N, R] -> y [B, N]. Differentiable by autograd."""
    gathered = x.to(weight.dtype)[:, index.long()]  # [B, N, R]: x[b, index[n, r]]
    return bias + (gathered * weight).sum(dim=-1)


def locally_connected_backward_ref(
    x: Tensor, weight: Tensor, index: Tensor, grad_y: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """The vector-Jacobian products, spelled out: (grad_x [B, N_in], grad_weight [N, R], grad_bias [N]).

    grad_x[b, i]      = sum over (n, r) with index[n, r] == i of weight[n, r] * grad_y[b, n]
    grad_weight[n, r] = sum_b grad_y[b, n] * x[b, index[n, r]]
    grad_bias[n]      = sum_b grad_y[b, n]
    """
    idx = index.long()
    B, n_in = x.shape
    x_dtype, x = x.dtype, x.to(weight.dtype)
    contrib = grad_y[:, :, None] * weight[None, :, :]  # [B, N, R]
    grad_x = torch.zeros(B, n_in, dtype=x.dtype, device=x.device)
    grad_x.index_add_(1, idx.reshape(-1), contrib.reshape(B, -1))
    grad_weight = (grad_y[:, :, None] * x[:, idx]).sum(dim=0)
    grad_bias = grad_y.sum(dim=0)
    return grad_x.to(x_dtype), grad_weight, grad_bias
