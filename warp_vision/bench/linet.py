"""`python -m warp_vision.bench linet`: the locally-connected layer, Warp kernels vs plain torch.

For each configuration (B, N_in -> N, R) it times forward, backward and forward+backward (gradients
for x, weight and bias; and the first-layer case, where the ONV needs no gradient) of:

- ``warp``: ``kernels.linet.locally_connected`` on 1 thread and on all cores;
- ``torch_gather``: advanced-index gather + sum, autograd backward;
- ``torch_index_add``: gather forward, hand-written index_add / gather backward;
- ``torch_csr``: torch.sparse CSR matmul forward and backward, sampled_addmm for grad_weight.

All run in one process on the same inputs, medians after warm-up. It reports each torch variant's
time over Warp's, and the memory bandwidth Warp achieves against the minimum bytes the op must move.
"""

from __future__ import annotations

import os
from contextlib import contextmanager

import numpy as np
import torch

from warp_vision.bench import torch_baselines as tb
from warp_vision.bench.common import median_ms, sync
from warp_vision.kernels.linet import locally_connected, plan_for
from warp_vision.nn.connectivity import build_connectivity, onv_positions


def log_polar_layout(P: int, seed: int = 0, rho_min: float = 0.01, rho_max: float = 1.0) -> np.ndarray:
    """A noisy log-polar photoreceptor layout in the retinal domain, ordered ring by ring: [P, 2]."""
    rng = np.random.default_rng(seed)
    # Isotropic sampling: the log step between rings equals the angular step within a ring.
    rings = max(1, int(round(np.sqrt(P * np.log(rho_max / rho_min) / (2 * np.pi)))))
    per_ring = int(np.ceil(P / rings))
    ring = np.repeat(np.arange(rings), per_ring)[:P]
    k = np.tile(np.arange(per_ring), rings)[:P]
    rho = rho_min * (rho_max / rho_min) ** ((ring + 0.5) / rings)
    theta = 2 * np.pi * (k + 0.5 * (ring % 2)) / per_ring
    xy = np.stack([rho * np.cos(theta), rho * np.sin(theta)], axis=1)
    spacing = rho * 2 * np.pi / per_ring
    return xy + rng.normal(scale=0.15, size=xy.shape) * spacing[:, None]


@contextmanager
def _threads(n: int | None):
    old = os.environ.get("WARP_VISION_THREADS")
    if n is not None:
        os.environ["WARP_VISION_THREADS"] = str(n)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("WARP_VISION_THREADS", None)
        else:
            os.environ["WARP_VISION_THREADS"] = old


def min_bytes(B: int, n_in: int, N: int, R: int, itemsize: int = 4, grad_x: bool = True) -> dict:
    """Minimum bytes each pass must move (each array read or written once)."""
    params = N * R * (itemsize + 4) + N * itemsize  # weight + int32 index + bias
    fwd = B * n_in * itemsize + params + B * N * itemsize
    # backward: read grad_y, x, weight, index (+ transposed index for grad_x); write grads
    bwd = B * N * itemsize + B * n_in * itemsize + params + N * R * itemsize + N * itemsize
    if grad_x:
        bwd += B * n_in * itemsize + N * R * 4 + (n_in + 1) * 4
    return {"forward": fwd, "backward": bwd, "forward_backward": fwd + bwd}


def run_config(B: int, P: int, reduction: int, R: int, repeats: int, seed: int = 0, log=print) -> dict:
    """Benchmark one layer: ONV of P photoreceptors (N_in = 3P) -> N = N_in // reduction units."""
    pos = onv_positions(log_polar_layout(P, seed))
    conn = build_connectivity(pos, layers=1, receptive_field=R, reduction=reduction, seed=seed)[0]
    n_in, N = pos.shape[0], conn.index.shape[0]
    g = torch.Generator().manual_seed(seed)
    index = torch.from_numpy(conn.index)
    x = torch.rand(B, n_in, generator=g)
    weight = (torch.randn(N, R, generator=g) * (2.0 / R) ** 0.5).requires_grad_(True)
    bias = torch.zeros(N).requires_grad_(True)
    grad_y = torch.randn(B, N, generator=g)
    x_req = x.clone().requires_grad_(True)

    csr_plan = tb.CsrPlan(index, n_in)
    flat = index.reshape(-1).long().contiguous()
    plan_for(index, n_in)  # the Warp op's per-index plan, cached like the torch variants' preparation
    impls = {
        "warp_1thread": (lambda xx: locally_connected(xx, weight, bias, index), 1),
        "warp": (lambda xx: locally_connected(xx, weight, bias, index), None),
        "torch_gather": (lambda xx: tb.gather_sum(xx, weight, bias, index), None),
        "torch_index_add": (lambda xx: tb.index_add(xx, weight, bias, flat), None),
        "torch_csr": (lambda xx: tb.csr_matmul(xx, weight, bias, csr_plan), None),
    }
    # Agreement check before timing: every implementation against the Warp op.
    y0 = locally_connected(x_req, weight, bias, index)
    ref = (y0, *torch.autograd.grad(y0, (x_req, weight, bias), grad_y))
    result = {
        "B": B, "N_in": n_in, "N": N, "R": R, "P": P, "dtype": "float32",
        "min_bytes": min_bytes(B, n_in, N, R), "impls": {},
    }
    for name, (fn, threads) in impls.items():
        with _threads(threads):
            y = fn(x_req)
            got = (y, *torch.autograd.grad(y, (x_req, weight, bias), grad_y))
            err = max(float((a - c).detach().abs().max() / (c.detach().abs().max() + 1e-30)) for a, c in zip(got, ref))
            holder = {}

            def fwd_only():
                with torch.no_grad():
                    fn(x)

            def make_graph():
                holder["y"] = fn(x_req)

            def bwd_only():
                torch.autograd.grad(holder["y"], (x_req, weight, bias), grad_y)

            def fwd_bwd():
                torch.autograd.grad(fn(x_req), (x_req, weight, bias), grad_y)

            def fwd_bwd_first_layer():  # the ONV layer: no gradient for x
                torch.autograd.grad(fn(x), (weight, bias), grad_y)

            times = {
                "forward": median_ms(fwd_only, repeats),
                "backward": median_ms(bwd_only, repeats, setup=make_graph),
                "forward_backward": median_ms(fwd_bwd, repeats),
                "forward_backward_no_grad_x": median_ms(fwd_bwd_first_layer, repeats),
            }
        result["impls"][name] = {"max_rel_err_vs_warp": err, "times": times}
        log(
            f"  {name:16s} fwd {times['forward']['median_ms']:8.2f} ms  bwd {times['backward']['median_ms']:8.2f} ms"
            f"  fwd+bwd {times['forward_backward']['median_ms']:8.2f} ms"
            f"  (no grad x {times['forward_backward_no_grad_x']['median_ms']:8.2f} ms)  rel.err {err:.1e}"
        )
    warp_t = result["impls"]["warp"]["times"]
    torch_names = [k for k in impls if k.startswith("torch")]
    ratios = {}
    for phase in warp_t:
        w_ms = warp_t[phase]["median_ms"]
        per = {k: result["impls"][k]["times"][phase]["median_ms"] / w_ms for k in torch_names}
        ratios[phase] = {"vs": per, "vs_best_torch": min(per.values())}
    result["speedup_of_warp"] = ratios
    bw = {}
    mb = result["min_bytes"]
    for phase in ("forward", "backward", "forward_backward"):
        bw[phase] = mb[phase] / (warp_t[phase]["median_ms"] * 1e-3) / 1e9
    result["warp_achieved_GBps_vs_min_bytes"] = bw
    log(
        "  warp speed-up over the best torch: "
        + ", ".join(f"{k} {v['vs_best_torch']:.2f}x" for k, v in ratios.items())
        + f"; achieved {bw['forward_backward']:.2f} GB/s of minimum traffic (fwd+bwd)"
    )
    sync()
    return result


def run(sizes: list[int], batch: int = 64, reduction: int = 5, receptive_field: int = 20, repeats: int = 10, log=print) -> dict:
    """Benchmark each photoreceptor count in ``sizes`` (N_in = 3P)."""
    out = []
    for P in sizes:
        log(f"linet layer: B={batch}, N_in={3 * P} -> N={3 * P // reduction}, R={receptive_field}")
        out.append(run_config(batch, P, reduction, receptive_field, repeats, log=log))
    return {"configs": out}
