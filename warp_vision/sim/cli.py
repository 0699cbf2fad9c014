"""``python -m warp_vision.sim``: the virtual human's closed-loop demos and measurements.

  demo         the cannon scenario: a ball flies into the periphery; both eyes saccade, converge and track
               it, the head follows. Writes an MP4 (640x480 third-person view with the gaze lines beside
               both eyes' retina images, simulated time on every frame; --gif for a GIF too), the left
               retina at four moments (Fig. 7) and the gaze error over time.
  experiments  saccades to a ball appearing at 20 deg in eight directions, vergence at 1 m, tracking a
               ball moving at 15 and 30 deg/s both ways round, the loop's time shares. Writes experiments.json.
  intraocular  light steps of +2 and -2 log units, and focus steps (a textured card from 2 m to 0.33 m and
               back, fixated): the pupils and lenses under their nets and, in the same run, under the
               analytic laws (their teachers). Writes intraocular.json and figures/light_steps.png,
               focus_steps.png and focus_retina.png.
  oculomotor   both eyes' oculomotor nets only: trains the missing ones.
  intercept    the paper's Fig. 8: the cannon shoots a held-out shot, the eyes and head track the ball, both eyes'
               limb vision nets see it and the left arm (--side) strikes it. One shot: intercept.gif (the
               third-person view with the gaze lines and the hand's path beside the left retina), the hand-ball
               distance over time (true and as the limb vision nets saw it) and shot.json. --shots N: N held-out
               shots three ways (limb vision in the closed loop, the true ball state, passive arms):
               intercept_stats.json and figures of the deflected fraction by speed and by target, and of the
               closest approaches.

Demo, experiments and intraocular work from a fresh clone: each net the loop needs (both eyes' foveation
liNets, oculomotor nets and, unless --intraocular analytic, pupil nets) that is missing is trained first,
after a plan with time estimates, and cached (``runs/foveation_left``, ``runs/foveation_right``,
``runs/oculomotor/<eye>``, ``runs/pupil/<eye>``; intercept also the arm's motor nets, ``runs/arm/<side>``, and
both eyes' limb vision nets, ``runs/limb/<eye>``; with --quick, smaller nets in ``runs/quick/``). Each output
directory gets ``nets.json``: the nets used, with their training configs and checksums.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os

import numpy as np

from warp_vision.errors import add_debug_flag, guarded
from warp_vision.fileio import write_json
from warp_vision.body import SIDES, Body, BodyConfig
from warp_vision.sim.scenarios import SETTLE_S, experiments, run_scenario


def _specs(args):
    from warp_vision.sim.provision import default_runs, plan

    runs = default_runs(args.quick)
    left = getattr(args, "left", None) or runs["left"]
    right = getattr(args, "right", None) or runs["right"]
    nets = getattr(args, "intraocular", "analytic") == "nets"
    specs = plan(left, right, args.oculomotor or runs["oculomotor"], quick=args.quick,
                 pupil=(getattr(args, "pupil", None) or runs["pupil"]) if nets else None,
                 lens=(getattr(args, "lens", None) or runs["lens"]) if nets else None)
    if args.command == "intercept":
        from warp_vision.sim.provision import strike_plan

        specs += strike_plan(args.side, args.arm or runs["arm"],
                             (args.limb or runs["limb"]) if args.perception == "vision" else None, quick=args.quick)
    return specs


def _setup(args):
    """Provide the nets (training missing ones), build the body and the loop; writes nets.json to --out."""
    from warp_vision.sim.loop import Foveator, VisuomotorLoop, load_lens, load_pupil
    from warp_vision.sim.oculomotor import load_oculomotor
    from warp_vision.sim.provision import manifest, provide

    specs = _specs(args)
    provide(specs, progress=not args.no_progress)
    os.makedirs(args.out, exist_ok=True)
    write_json(os.path.join(args.out, "nets.json"), manifest(specs))
    body = Body(BodyConfig(arms=not args.no_arms))
    body.step(int(SETTLE_S / body.model.opt.timestep))
    fov = {s: Foveator(spec.run) for s, spec in zip(SIDES, specs[:2])}
    old = [spec.run for s, spec in zip(SIDES, specs[:2]) if fov[s].generator < 8]
    if old and args.ball == "ordinary":
        print(f"note: {', '.join(old)} learnt on generator v7 (a glowing ball in a dim room); with --ball ordinary "
              "it will not find the ball. Retrain it (python -m warp_vision.train --eye EYE --overwrite) or use --ball glowing.")
    ocu_root = os.path.dirname(specs[2].run)
    runs = {(spec.kind, spec.eye): spec.run for spec in specs}
    pupil = {s: load_pupil(runs["pupil", s]) for s in SIDES} if ("pupil", "left") in runs else None
    lens = {s: load_lens(runs["lens", s]) for s in SIDES} if ("lens", "left") in runs else None
    return body, VisuomotorLoop(body, fov, load_oculomotor(ocu_root), seed=args.seed, frame_every=args.frame_every,
                                ball=args.ball, pupil_nets=pupil, lens_nets=lens)


class _Viewer:
    """MuJoCo's passive viewer on the running loop, where a display exists (``--viewer``); on a headless
    machine, one line saying so and nothing else."""

    def __init__(self, body: Body, wanted: bool):
        self.handle = None
        if not wanted:
            return
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY") or os.name == "nt"
                or os.uname().sysname == "Darwin"):
            print("--viewer: no display here (DISPLAY and WAYLAND_DISPLAY are unset); running without the viewer")
            return
        import mujoco.viewer

        self.handle = mujoco.viewer.launch_passive(body.model, body.data)

    def sync(self) -> None:
        if self.handle is not None and self.handle.is_running():
            self.handle.sync()

    def close(self) -> None:
        if self.handle is not None:
            self.handle.close()


def demo(args) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warp_vision.frames import look_at
    from warp_vision.kernels.render import render_camera
    from warp_vision.sim.loop import CONTROL_DT, set_eye_view, sync_scene
    from warp_vision.sim.video import RetinaRaster, VideoWriter, compose_frame
    from warp_vision.viz import plot_onv, tone_map

    body, loop = _setup(args)
    viewer = _Viewer(body, args.viewer)
    head = body.head_pose()[:3, 3]
    # the cannon, 25 deg to the left in the periphery, lobs the ball to a point 1 m before the face
    muzzle = body.data.site_xpos[body.model.site("muzzle").id]
    v = body.fire_cannon(head + args.stop * (muzzle - head) / np.linalg.norm(muzzle - head), after=args.flight)
    retinas = []
    t_start = body.time
    # behind the body's right shoulder, so the body, the gaze lines, the ball's path and the cannon show
    cam = look_at([-1.3, 1.6, 2.0], [0.4, -1.0, 1.0])
    rasters = {s: RetinaRaster(loop.fov[s].retina, size=args.height // 2) for s in SIDES}
    # one exposure per eye for the whole video (set on the first frame), so brightness changes are real
    white: dict = {}
    # a video frame every --video-every periods, played --slow-motion times slower than simulated time
    fps = 1.0 / (args.video_every * CONTROL_DT * args.slow_motion)
    paths = [os.path.join(args.out, "demo.mp4")] + ([os.path.join(args.out, "demo.gif")] if args.gif else [])
    size: list = []  # (width, height) of the frames written

    def record(lp):
        k = len(retinas)
        retinas.append((body.time - t_start, lp.onv["left"][0].clone()))
        viewer.sync()
        if k % args.video_every:
            return
        sync_scene(lp.scene, body)
        set_eye_view(lp.scene, False)
        img = render_camera(lp.scene, cam, args.width, args.height, fov_deg=50).numpy()
        third = _draw_gaze(tone_map(img), body, cam, args.width, args.height, 50)
        eyes = {}
        for s in SIDES:
            onv = lp.onv[s][0].numpy()
            white.setdefault(s, max(float(np.percentile(onv, 99.5)), 1e-12))
            eyes[s] = rasters[s](onv, white=white[s])
        frame = compose_frame(third, eyes["left"], eyes["right"], body.time - t_start)
        size[:] = [frame.shape[1], frame.shape[0]]
        for w in writers:
            w.append(frame)

    # a failed run leaves no video: each writer removes its temporary file when the block raises
    with contextlib.ExitStack() as stack:
        writers = [stack.enter_context(VideoWriter(p, fps)) for p in paths]
        stack.callback(viewer.close)
        tr = run_scenario(loop, args.duration, record=record, progress=not args.no_progress)
    # the left retina at four moments: the ball's entry, mid-saccade, fixation and tracking (Fig. 7)
    err = tr["error_left"]
    seen = np.nonzero(err < 60)[0]
    k0 = int(seen[0]) if len(seen) else 0
    moments = [k0, min(k0 + 4, len(err) - 1), min(k0 + 15, len(err) - 1), len(err) - 1]
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.4))
    white_fig = max(float(np.percentile(retinas[k][1].numpy(), 99.5)) for k in moments)  # one exposure for all four
    for ax, k, label in zip(axes, moments, ("t0", "t1", "t2", "t3")):
        plot_onv(loop.fov["left"].retina, retinas[k][1], ax=ax, white=white_fig,
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
            "video": {"paths": paths, "frames": writers[0].frames, "fps": fps, "size": size},
            "timing_s": dict(loop.timing)}


def intraocular(args) -> dict:
    """Light steps of +2 and -2 log units and focus steps (a textured card from 2 m to 0.33 m and back),
    with the pupil and lens nets and, in the same run, with their teachers (the analytic laws): the
    measures of :func:`warp_vision.sim.scenarios.light_steps` and :func:`~warp_vision.sim.scenarios.focus_steps`,
    and figures of the responses over time and of the left retina blurred, then sharp."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warp_vision.sim.loop import VisuomotorLoop
    from warp_vision.sim.scenarios import FOCUS_PHASES, LIGHT_PHASES, focus_steps, light_steps

    args.intraocular = "nets"
    _body, nets_loop = _setup(args)
    body = Body(BodyConfig(arms=not args.no_arms))
    body.step(int(SETTLE_S / body.model.opt.timestep))
    analytic_loop = VisuomotorLoop(body, nets_loop.fov, nets_loop.ocu, seed=args.seed, frame_every=args.frame_every,
                                   ball=args.ball)
    loops = {"nets": nets_loop, "analytic": analytic_loop}
    light = {m: light_steps(lp, progress=not args.no_progress) for m, lp in loops.items()}
    focus = {m: focus_steps(lp, progress=not args.no_progress) for m, lp in loops.items()}
    fig_dir = os.path.join(args.out, "figures")
    os.makedirs(fig_dir, exist_ok=True)
    labels = {"nets": "nets in the loop", "analytic": "analytic law in the loop"}
    for name, runs, key, teacher, ylabel, title in (
            ("light_steps", light, "pupil", "teacher", "pupil diameter (mm)", "light steps of +2 and -2 log units"),
            ("focus_steps", focus, "accommodation", "vergence", "dioptres", "focus steps: card at 2 m, 0.33 m, 2 m")):
        fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharey=True)
        for ax, s in zip(axes, SIDES):
            for mode, style in (("nets", "C0-"), ("analytic", "C1--")):
                tr = runs[mode]["traces"]
                ax.plot(tr["t"], tr[f"{key}_{s}"], style, label=f"{key}, {labels[mode]}")
            tr = runs["nets"]["traces"]
            ax.plot(tr["t"], tr[f"{teacher}_{s}"], "k:", lw=1,
                    label="teacher's command (Watson & Yellott)" if key == "pupil" else "the card's vergence")
            for st in runs["nets"]["steps"]:
                if st["eye"] == s:
                    ax.axvline(st["at_s"], color="0.7", lw=0.8)
            ax.set(xlabel="simulated time (s)", title=f"{s} eye: {title}")
            ax.grid(alpha=0.3)
        axes[0].set_ylabel(ylabel)
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(os.path.join(fig_dir, f"{name}.png"), dpi=110)
        plt.close(fig)
    _focus_retinas(focus["nets"]["snapshots"], nets_loop.fov["left"].retina, os.path.join(fig_dir, "focus_retina.png"))
    out = {"light_phases_s_scale": [list(p) for p in LIGHT_PHASES], "focus_phases_s_m": [list(p) for p in FOCUS_PHASES]}
    for mode in loops:
        out[mode] = {"light_steps": light[mode]["steps"], "focus_steps": focus[mode]["steps"],
                     "light_traces": {k: v.tolist() for k, v in light[mode]["traces"].items()},
                     "focus_traces": {k: v.tolist() for k, v in focus[mode]["traces"].items()}}
    return out


def _focus_retinas(shots: list, retina, path: str) -> None:
    """The left retina's central 3 degrees in the focus steps' snapshots (just after a step, blurred; at
    the phase's end, sharp)."""
    import matplotlib.pyplot as plt

    if not shots:
        return
    rho = np.degrees(retina.rho)
    keep = rho <= 3.0
    xy = np.degrees(retina.domain_xy[keep])
    fig, axes = plt.subplots(1, len(shots), figsize=(3.2 * len(shots), 3.4))
    for ax, sh in zip(np.atleast_1d(axes), shots):
        rgb = sh["onv"].reshape(-1, 3)[keep]
        ax.scatter(xy[:, 0], xy[:, 1], c=np.clip(rgb / max(np.percentile(rgb, 99), 1e-12), 0, 1), s=2)
        ax.set(title=f"t = {sh['t']:.2f} s, defocus {sh['defocus_D']:+.2f} D", xticks=[], yticks=[])
        ax.set_aspect("equal")
        ax.title.set_fontsize(9)
    fig.suptitle("left retina, central 3 deg, lens nets in the loop: after each step (blurred) and at its end (sharp)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: The interception video's camera: behind the body's left shoulder, the cannon at the left edge
#: (world from camera: position, target), and its vertical field of view (deg).
STRIKE_CAMERA = ((1.9, 0.9, 1.75), (0.3, -0.8, 1.0))
STRIKE_FOV_DEG = 50.0


def _pick_shots(args) -> list:
    """The shots of ``intercept`` (checked before any net is trained): --shot-seed's, or --shots N held-out
    ones from --seed (one without --shots)."""
    from warp_vision.sim.cannon import SPLITS, sample_shots, shot_from_seed

    if args.side not in SIDES:
        raise ValueError(f"--side: expected one of {', '.join(SIDES)}, got {args.side!r}")
    if args.shots is not None and args.shots < 1:
        raise ValueError(f"--shots: expected a number of shots >= 1, got {args.shots}")
    if args.shot_seed is not None:
        if args.shots is not None:
            raise ValueError("--shot-seed picks one shot; with --shots N the shots are N held-out ones from --seed")
        if args.shot_seed < 0:
            raise ValueError(f"--shot-seed: expected a shot's seed >= 0, got {args.shot_seed}")
        return [shot_from_seed(args.shot_seed, args.side)]
    n = args.shots or 1
    last = len(SPLITS["heldout"]) - n
    if not 0 <= args.seed <= last:
        raise ValueError(f"--seed: the held-out shots start at seed {SPLITS['heldout'][0]:,} + --seed; expected "
                         f"0..{last:,} for {n} shot(s), got {args.seed}")
    return sample_shots(n, seed=args.seed, split="heldout", side=args.side)


def _strike_runs(args) -> tuple[str, dict]:
    """(the arm's run directory, {eye: limb vision run directory}) of ``intercept``."""
    from warp_vision.sim.provision import default_runs

    runs = default_runs(args.quick)
    limb = args.limb or runs["limb"]
    return os.path.join(args.arm or runs["arm"], args.side), {s: os.path.join(limb, s) for s in SIDES}


def _shot_dict(shot) -> dict:
    import dataclasses

    from warp_vision.sim.cannon import SPLITS
    from warp_vision.sim.strike_figures import target_offset

    split = next((k for k, r in SPLITS.items() if shot.seed is not None and shot.seed in r), None)
    return {**dataclasses.asdict(shot), "split": split, "direction": [float(x) for x in shot.direction],
            "target_offset_outward_forward_up_m": target_offset(shot)}


def _result_dict(r) -> dict:
    """A :class:`~warp_vision.sim.cannon.ShotResult` as JSON-ready values."""
    import dataclasses

    out = {}
    for f in dataclasses.fields(r):
        v = getattr(r, f.name)
        if f.name == "first_contacts":
            v = {k: dataclasses.asdict(c) for k, c in v.items()}
        elif isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, (np.floating, np.bool_)):
            v = v.item()
        out[f.name] = v
    out["speed_change_m_s"] = r.speed_change
    c = r.first_contacts.get(r.arm_contact) if r.arm_contact else None
    out["arm_contact_t"] = c.t if c is not None else None
    return out


def _shares(timing: dict, wall: float) -> dict:
    """Each stage's wall seconds as a share of ``wall``, and "other": the rest."""
    keys = [k for k in ("render", "nets", "limb_vision", "arm", "mujoco", "control", "video") if k in timing]
    out = {k: timing[k] / wall for k in keys}
    out["other"] = max(0.0, wall - sum(timing[k] for k in keys)) / wall
    return out


def intercept(args) -> dict:
    """``python -m warp_vision.sim intercept``: one shot with its video and figure, or (--shots N) the
    comparison of limb vision in the closed loop with the eyes' fixation, the true ball state and passive arms."""
    from warp_vision.sim.arm import load_arm
    from warp_vision.sim.intercept import arm_interceptor

    shots = _pick_shots(args)
    body, loop = _setup(args)
    arm_run, limb_runs = _strike_runs(args)
    nets = load_arm(arm_run)
    vision = None
    if args.perception == "vision":
        from warp_vision.sim.limb import LimbVision

        vision = LimbVision(limb_runs, arm=args.side)
        vision.check_retinas({s: loop.fov[s].retina for s in SIDES})
    elif args.perception == "fixation":
        from warp_vision.sim.limb import FixationVision

        vision = FixationVision(args.side)
    interceptor = arm_interceptor(body, nets, args.side, perception=vision if vision is not None else "oracle")
    if args.shots is None:
        return _intercept_one(args, loop, interceptor, vision, shots[0])
    return _intercept_many(args, loop, interceptor, vision, nets, shots)


def _intercept_one(args, loop, interceptor, vision, shot) -> dict:
    import time

    from tqdm import tqdm

    from warp_vision.frames import look_at
    from warp_vision.kernels.render import render_camera
    from warp_vision.sim.cannon import TAIL_S
    from warp_vision.sim.intercept import run_vision_shot
    from warp_vision.sim.loop import CONTROL_DT, set_eye_view, sync_scene
    from warp_vision.sim.strike_figures import compose_strike_frame, draw_strike, plot_hand_ball_distance
    from warp_vision.sim.video import RetinaRaster, VideoWriter
    from warp_vision.viz import tone_map

    body = loop.body
    cam = look_at(*STRIKE_CAMERA)
    raster = RetinaRaster(loop.fov["left"].retina, size=args.height // 2)
    white: list = []  # one exposure for the whole video, set on its first frame
    samples: dict = {}  # control period k -> (t s since the launch, ball [3], hand [3]) at its start
    hands, balls = [], []
    extra = {"video": 0.0}
    fps = 1.0 / (loop.frame_every * CONTROL_DT * args.slow_motion)
    video = os.path.join(args.out, f"intercept.{args.video_format}")
    bar = tqdm(total=int(np.ceil((shot.flight_time + TAIL_S) / CONTROL_DT)), desc="the shot (10 ms periods)",
               unit="period", disable=args.no_progress, dynamic_ncols=True)

    def record(lp, det):
        t0 = time.perf_counter()
        bar.update(1)
        if not samples:  # the launch: the hand the interceptor saw then
            samples[0] = (0.0, np.asarray(shot.muzzle, float), interceptor.log[0][2].copy())
            hands.append(samples[0][2])
            balls.append(samples[0][1])
        hand, ball = interceptor.arm.hand(body.data), body.ball_position()
        samples[int(round(det.t / CONTROL_DT))] = (det.t, ball, hand)
        hands.append(hand)
        balls.append(ball)
        if (lp.period - 1) % lp.frame_every == 0:  # the eyes rendered in this period: a video frame
            sync_scene(lp.scene, body)
            set_eye_view(lp.scene, False)
            img = render_camera(lp.scene, cam, args.width, args.height, fov_deg=STRIKE_FOV_DEG).numpy()
            third = _draw_gaze(tone_map(img), body, cam, args.width, args.height, STRIKE_FOV_DEG)
            aim = interceptor.log[-1][1] if interceptor.log else None
            third = draw_strike(third, cam, STRIKE_FOV_DEG, np.array(hands), np.array(balls), aim)
            onv = lp.onv["left"][0].numpy()
            if not white:
                white.append(max(float(np.percentile(onv, 99.5)), 1e-12))
            frame = compose_strike_frame(third, raster(onv, white=white[0]),
                                         f"t = {det.t:.3f} s\nhand-ball {np.linalg.norm(ball - hand):.3f} m")
            writer.append(frame)
        extra["video"] += time.perf_counter() - t0

    timing0 = dict(loop.timing)
    t0 = time.perf_counter()
    with VideoWriter(video, fps) as writer:
        try:
            result = run_vision_shot(loop, shot, interceptor, vision, record=record)
        finally:
            bar.close()
    wall = time.perf_counter() - t0
    timing = {k: v - timing0.get(k, 0.0) for k, v in loop.timing.items()}
    timing.update(extra)
    ks = sorted(samples)
    trace = {"t": [samples[k][0] for k in ks],
             "true_m": [float(np.linalg.norm(samples[k][1] - samples[k][2])) for k in ks],
             "frame_t": None, "estimate_m": None}
    limb = None
    if vision is not None:
        frame_t, est, pos_err, dist_err = [], [], [], []
        for tf, p, _per_eye in vision.log:  # each frame: the estimate against the state at the render
            k = int(round(tf / CONTROL_DT))
            if k not in samples:
                continue
            _t, ball, hand = samples[k]
            frame_t.append(float(tf))
            est.append(float(np.linalg.norm(p - hand)))
            pos_err.append(float(np.linalg.norm(p - ball)))
            dist_err.append(abs(est[-1] - float(np.linalg.norm(ball - hand))))
        trace.update(frame_t=frame_t, estimate_m=est, position_error_m=pos_err)
        limb = {"frames": len(frame_t), "median_position_error_m": float(np.median(pos_err)) if pos_err else None,
                "median_distance_error_m": float(np.median(dist_err)) if dist_err else None}
    res = _result_dict(result)
    plot_hand_ball_distance(trace, os.path.join(args.out, "hand_ball_distance.png"), res["arm_contact_t"],
                            result.deflected, result.closest_t,
                            seen_by="limb vision nets'" if args.perception == "vision" else "the eyes' fixation",
                            title=f"shot {shot.seed}: {shot.speed:.1f} m/s, {'deflected' if result.deflected else 'missed'}; "
                                  f"closest approach {result.closest:.3f} m")
    out = {"shot": _shot_dict(shot), "perception": args.perception, "side": args.side, "result": res,
           "limb_vision": limb, "wall_s": wall, "timing_s": timing, "timing_shares": _shares(timing, wall),
           "video": {"path": video, "frames": writer.frames, "fps": fps}, "trace": trace}
    write_json(os.path.join(args.out, "shot.json"), out)
    print(f"shot {shot.seed} ({shot.speed:.1f} m/s, flight {shot.flight_time:.3f} s), {args.side} arm, perception "
          f"{args.perception}: {'DEFLECTED' if result.deflected else 'missed'}; closest approach {result.closest:.3f} m "
          f"at {result.closest_t:.3f} s ({result.closest_part}); first arm contact {result.arm_contact}")
    if limb:
        print(f"{args.perception}: {limb['frames']} frames, median ball position error {limb['median_position_error_m']:.3f} m")
    print(f"wall {wall:.1f} s: " + ", ".join(f"{k} {100 * v:.0f}%" for k, v in out["timing_shares"].items()))
    print(f"wrote {video}, {os.path.join(args.out, 'hand_ball_distance.png')} and {os.path.join(args.out, 'shot.json')}")
    return out


def _intercept_many(args, loop, interceptor, vision, nets, shots) -> dict:
    import time

    from warp_vision.sim.intercept import OffsetOracle, arm_interceptor, intercept_stats, run_vision_shot
    from warp_vision.sim.strike_figures import mode_label, stats_figures, target_offset

    from warp_vision.sim.limb import FixationVision

    progress = not args.no_progress
    loop_mode = {"vision": "vision", "fixation": "fixation"}.get(args.perception, "loop_oracle")
    results, wall = {}, {}
    timing0 = dict(loop.timing)
    t0 = time.perf_counter()
    results[loop_mode] = intercept_stats(shots, runner=lambda shot: run_vision_shot(loop, shot, interceptor, vision),
                                         progress=progress, desc=mode_label(loop_mode))
    wall[loop_mode] = time.perf_counter() - t0
    timing = {k: v - timing0.get(k, 0.0) for k, v in loop.timing.items()}
    if loop_mode == "vision":  # the same loop with the eyes' fixation in place of the limb vision nets
        fixation = FixationVision(args.side)
        other = arm_interceptor(loop.body, nets, args.side, perception=fixation)
        t0 = time.perf_counter()
        results["fixation"] = intercept_stats(shots, runner=lambda shot: run_vision_shot(loop, shot, other, fixation),
                                              progress=progress, desc=mode_label("fixation"))
        wall["fixation"] = time.perf_counter() - t0
    bare = Body()  # oracle and passive: run_shot on a body of their own, no rendering
    modes = [("oracle", lambda b: arm_interceptor(b, nets, args.side))]
    for e in args.perception_error_cm:  # each factory makes a perception of its own, seeded alike
        modes.append((f"oracle_{e:g}cm", lambda b, e=e: arm_interceptor(b, nets, args.side,
                                                                         perception=OffsetOracle(e / 100, args.seed))))
    for mode, factory in modes + [("passive", None)]:
        t0 = time.perf_counter()
        results[mode] = intercept_stats(shots, factory, bare, progress=progress, desc=mode_label(mode))
        wall[mode] = time.perf_counter() - t0
    for res in results.values():
        for row, shot in zip(res["shots"], shots):
            row["target_offset"] = target_offset(shot)
    figures = stats_figures(results, args.out)
    out = {"side": args.side, "perception": args.perception, "frame_every": loop.frame_every,
           "shots": [_shot_dict(s) for s in shots], "modes": {m: mode_label(m) for m in results},
           "results": results,
           "median_closest_miss_m": {m: r["median_closest_miss_m"] for m, r in results.items()},
           "deflected_fraction": {m: r["deflected_fraction"] for m, r in results.items()},
           "wall_s": wall, "timing_s": timing, "timing_shares": _shares(timing, wall[loop_mode]),
           "figures": figures}
    write_json(os.path.join(args.out, "intercept_stats.json"), out)
    print(f"\n{len(shots)} held-out shot(s) at the {args.side} arm (seeds {shots[0].seed}..{shots[-1].seed}):")
    print(f"{'mode':28s} {'deflected':>10s} {'fraction':>9s} {'median miss':>12s} {'median closest':>15s} {'wall s/shot':>12s}")
    for m, r in results.items():
        hits = f"{sum(bool(x['deflected']) for x in r['shots'])}/{r['n']}"
        miss = "-" if r["median_closest_miss_m"] is None else f"{r['median_closest_miss_m']:.3f} m"
        print(f"{mode_label(m):28s} {hits:>10s} {r['deflected_fraction']:>9.2f} {miss:>12s} "
              f"{r['median_closest_m']:>13.3f} m {wall[m] / len(shots):>12.1f}")
    print(f"{mode_label(loop_mode)}, wall time: " + ", ".join(f"{k} {100 * v:.0f}%" for k, v in out["timing_shares"].items()))
    print(f"wrote {os.path.join(args.out, 'intercept_stats.json')} and {', '.join(os.path.basename(f) for f in figures)}")
    return out


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
    from warp_vision.sim.loop import BALLS, FRAME_EVERY, INTRAOCULAR

    ap = argparse.ArgumentParser(prog="python -m warp_vision.sim", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    for name in ("demo", "experiments", "intraocular", "oculomotor", "intercept"):
        p = sub.add_parser(name)
        p.add_argument("--quick", action="store_true",
                       help="smaller nets (runs/quick/..., trained in a few minutes when missing) for a first look")
        p.add_argument("--oculomotor", default=None,
                       help="the oculomotor runs' directory: <dir>/left, <dir>/right, trained there if missing "
                            "(default runs/oculomotor, or runs/quick/oculomotor with --quick)")
        p.add_argument("--no-progress", action="store_true", help="no progress bars")
        add_debug_flag(p)
        if name == "oculomotor":
            continue
        p.add_argument("--left", default=None, help="the left eye's foveation run, trained there if missing "
                                                    "(default runs/foveation_left, or runs/quick/foveation_left)")
        p.add_argument("--right", default=None, help="the right eye's foveation run (likewise)")
        if name == "intercept":  # the arms strike; the ball glows (what the foveation and limb vision nets learnt)
            p.set_defaults(no_arms=False, ball="glowing")
            p.add_argument("--seed", type=int, default=0,
                           help="the room's seed, and the first held-out shot: seed 1,000,000 + --seed (default 0)")
        else:
            p.add_argument("--no-arms", action="store_true", help="a bare torso instead of myo-sim's arms (faster)")
            p.add_argument("--seed", type=int, default=0, help="the room's seed")
        if name != "intraocular":  # that command runs both, nets and teachers
            default = "analytic" if name == "intercept" else "nets"
            p.add_argument("--intraocular", choices=INTRAOCULAR, default=default,
                           help=f"nets{' (default)' if default == 'nets' else ''}: each eye's pupil and lens nets command "
                                "its iris and lens from the ONV (trained into runs/pupil/<eye> and runs/lens/<eye> if "
                                f"missing); analytic{' (default)' if default == 'analytic' else ''}: their teachers, "
                                "Watson & Yellott's pupil for the adapting luminance and accommodation to where the gaze "
                                "lines converge")
        p.add_argument("--pupil", default=None, help="the pupil runs' directory: <dir>/left, <dir>/right (default "
                                                     "runs/pupil, or runs/quick/pupil with --quick)")
        p.add_argument("--lens", default=None, help="the lens runs' directory (likewise: runs/lens, runs/quick/lens)")
        if name != "intercept":
            p.add_argument("--ball", choices=BALLS, default="glowing",
                           help="glowing (default): a white ball that glows, in the room dimmed (generator v7's scene, what "
                                "the default foveation nets learn); ordinary: a grey-white ball lit by the room's lamps, in a "
                                "room at its everyday albedos (generator v8's kind of scene; no net trained so far finds it "
                                "reliably: README)")
        p.add_argument("--frame-every", type=int, default=FRAME_EVERY,
                       help=f"the eyes render (and the foveation nets run) every N control periods of 10 ms "
                            f"(default {FRAME_EVERY}: 25 frames a second; 1 renders every period)")
        p.add_argument("--out", default=None, help=f"output directory (default runs/sim_{name}, or runs/quick/sim_{name} with --quick)")
        if name == "intercept":
            p.add_argument("--side", default="left", help="the striking arm: left (default) or right (the other hangs)")
            p.add_argument("--shots", type=int, default=None,
                           help="N held-out shots (seeds 1,000,000 + --seed ...), each run three ways: limb vision in "
                                "the closed loop, the true ball state (no rendering), passive arms; writes "
                                "intercept_stats.json and figures. Default: one shot with its video")
            p.add_argument("--shot-seed", type=int, default=None,
                           help="one shot: the shot of this seed (training seeds 0-999,999, held-out 1,000,000-1,999,999; "
                                "default the first held-out one, 1,000,000 + --seed)")
            p.add_argument("--perception", choices=("vision", "fixation", "oracle"), default="vision",
                           help="how the arm knows the ball: vision (default), both eyes' limb vision nets (trained into "
                                "runs/limb/<eye> if missing; with --shots the loop then also runs with fixation); "
                                "fixation: where the two eyes' foveation nets see the ball (the gaze lines' crossing; no "
                                "limb nets); oracle: the simulation's true ball state (no limb nets; with --shots the "
                                "closed-loop mode then runs on it too, as 'loop_oracle')")
            p.add_argument("--perception-error-cm", type=float, nargs="*", default=[],
                           help="with --shots, also run the shots with the true ball state off by each of these errors "
                                "(cm; a fixed offset per shot in a random direction, no rendering): how accurate the limb "
                                "vision nets must be for the interception")
            p.add_argument("--arm", default=None, help="the arm runs' directory: <dir>/<side>, trained there if missing "
                                                       "(default runs/arm, or runs/quick/arm with --quick)")
            p.add_argument("--limb", default=None, help="the limb vision runs' directory: <dir>/left, <dir>/right "
                                                        "(default runs/limb, or runs/quick/limb with --quick)")
            p.add_argument("--width", type=int, default=640, help="third-person view width (pixels)")
            p.add_argument("--height", type=int, default=480, help="third-person view height (pixels); the left "
                                                                   "retina beside it is half as high")
            p.add_argument("--slow-motion", type=float, default=4.0,
                           help="the video plays this many times slower than simulated time (default 4)")
            p.add_argument("--video-format", choices=("gif", "mp4"), default="gif",
                           help="intercept.gif (default) or intercept.mp4 (H.264)")
        if name == "demo":
            p.add_argument("--duration", type=float, default=0.8, help="simulated seconds")
            p.add_argument("--flight", type=float, default=0.9, help="s of flight to the point --stop m before the face")
            p.add_argument("--stop", type=float, default=1.0, help="m from the head where the ball's flight is aimed")
            p.add_argument("--width", type=int, default=640, help="third-person view width (pixels)")
            p.add_argument("--height", type=int, default=480, help="third-person view height (pixels); the "
                                                                   "retina images beside it are half as high")
            p.add_argument("--video-every", type=int, default=1, help="a video frame every N control periods (10 ms)")
            p.add_argument("--slow-motion", type=float, default=4.0,
                           help="the video plays this many times slower than simulated time (default 4)")
            p.add_argument("--gif", action="store_true", help="also write demo.gif (same frames)")
            p.add_argument("--viewer", action="store_true",
                           help="open MuJoCo's passive viewer on the running loop (skipped, with a note, without a display)")
    args = ap.parse_args(argv)
    return guarded(lambda: _run(args), args.debug)


def _run(args) -> None:
    if getattr(args, "out", "") is None:
        args.out = os.path.join("runs", "quick", f"sim_{args.command}") if args.quick else f"runs/sim_{args.command}"
    # bad settings are refused before any net is trained
    for flag in ("width", "height", "video_every", "frame_every"):
        if getattr(args, flag, 1) < 1:
            raise ValueError(f"--{flag.replace('_', '-')}: expected >= 1, got {getattr(args, flag)}")
    if not getattr(args, "slow_motion", 1.0) > 0:
        raise ValueError(f"--slow-motion: expected > 0, got {args.slow_motion}")
    if args.command == "oculomotor":
        from warp_vision.sim.provision import provide

        specs = _specs(args)[2:]
        provide(specs, progress=not args.no_progress)
        print(json.dumps({s.eye: json.loads(open(os.path.join(s.run, "summary.json")).read()) for s in specs}, indent=2))
        return
    if args.command == "intercept":
        _pick_shots(args)  # bad settings are refused before any net is trained
        bad = [e for e in args.perception_error_cm if not (np.isfinite(e) and 0 <= e <= 500)]
        if bad or (args.perception_error_cm and args.shots is None):
            raise ValueError(f"--perception-error-cm: expected distances of 0-500 cm with --shots, got {args.perception_error_cm}")
        if args.height < 8:
            raise ValueError(f"--height: expected >= 8, got {args.height}")
        intercept(args)
        return
    if args.command == "demo":
        result = demo(args)
    elif args.command == "intraocular":
        result = intraocular(args)
        for mode in ("nets", "analytic"):
            for st in result[mode]["light_steps"]:
                print(f"{mode:8s} {st['eye']:5s} eye, {st['log_units']:+.0f} log units at {st['at_s']:.1f} s ({st['direction']}): "
                      f"{st['from_mm']:.2f} -> {st['end_mm']:.2f} mm (steady state {st['steady_state_mm']:.2f}, off by "
                      f"{100 * st['end_relative_error']:.1f}%), latency {st['latency_s']} s, 10-90% {st['rise_10_90_s']} s, "
                      f"settled within 5% after {st['settle_s']} s")
            for st in result[mode]["focus_steps"]:
                print(f"{mode:8s} {st['eye']:5s} eye, card {st['from_m']:.2f} -> {st['to_m']:.2f} m at {st['at_s']:.1f} s: "
                      f"{st['from_D']:.2f} -> {st['to_D']:.2f} D, latency {st['latency_s']} s, in focus (0.25 D) after "
                      f"{st['in_focus_s']} s, defocus at the end {st['end_defocus_D']:+.3f} D")
        write_json(os.path.join(args.out, "intraocular.json"), result)
        print(f"wrote {os.path.join(args.out, 'intraocular.json')} and figures in {os.path.join(args.out, 'figures')}")
        return
    else:
        _body, loop = _setup(args)
        result = experiments(loop, progress=not args.no_progress)
    write_json(os.path.join(args.out, f"{args.command}.json"), result)
    print(json.dumps(result, indent=2))
