"""The retina CNN's training step: float32 against bfloat16 autocast (the training configs' ``precision``).

The net is the foveation CNN (:class:`warp_vision.nn.retina_cnn.RetinaCNNFoveationNet`, untrained: its cost
does not depend on its weights) on the default foveation data config's retina (P = 14,400), at each width
asked. One step is what the foveation task's training does for a batch: the ONVs binned through four
augmentations, the heat map's cross-entropy plus a regression loss of the read-out, backward, Adam. Inputs
are random standardised ONVs. The precisions are timed in interleaved rounds
(:func:`warp_vision.bench.common.interleaved_ms`), so each ratio comes from one run. ``native_bfloat16``
says whether the device computes bfloat16 in hardware (where it does not, torch emulates it).
"""

from __future__ import annotations

import torch

from warp_vision.bench.common import interleaved_ms

#: the precisions timed, the first the ratios' base
TIMED = ("float32", "bfloat16")


def run(channels=(16, 24, 32), batch: int = 64, repeats: int = 10, device: str = "cpu", log=print) -> dict:
    from warp_vision.data.foveation import FoveationDataConfig, make_eye, make_retina
    from warp_vision.nn.retina_cnn import RetinaCNNFoveationNet, native_bfloat16

    data = FoveationDataConfig()
    angles = make_retina(data).visual_angles(make_eye(data))
    dev = torch.device(device)
    out = {"photoreceptors": int(len(angles)), "batch": batch, "channels": list(channels),
           "native_bfloat16": native_bfloat16(dev.type), "results": []}
    g = torch.Generator().manual_seed(0)
    x = torch.randn(batch, 3 * len(angles), generator=g).to(dev)
    target = (torch.rand(batch, 2, generator=g) - 0.5).to(dev)  # rad: yaw and pitch within 0.5 (29 deg)
    ks = [0, 3, 10, 17]
    for c in channels:
        torch.manual_seed(0)
        net = RetinaCNNFoveationNet(angles, channels=c).to(dev).train()
        opt = torch.optim.Adam(net.parameters(), 1e-3)

        def case(precision):
            def step():
                net.train_precision = precision
                pred, logits = net(x, transform=ks, with_logits=True)
                loss = pred.square().mean() + net.heatmap_loss(logits, target)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
            return step, None

        t = interleaved_ms({p: case(p) for p in TIMED}, repeats=repeats, warmup=2, device=device)
        base = t[TIMED[0]]["median_ms"]
        for p in TIMED:
            row = {"channels": c, "parameters": sum(q.numel() for q in net.parameters()), "precision": p, **t[p],
                   "speedup_over_float32": base / t[p]["median_ms"]}
            out["results"].append(row)
            log(f"{c:3d} channels, {p:8s}: median {row['median_ms']:7.1f} ms a step of {batch} ONVs, "
                f"{row['speedup_over_float32']:.2f}x float32")
    return out
