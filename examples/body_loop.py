"""The body in the loop for one second.

The MuJoCo body (a head on neck muscles, two eyes each turned by six Hill-type muscles, optionally
myo-sim's arms) runs in the closed visuomotor loop, warp_vision.sim.loop.VisuomotorLoop: every 10 ms
control period the gaze controller decides a change of gaze and the oculomotor nets turn it into muscle
activations; every 4th period (25 frames a second) both eyes render their ONVs from the MuJoCo state.
A ball appears 15 deg to the right and 1 m away, then at 0.5 s jumps 25 deg to the left: the eyes
saccade to it, converge on it, and the neck turns the head after them.

By default it needs no training: the gaze controller is told the ball's true direction
(perception="oracle"; the eyes still render) and the oculomotor nets are stood in for by what they are
trained to reproduce, the body's own least-effort holding activations. With --nets DIR it uses trained
nets instead: DIR/foveation_left, DIR/foveation_right and DIR/oculomotor/{left,right}, as
`python -m warp_vision.sim demo --quick` leaves them in runs/quick.

Run:
    python examples/body_loop.py                        # the bare torso, oracle perception (about 10 s on 2 CPU cores)
    python examples/body_loop.py --arms --photoreceptors 2000
    python examples/body_loop.py --nets runs/quick      # the quick nets of sim demo --quick (about 40 s)
"""

from __future__ import annotations

import argparse
import os
import time
from types import SimpleNamespace

import numpy as np
import torch


class HoldingActivations:
    """Stands in for an oculomotor net: integrates the commanded gaze changes and returns the least-effort
    activations that hold that gaze (:func:`warp_vision.sim.oculomotor.eye_holding_activations`)."""

    def __init__(self, body, side):
        self.body, self.side, self.gaze = body, side, np.zeros(2)

    def __call__(self, change, activations):
        from warp_vision.sim.oculomotor import eye_holding_activations

        self.gaze = self.gaze + change[0].numpy()
        return torch.as_tensor(eye_holding_activations(self.body, self.side, self.gaze[None])[0], dtype=torch.float32)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda: where the trained nets run (--nets)")
    p.add_argument("--nets", help="a directory of trained nets (e.g. runs/quick); default: oracle and stand-ins")
    p.add_argument("--arms", action="store_true", help="myo-sim's muscle-driven arms (slower to step and render)")
    p.add_argument("--photoreceptors", type=int, default=1000, help="P of the stand-ins' retinas (not with --nets)")
    p.add_argument("--duration", type=float, default=1.0, help="simulated seconds")
    p.add_argument("--out", default="runs/examples/body_loop", help="output directory (gaze_error.png)")
    args = p.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warp_vision.body import SIDES, Body, BodyConfig
    from warp_vision.data.foveation import FoveationDataConfig, make_retina
    from warp_vision.kernels.launch import require_device
    from warp_vision.sim.loop import Foveator, VisuomotorLoop, point_at
    from warp_vision.sim.oculomotor import load_oculomotor
    from warp_vision.sim.scenarios import SETTLE_S, run_scenario

    device = require_device(args.device)
    body = Body(BodyConfig(arms=args.arms))
    body.step(int(SETTLE_S / body.model.opt.timestep))  # the passive arms settle under gravity
    body.model.opt.gravity[:] = 0  # the ball is placed kinematically
    if args.nets:
        fov = {s: Foveator(os.path.join(args.nets, f"foveation_{s}"), device, eye=s) for s in SIDES}
        loop = VisuomotorLoop(body, fov, load_oculomotor(os.path.join(args.nets, "oculomotor")), ball="ordinary")
    else:  # what the eyes render with: a retina each (P photoreceptors), one ray per photoreceptor and channel
        fov = {s: SimpleNamespace(retina=make_retina(FoveationDataConfig(photoreceptors=args.photoreceptors, eye=s)),
                                  samples_per_receptor=1) for s in SIDES}
        loop = VisuomotorLoop(body, fov, {s: HoldingActivations(body, s) for s in SIDES}, ball="ordinary",
                              perception="oracle")
    first, second = point_at(body, 15.0, 5.0, 1.0), point_at(body, -10.0, -3.0, 0.8)

    t0 = time.perf_counter()
    tr = run_scenario(loop, args.duration, ball=lambda t: first if t < 0.5 else second, progress=False)
    wall = time.perf_counter() - t0
    print(f"{'nets in ' + args.nets if args.nets else 'oracle perception, holding activations'}; "
          f"{'arms' if args.arms else 'bare torso'}; {len(tr['t'])} control periods, "
          f"{-(-loop.period // loop.frame_every)} frames")
    print("    t (s)   gaze error left, right (deg)   head yaw (deg)")
    for k in range(9, len(tr["t"]), 10):
        print(f"   {tr['t'][k]:5.2f}   {tr['error_left'][k]:8.2f} {tr['error_right'][k]:8.2f}"
              f"           {np.degrees(tr['neck'][k][0]):+6.2f}")
    shares = ", ".join(f"{k} {v / wall:.0%}" for k, v in loop.timing.items())
    print(f"{args.duration:g} simulated s in {wall:.1f} wall s ({shares})")

    fig, ax = plt.subplots(figsize=(7, 3.5))
    for s in SIDES:
        ax.plot(tr["t"], tr[f"error_{s}"], label=f"{s} eye")
    ax.axvline(0.5, color="0.6", ls=":", label="the ball jumps")
    ax.set(xlabel="simulated time (s)", ylabel="gaze error (deg)", yscale="log", title="the body in the loop")
    ax.legend()
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "gaze_error.png")
    fig.savefig(path, dpi=100, bbox_inches="tight")
    np.savez(os.path.join(args.out, "trace.npz"), **tr)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
