"""`python -m warp_vision.bench linet`: the locally-connected layer, Warp kernels vs plain torch.

For each configuration (B, N_in -> N, R) it times forward, backward and forward+backward (gradients
for x, weight and bias; and the first-layer case, where the ONV needs no gradient) of:

- ``warp``: :func:`warp_vision.kernels.linet.locally_connected` on 1 thread and on all cores;
- ``torch_gather``: advanced-index gather + sum, autograd backward;
- ``torch_index_add``: gather forward, hand-written index_add / gather backward;
- ``torch_csr``: torch.sparse CSR matmul forward and backward, sampled_addmm for grad_weight.

The layer's inputs are the ONV of the paper's noisy log-polar retina (:meth:`Retina.log_polar
<warp_vision.eye.retina.Retina.log_polar>`, default eye). All run in one process on the same inputs,
medians after warm-up, for both input layouts (x
batch-major, as an ONV batch arrives; x feature-major, as one liNet layer hands it to the next). It
reports each torch variant's time over Warp's, and the memory bandwidth Warp achieves against the
minimum bytes the op must move. Then the first layer as training runs it (``half_onv``): a batch-major
ONV batch that needs no gradient, fed as float16 (as the dataset stores it; the kernels widen it on
load) against float32, forward and forward+backward, with the bytes each moves against its traffic
floor. Last, the op's three feature-major kernels are timed alone on preallocated outputs
(``warp_kernels_only_ms``): how much of the op is kernel time, and the best torch time over that sum,
the speed-up these kernels would give with no overhead at all.

``--device cuda`` (or ``cuda:N``) runs the same layer on the GPU: the seeded tensors are made on the CPU
as above and moved there (so the values match a CPU run), and the Warp op (all four phases, both
layouts, the float16 first layer) and the torch baselines are timed on the device, every timing
synchronised with the device (:func:`warp_vision.bench.common.sync`). The CPU-only parts are skipped and
named, with the reason, under ``"skipped"`` in the JSON (:data:`CUDA_SKIPPED`): ``warp_1thread`` (a CPU
thread count) and the kernels-alone timing (CPU launches). The JSON then also holds ``"device"`` and
``"device_name"``.
"""

from __future__ import annotations

import torch

from warp_vision.bench import torch_baselines as tb
from warp_vision.bench.common import interleaved_ms, sync
from warp_vision.eye.retina import Retina
from warp_vision.kernels import launch
from warp_vision.kernels.linet import locally_connected
from warp_vision.kernels.linet.kernels import linet_forward_fm, linet_grad_weight_fm, linet_grad_x_fm
from warp_vision.kernels.linet.layout import LANES, flat_vectors, warp_array
from warp_vision.kernels.linet.op import launch_kernel, plan_for
from warp_vision.nn.connectivity import build_connectivity, onv_positions

#: What a run on a CUDA device leaves out, and why (its JSON's ``"skipped"``).
CUDA_SKIPPED = {
    "warp_1thread": "a CPU thread count (WARP_VISION_THREADS): a CUDA launch is not split across CPU threads",
    "warp_kernels_only_ms": "kernel_calls launches the op's feature-major kernels on the CPU only",
}


def min_bytes(B: int, n_in: int, N: int, R: int, itemsize: int = 4, grad_x: bool = True,
              x_itemsize: int | None = None) -> dict:
    """Minimum bytes each pass must move (each array read or written once); x (and grad_x) in
    ``x_itemsize`` bytes (default ``itemsize``), everything else in ``itemsize``."""
    xs = itemsize if x_itemsize is None else x_itemsize
    params = N * R * (itemsize + 4) + N * itemsize  # weight + int32 index + bias
    fwd = B * n_in * xs + params + B * N * itemsize
    # backward: read grad_y, x, weight, index (+ transposed index for grad_x); write grads
    bwd = B * N * itemsize + B * n_in * xs + params + N * R * itemsize + N * itemsize
    if grad_x:
        bwd += B * n_in * xs + N * R * 4 + (n_in + 1) * 4
    return {"forward": fwd, "backward": bwd, "forward_backward": fwd + bwd}


def _layout(t: torch.Tensor, feature_major: bool) -> torch.Tensor:
    """``t`` [B, F] batch-major (contiguous) or feature-major (a view of a contiguous [F, B] copy)."""
    return t.t().contiguous().t() if feature_major else t.contiguous()


def _phases(fn, threads, x, x_req, weight, bias, gy) -> dict:
    """The four timed phases of one implementation as (call, untimed setup) pairs, each run under
    its own thread setting."""
    holder = {}

    def under(f):
        def call():
            with launch.threads_set(threads):
                f()
        return call

    def fwd_only():
        with torch.no_grad():
            fn(x)

    def make_graph():
        holder["y"] = fn(x_req)

    return {
        "forward": (under(fwd_only), None),
        "backward": (under(lambda: torch.autograd.grad(holder["y"], (x_req, weight, bias), gy)), under(make_graph)),
        "forward_backward": (under(lambda: torch.autograd.grad(fn(x_req), (x_req, weight, bias), gy)), None),
        # the ONV layer: no gradient for x
        "forward_backward_no_grad_x": (under(lambda: torch.autograd.grad(fn(x), (weight, bias), gy)), None),
    }


def kernel_calls(x_bm: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, index: torch.Tensor,
                 grad_y_bm: torch.Tensor) -> dict:
    """The op's three feature-major kernel launches (forward, grad_x, grad_weight with grad_bias) as
    callables on preallocated outputs: no allocation, autograd, checks or layout change. CPU only,
    B a multiple of 64."""
    B = x_bm.shape[0]
    if B % LANES or x_bm.device.type != "cpu":
        raise ValueError(f"kernel_calls: expected a CPU batch of a multiple of 64 rows, got {B} on {x_bm.device}")
    launch.init()
    plan = plan_for(index, x_bm.shape[1])
    t_offsets, t_entries, t_units = plan.transposed()
    xT, gT = x_bm.t().contiguous(), grad_y_bm.t().contiguous()
    w, b = weight.detach().reshape(-1), bias.detach()
    yT, gxT = torch.empty(plan.num_units, B), torch.empty(plan.in_features, B)
    gw, gb = torch.empty_like(w), torch.empty_like(b)
    fv, wa, chunks, R = flat_vectors, warp_array, B // LANES, plan.receptive_field
    idx = wa(plan.index.reshape(-1))
    return {
        "forward": lambda: launch_kernel(linet_forward_fm, plan.num_units,
                                         [fv(xT), wa(w), wa(b), idx, R, chunks, 0], [fv(yT)], "cpu"),
        "grad_x": lambda: launch_kernel(linet_grad_x_fm, plan.in_features,
                                        [fv(gT), wa(w), wa(t_offsets), wa(t_entries), wa(t_units), chunks], [fv(gxT)],
                                        "cpu"),
        "grad_weight_bias": lambda: launch_kernel(linet_grad_weight_fm, plan.num_units,
                                                  [fv(xT), fv(gT), idx, R, chunks], [wa(gw), wa(gb)], "cpu"),
    }


def kernels_only(x_bm: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, index: torch.Tensor,
                 grad_y_bm: torch.Tensor, repeats: int) -> dict:
    """:func:`kernel_calls` timed in interleaved rounds (ms), with their sum: the fastest the op
    could run between liNet layers with these kernels; the op's own time minus it is its overhead.
    Empty for a batch that is not a multiple of 64."""
    if x_bm.shape[0] % LANES:
        return {}
    calls = kernel_calls(x_bm, weight, bias, index, grad_y_bm)
    timed = interleaved_ms({k: (f, None) for k, f in calls.items()}, repeats)
    out = {k: v["median_ms"] for k, v in timed.items()}
    out["forward_backward"] = sum(out.values())
    return out


def layer_inputs(B: int, P: int, reduction: int, R: int, seed: int = 0, device: str = "cpu") -> dict:
    """One layer's connectivity and seeded tensors: the ONV of a log-polar retina of P photoreceptors
    (N_in = 3P) -> N = N_in // reduction units of R connections. Returns {"n_in", "N", "index" [N, R],
    "x_bm" [B, N_in] (batch-major), "weight" [N, R] and "bias" [N] (requiring grad), "grad_y_bm" [B, N]},
    the tensors on ``device`` (drawn on the CPU and moved there: the same values on every device)."""
    pos = onv_positions(Retina.log_polar(P, seed=seed).domain_xy)
    conn = build_connectivity(pos, layers=1, receptive_field=R, reduction=reduction, seed=seed)[0]
    N = conn.index.shape[0]
    g = torch.Generator().manual_seed(seed)
    inputs = {"n_in": pos.shape[0], "N": N, "index": torch.from_numpy(conn.index).to(device)}
    inputs["x_bm"] = torch.rand(B, inputs["n_in"], generator=g).to(device)
    inputs["weight"] = (torch.randn(N, R, generator=g) * (2.0 / R) ** 0.5).to(device).requires_grad_(True)
    inputs["bias"] = torch.zeros(N).to(device).requires_grad_(True)
    inputs["grad_y_bm"] = torch.randn(B, N, generator=g).to(device)
    return inputs


def _implementations(weight: torch.Tensor, bias: torch.Tensor, index: torch.Tensor, n_in: int) -> dict:
    """name -> (fn(x) -> y, CPU threads or None for all): the Warp op and the torch baselines, each
    with its per-index preparation done here (outside the timed region), on ``index``'s device
    (``warp_1thread`` on the CPU only)."""
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
    if index.device.type != "cpu":
        del impls["warp_1thread"]
    return impls


def _time_layout(impls: dict, inp: dict, feature_major: bool, repeats: int, log) -> dict:
    """Every implementation on x in one layout: its largest relative error against the Warp op, then
    its four phases timed in interleaved rounds. Returns {name: {"max_rel_err_vs_warp", "times"}}."""
    weight, bias, grad_y_bm = inp["weight"], inp["bias"], inp["grad_y_bm"]
    device = str(grad_y_bm.device)
    grad_y_fm = _layout(grad_y_bm, True)
    x = _layout(inp["x_bm"], feature_major)
    x_req = _layout(inp["x_bm"], feature_major).requires_grad_(True)
    # Agreement check before timing: every implementation against the Warp op.
    y0 = locally_connected(x_req, weight, bias, inp["index"])
    ref = (y0, *torch.autograd.grad(y0, (x_req, weight, bias), grad_y_bm))
    per_layout, cases = {}, {}
    for name, (fn, threads) in impls.items():
        with launch.threads_set(threads):
            y = fn(x_req)
            gy = grad_y_bm if y.is_contiguous() else grad_y_fm  # what the next layer would return
            got = (y, *torch.autograd.grad(y, (x_req, weight, bias), gy))
        err = max(float((a - c).detach().abs().max() / (c.detach().abs().max() + 1e-30)) for a, c in zip(got, ref))
        per_layout[name] = {"max_rel_err_vs_warp": err}
        cases[name] = _phases(fn, threads, x, x_req, weight, bias, gy)
    # Each phase interleaves the implementations round by round (drift falls on all alike).
    for phase in ("forward", "backward", "forward_backward", "forward_backward_no_grad_x"):
        timed = interleaved_ms({name: cases[name][phase] for name in impls}, repeats, device=device)
        for name in impls:
            per_layout[name].setdefault("times", {})[phase] = timed[name]
    for name in impls:
        times, err = per_layout[name]["times"], per_layout[name]["max_rel_err_vs_warp"]
        log(
            f"  {name:16s} fwd {times['forward']['median_ms']:8.2f} ms  bwd {times['backward']['median_ms']:8.2f} ms"
            f"  fwd+bwd {times['forward_backward']['median_ms']:8.2f} ms"
            f"  (no grad x {times['forward_backward_no_grad_x']['median_ms']:8.2f} ms)  rel.err {err:.1e}"
        )
    return per_layout


def _layout_summary(per_layout: dict, mb: dict, log) -> dict:
    """Warp's speed-up over each torch variant per phase, and the bandwidth it achieves against the
    minimum bytes ``mb`` each phase must move."""
    warp_t = per_layout["warp"]["times"]
    torch_names = [k for k in per_layout if k.startswith("torch")]
    ratios = {}
    for phase in warp_t:
        w_ms = warp_t[phase]["median_ms"]
        per = {k: per_layout[k]["times"][phase]["median_ms"] / w_ms for k in torch_names}
        best = min(per, key=per.get)
        ratios[phase] = {"vs": per, "vs_best_torch": per[best], "best_torch": best}
    bw = {ph: mb[ph] / (warp_t[ph]["median_ms"] * 1e-3) / 1e9 for ph in ("forward", "backward", "forward_backward")}
    log(
        "  warp speed-up over the best torch: "
        + ", ".join(f"{k} {v['vs_best_torch']:.2f}x" for k, v in ratios.items())
        + f"; achieved {bw['forward_backward']:.2f} GB/s of minimum traffic (fwd+bwd)"
    )
    return {"impls": per_layout, "speedup_of_warp": ratios, "warp_achieved_GBps_vs_min_bytes": bw}


def _add_kernels_only(result: dict, inp: dict, repeats: int, log) -> None:
    """Times the op's kernels alone (CPU, B a multiple of 64) into ``result["warp_kernels_only_ms"]``,
    beside the feature-major op and the best torch variant."""
    k = kernels_only(inp["x_bm"], inp["weight"], inp["bias"], inp["index"], inp["grad_y_bm"], repeats)
    if not k:
        return
    fm = result["layouts"]["feature_major"]
    op_ms = fm["impls"]["warp"]["times"]["forward_backward"]["median_ms"]
    best = fm["speedup_of_warp"]["forward_backward"]["best_torch"]
    best_ms = fm["impls"][best]["times"]["forward_backward"]["median_ms"]
    k.update({"op_forward_backward_ms": op_ms, "op_overhead_ms": op_ms - k["forward_backward"],
              "best_torch_over_kernels": best_ms / k["forward_backward"]})
    result["warp_kernels_only_ms"] = k
    log(
        f" Warp kernels alone (feature-major, preallocated): fwd {k['forward']:.2f} + grad_x {k['grad_x']:.2f}"
        f" + grad_weight/bias {k['grad_weight_bias']:.2f} = {k['forward_backward']:.2f} ms; the op"
        f" {op_ms:.2f} ms; {best} over the kernels alone: {k['best_torch_over_kernels']:.2f}x"
    )


def half_onv(inp: dict, repeats: int, log) -> dict:
    """The first layer on a batch-major ONV batch that needs no gradient (as training feeds it): the op
    on the float32 batch and on the same batch in float16, forward and forward+backward (weight and
    bias), timed in interleaved rounds; the float32/float16 time ratio and the bandwidth each achieves
    against its traffic floor (:func:`min_bytes` with x in 4 or 2 bytes, no grad_x)."""
    w, b, index, gy = inp["weight"], inp["bias"], inp["index"], inp["grad_y_bm"]
    xs = {"float32": inp["x_bm"], "float16": inp["x_bm"].half()}
    B, n_in = xs["float32"].shape
    N, R = w.shape
    cases = {}
    for name, x in xs.items():
        def fwd(x=x):
            with torch.no_grad():
                locally_connected(x, w, b, index)

        def fwd_bwd(x=x):
            y = locally_connected(x, w, b, index)
            torch.autograd.grad(y, (w, b), gy if y.is_contiguous() else _layout(gy, True))

        cases[f"{name}/forward"], cases[f"{name}/forward_backward"] = (fwd, None), (fwd_bwd, None)
    timed = interleaved_ms(cases, repeats, device=str(gy.device))
    out = {"ratio_float32_over_float16": {}, "GBps_vs_min_bytes": {}, "min_bytes": {}, "median_ms": {}}
    for name, x in xs.items():
        mb = min_bytes(B, n_in, N, R, grad_x=False, x_itemsize=x.element_size())
        out["min_bytes"][name] = {k: mb[k] for k in ("forward", "forward_backward")}
        for phase in ("forward", "forward_backward"):
            ms = timed[f"{name}/{phase}"]["median_ms"]
            out["median_ms"].setdefault(name, {})[phase] = ms
            out["GBps_vs_min_bytes"].setdefault(name, {})[phase] = mb[phase] / (ms * 1e-3) / 1e9
    for phase in ("forward", "forward_backward"):
        out["ratio_float32_over_float16"][phase] = (
            out["median_ms"]["float32"][phase] / out["median_ms"]["float16"][phase]
        )
    m, g = out["median_ms"], out["GBps_vs_min_bytes"]
    log(f" first layer, batch-major ONV, no grad x: float32 fwd {m['float32']['forward']:.2f} ms, fwd+bwd "
        f"{m['float32']['forward_backward']:.2f} ms ({g['float32']['forward_backward']:.2f} GB/s of its floor); "
        f"float16 fwd {m['float16']['forward']:.2f} ms, fwd+bwd {m['float16']['forward_backward']:.2f} ms "
        f"({g['float16']['forward_backward']:.2f} GB/s); float32/float16 "
        f"{out['ratio_float32_over_float16']['forward_backward']:.2f}x")
    return out


def run_config(B: int, P: int, reduction: int, R: int, repeats: int, seed: int = 0, log=print,
               device: str = "cpu") -> dict:
    """Benchmark one layer: ONV of P photoreceptors (N_in = 3P) -> N = N_in // reduction units.

    Both input layouts are timed, every implementation getting the same tensors: ``batch_major``
    (x contiguous [B, N_in], as an ONV batch arrives) and ``feature_major`` (x a view of a contiguous
    [N_in, B] buffer, as the Warp op hands its output to the next liNet layer). In backward each
    implementation receives grad_y in the layout of its own output, as the next layer would return it.

    On a CUDA ``device`` the result also holds ``"device"`` and ``"skipped"`` (:data:`CUDA_SKIPPED`).
    """
    inp = layer_inputs(B, P, reduction, R, seed, device)
    n_in, N = inp["n_in"], inp["N"]
    impls = _implementations(inp["weight"], inp["bias"], inp["index"], n_in)
    result = {
        "B": B, "N_in": n_in, "N": N, "R": R, "P": P, "dtype": "float32",
        "min_bytes": min_bytes(B, n_in, N, R), "layouts": {},
    }
    for layout in ("batch_major", "feature_major"):
        log(f" x {layout.replace('_', '-')}:")
        per_layout = _time_layout(impls, inp, layout == "feature_major", repeats, log)
        result["layouts"][layout] = _layout_summary(per_layout, result["min_bytes"], log)
    result["half_onv"] = half_onv(inp, repeats, log)
    if inp["x_bm"].device.type == "cpu":
        _add_kernels_only(result, inp, repeats, log)
    else:
        result["device"] = device
        result["skipped"] = dict(CUDA_SKIPPED)
    sync(device)
    return result


def run(sizes: list[int], batch: int = 64, reduction: int = 5, receptive_field: int = 20, repeats: int = 10, log=print,
        device: str = "cpu") -> dict:
    """Benchmark each photoreceptor count in ``sizes`` (N_in = 3P) on ``device`` ("cpu", "cuda:N")."""
    head = {}
    if torch.device(device).type != "cpu":
        head = {"device": device, "device_name": torch.cuda.get_device_name(device), "skipped": dict(CUDA_SKIPPED)}
        log(f"device: {device} ({head['device_name']}); skipped: {', '.join(CUDA_SKIPPED)} (CPU only)")
    out = []
    for P in sizes:
        log(f"linet layer: B={batch}, N_in={3 * P} -> N={3 * P // reduction}, R={receptive_field}")
        out.append(run_config(batch, P, reduction, receptive_field, repeats, log=log, device=device))
    return {**head, "configs": out}
