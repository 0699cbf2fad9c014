"""Pictures of the interception (``python -m warp_vision.sim intercept``, the paper's Fig. 8).

The video's frames:

- :func:`warp_vision.sim.video.project` puts world points onto the third-person camera's image;
- :func:`draw_strike`: the hand's path so far (cyan), the ball's (yellow) and the interceptor's current
  aim point (a magenta cross) drawn onto a third-person image;
- :func:`compose_strike_frame`: that image beside the left retina's image, with a caption (time,
  hand-ball distance) and a legend below the retina::

      +---------------------------+--------+
      | t = 0.120 s               | left   |
      | hand-ball 0.214 m         | retina |
      |   third-person view       +--------+
      |   (H x W)                 | legend |
      +---------------------------+--------+
                                   H/2 wide

The figures (matplotlib, PNG):

- :func:`plot_hand_ball_distance`: one shot's hand-ball distance over time, true and as the limb vision
  nets saw it, the contact (or closest approach) marked;
- :func:`plot_success_by_speed`, :func:`plot_success_by_direction`, :func:`plot_closest_approach`: the
  deflected fraction per launch-speed bin, the shots' targets (deflected or missed) around the shoulder,
  and the distribution of the closest approaches, one colour (or panel) per mode (limb vision in the
  closed loop, the true ball state, passive arms), from :func:`warp_vision.sim.intercept.intercept_stats`'
  results.

Frames and units as :mod:`warp_vision.sim.cannon`: world frame (+z up, the body faces -y, its left is
+x), m, s.
"""

from __future__ import annotations

import os

import numpy as np

from warp_vision.sim.video import project

#: Each mode's name in the figures and tables, and its colour.
MODE_LABELS = {"vision": "limb vision (closed loop)", "fixation": "eyes' fixation (closed loop)",
               "loop_oracle": "true ball (closed loop)",
               "oracle": "true ball (oracle)", "passive": "passive arms"}
MODE_COLOURS = {"vision": "C0", "fixation": "C1", "loop_oracle": "C0", "oracle": "C2", "passive": "C7"}
#: RGB of the paths drawn on the video frames
HAND_RGB, BALL_RGB, AIM_RGB = (60, 220, 255), (255, 220, 60), (255, 60, 255)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def mode_label(mode: str) -> str:
    """A comparison mode in words: :data:`MODE_LABELS`, or "true ball off by 5 cm" for ``oracle_5cm``."""
    if mode.startswith("oracle_") and mode.endswith("cm"):
        return f"true ball off by {mode[7:-2]} cm"
    return MODE_LABELS.get(mode, mode)


def _colour(mode: str, k: int) -> str:
    return MODE_COLOURS.get(mode, f"C{k}")


# --- the video's frames -----------------------------------------------------------------------------
def _polyline(draw, pts: list, fill, width: int) -> None:
    """Draw the runs of consecutive visible points as lines (a point behind the camera breaks the line)."""
    run: list = []
    for p in pts + [None]:
        if p is None:
            if len(run) > 1:
                draw.line(run, fill=fill, width=width, joint="curve")
            run = []
        else:
            run.append(p)


def draw_strike(img: np.ndarray, cam: np.ndarray, fov_deg: float, hand_path, ball_path=None, aim=None) -> np.ndarray:
    """A copy of ``img`` (uint8 [H, W, 3], the third-person view of camera ``cam``) with the hand's path
    ``hand_path`` [N, 3] (m, world; cyan, a dot at its end), the ball's ``ball_path`` (yellow) and the
    aim point ``aim`` [3] (a magenta cross; None: none) drawn on it."""
    from PIL import Image, ImageDraw

    from warp_vision.sim.video import check_rgb_u8

    img = check_rgb_u8("img", img)
    h, w = img.shape[:2]
    im = Image.fromarray(img)
    dr = ImageDraw.Draw(im)
    if ball_path is not None and len(ball_path):
        _polyline(dr, project(cam, w, h, fov_deg, ball_path), BALL_RGB, 1)
    if hand_path is not None and len(hand_path):
        pts = project(cam, w, h, fov_deg, hand_path)
        _polyline(dr, pts, HAND_RGB, 2)
        if pts[-1] is not None:
            x, y = pts[-1]
            dr.ellipse((x - 3, y - 3, x + 3, y + 3), fill=HAND_RGB)
    if aim is not None:
        p = project(cam, w, h, fov_deg, aim)[0]
        if p is not None:
            x, y = p
            dr.line([(x - 5, y - 5), (x + 5, y + 5)], fill=AIM_RGB, width=2)
            dr.line([(x - 5, y + 5), (x + 5, y - 5)], fill=AIM_RGB, width=2)
    return np.asarray(im).copy()


LEGEND = (("hand's path", HAND_RGB), ("ball's path", BALL_RGB), ("aim point", AIM_RGB), ("gaze lines", (230, 40, 40)))


def compose_strike_frame(third_person: np.ndarray, retina: np.ndarray, caption: str,
                         retina_caption: str = "left retina") -> np.ndarray:
    """One frame of the interception video: the third-person view (uint8 [H, W, 3]) with ``caption`` at its
    top-left, the retina image (uint8 [s, s, 3], scaled to H/2) to its right with ``retina_caption``, and
    the legend of :func:`draw_strike`'s colours below the retina. Padded with black to an even height and
    width (as an .mp4 needs): uint8 [H + H % 2, W + H/2 (+1), 3]."""
    from PIL import Image, ImageDraw

    from warp_vision.sim.video import check_rgb_u8, label, resize_square

    third_person = check_rgb_u8("third_person", third_person)
    H, W = third_person.shape[:2]
    if H < 8:
        raise ValueError(f"third_person: expected a height >= 8, got shape {third_person.shape}")
    h = H // 2
    eye = resize_square("retina", retina, h)
    frame = np.zeros((H + H % 2, W + h + (W + h) % 2, 3), np.uint8)
    frame[:H, :W] = label(third_person, caption)
    frame[:h, W:W + h] = label(eye, retina_caption, (4, 3)) if retina_caption else eye
    panel = np.zeros((H - h, h, 3), np.uint8)
    step = max(12, round(H / 17))
    for k, (text, _rgb) in enumerate(LEGEND):
        panel = label(panel, text, (22, 6 + k * step))
    im = Image.fromarray(panel)
    dr = ImageDraw.Draw(im)
    for k, (_text, rgb) in enumerate(LEGEND):
        y = 6 + k * step + step // 3
        dr.line([(4, y), (17, y)], fill=rgb, width=3)
    frame[h:H, W:W + h] = np.asarray(im)
    return frame


# --- one shot ---------------------------------------------------------------------------------------
def plot_hand_ball_distance(trace: dict, path: str, contact_t: float | None = None, deflected: bool = False,
                            closest_t: float | None = None, title: str = "",
                            seen_by: str = "limb vision nets'") -> str:
    """Write ``path`` (PNG): the distance from the hand point to the ball's centre over time since the
    launch, ``trace["t"]`` (s) and ``trace["true_m"]`` (m), and, where ``trace`` has them (not None),
    the perception's view of it at each visual frame (labelled "``seen_by`` estimate"),
    ``trace["frame_t"]`` and ``trace["estimate_m"]``
    (|estimated ball - hand|). ``contact_t``: the first hand or forearm contact (a solid line, "deflected"
    or "touched" by ``deflected``); ``closest_t``: the closest approach of the ball to a hand or forearm
    (dotted). Returns ``path``."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(trace["t"], trace["true_m"], "k-", lw=1.5, label="true")
    if trace.get("estimate_m") is not None and len(trace["estimate_m"]):
        ax.plot(trace["frame_t"], trace["estimate_m"], "o-", color="C0", ms=4, lw=0.8,
                label=f"{seen_by} estimate (each visual frame)")
    if contact_t is not None:
        ax.axvline(contact_t, color="C3", lw=1.2,
                   label=f"{'deflected' if deflected else 'touched'} at {contact_t:.3f} s")
    if closest_t is not None and np.isfinite(closest_t):
        ax.axvline(closest_t, color="C1", lw=1, ls=":", label=f"closest approach at {closest_t:.3f} s")
    ax.set(xlabel="time since the launch (s)", ylabel="hand point to ball centre (m)", ylim=(0, None))
    if title:
        ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --- many shots -------------------------------------------------------------------------------------
def plot_success_by_speed(results: dict, path: str) -> str:
    """Write ``path`` (PNG): the deflected fraction per launch-speed bin (``results[mode]["by_speed"]``,
    :func:`~warp_vision.sim.intercept.intercept_stats`' aggregates), the modes' bars side by side, each bar
    labelled with its shots' count. Returns ``path``."""
    plt = _plt()
    modes = list(results)
    bins = list(next(iter(results.values()))["by_speed"]) if modes else []
    fig, ax = plt.subplots(figsize=(7, 4))
    width = 0.8 / max(len(modes), 1)
    x = np.arange(len(bins))
    for k, m in enumerate(modes):
        agg = [results[m]["by_speed"].get(b, {}) for b in bins]
        frac = [a.get("deflected_fraction") or 0.0 for a in agg]
        bars = ax.bar(x + (k - (len(modes) - 1) / 2) * width, frac, width, color=_colour(m, k), label=mode_label(m))
        for bar, a in zip(bars, agg):
            n = a.get("n", 0)
            ax.annotate("n=0" if not n else f"{round((a['deflected_fraction'] or 0) * n)}/{n}",
                        (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom", fontsize=7)
    ax.set_xticks(x, [f"{b} m/s" for b in bins])
    ax.set(xlabel="launch speed", ylabel="deflected fraction", ylim=(0, 1.25), yticks=np.linspace(0, 1, 6))
    ax.set_title("shots deflected, by launch speed", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", ncol=max(len(modes), 1))
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def target_offset(shot) -> list:
    """(outward, forward, up) m of ``shot``'s target from its side's shoulder at rest (outward: away from
    the body's midline), as :data:`warp_vision.sim.cannon.ENVELOPE` draws them."""
    from warp_vision.sim.cannon import shoulder

    o = np.asarray(shot.target, float) - shoulder(shot.side)
    return [float(o[0] if shot.side == "left" else -o[0]), float(-o[1]), float(o[2])]


def plot_success_by_direction(results: dict, path: str) -> str:
    """Write ``path`` (PNG): one panel per mode, each shot's target around the shoulder (its
    ``"target_offset"``: outward on x, up on y, m; the :data:`~warp_vision.sim.cannon.ENVELOPE`'s box
    dashed), a filled green dot where the shot was deflected, a red cross where it was missed; marker size
    grows with the launch speed. Returns ``path``."""
    from warp_vision.sim.cannon import ENVELOPE

    plt = _plt()
    modes = list(results)
    fig, axes = plt.subplots(1, max(len(modes), 1), figsize=(3.6 * max(len(modes), 1), 4.4), sharex=True, sharey=True,
                             squeeze=False)
    (o0, o1), (u0, u1) = ENVELOPE["outward"], ENVELOPE["up"]
    for ax, m in zip(axes[0], modes):
        rows = results[m]["shots"]
        off = np.array([r["target_offset"] for r in rows], float).reshape(-1, 3)
        hit = np.array([bool(r["deflected"]) for r in rows])
        size = 10 + 6 * (np.array([r["speed"] for r in rows], float) - 5.0) if rows else []
        if len(rows):
            ax.scatter(off[hit, 0], off[hit, 2], s=np.asarray(size)[hit], c="C2", label="deflected")
            ax.scatter(off[~hit, 0], off[~hit, 2], s=np.asarray(size)[~hit], c="C3", marker="x", label="missed")
        ax.plot([o0, o1, o1, o0, o0], [u0, u0, u1, u1, u0], "k--", lw=0.7)
        frac = results[m].get("deflected_fraction")
        ax.set_title(f"{mode_label(m)}: {int(hit.sum())}/{len(rows)} deflected" if frac is not None else mode_label(m),
                     fontsize=9)
        ax.set_xlabel("target outward of the shoulder (m)")
        ax.grid(alpha=0.3)
        ax.set_aspect("equal")
    axes[0][0].set_ylabel("target above the shoulder (m)")
    axes[0][0].legend(fontsize=8, loc="lower left")
    fig.suptitle("where the shots were aimed (0.25-0.5 m in front of the shoulder); bigger markers: faster shots",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_closest_approach(results: dict, path: str, xmax: float = 0.5) -> str:
    """Write ``path`` (PNG): the cumulative distribution of the shots' closest approach of the ball to a
    hand or forearm (``"closest"``, m; negative: overlapping) per mode, the axis cut at ``xmax`` m (a shot
    whose simulation failed counts at 10 m, off the chart). Returns ``path``."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4))
    for k, (m, res) in enumerate(results.items()):
        c = np.sort(np.array([r["closest"] for r in res["shots"]], float))
        if not len(c):
            continue
        y = np.arange(1, len(c) + 1) / len(c)
        ax.step(np.r_[min(c[0], 0.0) - 0.01, c], np.r_[0.0, y], where="post", color=_colour(m, k),
                label=f"{mode_label(m)} (median {np.median(c):.3f} m)")
    ax.axvline(0.0, color="k", lw=0.6)
    ax.set(xlabel="closest approach of the ball to a hand or forearm (m)", ylabel="fraction of shots",
           xlim=(None, xmax), ylim=(0, 1.02))
    ax.set_title("closest approach per shot (cumulative)", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def stats_figures(results: dict, out_dir: str) -> list[str]:
    """The three figures of a comparison (``results``: {mode: intercept_stats' result, its rows with
    ``"target_offset"``}) into ``out_dir``: success_by_speed.png, success_by_direction.png,
    closest_approach.png. Returns their paths."""
    os.makedirs(out_dir, exist_ok=True)
    return [plot_success_by_speed(results, os.path.join(out_dir, "success_by_speed.png")),
            plot_success_by_direction(results, os.path.join(out_dir, "success_by_direction.png")),
            plot_closest_approach(results, os.path.join(out_dir, "closest_approach.png"))]
