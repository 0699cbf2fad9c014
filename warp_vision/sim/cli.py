"""``python -m warp_vision.sim``: the virtual human's closed-loop demos and measurements.

  demo         the cannon scenario: a ball flies into the periphery; both eyes saccade, converge and track
               it, the head follows. Writes a third-person GIF with the gaze lines, the left retina at four
               moments (Fig. 7) and the gaze error over time.
  experiments  saccades to a ball appearing at 20 deg in eight directions, vergence at 1 m, tracking a
               ball moving at 15 and 30 deg/s, the loop's time shares. Writes experiments.json.
  oculomotor   both eyes' oculomotor nets: runs 'python -m warp_vision.train oculomotor --eye left|right'
               for each eye whose net is missing (about 6 minutes for both).

The foveation nets come from ``python -m warp_vision.train --eye left --out runs/foveation_left`` and
``--eye right --out runs/foveation_right`` (about 8 minutes each on a 2-core CPU).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from warp_vision.errors import add_debug_flag, guarded
from warp_vision.fileio import write_json
from warp_vision.sim.body import SIDES, Body, BodyConfig

SETTLE_S = 0.2  # s of simulation before a scenario starts: the passive arms settle under gravity


def _setup(args):
    from warp_vision.sim.loop import Foveator, VisuomotorLoop
    from warp_vision.sim.oculomotor import load_oculomotor

    for side, run in (("left", args.left), ("right", args.right)):
        if not os.path.exists(os.path.join(run, "best.pt")):
            raise SystemExit(f"--{side} {run}: no trained foveation net there; make one with\n"
                             f"  python -m warp_vision.train --eye {side} --out {run}")
    provide_oculomotor(args.oculomotor, progress=not args.no_progress)
    body = Body(BodyConfig(arms=not args.no_arms))
    body.step(int(SETTLE_S / body.model.opt.timestep))
    fov = {"left": Foveator(args.left), "right": Foveator(args.right)}
    return body, VisuomotorLoop(body, fov, load_oculomotor(args.oculomotor), seed=args.seed)


def provide_oculomotor(root: str, progress: bool = True) -> None:
    """Train each eye's oculomotor net that ``root/<eye>`` lacks, with the training command (a process of
    its own: the simulation does not import the training code)."""
    import subprocess
    import sys

    for side in SIDES:
        out = os.path.join(root, side)
        if os.path.exists(os.path.join(out, "best.pt")):
            continue
        cmd = [sys.executable, "-m", "warp_vision.train", "oculomotor", "--eye", side, "--out", out]
        if os.path.exists(os.path.join(out, "latest.pt")):
            cmd = [sys.executable, "-m", "warp_vision.train", "oculomotor", "--resume", out]
        print(f"training the {side} eye's oculomotor net into {out} (about 3 minutes): {' '.join(cmd[1:])}", flush=True)
        if subprocess.run(cmd + ([] if progress else ["--no-progress"])).returncode != 0:
            raise SystemExit(f"training the {side} eye's oculomotor net failed (see above)")


def run_scenario(loop, duration: float, ball=None, record=None, progress: bool = True) -> dict:
    """Run the loop for ``duration`` s. ``ball(t)`` (optional) places the ball kinematically each period
    (t from the start); otherwise it flies freely. Returns per-period traces: time, ball position, each
    eye's gaze error (deg) and distance from its gaze line to the ball (m), neck angles (rad), the eyes'
    mean eccentricity in the head (deg)."""
    from tqdm import tqdm

    from warp_vision.sim.loop import CONTROL_DT, gaze_error_deg, line_distance

    body = loop.body
    t0 = body.time
    tr = {"t": [], "ball": [], "neck": [], "eye_in_head": [], **{f"error_{s}": [] for s in SIDES}, **{f"line_{s}": [] for s in SIDES}}
    for _ in tqdm(range(int(round(duration / CONTROL_DT))), desc="closed loop", disable=not progress, leave=False):
        if ball is not None:
            body.set_ball(ball(body.time - t0))
        loop.step()
        if ball is not None:
            body.set_ball(ball(body.time - t0))
        p = body.ball_position()
        tr["t"].append(body.time - t0)
        tr["ball"].append(p)
        tr["neck"].append(body.neck_angles())
        tr["eye_in_head"].append(np.mean([np.degrees(np.linalg.norm(body.gaze_in_head(s))) for s in SIDES]))
        for s in SIDES:
            tr[f"error_{s}"].append(gaze_error_deg(body, s, p))
            tr[f"line_{s}"].append(line_distance(body, s, p))
        if record is not None:
            record(loop)
    return {k: np.asarray(v) for k, v in tr.items()}


def experiments(args) -> dict:
    """Saccades to a ball appearing at 20 deg in eight directions (1 m away), vergence at the end of each,
    and tracking a ball circling the eyes at 15 and 30 deg/s; the loop's time shares."""
    from warp_vision.sim.loop import point_at

    body, loop = _setup(args)
    body.model.opt.gravity[:] = 0  # the ball is placed kinematically in these
    t = time.perf_counter()
    sim = 0.0
    trials = []
    for k in range(8):
        loop.reset(SETTLE_S)
        ang = np.radians(45.0 * k)
        p = point_at(body, 20.0 * np.cos(ang), 20.0 * np.sin(ang), 1.0)
        tr = run_scenario(loop, 0.8, ball=lambda _t: p, progress=not args.no_progress)
        sim += tr["t"][-1]
        both = np.maximum(tr["error_left"], tr["error_right"])
        within = both < 1.0
        trials.append({"direction_deg": 45.0 * k, "time_both_within_1deg_s": float(tr["t"][np.argmax(within)]) if within.any() else None,
                       "error_at_0.3s_deg": float(np.interp(0.3, tr["t"], both)),
                       "max_error_after_0.3s_deg": float(both[tr["t"] >= 0.3].max()),
                       "gaze_line_distance_cm": 100 * float(max(tr["line_left"][-1], tr["line_right"][-1])),
                       # the eye-head synergy: the eyes' eccentricity in the head falls as the head turns
                       "eye_in_head_deg_peak": float(tr["eye_in_head"].max()), "eye_in_head_deg_end": float(tr["eye_in_head"][-1]),
                       "head_turn_deg_end": float(np.degrees(np.linalg.norm(tr["neck"][-1][:2])))})
    times = [tt["time_both_within_1deg_s"] for tt in trials]
    out = {"saccade_20deg": {"trials": trials,
                             "all_within_1deg_by_0.3s": all(tt is not None and tt <= 0.3 for tt in times),
                             "time_both_within_1deg_s_max": max(tt if tt is not None else np.inf for tt in times),
                             "error_at_0.3s_deg_max": max(tt["error_at_0.3s_deg"] for tt in trials),
                             "max_error_after_0.3s_deg_median": float(np.median([tt["max_error_after_0.3s_deg"] for tt in trials]))},
           "vergence_1m": {"gaze_line_distance_cm_max": max(tt["gaze_line_distance_cm"] for tt in trials),
                           "gaze_line_distance_cm_median": float(np.median([tt["gaze_line_distance_cm"] for tt in trials]))}}
    for omega in (15.0, 30.0):
        loop.reset(SETTLE_S)
        # a circle of 1 m around the eyes' midpoint in the horizontal plane, fixed in the world as the head turns
        mid = 0.5 * (body.eye_pose("left")[:3, 3] + body.eye_pose("right")[:3, 3])

        def orbit(tt, omega=omega, mid=mid):
            yaw = np.radians(-18.0 + omega * tt)
            return mid + np.array([np.sin(yaw), -np.cos(yaw), 0.0])

        tr = run_scenario(loop, 1.2, ball=orbit, progress=not args.no_progress)
        sim += tr["t"][-1]
        late = tr["t"] > 0.3  # after the first saccade onto it
        out[f"tracking_{omega:g}deg_s"] = {"median_error_deg": {s: float(np.median(tr[f"error_{s}"][late])) for s in SIDES},
                                           "p90_error_deg": {s: float(np.percentile(tr[f"error_{s}"][late], 90)) for s in SIDES}}
    wall = time.perf_counter() - t
    out["timing"] = {"sim_s": sim, "wall_s": wall, "sim_to_wall": sim / wall,
                     "share": {k: v / wall for k, v in loop.timing.items()}}
    return out


def demo(args) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    from warp_vision.frames import look_at
    from warp_vision.kernels.render import render_camera
    from warp_vision.sim.loop import set_eye_view, sync_scene
    from warp_vision.viz import plot_onv, tone_map

    os.makedirs(args.out, exist_ok=True)
    body, loop = _setup(args)
    head = body.head_pose()[:3, 3]
    # the cannon, 25 deg to the left in the periphery, lobs the ball to a point 1 m before the face
    muzzle = body.data.site_xpos[body.model.site("muzzle").id]
    v = body.fire_cannon(head + args.stop * (muzzle - head) / np.linalg.norm(muzzle - head), after=args.flight)
    frames, retinas = [], []
    t_start = body.time
    # behind the body's right shoulder, so the body, the gaze lines, the ball's path and the cannon show
    cam = look_at([-1.3, 1.6, 2.0], [0.4, -1.0, 1.0])

    def record(lp):
        sync_scene(lp.scene, body)
        set_eye_view(lp.scene, False)
        k = len(retinas)
        retinas.append((body.time - t_start, lp.onv["left"][0].clone()))
        if k % args.frame_every == 0:
            img = render_camera(lp.scene, cam, args.width, args.height, fov_deg=50).numpy()
            frames.append(_draw_gaze(tone_map(img), body, cam, args.width, args.height, 50))

    tr = run_scenario(loop, args.duration, record=record, progress=not args.no_progress)
    gif = os.path.join(args.out, "demo.gif")
    Image.fromarray(frames[0]).save(gif, save_all=True, append_images=[Image.fromarray(f) for f in frames[1:]],
                                    duration=int(1000 * 0.01 * args.frame_every), loop=0)
    # the left retina at four moments: the ball's entry, mid-saccade, fixation and tracking (Fig. 7)
    err = tr["error_left"]
    seen = np.nonzero(err < 60)[0]
    k0 = int(seen[0]) if len(seen) else 0
    moments = [k0, min(k0 + 4, len(err) - 1), min(k0 + 15, len(err) - 1), len(err) - 1]
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.4))
    white = max(float(np.percentile(retinas[k][1].numpy(), 99.5)) for k in moments)  # one exposure for all four
    for ax, k, label in zip(axes, moments, ("t0", "t1", "t2", "t3")):
        plot_onv(loop.fov["left"].retina, retinas[k][1], ax=ax, white=white,
                 title=f"{label}: t = {retinas[k][0]:.2f} s, error {err[k]:.1f} deg")
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "left_retina.png"), dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 4))
    for s in SIDES:
        ax.plot(tr["t"], tr[f"error_{s}"], label=f"{s} eye")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("gaze error (deg)")
    ax.set_yscale("log")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(args.out, "gaze_error.png"), dpi=110)
    plt.close(fig)
    return {"launch_velocity_m_s": v.tolist(), "final_error_deg": {s: float(tr[f"error_{s}"][-1]) for s in SIDES},
            "timing_s": dict(loop.timing)}


def _draw_gaze(img: np.ndarray, body: Body, cam: np.ndarray, w: int, h: int, fov_deg: float) -> np.ndarray:
    """Draw each eye's gaze line (1.5 m, red) onto a tone-mapped image [h, w, 3] (uint8 out)."""
    from PIL import Image, ImageDraw

    im = Image.fromarray((np.clip(img, 0, 1) * 255).astype(np.uint8))
    dr = ImageDraw.Draw(im)
    f = 0.5 * h / np.tan(np.radians(fov_deg) / 2)
    inv = np.linalg.inv(cam)

    def project(p):
        q = inv[:3, :3] @ p + inv[:3, 3]
        return (w / 2 + f * q[0] / -q[2], h / 2 - f * q[1] / -q[2]) if q[2] < -1e-3 else None

    for s in SIDES:
        T = body.eye_pose(s)
        a, b = project(T[:3, 3]), project(T[:3, 3] + 1.5 * T[:3, 2])
        if a and b:
            dr.line([a, b], fill=(230, 40, 40), width=2)
    return np.asarray(im)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m warp_vision.sim", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    for name in ("demo", "experiments", "oculomotor"):
        p = sub.add_parser(name)
        p.add_argument("--oculomotor", default="runs/oculomotor", help="the oculomotor runs' directory: <dir>/left, <dir>/right (trained there if missing)")
        p.add_argument("--no-progress", action="store_true", help="no progress bars")
        add_debug_flag(p)
        if name == "oculomotor":
            continue
        p.add_argument("--left", default="runs/foveation_left", help="the left eye's foveation run")
        p.add_argument("--right", default="runs/foveation_right", help="the right eye's foveation run")
        p.add_argument("--no-arms", action="store_true", help="a bare torso instead of myo-sim's arms (faster)")
        p.add_argument("--seed", type=int, default=0, help="the room's seed")
        p.add_argument("--out", default=f"runs/sim_{name}", help="output directory")
        if name == "demo":
            p.add_argument("--duration", type=float, default=0.8, help="simulated seconds")
            p.add_argument("--flight", type=float, default=0.9, help="s of flight to the point --stop m before the face")
            p.add_argument("--stop", type=float, default=1.0, help="m from the head where the ball's flight is aimed")
            p.add_argument("--width", type=int, default=320, help="GIF width (pixels)")
            p.add_argument("--height", type=int, default=240, help="GIF height (pixels)")
            p.add_argument("--frame-every", type=int, default=2, help="GIF frame every N control periods (10 ms)")
    args = ap.parse_args(argv)
    return guarded(lambda: _run(args), args.debug)


def _run(args) -> None:
    if args.command == "oculomotor":
        provide_oculomotor(args.oculomotor, progress=not args.no_progress)
        print(json.dumps({s: json.loads(open(os.path.join(args.oculomotor, s, "summary.json")).read()) for s in SIDES}, indent=2))
        return
    result = demo(args) if args.command == "demo" else experiments(args)
    write_json(os.path.join(args.out, f"{args.command}.json"), result)
    print(json.dumps(result, indent=2))
