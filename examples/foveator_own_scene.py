"""A trained foveation net on a scene of your own.

A foveation run (python -m warp_vision.train ...) leaves a run directory whose net reads an ONV and says
where the ball is: its (yaw, pitch) in the eye frame, the eye rotation that would bring it onto the fovea.
`Foveator` loads that net together with the retina and the optical state its training ONVs were rendered
with. This script builds a scene the net never saw, with warp_vision.scene (a ball on a table, a lamp, a
floor and a wall), lets the eye look at several points around the ball, renders each ONV with the run's
retina, and prints the net's estimate beside the truth. A v7 net (the smoke and paper presets' generator)
learnt a glowing ball in a dim room, a v8 or v9 net an ordinary lit ball: the scene follows the run.

Run:
    python -m warp_vision.train --preset smoke --out runs/smoke    # a first run: about a minute on 2 CPU cores
    python examples/foveator_own_scene.py --run runs/smoke
    python examples/foveator_own_scene.py --run runs/foveation --views 8   # the main job's net (v9, P = 14,400)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def table_scene(glowing: bool, ball_at: np.ndarray, radius: float):
    """A floor, a wall, a table with a ball on it and a lamp; dimmed, with the ball glowing, for a v7 net."""
    from warp_vision.data.foveation import BALL_EMISSION, ROOM_ALBEDO
    from warp_vision.frames import translation
    from warp_vision.scene import Material, Scene

    dim = ROOM_ALBEDO / 0.4 if glowing else 1.0  # v7's rooms: everyday albedos times ROOM_ALBEDO / 0.4

    def matte(rgb):
        return Material(tuple(dim * np.asarray(rgb)))

    sc = Scene(ambient=(0.05, 0.05, 0.05))
    sc.add_box("floor", (8.0, 8.0, 0.05), translation([0, 0, -0.025]), matte((0.45, 0.42, 0.38)), static=True)
    sc.add_box("wall", (8.0, 0.05, 3.0), translation([0, 2.5, 1.5]), matte((0.62, 0.55, 0.45)), static=True)
    sc.add_box("table_top", (1.2, 0.8, 0.04), translation([0, 1.0, 0.73]), matte((0.5, 0.32, 0.18)), static=True)
    for i, (x, y) in enumerate([(-0.55, 0.65), (0.55, 0.65), (-0.55, 1.35), (0.55, 1.35)]):
        sc.add_box(f"leg_{i}", (0.05, 0.05, 0.71), translation([x, y, 0.355]), matte((0.4, 0.26, 0.15)), static=True)
    ball = (Material((1.0, 1.0, 1.0), specular=0.4, smooth=True, emission=(BALL_EMISSION,) * 3) if glowing
            else Material((0.7, 0.7, 0.7), specular=0.3, shininess=32, smooth=True))
    sc.add_sphere("ball", radius, ball_at, ball)
    sc.add_light([0.3, 0.6, 2.6], (1.0, 0.95, 0.85), 6.0)
    return sc


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", help="a foveation run's directory (e.g. runs/smoke, runs/foveation)")
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda")
    p.add_argument("--views", type=int, default=6, help="how many eye poses (fixation points around the ball)")
    p.add_argument("--max-offset", type=float, default=20.0, help="deg: the farthest the eye looks from the ball")
    p.add_argument("--out", default="runs/examples/foveator_own_scene", help="output directory (estimates.json)")
    args = p.parse_args()
    if not args.run or not (Path(args.run) / "best.pt").is_file():
        sys.exit(f"--run: {args.run or '(none given)'} holds no finished foveation run; make one with\n"
                 "    python -m warp_vision.train --preset smoke --out runs/smoke\n"
                 "(about a minute) and pass --run runs/smoke")

    from warp_vision.frames import eye_look_at, gaze_angles, gaze_directions
    from warp_vision.kernels.launch import require_device
    from warp_vision.kernels.render import render_onv
    from warp_vision.sim.loop import Foveator

    device = require_device(args.device)
    fov = Foveator(args.run, device=device)  # the net, its retina and the eye its training ONVs were rendered through
    print(f"{args.run}: a generator v{fov.generator} net, P = {fov.retina.P:,}, {fov.trained_eye!r}")

    ball, radius, eye_at = np.array([0.15, 1.0, 0.81]), 0.06, np.array([0.0, -0.1, 1.25])
    scene = table_scene(fov.generator == 7, ball, radius)
    rng = np.random.default_rng(0)
    toward = eye_look_at(eye_at, ball)  # fixating the ball; the other views look away from it by up to --max-offset
    away = np.radians(rng.uniform(-args.max_offset, args.max_offset, (args.views, 2)))
    away[0] = 0.0
    poses = np.stack([eye_look_at(eye_at, eye_at + toward[:3, :3] @ gaze_directions(a)) for a in away])  # [B, 4, 4]
    onv = render_onv(scene, fov.retina, fov.trained_eye, poses, fov.samples_per_receptor, device=device)  # [B, 3P]
    true = np.stack([gaze_angles(T[:3, :3].T @ (ball - T[:3, 3])) for T in poses])  # the ball in each eye frame
    est = fov(onv)  # [B, 2] rad
    err = np.degrees(np.arccos(np.clip(np.sum(gaze_directions(true) * gaze_directions(est), 1), -1, 1)))

    print(" view   true yaw, pitch (deg)   estimate yaw, pitch (deg)   off by (deg)")
    for i in range(len(poses)):
        t, e = np.degrees(true[i]), np.degrees(est[i])
        print(f" {i:4d}   {t[0]:+7.1f} {t[1]:+7.1f}          {e[0]:+7.1f} {e[1]:+7.1f}            {err[i]:6.2f}")
    print(f"median error {np.median(err):.2f} deg over {len(poses)} views")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "estimates.json").write_text(json.dumps(
        {"run": str(args.run), "true_deg": np.degrees(true).tolist(), "estimate_deg": np.degrees(est).tolist(),
         "error_deg": err.tolist()}, indent=1))
    print(f"wrote {out / 'estimates.json'}")


if __name__ == "__main__":
    main()
