"""``python -m warp_vision.sim demo``'s run: the cannon lobs the ball toward the face while the loop runs; the
video (a third-person view with the gaze lines beside both retinas, and the active search's state when it is
the loop's perception), the left retina at four moments (the paper's Fig. 7), the gaze error over time, and the
lines the command prints."""

from __future__ import annotations

import contextlib
import os

import numpy as np

from warp_vision.body import SIDES, Body
from warp_vision.sim.build import setup_loop
from warp_vision.sim.loop import CONTROL_DT, set_eye_view, sync_scene
from warp_vision.sim.scenarios import run_scenario


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
    """``sim demo``'s run: the cannon lobs the ball toward the face; the video, the left retina at four moments
    (Fig. 7) and the gaze error over time are written to --out."""
    body, loop = setup_loop(args)
    viewer = _Viewer(body, args.viewer)
    head = body.head_pose()[:3, 3]
    # the cannon, 25 deg to the left in the periphery, lobs the ball to a point 1 m before the face
    muzzle = body.data.site_xpos[body.model.site("muzzle").id]
    v = body.fire_cannon(head + args.stop * (muzzle - head) / np.linalg.norm(muzzle - head), after=args.flight)
    retinas: list = []
    fps = 1.0 / (args.video_every * CONTROL_DT * args.slow_motion)  # --slow-motion times slower than simulated time
    paths = [os.path.join(args.out, "demo.mp4")] + ([os.path.join(args.out, "demo.gif")] if args.gif else [])
    size: list = []  # (width, height) of the frames written
    # a failed run leaves no video: each writer removes its temporary file when the block raises
    with contextlib.ExitStack() as stack:
        from warp_vision.sim.video import VideoWriter

        writers = [stack.enter_context(VideoWriter(p, fps)) for p in paths]
        stack.callback(viewer.close)
        record = _demo_recorder(args, body, loop, viewer, writers, retinas, size)
        tr = run_scenario(loop, args.duration, record=record, progress=not args.no_progress)
    _fig7_retinas(loop, tr, retinas, os.path.join(args.out, "left_retina.png"))
    _gaze_error_figure(tr, os.path.join(args.out, "gaze_error.png"))
    return {"launch_velocity_m_s": v.tolist(), "final_error_deg": {s: float(tr[f"error_{s}"][-1]) for s in SIDES},
            "gaze_error_deg": {s: flight_error_summary(tr["t"], tr[f"error_{s}"]) for s in SIDES},
            "video": {"paths": paths, "frames": writers[0].frames, "fps": fps, "size": size},
            "timing_s": dict(loop.timing)}


def _demo_recorder(args, body, loop, viewer, writers, retinas: list, size: list):
    """The per-period callback of the demo: keeps the left ONV (for Fig. 7), and every --video-every periods
    renders the third-person view (behind the body's right shoulder: the body, the gaze lines, the ball's path
    and the cannon show) with the gaze lines, beside both retinas, and writes the frame; with the active
    search, its state is written on the view."""
    from warp_vision.frames import look_at
    from warp_vision.kernels.render import render_camera
    from warp_vision.sim.video import RetinaRaster, compose_frame, draw_gaze, label
    from warp_vision.viz import tone_map

    t_start = body.time
    cam = look_at([-1.3, 1.6, 2.0], [0.4, -1.0, 1.0])
    rasters = {s: RetinaRaster(loop.fov[s].retina, size=args.height // 2) for s in SIDES}
    white: dict = {}  # one exposure per eye for the whole video (set on the first frame), so brightness changes are
                      # real

    def record(lp):
        k = len(retinas)
        retinas.append((body.time - t_start, lp.onv["left"][0].clone()))
        viewer.sync()
        if k % args.video_every:
            return
        sync_scene(lp.scene, body)
        set_eye_view(lp.scene, False)
        img = render_camera(lp.scene, cam, args.width, args.height, fov_deg=50).numpy()
        third = draw_gaze(tone_map(img), body, cam, args.width, args.height, 50)
        if lp.search is not None:
            third = label(third, search_caption(lp.search), (6, args.height - max(10, round(args.height / 20)) - 8))
        eyes = {}
        for s in SIDES:
            onv = lp.onv[s][0].numpy()
            white.setdefault(s, max(float(np.percentile(onv, 99.5)), 1e-12))
            eyes[s] = rasters[s](onv, white=white[s])
        frame = compose_frame(third, eyes["left"], eyes["right"], body.time - t_start)
        size[:] = [frame.shape[1], frame.shape[0]]
        for w in writers:
            w.append(frame)

    return record


def search_caption(search) -> str:
    """The active search's state in words, for the video: its state, and how many candidates it has rejected."""
    rejected = sum(kind in ("reject", "lost") for _, kind, _ in search.log)
    state = {"search": "searching", "verify": "verifying a candidate", "track": "tracking"}[search.s.state]
    return f"active search: {state}; {rejected} rejected"


def _fig7_retinas(loop, tr: dict, retinas: list, path: str) -> None:
    """The left retina at four moments: the ball's entry, mid-saccade, fixation and tracking (Fig. 7)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warp_vision.viz import plot_onv

    err = tr["error_left"]
    seen = np.nonzero(err < 60)[0]
    k0 = int(seen[0]) if len(seen) else 0
    moments = [k0, min(k0 + 4, len(err) - 1), min(k0 + 15, len(err) - 1), len(err) - 1]
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.4))
    white_fig = max(float(np.percentile(retinas[k][1].numpy(), 99.5)) for k in moments)  # one exposure for all four
    for ax, k, name in zip(axes, moments, ("t0", "t1", "t2", "t3")):
        plot_onv(loop.fov["left"].retina, retinas[k][1], ax=ax, white=white_fig,
                 title=f"{name}: t = {retinas[k][0]:.2f} s, error {err[k]:.1f} deg")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _gaze_error_figure(tr: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for s in SIDES:
        ax.plot(tr["t"], tr[f"error_{s}"], label=f"{s} eye")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("gaze error (deg)")
    ax.set_yscale("log")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def flight_error_summary(t, err, times=(0.1, 0.2, 0.3, 0.4, 0.5)) -> dict:
    """One eye's gaze error (deg) over a shot: its median, the share of the time it is over 5 degrees (a
    decoy fixated, or the ball lost), and its value at ``times`` (s from the launch)."""
    t, err = np.asarray(t, float), np.asarray(err, float)
    if len(t) == 0 or len(t) != len(err):
        raise ValueError(f"t and err: expected equal, non-zero lengths, got {len(t)} and {len(err)}")
    return {"median": float(np.median(err)), "share_over_5deg": float(np.mean(err > 5.0)),
            **{f"at_{x:.1f}_s": float(np.interp(x, t, err)) for x in times if x <= t[-1]}}


def demo_lines(result: dict, out: str) -> list[str]:
    """What ``sim demo`` prints: both eyes' gaze error over the flight, and the files it wrote."""
    g = {s: result["gaze_error_deg"][s] for s in SIDES}

    def both(key: str, scale: float = 1.0, fmt: str = ".2f") -> str:
        return " / ".join(f"{scale * g[s][key]:{fmt}}" for s in SIDES)

    at = [k for k in g[SIDES[0]] if k.startswith("at_")]
    end = " / ".join(f"{result['final_error_deg'][s]:.2f}" for s in SIDES)
    video = result["video"]
    return [f"gaze error over the flight ({' / '.join(SIDES)} eye): median {both('median')} deg, over 5 deg "
            f"{both('share_over_5deg', 100, '.0f')}% of the time; "
            + ", ".join(f"at {k[3:-2]} s {both(k)}" for k in at)
            + f"; at the end {end} deg",
            f"wrote {', '.join(video['paths'])} ({video['frames']} frames, {video['fps']:g} fps, "
            f"{video['size'][0]}x{video['size'][1]}), {os.path.join(out, 'left_retina.png')}, "
            f"{os.path.join(out, 'gaze_error.png')} and {os.path.join(out, 'demo.json')}"]
