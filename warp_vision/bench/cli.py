"""Command line of ``python -m warp_vision.bench``: kernel microbenchmarks written as JSON.

``linet`` and ``raytrace`` take ``--device`` (``cpu``, ``cuda`` or ``cuda:N``); a device that Warp and
torch cannot run on here is refused in one ``error:`` line (exit code 2) before any work is done.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from warp_vision.bench.common import machine_info
from warp_vision.errors import ArgumentParser, add_debug_flag, guarded, long_options, require_positive
from warp_vision.fileio import require_output, write_json
from warp_vision.limits import require_int
from warp_vision.provenance import software

#: what ``python -m warp_vision.bench`` with no command runs, in order, each on its defaults: the benchmarks of
#: the two kernels everything else stands on (the liNet layer, the ray tracer)
KERNELS = ("linet", "raytrace")


def _parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="python -m warp_vision.bench",
        description="Kernel microbenchmarks. Each writes JSON (with machine info) to --out. With no command: "
                    f"{' and '.join(KERNELS)}, the kernels' benchmarks, on their defaults (about 5 minutes on a "
                    "2-core CPU).",
    )
    sub = p.add_subparsers(dest="bench")

    lin = sub.add_parser("linet", help="locally-connected layer: Warp vs plain-torch gather, index_add and CSR")
    lin.add_argument("--photoreceptors", type=int, nargs="+", default=[14_400, 144_000],
                     help="photoreceptor counts P (N_in = 3P); default: the paper's 14,400 and 10x that")
    lin.add_argument("--batch", type=int, default=64, help="batch size B (default 64)")
    lin.add_argument("--reduction", type=int, default=5, help="N = N_in // reduction (default 5)")
    lin.add_argument("--receptive-field", type=int, default=20, help="R (default 20)")
    lin.add_argument("--device", default="cpu",
                     help="cpu (default), cuda or cuda:N. On cuda the layer's tensors (drawn as on the CPU) move to "
                          "the GPU and the Warp op and the torch baselines are timed there; the CPU-only parts (the "
                          "1-thread Warp variant, the Warp kernels timed alone) are skipped and named under "
                          "\"skipped\" in the JSON")

    mem = sub.add_parser("memory", help="Fig. 4: parameters and peak training-step memory vs ONV size")
    mem.add_argument("--sizes", type=int, nargs="+", default=None, help="ONV sizes 3P (default 1e3 .. 1.28e7)")
    mem.add_argument("--batch", type=int, default=64, help="batch size (default 64)")
    mem.add_argument("--budget-gib", type=float, default=14.0,
                     help="run only configurations whose memory floor fits this (GiB; default 14); estimate the rest")
    mem.add_argument("--worker", nargs=3, metavar=("MODEL", "ONV", "DTYPE"), help=argparse.SUPPRESS)

    rtp = sub.add_parser("raytrace", help="closest-hit rays/s (Warp packets vs wp.Mesh vs Embree) and ONVs/s")
    rtp.add_argument("--photoreceptors", type=int, default=14_400, help="P per retina (default 14,400)")
    rtp.add_argument("--samples", type=int, default=16, help="S rays per photoreceptor and channel (default 16)")
    rtp.add_argument("--batch", type=int, default=4, help="ONVs rendered per launch (default 4)")
    rtp.add_argument("--device", default="cpu",
                     help="cpu (default), cuda or cuda:N. On cuda the eye rays, the Warp packet and wp.Mesh "
                          "closest-hit kernels (one launch each: no thread variants) and the ONV render run on the "
                          "GPU; Embree (CPU) is not timed, its hits only checking agreement when embreex is "
                          "installed; the JSON names what was skipped under \"skipped\"")
    lop = sub.add_parser("loop", help="the closed loop: simulated/wall, time shares and accuracy per visual frame rate")
    lop.add_argument("--frame-every", type=int, nargs="+", default=None,
                     help="settings: the eyes render every N control periods of 10 ms (default: 1, a render every "
                          "period, and the loop's default)")
    lop.add_argument("--quick", action="store_true", help="the --quick nets of python -m warp_vision.sim")
    lop.add_argument("--no-progress", action="store_true", help="no progress bars")
    rdo = sub.add_parser("readout", help="the foveation CNN's inference: the consensus of N views vs the plain image, "
                                         "float32 vs bfloat16, and the views' binning: CSR product vs index_add_")
    rdo.add_argument("--views", type=int, nargs="+", default=[1, 4, 8],
                     help="settings (default 1 4 8; the first is the ratios' base)")
    rdo.add_argument("--batch", type=int, nargs="+", default=[1, 64],
                     help="ONVs per call (default 1, as the loop's eyes, and 64)")
    rdo.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    cnn = sub.add_parser("cnn", help="the retina CNN's training step: float32 vs bfloat16 autocast (--precision)")
    cnn.add_argument("--channels", type=int, nargs="+", default=[16, 24, 32],
                     help="widths (default 16, the default preset's, 24 and 32)")
    cnn.add_argument("--batch", type=int, default=64, help="ONVs per step (default 64)")
    cnn.add_argument("--device", default="cpu", help="cpu (default), cuda or cuda:N")
    repeats = {"linet": 10, "raytrace": 5, "readout": 10, "cnn": 10}  # (memory and loop time no repeats)
    for name, q in sub.choices.items():
        if name in repeats:
            q.add_argument("--repeats", type=int, default=repeats[name],
                           help=f"timed repeats per measurement, the median reported (default {repeats[name]})")
        q.add_argument("--out", default=f"bench_results/{name}.json",
                       help="JSON output path (default "
                            f"bench_results/{name}.json{'; the PNG goes beside it' if q is mem else ''})")
        add_debug_flag(q)
    return p


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    if args.bench is None:
        runs = [p.parse_args([name]) for name in KERNELS]
        return guarded(lambda: _kernels(runs), False, options=long_options(p))
    return guarded(lambda: _bench(args), args.debug, options=long_options(p))


def _kernels(runs: list) -> int:
    """Each of ``runs`` (parsed ``KERNELS`` commands) in turn, every output checked before the first's timing."""
    for args in runs:
        require_output(args.out, "--out", kind="file")
    print(f"the kernel benchmarks, on their defaults: {', then '.join(a.bench for a in runs)} "
          f"('python -m warp_vision.bench --help' lists the others)")
    for args in runs:
        print(f"-- python -m warp_vision.bench {args.bench}")
        _bench(args)
    return 0


def _device(name: str) -> str:
    """``--device`` as a torch device name ("cpu", "cuda:N"), or a one-line ValueError when it is not
    one, Warp and torch see no such GPU here, or (cpu) Warp cannot compile CPU kernels here."""
    import torch

    from warp_vision.kernels.launch import require_device

    dev = "cuda:0" if name == "cuda" else str(name)
    n = torch.cuda.device_count()
    if dev.startswith("cuda:") and dev[5:].isdigit() and int(dev[5:]) >= n:
        # asked of torch first: initialising Warp on a machine without a driver prints a warning of its own
        raise ValueError(f"--device: {name} requested, but torch sees {n} CUDA device(s) on this machine; use --device "
                         "cpu")
    try:
        dev = require_device(name)
    except ValueError as e:
        raise ValueError(f"--{e}") from None
    if dev == "cpu":
        import warp as wp

        from warp_vision.kernels.launch import init

        init()
        if not wp.is_cpu_available():
            raise ValueError("--device: cpu requested, but this Warp cannot compile CPU kernels (no warp-clang); "
                             "use --device cuda")
    return dev


def _bench(args) -> int:
    if args.bench == "memory" and args.worker:
        from warp_vision.bench.memory import worker

        print(json.dumps(worker(args.worker[0], int(args.worker[1]), args.batch, input_dtype=args.worker[2])))
        return 0
    device = _device(args.device) if hasattr(args, "device") else "cpu"  # before any work
    require_output(args.out, "--out", kind="file")  # (and the memory figure beside it) before minutes of timing
    if args.bench == "memory":
        if Path(args.out).suffix == ".png":
            raise ValueError(f"--out: {args.out} names the figure's path (the JSON's, with .png); give the JSON's, "
                             f"e.g. {Path(args.out).with_suffix('.json')}")
        require_output(Path(args.out).with_suffix(".png"), "--out (its figure)", kind="file")
    t0 = time.time()
    info, code = machine_info(), software()
    print(f"machine: {info['cpu']}, {info['cores']} cores; torch {code['torch']} ({info['torch_threads']} threads), "
          f"warp {code['warp-lang']}")
    if args.bench == "linet":
        from warp_vision.bench import linet

        require_positive(args, ("photoreceptors", "batch", "reduction", "receptive_field", "repeats"))
        result = linet.run(args.photoreceptors, args.batch, args.reduction, args.receptive_field, args.repeats,
                           device=device)
    elif args.bench == "raytrace":
        from warp_vision.bench import raytrace

        require_positive(args, ("photoreceptors", "samples", "batch", "repeats"))
        result = raytrace.run(args.repeats, args.photoreceptors, args.samples, args.batch, device=device)
    elif args.bench == "readout":
        from warp_vision.bench import readout
        from warp_vision.nn.retina_cnn import consensus_transforms

        for n in args.views:
            consensus_transforms(n)  # (validates: 1 to 48)
        require_positive(args, ("batch", "repeats"))
        result = readout.run(args.views, args.batch, args.repeats, device=device)
    elif args.bench == "cnn":
        from warp_vision.bench import cnn

        require_positive(args, ("channels", "repeats"))
        if args.batch < 4:
            raise ValueError(f"--batch: expected at least 4 (four augmentation groups), got {args.batch}")
        result = cnn.run(args.channels, args.batch, args.repeats, device=device)
    elif args.bench == "loop":
        from warp_vision.bench import loop

        if args.frame_every:
            require_positive(args, ("frame_every",))
        result = loop.run(args.frame_every or (1, None), quick=args.quick, progress=not args.no_progress)
    else:
        from warp_vision.bench import memory

        sizes = args.sizes or memory.DEFAULT_SIZES
        require_positive(args, ("batch",))
        for size in sizes:  # (each of the liNet's 4 layers a fifth of the last: 375 inputs leave 3 at the top)
            require_int(size, memory.ONV_SIZES, "--sizes")
        if not (math.isfinite(args.budget_gib) and args.budget_gib > 0):
            raise ValueError(f"--budget-gib: expected a positive number, got {args.budget_gib}")
        result = memory.run(sizes, args.batch, args.budget_gib)
        png = str(Path(args.out).with_suffix(".png"))
        memory.plot(result, png)
        result["figure"] = png
        print(f"figure: {png}")
    result = {"benchmark": args.bench, "machine": info, "software": code, "seconds": time.time() - t0, **result}
    write_json(args.out, result)
    print(f"results: {args.out}")
    return 0
