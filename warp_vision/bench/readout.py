"""The foveation CNN's read-out: inference time of the consensus of N views against the plain image's.

The net is the default preset's retina CNN (untrained: its cost does not depend on its weights) on the
default foveation data config's retina (P = 14,400); inputs are random standardised ONVs. Each setting is timed in interleaved
rounds (:func:`warp_vision.bench.common.interleaved_ms`), so its ratio to one view comes from one run.
"""

from __future__ import annotations

import torch

from warp_vision.bench.common import interleaved_ms


def run(views=(1, 4, 8), batches=(1, 64), repeats: int = 10, device: str = "cpu", log=print) -> dict:
    from warp_vision.data.foveation import FoveationDataConfig, make_eye, make_retina
    from warp_vision.nn.retina_cnn import RetinaCNNFoveationNet

    data = FoveationDataConfig()
    angles = make_retina(data).visual_angles(make_eye(data))
    torch.manual_seed(0)
    net = RetinaCNNFoveationNet(angles).to(device).eval()
    out = {"photoreceptors": int(len(angles)), "views": list(views), "batches": list(batches), "results": []}
    for b in batches:
        x = torch.randn(b, 3 * len(angles), device=device)

        def case(n):
            def fn():
                net.views = n
                with torch.no_grad():
                    net(x)
            return fn, None

        t = interleaved_ms({str(n): case(n) for n in views}, repeats=repeats, warmup=2, device=device)
        base = t[str(views[0])]["median_ms"]
        for n in views:
            row = {"batch": b, "views": n, **t[str(n)], f"ratio_to_{views[0]}_views": t[str(n)]["median_ms"] / base}
            out["results"].append(row)
            log(f"batch {b:4d}, {n:2d} view(s): median {row['median_ms']:8.1f} ms "
                f"({row['median_ms'] / b:6.2f} ms an ONV), {row[f'ratio_to_{views[0]}_views']:.2f}x {views[0]} view(s)")
    return out
