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

import numpy as np
import torch

from warp_vision.bench import torch_baselines as tb
from warp_vision.bench.common import interleaved_ms, machine_info
from warp_vision.bench.linet import kernel_calls, layer_inputs
from warp_vision.fileio import write_json
from warp_vision.kernels.launch import cpu_threads
from warp_vision.kernels.linet import locally_connected
from warp_vision.kernels.linet.layout import as_feature_major
from warp_vision.kernels.linet.op import plan_for
from warp_vision.provenance import software


def _parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    ap.add_argument("--photoreceptors", type=int, default=14_400)
    ap.add_argument("--receptive-field", type=int, default=20)
    ap.add_argument("--reduction", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds (median reported)")
    ap.add_argument("--repeats", type=int, default=15, help="timed repeats per measurement in a round")
    ap.add_argument("--out", default="bench_results/linet_floor.json")
    return ap.parse_args()


def _timed_calls(inp: dict) -> dict:
    """The Python-side cases, each forward+backward: the Warp kernels alone, the Warp op and torch's
    CSR op from a feature-major and from a batch-major x, and the Warp transpose of a batch-major x."""
    index, weight, bias, x_bm, grad_y = inp["index"], inp["weight"], inp["bias"], inp["x_bm"], inp["grad_y_bm"]
    x_fm = x_bm.t().contiguous().t().requires_grad_(True)
    gy_fm = grad_y.t().contiguous().t()
    x_bmr = x_bm.clone().requires_grad_(True)
    csr = tb.CsrPlan(index, inp["n_in"])
    calls = kernel_calls(x_bm, weight, bias, index, grad_y)

    def warp_kernels():
        for f in calls.values():
            f()

    return {
        "warp_kernels": warp_kernels,
        "warp_op": lambda: torch.autograd.grad(locally_connected(x_fm, weight, bias, index), (x_fm, weight, bias),
                                               gy_fm),
        "torch_csr_op": lambda: torch.autograd.grad(tb.csr_matmul(x_fm, weight, bias, csr), (x_fm, weight, bias),
                                                    grad_y),
        "warp_transpose": lambda: as_feature_major(x_bm),
        "warp_op_bm": lambda: torch.autograd.grad(locally_connected(x_bmr, weight, bias, index), (x_bmr, weight, bias),
                                                  gy_fm),
        "torch_csr_op_bm": lambda: torch.autograd.grad(tb.csr_matmul(x_bmr, weight, bias, csr), (x_bmr, weight, bias),
                                                       grad_y),
    }


def _build_c_kernels(cc: str, index: torch.Tensor, n_in: int, tmp: str) -> str:
    """Writes the connectivity files the C program reads into ``tmp`` and compiles it there; returns
    the executable's path."""
    plan = plan_for(index, n_in)
    t_offsets, t_entries, t_units = plan.transposed()
    for name, t in (("index", plan.index), ("t_offsets", t_offsets), ("t_entries", t_entries), ("t_units", t_units)):
        t.numpy().astype(np.int32).tofile(os.path.join(tmp, f"{name}.bin"))
    exe = os.path.join(tmp, "linet_floor")
    src = Path(__file__).with_name("linet_floor.c")
    subprocess.run([cc, "-O3", "-march=native", "-fopenmp", str(src), "-o", exe], check=True)
    return exe


def _run_rounds(args, cc: str, inp: dict) -> dict:
    """Alternating rounds of the C kernels and the Python-side cases, every call after a cache flush;
    returns {case: [median ms per round]}."""
    calls = _timed_calls(inp)
    flush_buf = torch.empty(16 << 20)  # 64 MiB

    def flush():
        flush_buf.fill_(1.0)

    rows = {"c_avx2_kernels": [], **{k: [] for k in calls}}
    N, R = inp["index"].shape
    with tempfile.TemporaryDirectory() as tmp:
        exe = _build_c_kernels(cc, inp["index"], inp["n_in"], tmp)
        for r in range(args.rounds):
            out = subprocess.run([exe, tmp, str(N), str(R), str(inp["n_in"]), str(cpu_threads()), str(args.repeats)],
                                 check=True, capture_output=True, text=True).stdout
            rows["c_avx2_kernels"].append(json.loads(out)["forward_backward"])
            ops = interleaved_ms({k: (f, flush) for k, f in calls.items()}, args.repeats)
            for k, v in ops.items():
                rows[k].append(v["median_ms"])
            print(f"round {r + 1}: " + "  ".join(f"{k} {v[-1]:.2f} ms" for k, v in rows.items()), flush=True)
    return rows


def main() -> None:
    args = _parse_args()
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise SystemExit("linet_floor: no C compiler (cc) on PATH")
    B, R = 64, args.receptive_field
    inp = layer_inputs(B, args.photoreceptors, args.reduction, R, seed=0)
    rows = _run_rounds(args, cc, inp)
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
    write_json(args.out, {
        "benchmark": "linet_floor", "machine": machine_info(), "software": software(), "B": B, "N_in": inp["n_in"],
        "N": inp["N"], "R": R, "rounds": rows, "median_ms": med, "csr_over_warp_op": achieved,
        "csr_over_c_kernels_bound": bound,
    })
    print(f"results: {args.out}")


if __name__ == "__main__":
    main()
