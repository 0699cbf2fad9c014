"""A liNet on ONVs, forward and backward.

A liNet layer connects each unit only to its R nearest units of the previous layer on the retina, with a
weight of its own per connection: y[b, n] = bias[n] + sum_r weight[n, r] * x[b, index[n, r]]. Its forward
and backward passes are Warp gather kernels inside a torch.autograd.Function, so the net trains like any
torch module. This script renders a batch of ONVs of a glowing ball at random places in a dark room, puts a
liNet (H layers) and a linear read-out on them, and takes a few Adam steps on the ball's direction
(yaw, pitch), printing the shapes, the loss and each layer's gradient norm. It then checks the first
layer's Warp gradients against the plain-torch reference (warp_vision.kernels.linet.reference).

Run:
    python examples/linet_onv.py                          # P = 1,600, B = 64, 20 steps (about 10 s on 2 CPU cores)
    python examples/linet_onv.py --photoreceptors 400 --batch 16 --steps 5
    python examples/linet_onv.py --device cuda
"""

from __future__ import annotations

import argparse

import numpy as np
import torch


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    p.add_argument("--photoreceptors", type=int, default=1600, help="P, photoreceptors (the ONV is 3P wide)")
    p.add_argument("--batch", type=int, default=64, help="B, ONVs rendered (a multiple of 64 takes the SIMD kernels)")
    p.add_argument("--layers", type=int, default=3, help="H, liNet layers")
    p.add_argument("--receptive-field", type=int, default=20, help="R, connections per unit")
    p.add_argument("--steps", type=int, default=20, help="Adam steps")
    args = p.parse_args()

    from warp_vision.eye.optics import NavarroEye
    from warp_vision.eye.retina import Retina
    from warp_vision.frames import eye_look_at, gaze_angles, translation
    from warp_vision.kernels.launch import require_device
    from warp_vision.kernels.linet import locally_connected
    from warp_vision.kernels.linet.reference import locally_connected_ref
    from warp_vision.kernels.render import render_onv
    from warp_vision.nn import LiNet, onv_positions
    from warp_vision.scene import Material, Scene

    device = require_device(args.device)
    torch.manual_seed(0)
    rng = np.random.default_rng(0)

    # B ONVs: one eye at the origin looking along +y, a glowing ball at a random place within 25 deg
    eye = NavarroEye(accommodation_D=0.5, pupil_diameter_mm=4.0)
    retina = Retina.log_polar(args.photoreceptors, seed=1, eye=eye)
    scene = Scene(ambient=(0.02, 0.02, 0.02))
    scene.add_box("floor", (8.0, 8.0, 0.05), translation([0.0, 0.0, -1.2]), Material((0.3, 0.3, 0.3)), static=True)
    scene.add_sphere("ball", 0.12, material=Material(emission=(2.0, 2.0, 2.0), smooth=True))
    scene.add_light([0.0, 0.0, 2.0], intensity=2.0)
    yaw, pitch = np.radians(rng.uniform(-25, 25, (2, args.batch)))
    ball = 2.0 * np.stack([np.sin(yaw) * np.cos(pitch), np.cos(yaw) * np.cos(pitch), np.sin(pitch)], 1)
    scene.set_transform("ball", translation(ball))  # [B, 4, 4]: one ball position per batch row
    pose = eye_look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    onv = render_onv(scene, retina, eye, np.stack([pose] * args.batch), samples_per_receptor=4, device=device)
    x = torch.log1p(onv / onv.mean())  # a compressive photoreceptor response, [B, 3P]
    x = (x - x.mean()) / x.std()
    target = torch.as_tensor(gaze_angles(ball @ pose[:3, :3]), dtype=torch.float32, device=device)  # [B, 2] rad

    # the net: H liNet layers on the photoreceptors' positions in the retinal domain, and a linear read-out
    net = LiNet(onv_positions(retina.domain_xy), layers=args.layers, receptive_field=args.receptive_field,
                reduction=4, seed=0).to(device)
    head = torch.nn.Linear(net.out_features, 2).to(device)
    params = list(net.parameters()) + list(head.parameters())
    print(f"ONV x: {tuple(x.shape)}; liNet widths {net.layer_sizes}; "
          f"{net.num_parameters():,} liNet parameters (a dense first layer would have "
          f"{x.shape[1] * net.layer_sizes[1]:,})")
    opt = torch.optim.Adam(params, lr=1e-3)
    for step in range(args.steps):
        features = net(x)  # [B, N_H]: Warp forward kernels
        loss = torch.nn.functional.mse_loss(head(features), target)
        opt.zero_grad()
        loss.backward()  # Warp backward kernels (gathers over the transposed index)
        if step in (0, args.steps - 1):
            norms = ", ".join(f"{layer.weight.grad.norm():.3g}" for layer in net.layers)
            print(f"step {step:3d}: loss {loss.item():.5f} (rad^2); |grad weight| per layer: {norms}")
        opt.step()

    # the first layer's op against the plain-torch reference, values and gradients
    layer = net.layers[0]
    w = layer.weight.detach().clone().requires_grad_()
    xs = x[:8].clone().requires_grad_()
    y = locally_connected(xs, w, layer.bias.detach(), layer.index, relu=False)
    gx, gw = torch.autograd.grad(y.square().sum(), (xs, w))
    y_ref = locally_connected_ref(xs, w, layer.bias.detach(), layer.index)
    gx_ref, gw_ref = torch.autograd.grad(y_ref.square().sum(), (xs, w))
    def rel(a, b):  # the largest difference, relative to the largest value
        return ((a - b).abs().max() / b.abs().max()).item()

    print(f"Warp vs reference, largest relative difference: y {rel(y, y_ref):.1e}, grad_x {rel(gx, gx_ref):.1e}, "
          f"grad_weight {rel(gw, gw_ref):.1e}")

if __name__ == "__main__":
    main()
