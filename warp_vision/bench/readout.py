"""The foveation CNN's read-out: inference time of the consensus of N views against the plain image's, in
float32 (what inference runs in) and under bfloat16 autocast (the alternative, not adopted: docs/RESULTS.md,
"bfloat16 inference"; here the whole call runs under it, read-out included, whose cost is negligible),
and the binning of the views' images (one CSR product) against an ``index_add_`` of the same entries
(what it replaced).

The net is the default preset's retina CNN (untrained: its cost does not depend on its weights) on the
default foveation data config's retina (P = 14,400); inputs are random standardised ONVs. Each group of
settings is timed in interleaved rounds (:func:`warp_vision.bench.common.interleaved_ms`), so its ratios
come from one run. ``native_bfloat16`` says whether the device computes bfloat16 in hardware (elsewhere
torch emulates it).
"""

from __future__ import annotations

import torch

from warp_vision.bench.common import interleaved_ms

#: what the read-out is timed in, the first the ratios' base
TIMED = ("float32", "bfloat16")


def index_add_images(net, x: torch.Tensor, ks) -> torch.Tensor:
    """The reference for :meth:`~warp_vision.nn.retina_cnn.RetinaImageCNN.view_images` (and its binning before
    the CSR product): each view's image by an ``index_add_`` of its (pixel, photoreceptor, weight) entries,
    concatenated view by view, channels_last."""
    b, n = x.shape[0], net.warp.size
    cols = x.reshape(b, net.P, 3).permute(1, 0, 2).reshape(net.P, b * 3).float()
    out = []
    for k in ks:
        pix, pr, w = (t.to(x.device) for t in net.binning(int(k)))
        img = cols.new_zeros(n * n, b * 3).index_add_(0, pix, cols[pr] * w[:, None])
        out.append(img.reshape(n, n, b, 3).permute(2, 3, 0, 1))
    return torch.cat(out).contiguous(memory_format=torch.channels_last)


def run(views=(1, 4, 8), batches=(1, 64), repeats: int = 10, device: str = "cpu", log=print) -> dict:
    from warp_vision.data.foveation import FoveationDataConfig, make_eye, make_retina
    from warp_vision.nn.retina_cnn import RetinaCNNFoveationNet, consensus_transforms, native_bfloat16

    data = FoveationDataConfig()
    angles = make_retina(data).visual_angles(make_eye(data))
    dev = torch.device(device)
    torch.manual_seed(0)
    net = RetinaCNNFoveationNet(angles).to(dev).eval()
    out = {"photoreceptors": int(len(angles)), "views": list(views), "batches": list(batches),
           "native_bfloat16": native_bfloat16(dev.type), "results": [], "binning": []}
    base_name = f"ratio_to_{views[0]}_views"
    for b in batches:
        x = torch.randn(b, 3 * len(angles), device=dev)

        def case(n, precision):
            def fn():
                net.views = n
                with torch.no_grad(), torch.autocast(dev.type, dtype=torch.bfloat16, enabled=precision == "bfloat16"):
                    net(x)
            return fn, None

        t = interleaved_ms({f"{n} {p}": case(n, p) for n in views for p in TIMED}, repeats=repeats, warmup=2,
                           device=device)
        base = t[f"{views[0]} {TIMED[0]}"]["median_ms"]
        for n in views:
            for p in TIMED:
                m = t[f"{n} {p}"]["median_ms"]
                row = {"batch": b, "views": n, "precision": p, **t[f"{n} {p}"], base_name: m / base,
                       "speedup_over_float32": t[f"{n} {TIMED[0]}"]["median_ms"] / m}
                out["results"].append(row)
                log(f"batch {b:4d}, {n:2d} view(s), {p:8s}: median {m:8.1f} ms ({m / b:6.2f} ms an ONV), "
                    f"{row[base_name]:.2f}x {views[0]} view(s) in {TIMED[0]}, {row['speedup_over_float32']:.2f}x "
                    f"faster than {TIMED[0]}")
        ks = consensus_transforms(max(views))
        with torch.no_grad():
            if not torch.allclose(net.view_images(x, ks), index_add_images(net, x, ks), atol=1e-5):
                raise AssertionError("view_images: the CSR product differs from the index_add_ reference")
            tb = interleaved_ms({"csr": (lambda: net.view_images(x, ks), None),
                                 "index_add": (lambda: index_add_images(net, x, ks), None)},
                                repeats=repeats, warmup=2, device=device)
        row = {"batch": b, "views": len(ks), "csr_ms": tb["csr"]["median_ms"],
               "index_add_ms": tb["index_add"]["median_ms"],
               "speedup": tb["index_add"]["median_ms"] / tb["csr"]["median_ms"]}
        out["binning"].append(row)
        log(f"batch {b:4d}, binning {len(ks)} views: CSR product {row['csr_ms']:7.2f} ms, index_add_ "
            f"{row['index_add_ms']:7.2f} ms ({row['speedup']:.2f}x)")
    return out
