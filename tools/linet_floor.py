"""How fast can this machine run the liNet layer's work at all? A one-off probe, not part of the package.

Builds the benchmark's connectivity (``python -m warp_vision.bench linet``'s first configuration by
default), compiles ``linet_floor.c`` (the same gathers hand-written with AVX2 intrinsics and OpenMP)
with the system C compiler, and times forward+backward (feature-major x), alternating in rounds so
the machine's drift falls on all: the C kernels, the Warp kernels alone (the bench's
``kernel_calls``), the Warp op and torch's sparse CSR op, and from a batch-major x the Warp
transpose, op and CSR op. Every timed call starts after a 64 MiB
write that evicts the caches, as an op finds them between other work (warm repeats of one kernel
flatter whichever code's working set happens to fit). Prints medians over rounds and writes JSON.

    python tools/linet_floor.py [--photoreceptors 14400] [--rounds 5] [--out bench_results/linet_floor.json]

Needs a C compiler with OpenMP (``cc``) and an x86-64 CPU with AVX2 and FMA.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

importlib.import_module("warp_vision")  # before torch: it sets OMP_WAIT_POLICY=PASSIVE

import numpy as np  # noqa: E402
import torch  # noqa: E402

from warp_vision.bench import torch_baselines as tb
from warp_vision.bench.common import interleaved_ms, machine_info, write_json
from warp_vision.bench.linet import kernel_calls, log_polar_layout
from warp_vision.kernels.launch import cpu_threads
from warp_vision.kernels.layout import as_feature_major
from warp_vision.kernels.linet import locally_connected, plan_for
from warp_vision.nn.connectivity import build_connectivity, onv_positions


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--photoreceptors", type=int, default=14_400)
    ap.add_argument("--receptive-field", type=int, default=20)
    ap.add_argument("--reduction", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds (median reported)")
    ap.add_argument("--repeats", type=int, default=15, help="timed repeats per measurement in a round")
    ap.add_argument("--out", default="bench_results/linet_floor.json")
    args = ap.parse_args()
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise SystemExit("linet_floor: no C compiler (cc) on PATH")

    B, R = 64, args.receptive_field
    pos = onv_positions(log_polar_layout(args.photoreceptors, 0))
    conn = build_connectivity(pos, layers=1, receptive_field=R, reduction=args.reduction, seed=0)[0]
    index = torch.from_numpy(conn.index)
    n_in, N = pos.shape[0], index.shape[0]
    plan = plan_for(index, n_in)
    g = torch.Generator().manual_seed(0)
    x_bm = torch.rand(B, n_in, generator=g)
    weight = (torch.randn(N, R, generator=g) * (2.0 / R) ** 0.5).requires_grad_(True)
    bias = torch.zeros(N).requires_grad_(True)
    grad_y = torch.randn(B, N, generator=g)
    x_fm = x_bm.t().contiguous().t().requires_grad_(True)
    gy_fm = grad_y.t().contiguous().t()
    csr = tb.CsrPlan(index, n_in)

    x_bmr = x_bm.clone().requires_grad_(True)

    def op():
        torch.autograd.grad(locally_connected(x_fm, weight, bias, index), (x_fm, weight, bias), gy_fm)

    def csr_op():
        torch.autograd.grad(tb.csr_matmul(x_fm, weight, bias, csr), (x_fm, weight, bias), grad_y)

    def op_bm():
        torch.autograd.grad(locally_connected(x_bmr, weight, bias, index), (x_bmr, weight, bias), gy_fm)

    def csr_op_bm():
        torch.autograd.grad(tb.csr_matmul(x_bmr, weight, bias, csr), (x_bmr, weight, bias), grad_y)

    def transpose():
        as_feature_major(x_bm)

    calls = kernel_calls(x_bm, weight, bias, index, grad_y)

    def warp_kernels():
        for f in calls.values():
            f()

    flush_buf = torch.empty(16 << 20)  # 64 MiB

    def flush():
        flush_buf.fill_(1.0)

    rows = {"c_avx2_kernels": [], "warp_kernels": [], "warp_op": [], "torch_csr_op": [],
            "warp_transpose": [], "warp_op_bm": [], "torch_csr_op_bm": []}
    with tempfile.TemporaryDirectory() as tmp:
        t_offsets, t_entries, t_units = plan.transposed()
        for name, t in (("index", plan.index), ("t_offsets", t_offsets), ("t_entries", t_entries), ("t_units", t_units)):
            t.numpy().astype(np.int32).tofile(os.path.join(tmp, f"{name}.bin"))
        exe = os.path.join(tmp, "linet_floor")
        src = Path(__file__).with_name("linet_floor.c")
        subprocess.run([cc, "-O3", "-march=native", "-fopenmp", str(src), "-o", exe], check=True)
        for r in range(args.rounds):
            out = subprocess.run([exe, tmp, str(N), str(R), str(n_in), str(cpu_threads()), str(args.repeats)],
                                 check=True, capture_output=True, text=True).stdout
            rows["c_avx2_kernels"].append(json.loads(out)["forward_backward"])
            ops = interleaved_ms({"warp_kernels": (warp_kernels, flush), "warp_op": (op, flush),
                                  "torch_csr_op": (csr_op, flush), "warp_transpose": (transpose, flush),
                                  "warp_op_bm": (op_bm, flush), "torch_csr_op_bm": (csr_op_bm, flush)}, args.repeats)
            for k, v in ops.items():
                rows[k].append(v["median_ms"])
            print(f"round {r + 1}: " + "  ".join(f"{k} {v[-1]:.2f} ms" for k, v in rows.items()), flush=True)
    med = {k: float(np.median(v)) for k, v in rows.items()}
    # The most any implementation of these gathers could gain over torch's CSR here: CSR's whole op
    # over the C kernels alone (plus, from a batch-major ONV, the Warp transpose to the vector layout).
    bound = {"feature_major": med["torch_csr_op"] / med["c_avx2_kernels"],
             "batch_major": med["torch_csr_op_bm"] / (med["c_avx2_kernels"] + med["warp_transpose"])}
    achieved = {"feature_major": med["torch_csr_op"] / med["warp_op"],
                "batch_major": med["torch_csr_op_bm"] / med["warp_op_bm"]}
    print("medians (fwd+bwd): " + "  ".join(f"{k} {v:.2f} ms" for k, v in med.items()))
    for lay in ("batch_major", "feature_major"):
        print(f"x {lay.replace('_', '-')}: torch CSR over the Warp op {achieved[lay]:.2f}x; the bound (CSR over the C"
              f" kernels{' + the transpose' if lay == 'batch_major' else ''}) {bound[lay]:.2f}x")
    path = write_json(args.out, {
        "benchmark": "linet_floor", "machine": machine_info(), "B": B, "N_in": n_in, "N": N, "R": R,
        "rounds": rows, "median_ms": med, "csr_over_warp_op": achieved, "csr_over_c_kernels_bound": bound,
    })
    print(f"results: {path}")


if __name__ == "__main__":
    main()
