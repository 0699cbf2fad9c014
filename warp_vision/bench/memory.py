"""`python -m warp_vision.bench memory`: the paper's Fig. 4 — parameters and training-step memory vs ONV size.

For H=4 hidden layers, reduction f=5, receptive field R=5 (the paper's Fig. 4 set-up), batch 64 and
Adam, and ONV sizes 3P from 1e3 to 1.28e7, it reports for the liNet (fed float32 ONVs, and float16 ONVs
as the dataset stores them) and for the fully-connected net with the same hidden sizes (float32; each
followed by the same 2-output linear layer):

- the trainable-parameter count (from the formula, checked against the built model when built);
- the peak memory of one training step (forward, MSE loss, backward, Adam step, including the input
  batch and Adam's state), measured in a fresh subprocess as the rise of the resident set's
  high-water mark (Linux ``VmHWM``, reset through ``/proc/self/clear_refs``) over the resident set
  before the input batch and the model were allocated, and the whole process's high-water mark during
  the step (``process_peak_bytes``: interpreter, libraries, model and all);
- the *floor* such a step must hold: input batch + saved activations + the largest activation
  gradient + parameters, gradients and Adam's two moments.

Configurations whose floor does not fit in the memory budget are not run: their figures are the
computed floor, marked ``"estimated": true``.
"""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
from collections.abc import Sequence

from warp_vision.fileio import atomic_write
from warp_vision.limits import Range

DEFAULT_SIZES = [1_000, 4_000, 10_000, 40_000, 100_000, 400_000, 1_000_000, 4_000_000, 12_800_000]
OUTPUTS = 2  # the (yaw, pitch) head of the foveation net
FLOAT = 4
#: the input dtypes measured per model: the fc baseline's torch.nn.Linear reads float32 only
INPUT_DTYPES = {"linet": ("float32", "float16"), "fc": ("float32",)}
ITEMSIZE = {"float32": 4, "float16": 2, "bfloat16": 2}


#: the ONV sizes the benchmark takes: a liNet of 4 layers, each a fifth of the last, keeps 3 units at the top from
#: 375 inputs; 3e8 float32 inputs are 1.2 GB an ONV
ONV_SIZES = Range(375, 3 * 10**8, "inputs")


def layer_sizes(onv: int, layers: int = 4, reduction: int = 5) -> list[int]:
    sizes = [onv]
    for _ in range(layers):
        sizes.append(sizes[-1] // reduction)
    return sizes


def param_count(model: str, sizes: Sequence[int], receptive_field: int = 5) -> int:
    """Trainable parameters of the backbone plus the 2-output head (weights and biases)."""
    if model == "linet":
        backbone = sum(n * receptive_field + n for n in sizes[1:])
    else:
        backbone = sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))
    return backbone + sizes[-1] * OUTPUTS + OUTPUTS


def floor_bytes(model: str, sizes: Sequence[int], batch: int, receptive_field: int = 5,
                input_dtype: str = "float32") -> dict:
    """What one training step must hold at its peak, in bytes, itemised."""
    params = param_count(model, sizes, receptive_field)
    parts = {
        "input_batch": batch * sizes[0] * ITEMSIZE[input_dtype],
        "saved_activations": batch * sum(sizes[1:]) * FLOAT,
        "largest_activation_gradient": batch * max(sizes[1:]) * FLOAT,
        "params_grads_adam": 4 * params * FLOAT,
    }
    parts["total"] = sum(parts.values())
    return parts


def _rss_bytes(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"{field} not found in /proc/self/status")


def worker(model: str, onv: int, batch: int, seed: int = 0, input_dtype: str = "float32") -> dict:
    """Run in a fresh process: build the model, then measure one training step's peak memory (the batch
    made directly in ``input_dtype``: no float32 copy of it ever exists)."""
    import numpy as np
    import torch

    from warp_vision.eye.retina import Retina
    from warp_vision.nn.connectivity import onv_positions
    from warp_vision.nn.linet import FullyConnected, LiNet

    torch.manual_seed(seed)
    # Load the kernels before the baseline so their code is not counted.
    if model == "linet":
        from warp_vision.kernels.linet import locally_connected

        locally_connected(torch.zeros(1, 2), torch.zeros(1, 1), torch.zeros(1), torch.zeros(1, 1, dtype=torch.int64))
    gc.collect()
    rss0 = _rss_bytes("VmRSS")
    if model == "linet":
        backbone = LiNet(onv_positions(Retina.log_polar(onv // 3, seed=seed).domain_xy), layers=4, receptive_field=5,
                         reduction=5, seed=seed)  # (the retina and its positions are freed: not part of a step)
        sizes = list(backbone.layer_sizes)
    else:
        sizes = layer_sizes(onv)
        backbone = FullyConnected(onv, sizes[1:])
    net = torch.nn.Sequential(backbone, torch.nn.Linear(sizes[-1], OUTPUTS))
    n_params = sum(p.numel() for p in net.parameters())
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    gc.collect()
    with open("/proc/self/clear_refs", "w") as f:  # reset the high-water mark to the current RSS
        f.write("5")
    x = torch.empty(batch, onv, dtype=getattr(torch, input_dtype)).uniform_()
    target = torch.zeros(batch, OUTPUTS)
    loss = torch.nn.functional.mse_loss(net(x), target)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    process_peak = _rss_bytes("VmHWM")
    return {"model": model, "onv": onv, "input_dtype": input_dtype, "layer_sizes": sizes, "params": n_params,
            "peak_bytes": process_peak - rss0, "process_peak_bytes": process_peak,
            "loss_finite": bool(np.isfinite(loss.item()))}


def run(sizes: Sequence[int] = DEFAULT_SIZES, batch: int = 64, budget_gib: float = 14.0, log=print) -> dict:
    """Measure every (model, size) whose floor fits in ``budget_gib``; estimate the rest."""
    rows = []
    sizes = [3 * (int(s) // 3) for s in sizes]  # an ONV holds 3 channels per photoreceptor
    for model, dtype in ((m, d) for m in ("linet", "fc") for d in INPUT_DTYPES[m]):
        for onv in sizes:
            ls = layer_sizes(onv)
            floor = floor_bytes(model, ls, batch, input_dtype=dtype)
            row = {
                "model": model, "input_dtype": dtype, "onv": onv, "layer_sizes": ls,
                "params": param_count(model, ls), "floor_bytes": floor,
            }
            if floor["total"] > budget_gib * 2**30:
                row.update(estimated=True, peak_bytes=floor["total"])
                log(f"  {model:6s} {dtype:8s} 3P={onv:>10,d}: floor {floor['total'] / 2**20:10.0f} MiB > budget: "
                    "estimated")
            else:
                cmd = [sys.executable, "-m", "warp_vision.bench", "memory", "--worker", model, str(onv), dtype,
                       "--batch", str(batch)]
                proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
                if proc.returncode != 0:
                    raise RuntimeError(f"memory worker {model} {onv} failed:\n{proc.stderr[-3000:]}")
                res = json.loads(proc.stdout.strip().splitlines()[-1])
                if res["params"] != row["params"]:
                    raise RuntimeError(f"{model} 3P={onv}: built model has {res['params']} parameters, formula "
                                       f"{row['params']}")
                row.update(estimated=False, peak_bytes=res["peak_bytes"], layer_sizes=res["layer_sizes"],
                           process_peak_bytes=res["process_peak_bytes"])
                row["peak_over_floor"] = res["peak_bytes"] / floor["total"]
                log(
                    f"  {model:6s} {dtype:8s} 3P={onv:>10,d}: params {row['params']:>14,d}  peak "
                    f"{res['peak_bytes'] / 2**20:9.0f} MiB  floor {floor['total'] / 2**20:9.0f} MiB  "
                    f"({row['peak_over_floor']:.2f}x)  process {res['process_peak_bytes'] / 2**20:9.0f} MiB"
                )
            rows.append(row)
    return {"batch": batch, "layers": 4, "reduction": 5, "receptive_field": 5, "optimizer": "Adam", "rows": rows}


def plot(result: dict, path: str) -> None:
    """Fig. 4: (a) peak memory and (b) trainable parameters vs ONV size, semi-log, liNet vs FC."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_m, ax_p) = plt.subplots(1, 2, figsize=(11, 4.2))
    for model, dtype, colour, label in (("fc", "float32", "tab:red", "fully-connected"),
                                        ("linet", "float32", "tab:blue", "liNet, float32 ONVs"),
                                        ("linet", "float16", "tab:green", "liNet, float16 ONVs")):
        rows = [r for r in result["rows"] if r["model"] == model and r.get("input_dtype", "float32") == dtype]
        if not rows:
            continue
        meas = [r for r in rows if not r["estimated"]]
        est = [r for r in rows if r["estimated"]]
        ax_m.plot([r["onv"] for r in meas], [r["peak_bytes"] / 2**20 for r in meas], "o-", color=colour,
                  label=f"{label} (measured)")
        if est:
            xs = ([meas[-1]] if meas else []) + est
            ax_m.plot([r["onv"] for r in xs], [r["peak_bytes"] / 2**20 for r in xs], "x--", color=colour,
                      label=f"{label} (estimated floor)")
        if dtype == "float32":  # the parameters do not depend on the input's dtype
            ax_p.plot([r["onv"] for r in rows], [r["params"] for r in rows], "o-", color=colour,
                      label=label.split(",")[0])
    ax_m.set(xscale="log", yscale="log", xlabel="ONV dimension 3P", ylabel="peak memory of one training step (MiB)",
             title="(a) memory: batch 64, Adam")
    ax_p.set(xscale="log", yscale="log", xlabel="ONV dimension 3P", ylabel="trainable parameters",
             title="(b) parameters: H=4, f=5, R=5")
    for ax in (ax_m, ax_p):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    try:
        atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=120))
    finally:
        plt.close(fig)
