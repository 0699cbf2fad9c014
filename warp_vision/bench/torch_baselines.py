"""The best plain-torch implementations of the locally-connected layer we could write, for comparison.

Each is a function ``(x, weight, bias, index) -> y`` differentiable in x, weight and bias, plus any
per-index preparation done once outside the timed region (as the Warp op caches its plan).
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor


def gather_sum(x: Tensor, weight: Tensor, bias: Tensor, index: Tensor) -> Tensor:
    """Advanced-index gather to [B, N, R], multiply, sum; autograd derives the backward (scatter-add)."""
    return bias + (x[:, index] * weight).sum(-1)


class _IndexAddFn(torch.autograd.Function):
    """Gather forward; hand-written backward: grad_x by ``index_add_``, grad_weight by gather-multiply-sum."""

    @staticmethod
    def forward(ctx, x, weight, bias, index_flat, n, r):
        ctx.save_for_backward(x, weight, index_flat)
        ctx.shape = (n, r)
        return bias + (x.index_select(1, index_flat).view(x.shape[0], n, r) * weight).sum(-1)

    @staticmethod
    def backward(ctx, gy):
        x, weight, index_flat = ctx.saved_tensors
        n, r = ctx.shape
        B = x.shape[0]
        gx = gw = gb = None
        if ctx.needs_input_grad[0]:
            gx = torch.zeros_like(x)
            gx.index_add_(1, index_flat, (gy[:, :, None] * weight).view(B, n * r))
        if ctx.needs_input_grad[1]:
            gw = torch.einsum("bn,bnr->nr", gy, x.index_select(1, index_flat).view(B, n, r))
        if ctx.needs_input_grad[2]:
            gb = gy.sum(0)
        return gx, gw, gb, None, None, None


def index_add(x: Tensor, weight: Tensor, bias: Tensor, index_flat: Tensor) -> Tensor:
    """``index_flat`` = index.reshape(-1) as int64 (prepared once)."""
    n, r = weight.shape
    return _IndexAddFn.apply(x, weight, bias, index_flat, n, r)


class CsrPlan:
    """CSR structure of the [N, N_in] sparse weight matrix and of its transpose, built once per index."""

    def __init__(self, index: Tensor, in_features: int):
        n, r = index.shape
        self.n, self.r, self.in_features = n, r, in_features
        flat = index.reshape(-1).long()
        self.crow = torch.arange(0, n * r + 1, r, dtype=torch.int64, device=index.device)
        self.col = flat
        # Transpose: rows = inputs, entries sorted by input; perm maps transposed entries to flat ids.
        self.perm = torch.sort(flat, stable=True).indices
        counts = torch.bincount(flat, minlength=in_features)
        self.crow_t = torch.zeros(in_features + 1, dtype=torch.int64, device=index.device)
        torch.cumsum(counts, 0, out=self.crow_t[1:])
        self.col_t = torch.div(self.perm, r, rounding_mode="floor")


class _CsrFn(torch.autograd.Function):
    """y^T = W_csr @ x^T; grad_x^T = W^T_csr @ grad_y^T; grad_W = sampled_addmm on W's pattern."""

    @staticmethod
    def forward(ctx, x, weight, bias, plan: CsrPlan):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            w_csr = torch.sparse_csr_tensor(plan.crow, plan.col, weight.reshape(-1), (plan.n, plan.in_features))
        ctx.save_for_backward(x, weight)
        ctx.plan = plan
        ctx.w_csr = w_csr
        return (w_csr @ x.t()).t() + bias

    @staticmethod
    def backward(ctx, gy):
        x, weight = ctx.saved_tensors
        plan = ctx.plan
        gx = gw = gb = None
        if ctx.needs_input_grad[0]:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                wt = torch.sparse_csr_tensor(
                    plan.crow_t, plan.col_t, weight.reshape(-1)[plan.perm], (plan.in_features, plan.n)
                )
            gx = (wt @ gy.t()).t()
        if ctx.needs_input_grad[1]:
            gw = torch.sparse.sampled_addmm(ctx.w_csr, gy.t(), x, beta=0.0).values().view(plan.n, plan.r)
        if ctx.needs_input_grad[2]:
            gb = gy.sum(0)
        return gx, gw, gb, None


def csr_matmul(x: Tensor, weight: Tensor, bias: Tensor, plan: CsrPlan) -> Tensor:
    return _CsrFn.apply(x, weight, bias, plan)
