"""``python -m warp_vision.sim intercept`` (the paper's Fig. 8), the command's work; its arguments are
parsed in :mod:`warp_vision.sim.cli`.

- One shot (:func:`intercept` without ``--shots``): the held-out shot in the closed loop, the arm driven by
  the chosen perception (the limb vision nets, the eyes' fixation, or the true ball); writes the video
  (the third-person view with the gaze lines and the hand's and ball's paths beside the left retina),
  the hand-ball distance over time and ``shot.json``.
- ``--shots N``: the same held-out shots in the closed loop (limb vision, then the eyes' fixation; or the
  true ball), then without rendering with the true ball (also off by each ``--perception-error-cm``) and
  with passive arms; writes ``intercept_stats.json`` and the figures of
  :func:`warp_vision.sim.intercept_figures.stats_figures`.
"""

from __future__ import annotations

import os

import numpy as np

from warp_vision.body import SIDES, Body
from warp_vision.fileio import write_json
from warp_vision.provenance import software

#: The interception video's camera: behind the body's left shoulder, the cannon at the left edge
#: (world from camera: position, target), and its vertical field of view (deg).
STRIKE_CAMERA = ((1.9, 0.9, 1.75), (0.3, -0.8, 1.0))
STRIKE_FOV_DEG = 50.0


def pick_shots(args) -> list:
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
    if n > len(SPLITS["heldout"]):
        raise ValueError(f"--shots: expected 1..{len(SPLITS['heldout']):,} (the held-out shots), got {n:,}")
    last = len(SPLITS["heldout"]) - n
    if not 0 <= args.seed <= last:
        raise ValueError(f"--seed: the held-out shots start at seed {SPLITS['heldout'][0]:,} + --seed; expected "
                         f"0..{last:,} for {n} shot(s), got {args.seed}")
    return sample_shots(n, seed=args.seed, split="heldout", side=args.side)


def strike_runs(args) -> tuple[str, dict]:
    """(the arm's run directory, {eye: limb vision run directory}) of ``intercept``."""
    from warp_vision.sim.provision import default_runs

    runs = default_runs(args.quick)
    limb = args.limb or runs["limb"]
    return os.path.join(args.arm or runs["arm"], args.side), {s: os.path.join(limb, s) for s in SIDES}


def shot_dict(shot) -> dict:
    import dataclasses

    from warp_vision.sim.cannon import SPLITS
    from warp_vision.sim.intercept_figures import target_offset

    split = next((k for k, r in SPLITS.items() if shot.seed is not None and shot.seed in r), None)
    return {**dataclasses.asdict(shot), "split": split, "direction": [float(x) for x in shot.direction],
            "target_offset_outward_forward_up_m": target_offset(shot)}


def result_dict(r) -> dict:
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


def time_shares(timing: dict, wall: float) -> dict:
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

    shots = pick_shots(args)
    from warp_vision.sim.build import setup_loop

    body, loop = setup_loop(args)
    arm_run, limb_runs = strike_runs(args)
    nets = load_arm(arm_run, args.side)
    vision = None
    if args.perception == "vision":
        from warp_vision.sim.limb import LimbVision

        vision = LimbVision(limb_runs, arm=args.side)
        vision.check_retinas({s: loop.fov[s].retina for s in SIDES})
        vision.check_ball(args.ball)
    elif args.perception == "fixation":
        from warp_vision.sim.limb import FixationVision

        vision = FixationVision(args.side)
    interceptor = arm_interceptor(body, nets, args.side, perception=vision if vision is not None else "oracle")
    if args.shots is None:
        return _intercept_one(args, loop, interceptor, vision, shots[0])
    return _intercept_many(args, loop, interceptor, vision, nets, shots)


class _ShotVideo:
    """The one shot's video, recorded as it runs: the ``record`` hook of
    :func:`~warp_vision.sim.intercept.run_vision_shot`, called after every control period. It keeps each
    period's ball and hand (``samples``: control period k -> (t s since the launch, ball [3], hand [3]) at its
    start) and, on the periods the eyes rendered, appends a frame to ``writer``: the third-person view with the
    gaze lines and the hand's and ball's paths beside the left retina, captioned."""

    def __init__(self, args, loop, interceptor, shot):
        from tqdm import tqdm

        from warp_vision.frames import look_at
        from warp_vision.sim.cannon import TAIL_S
        from warp_vision.sim.loop import CONTROL_DT
        from warp_vision.sim.video import RetinaRaster

        self.args, self.body, self.interceptor, self.shot = args, loop.body, interceptor, shot
        self.cam = look_at(*STRIKE_CAMERA)
        self.raster = RetinaRaster(loop.fov["left"].retina, size=args.height // 2)
        self.white = None  # one exposure for the whole video, set on its first frame
        self.samples: dict = {}
        self.hands, self.balls = [], []
        self.seconds = 0.0  # wall time spent on the video
        self.fps = 1.0 / (loop.frame_every * CONTROL_DT * args.slow_motion)
        self.path = os.path.join(args.out, f"intercept.{args.video_format}")
        self.writer = None  # the VideoWriter, while the shot runs
        self.bar = tqdm(total=int(np.ceil((shot.flight_time + TAIL_S) / CONTROL_DT)), desc="the shot (10 ms periods)",
                        unit="period", disable=args.no_progress, dynamic_ncols=True)

    def __call__(self, lp, det) -> None:
        import time

        from warp_vision.sim.loop import CONTROL_DT

        t0 = time.perf_counter()
        self.bar.update(1)
        if not self.samples:  # the launch: the hand the interceptor saw then
            self.samples[0] = (0.0, np.asarray(self.shot.muzzle, float), self.interceptor.log[0][2].copy())
            self.hands.append(self.samples[0][2])
            self.balls.append(self.samples[0][1])
        hand, ball = self.interceptor.arm.hand(self.body.data), self.body.ball_position()
        self.samples[int(round(det.t / CONTROL_DT))] = (det.t, ball, hand)
        self.hands.append(hand)
        self.balls.append(ball)
        if (lp.period - 1) % lp.frame_every == 0:  # the eyes rendered in this period: a video frame
            self.writer.append(self._frame(lp, det.t, ball, hand))
        self.seconds += time.perf_counter() - t0

    def _frame(self, lp, t: float, ball, hand) -> np.ndarray:
        from warp_vision.kernels.render import render_camera
        from warp_vision.sim.intercept_figures import compose_strike_frame, draw_strike
        from warp_vision.sim.loop import set_eye_view, sync_scene
        from warp_vision.sim.video import draw_gaze
        from warp_vision.viz import tone_map

        args, cam = self.args, self.cam
        sync_scene(lp.scene, self.body)
        set_eye_view(lp.scene, False)
        img = render_camera(lp.scene, cam, args.width, args.height, fov_deg=STRIKE_FOV_DEG).numpy()
        third = draw_gaze(tone_map(img), self.body, cam, args.width, args.height, STRIKE_FOV_DEG)
        aim = self.interceptor.log[-1][1] if self.interceptor.log else None
        third = draw_strike(third, cam, STRIKE_FOV_DEG, np.array(self.hands), np.array(self.balls), aim)
        onv = lp.onv["left"][0].numpy()
        if self.white is None:
            self.white = max(float(np.percentile(onv, 99.5)), 1e-12)
        return compose_strike_frame(third, self.raster(onv, white=self.white),
                                    f"t = {t:.3f} s\nhand-ball {np.linalg.norm(ball - hand):.3f} m")


def _intercept_one(args, loop, interceptor, vision, shot) -> dict:
    """``intercept`` without ``--shots``: the shot in the closed loop, filmed; writes the video, the hand-ball
    distance over time and ``shot.json``."""
    video = _ShotVideo(args, loop, interceptor, shot)
    result, wall, timing = _run_filmed(loop, shot, interceptor, vision, video)
    trace, limb = _shot_trace(video.samples, vision)
    res = result_dict(result)
    _plot_shot(args, shot, result, res, trace)
    out = {"shot": shot_dict(shot), "perception": args.perception, "side": args.side, "result": res,
           "limb_vision": limb, "wall_s": wall, "timing_s": timing, "timing_shares": time_shares(timing, wall),
           "video": {"path": video.path, "frames": video.writer.frames, "fps": video.fps}, "trace": trace}
    write_json(os.path.join(args.out, "shot.json"), out)
    _print_shot(args, shot, result, limb, wall, out, video.path)
    return out


def _run_filmed(loop, shot, interceptor, vision, video: _ShotVideo):
    """(the shot's result, its wall seconds, each stage's wall seconds) of the shot run with ``video``
    recording it."""
    import time

    from warp_vision.sim.intercept import run_vision_shot
    from warp_vision.sim.video import VideoWriter

    timing0 = dict(loop.timing)
    t0 = time.perf_counter()
    with VideoWriter(video.path, video.fps) as video.writer:
        try:
            result = run_vision_shot(loop, shot, interceptor, vision, record=video)
        finally:
            video.bar.close()
    wall = time.perf_counter() - t0
    timing = {k: v - timing0.get(k, 0.0) for k, v in loop.timing.items()}
    timing["video"] = video.seconds
    return result, wall, timing


def _shot_trace(samples: dict, vision) -> tuple[dict, dict | None]:
    """(the hand-ball distance over the shot, and with a perception of the ball its estimate per frame; the
    perception's median errors, or None): each frame's estimate is read against the state at its render."""
    from warp_vision.sim.loop import CONTROL_DT

    ks = sorted(samples)
    trace = {"t": [samples[k][0] for k in ks],
             "true_m": [float(np.linalg.norm(samples[k][1] - samples[k][2])) for k in ks],
             "frame_t": None, "estimate_m": None}
    if vision is None:
        return trace, None
    frame_t, est, pos_err, dist_err = [], [], [], []
    for tf, p, _per_eye, _hand in vision.log:
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
    return trace, limb


def _plot_shot(args, shot, result, res: dict, trace: dict) -> None:
    from warp_vision.sim.intercept_figures import plot_hand_ball_distance

    plot_hand_ball_distance(trace, os.path.join(args.out, "hand_ball_distance.png"), res["arm_contact_t"],
                            result.deflected, result.closest_t,
                            seen_by="limb vision nets'" if args.perception == "vision" else "the eyes' fixation",
                            title=f"shot {shot.seed}: {shot.speed:.1f} m/s, "
                                  f"{'deflected' if result.deflected else 'missed'}; closest approach "
                                  f"{result.closest:.3f} m")


def _print_shot(args, shot, result, limb: dict | None, wall: float, out: dict, video: str) -> None:
    print(f"shot {shot.seed} ({shot.speed:.1f} m/s, flight {shot.flight_time:.3f} s), {args.side} arm, perception "
          f"{args.perception}: {'DEFLECTED' if result.deflected else 'missed'}; closest approach {result.closest:.3f} "
          f"m at {result.closest_t:.3f} s ({result.closest_part}); first arm contact {result.arm_contact}")
    if limb:
        print(f"{args.perception}: {limb['frames']} frames, median ball position error "
              f"{limb['median_position_error_m']:.3f} m")
    print(f"wall {wall:.1f} s: " + ", ".join(f"{k} {100 * v:.0f}%" for k, v in out["timing_shares"].items()))
    print(f"wrote {video}, {os.path.join(args.out, 'hand_ball_distance.png')} and "
          f"{os.path.join(args.out, 'shot.json')}")


def _intercept_many(args, loop, interceptor, vision, nets, shots) -> dict:
    """``intercept --shots N``: the shots in the closed loop with the chosen perception (and, for limb vision,
    again with the eyes' fixation), then without rendering with the true ball (also off by each
    ``--perception-error-cm``) and with passive arms; writes ``intercept_stats.json`` and the figures."""
    from warp_vision.sim.intercept_figures import mode_label, stats_figures, target_offset

    loop_mode = {"vision": "vision", "fixation": "fixation"}.get(args.perception, "loop_oracle")
    results, wall, seen, timing = _run_in_loop(args, loop, interceptor, vision, nets, shots, loop_mode)
    heldout = None
    if getattr(vision, "ranging", False):  # the limb vision nets on their held-out ONVs, with the loop's foveation nets
        from warp_vision.sim.limb_errors import heldout_limb_vision_errors

        heldout = {s: heldout_limb_vision_errors(vision.run_dirs[s], loop.fov[s]) for s in SIDES}
    _run_without_rendering(args, nets, shots, results, wall)
    for res in results.values():
        for row, shot in zip(res["shots"], shots):
            row["target_offset"] = target_offset(shot)
    figures = stats_figures(results, args.out)
    out = {"side": args.side, "perception": args.perception, "frame_every": loop.frame_every,
           "shots": [shot_dict(s) for s in shots], "modes": {m: mode_label(m) for m in results},
           "results": results,
           "median_closest_miss_m": {m: r["median_closest_miss_m"] for m, r in results.items()},
           "deflected_fraction": {m: r["deflected_fraction"] for m, r in results.items()},
           "perception_errors": seen, "limb_vision_heldout": heldout,
           "wall_s": wall, "timing_s": timing, "timing_shares": time_shares(timing, wall[loop_mode]),
           "figures": figures, "software": software()}
    write_json(os.path.join(args.out, "intercept_stats.json"), out)
    _print_stats(shots, args.side, results, wall, seen, heldout)
    print(f"{mode_label(loop_mode)}, wall time: " + ", ".join(f"{k} {100 * v:.0f}%" for k,
                                                              v in out["timing_shares"].items()))
    print(f"wrote {os.path.join(args.out, 'intercept_stats.json')} and "
          f"{', '.join(os.path.basename(f) for f in figures)}")
    return out


def _vision_runner(loop, ic, perception, rows: list):
    """A runner for :func:`~warp_vision.sim.intercept.intercept_stats`: ``run_vision_shot`` in ``loop``, the
    perception's per-frame errors until the ball's first contact appended to ``rows``."""
    from warp_vision.sim.intercept import run_vision_shot
    from warp_vision.sim.limb_errors import frame_errors

    def run(shot):
        start = len(perception.log) if perception is not None else 0
        r = run_vision_shot(loop, shot, ic, perception)
        if perception is not None:
            until = min([c.t for c in r.first_contacts.values()] + [shot.flight_time])
            rows.extend(frame_errors(perception.log[start:], shot, until))
        return r
    return run


def _run_in_loop(args, loop, interceptor, vision, nets, shots, loop_mode: str):
    """The closed-loop modes: (results, wall seconds, the perceptions' per-frame errors by mode, the loop's
    stage timings of the first mode)."""
    import time

    from warp_vision.sim.intercept import arm_interceptor, intercept_stats
    from warp_vision.sim.intercept_figures import mode_label
    from warp_vision.sim.limb import FixationVision
    from warp_vision.sim.limb_errors import frame_error_summary

    progress = not args.no_progress
    results, wall, seen = {}, {}, {}
    timing0 = dict(loop.timing)
    t0 = time.perf_counter()
    rows: list = []
    results[loop_mode] = intercept_stats(shots, runner=_vision_runner(loop, interceptor, vision, rows),
                                         progress=progress, desc=mode_label(loop_mode))
    if vision is not None:
        seen[loop_mode] = frame_error_summary(rows)
    wall[loop_mode] = time.perf_counter() - t0
    timing = {k: v - timing0.get(k, 0.0) for k, v in loop.timing.items()}
    if loop_mode == "vision":  # the same loop with the eyes' fixation in place of the limb vision nets
        fixation = FixationVision(args.side)
        other = arm_interceptor(loop.body, nets, args.side, perception=fixation)
        t0 = time.perf_counter()
        rows = []
        results["fixation"] = intercept_stats(shots, runner=_vision_runner(loop, other, fixation, rows),
                                              progress=progress, desc=mode_label("fixation"))
        seen["fixation"] = frame_error_summary(rows)
        wall["fixation"] = time.perf_counter() - t0
    return results, wall, seen, timing


def _run_without_rendering(args, nets, shots, results: dict, wall: dict) -> None:
    """The oracle modes (the true ball, and off by each ``--perception-error-cm``) and passive arms, each by
    ``run_shot`` on a body of their own, no rendering: into ``results`` and ``wall`` by mode."""
    import time

    from warp_vision.sim.intercept import OffsetOracle, arm_interceptor, intercept_stats
    from warp_vision.sim.intercept_figures import mode_label

    bare = Body()
    modes = [("oracle", lambda b: arm_interceptor(b, nets, args.side))]
    for e in args.perception_error_cm:  # each factory makes a perception of its own, seeded alike
        modes.append((f"oracle_{e:g}cm", lambda b, e=e: arm_interceptor(b, nets, args.side,
                                                                         perception=OffsetOracle(e / 100, args.seed))))
    for mode, factory in modes + [("passive", None)]:
        t0 = time.perf_counter()
        results[mode] = intercept_stats(shots, factory, bare, progress=not args.no_progress, desc=mode_label(mode))
        wall[mode] = time.perf_counter() - t0


def _print_stats(shots, side: str, results: dict, wall: dict, seen: dict, heldout: dict | None) -> None:
    """The table of the modes, and the perceptions' per-frame errors and held-out errors."""
    from warp_vision.sim.intercept_figures import mode_label

    print(f"\n{len(shots)} held-out shot(s) at the {side} arm (seeds {shots[0].seed}..{shots[-1].seed}):")
    print(f"{'mode':28s} {'deflected':>10s} {'fraction':>9s} {'median miss':>12s} {'median closest':>15s} "
          f"{'wall s/shot':>12s}")
    for m, r in results.items():
        hits = f"{sum(bool(x['deflected']) for x in r['shots'])}/{r['n']}"
        miss = "-" if r["median_closest_miss_m"] is None else f"{r['median_closest_miss_m']:.3f} m"
        print(f"{mode_label(m):28s} {hits:>10s} {r['deflected_fraction']:>9.2f} {miss:>12s} "
              f"{r['median_closest_m']:>13.3f} m {wall[m] / len(shots):>12.1f}")
    for m, e in seen.items():
        if e["all"]["frames"]:
            near = e["near"]
            near_text = (f"; within {e['near_m']:g} m of the hand ({near['frames']} frames): median "
                         f"{near['median_cm']:.1f} cm, p90 {near['p90_cm']:.1f} cm, {near['median_relative']:.2f} of "
                         "the distance") if near["frames"] else ""
            print(f"{mode_label(m)}: the ball's position per frame in flight, median error {e['all']['median_cm']:.1f} "
                  f"cm (p90 {e['all']['p90_cm']:.1f}, {e['all']['frames']} frames){near_text}")
    for s, e in (heldout or {}).items():
        print(f"limb vision, {s} eye, held-out ONVs ({e['seen_within_gate']} of {e['samples']} with the ball seen near "
              f"the line of sight): hand-ball error within 0.6 m median {e['near_median_cm']:.2f} cm, p90 "
              f"{e['near_p90_cm']:.2f} cm, {e['near_median_relative']:.3f} of the distance; every ball "
              f"{e['all_median_cm']:.2f} cm")
