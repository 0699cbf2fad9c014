"""Render what an eye sees, and draw it.

A furnished room with a white ball (warp_vision.scene.room), one physiological eye (the Navarro model with
an accommodating lens and a pupil), a foveated retina of P photoreceptors, and the Warp ray tracer that
traces S rays per photoreceptor through lens and cornea into the room. The result is the Optic Nerve
Vector (ONV): [B, 3P] linear irradiance, three colour channels per photoreceptor. The script draws it as
a retina image (each photoreceptor a dot of its colour, in degrees of eccentricity; the optics invert the
image: the ball straight ahead sits at the centre, the ceiling lamp near the bottom) beside a third-person view.

Run:
    python examples/render_eye.py                        # P = 14,400, S = 16 (a few seconds on a 2-core CPU)
    python examples/render_eye.py --photoreceptors 2000 --samples 4 --out /tmp/eye
    python examples/render_eye.py --device cuda          # the same kernels on a GPU
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    p.add_argument("--photoreceptors", type=int, default=14_400, help="P, photoreceptors on the retina")
    p.add_argument("--samples", type=int, default=16, help="S, rays per photoreceptor and channel")
    p.add_argument("--layout", choices=["log-polar", "cone-density"], default="log-polar")
    p.add_argument("--accommodation", type=float, default=0.5,
                   help="lens accommodation, dioptres (0.5: focused at 2 m)")
    p.add_argument("--pupil", type=float, default=4.0, help="pupil diameter, mm")
    p.add_argument("--out", default="runs/examples/render_eye", help="output directory")
    args = p.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warp_vision import viz
    from warp_vision.eye.optics import NavarroEye
    from warp_vision.eye.retina import Retina
    from warp_vision.frames import eye_look_at, look_at
    from warp_vision.kernels.launch import require_device
    from warp_vision.kernels.render import render_camera, render_onv
    from warp_vision.scene.room import make_room

    device = require_device(args.device)  # "cuda" -> "cuda:0"; a one-line error where there is none

    # the eye and its retina: the layout is bounded by the part of the retina this eye's optics light
    eye = NavarroEye(accommodation_D=args.accommodation, pupil_diameter_mm=args.pupil)
    make = Retina.log_polar if args.layout == "log-polar" else Retina.cone_density
    retina = make(args.photoreceptors, seed=1, eye=eye)

    # the scene: a 6 x 6 x 3 m room, a ceiling lamp, boxes and cylinders, and a white ball 3 m ahead
    room = make_room(seed=0)
    eye_at, ball_at = np.array([0.0, -1.5, 1.2]), np.array([0.0, 1.5, 1.2])
    poses = eye_look_at(eye_at, ball_at)[None]  # [B=1, 4, 4] world-from-eye: +z is the optical axis

    t0 = time.perf_counter()
    onv = render_onv(room, retina, eye, poses, samples_per_receptor=args.samples, device=device)  # [1, 3P]
    dt = time.perf_counter() - t0  # the first call also aims the eye's rays through the optics and builds the BVH
    rgb = onv[0].reshape(-1, 3).cpu().numpy()
    print(f"retina: {args.layout}, P = {retina.P:,}; eye: {eye!r}")
    print(f"ONV: shape {tuple(onv.shape)}, {onv.dtype}, rendered in {dt:.2f} s on {device}")
    central = np.argsort(retina.rho)[: max(1, retina.P // 50)]  # the 2% of photoreceptors nearest the fovea
    print(f"irradiance: mean {rgb.mean():.4f}, max {rgb.max():.4f}; "
          f"at the fovea {rgb[central].mean():.4f} (the white ball it looks at)")

    view = render_camera(room, look_at([2.4, -2.6, 2.2], [0.0, 0.5, 1.0]), 320, 240, 70.0, device=device)
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 5))
    viz.plot_onv(retina, onv[0], ax=a, title=f"what the eye sees: the ONV (P = {retina.P:,})")
    viz.plot_image(view, ax=b, title="a third-person view (the eye stands at y = -1.5 m)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "render_eye.png", dpi=100, bbox_inches="tight")
    np.save(out / "onv.npy", onv[0].cpu().numpy())
    print(f"wrote {out / 'render_eye.png'} and {out / 'onv.npy'}")


if __name__ == "__main__":
    main()
