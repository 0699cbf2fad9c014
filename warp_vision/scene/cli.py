"""``python -m warp_vision.scene demo``: render the furnished room through one biomimetic eye.

Writes to --out: ``camera.png`` (a third-person pinhole view of the room), ``onv.png`` (the ONV as a
retina image), ``eye_rays.png`` (photoreceptors' rays through the optics, Fig. 2c), ``retina.png`` (the
photoreceptor layout, Fig. 2b) and ``onv.npy`` (the ONV, [3P] float32).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from warp_vision.errors import ArgumentParser, add_debug_flag, guarded, long_options, require_positive
from warp_vision.limits import SEED, integer


def _parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="python -m warp_vision.scene", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("demo", help="render the room with a ball through one eye and write figures")
    d.add_argument("--photoreceptors", type=int, default=14_400,
                   help="P, photoreceptors on the retina (default 14,400)")
    d.add_argument("--layout", choices=["log-polar", "cone-density"], default="log-polar",
                   help="retina layout (default log-polar)")
    d.add_argument("--samples", type=int, default=16, help="S rays per photoreceptor and channel (default 16)")
    d.add_argument("--accommodation", type=float, default=0.0, help="lens accommodation in dioptres (default 0)")
    d.add_argument("--pupil", type=float, default=4.0, help="pupil diameter in mm (default 4)")
    d.add_argument("--seed", type=integer(SEED), default=0, help="seed of the retina and the room (default 0)")
    d.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    d.add_argument("--out", default="runs/eye_demo", help="output directory (default runs/eye_demo)")
    add_debug_flag(d)
    return p


def main(argv: list[str] | None = None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    return guarded(lambda: _eye_demo(args), args.debug, options=long_options(p))


def _eye_demo(args) -> int:
    from warp_vision import viz
    from warp_vision.eye.optics import NavarroEye
    from warp_vision.eye.retina import Retina
    from warp_vision.fileio import require_output
    from warp_vision.frames import eye_look_at, look_at
    from warp_vision.kernels.launch import require_device
    from warp_vision.kernels.render import render_camera, render_onv
    from warp_vision.scene.room import make_room

    require_positive(args, ("photoreceptors", "samples"))
    device = require_device(args.device)
    require_output(args.out, "--out")
    try:
        eye = NavarroEye(args.accommodation, args.pupil)
    except ValueError as e:  # named by the eye's parameters: said as this command's flags
        flag = {"accommodation_D": "--accommodation", "pupil_diameter_mm": "--pupil"}
        name, _, rest = str(e).partition(": ")
        raise ValueError(f"{flag[name]}: {rest}" if name in flag else str(e)) from None
    make = Retina.log_polar if args.layout == "log-polar" else Retina.cone_density
    retina = make(args.photoreceptors, seed=args.seed, eye=eye)
    out = Path(args.out)  # (made once the settings are known good: a bad --pupil left it behind, empty)
    out.mkdir(parents=True, exist_ok=True)
    room = make_room(seed=args.seed)
    eye_centre, ball = np.array([0.0, -1.5, 1.2]), np.array([0.0, 1.5, 1.2])
    pose = eye_look_at(eye_centre, ball)
    t0 = time.perf_counter()
    onv = render_onv(room, retina, eye, pose[None], args.samples, args.seed, device=device)
    t1 = time.perf_counter()
    onv = render_onv(room, retina, eye, pose[None], args.samples, args.seed, device=device)
    t2 = time.perf_counter()
    print(f"ONV: P={retina.P:,}, S={args.samples}: {t1 - t0:.2f} s first (eye rays + BVH), {t2 - t1:.3f} s again")
    np.save(out / "onv.npy", onv[0].cpu().numpy())
    files = {
        "onv.png": viz.plot_onv(retina, onv[0], title=f"ONV of the room, looking at the ball (P = {retina.P:,})"),
        "camera.png": viz.plot_image(
            render_camera(room, look_at([2.4, -2.6, 2.2], [0.0, 0.5, 1.0]), 480, 360, 70.0, device=device),
            title="third-person view",
        ),
        "eye_rays.png": viz.plot_eye_rays(eye),
        "retina.png": viz.plot_retina_layout(retina),
    }
    for name, fig in files.items():
        fig.savefig(out / name, dpi=120, bbox_inches="tight")
        print(f"wrote {out / name}")
    return 0
