"""The closed loop's scenarios: :func:`run_scenario` runs the loop with the ball free or placed by a
function of time and records traces; :func:`experiments` is the set of experiments (saccades in eight
directions, vergence at 1 m, tracking at 15 and 30 deg/s) that ``python -m warp_vision.sim experiments``
and ``python -m warp_vision.bench loop`` report."""

from __future__ import annotations

import itertools
import time

import numpy as np

from warp_vision.body import SIDES

SETTLE_S = 0.2  # s of simulation before a scenario starts: the passive arms settle under gravity
#: The experiments' goals: saccades to 20 deg settle within 1 deg by 0.3 s; vergence at 1 m brings the
#: gaze lines within 2 cm; tracking's median error (after the first 0.3 s, the saccade onto the ball) under 1 deg.
SACCADE_DEG = 20.0
SACCADE_DIRECTIONS_DEG = tuple(range(0, 360, 45))  # the eight saccades' directions (0 = rightward, 90 = up)
SACCADE_WITHIN_DEG, SACCADE_BY_S = 1.0, 0.3
VERGENCE_WITHIN_CM = 2.0
TRACKING_SPEEDS = (15.0, 30.0)  # deg/s
TRACKING_FROM_S, TRACKING_WITHIN_DEG = 0.3, 1.0


def run_scenario(loop, duration: float, ball=None, record=None, progress: bool = True) -> dict:
    """Run the loop for ``duration`` s. ``ball(t)`` (optional) places the ball kinematically each period
    (t from the start); otherwise it flies freely. Returns per-period traces: time, ball position, each
    eye's gaze error (deg) and distance from its gaze line to the ball (m), neck angles (rad), the eyes'
    mean eccentricity in the head (deg)."""
    from tqdm import tqdm

    from warp_vision.sim.loop import CONTROL_DT, gaze_error_deg, line_distance

    body = loop.body
    t0 = body.time
    tr = {"t": [], "ball": [], "neck": [], "eye_in_head": [], **{f"error_{s}": [] for s in SIDES},
          **{f"line_{s}": [] for s in SIDES}}
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


def _scenarios():
    """(name, duration s, ball maker) of the experiments: eight saccades, two pursuits. A maker takes the
    body, just reset, and returns ball(t), the ball's position at t s from the start."""
    from warp_vision.sim.loop import point_at

    out = []
    for d in SACCADE_DIRECTIONS_DEG:
        ang = np.radians(d)
        out.append((f"saccade_{d}", 0.8,
                    lambda body,
                    ang=ang: _fixed(point_at(body, SACCADE_DEG * np.cos(ang), SACCADE_DEG * np.sin(ang), 1.0))))
    for omega in TRACKING_SPEEDS:
        for way in TRACKING_WAYS:
            out.append((f"tracking_{omega:g}_{way}", 1.2, lambda body, omega=omega, way=way: _orbit(body, omega, way)))
    return out


def _fixed(p):
    return lambda _t: p


#: The pursuits run both ways round: leftward from 18 deg right, and rightward from 18 deg left.
TRACKING_WAYS = ("leftward", "rightward")


def _orbit(body, omega: float, way: str = "leftward"):
    """A circle of 1 m around the eyes' midpoint in the horizontal plane at ``omega`` deg/s, fixed in the
    world as the head turns, starting 18 deg to one side and moving ``way`` (:data:`TRACKING_WAYS`)."""
    if way not in TRACKING_WAYS:
        raise ValueError(f"way: expected one of {TRACKING_WAYS}, got {way!r}")
    mid = 0.5 * (body.eye_pose("left")[:3, 3] + body.eye_pose("right")[:3, 3])
    sign = 1.0 if way == "leftward" else -1.0

    def orbit(tt):
        yaw = sign * np.radians(-18.0 + omega * tt)
        return mid + np.array([np.sin(yaw), -np.cos(yaw), 0.0])

    return orbit


def experiments(loops, progress: bool = True, return_traces: bool = False):
    """Saccades to a ball appearing at 20 deg in eight directions (1 m away), vergence at the end of each,
    and tracking a ball circling the eyes at 15 and 30 deg/s, both ways round; the loop's time shares (over these runs
    alone). The bodies' gravity is switched off: the ball is placed kinematically.

    ``loops``: one loop, or a list of them (each with its own body); a list runs each scenario on every
    loop in turn (the first of them rotating) before the next scenario, so the loops meet the same machine
    (speed drifts fall on all alike), and returns one result per loop. With ``return_traces``, also each
    loop's traces: ``(result, traces)``, traces ``{scenario name: run_scenario's traces}`` (``saccade_0``
    ... ``saccade_315``, ``tracking_15_leftward`` ...), as :func:`plot_experiments` draws them."""
    from warp_vision.sim.loop import CONTROL_DT

    single = not isinstance(loops, (list, tuple))
    loops = [loops] if single else list(loops)
    state = []
    for loop in loops:
        loop.body.model.opt.gravity[:] = 0
        loop.timing = dict.fromkeys(loop.timing, 0.0)
        state.append({"wall": 0.0, "sim": 0.0, "traces": {}})
    for i, (name, duration, make_ball) in enumerate(_scenarios()):
        order = [(i + j) % len(loops) for j in range(len(loops))]  # who goes first rotates
        for loop, st in ((loops[j], state[j]) for j in order):
            loop.reset(SETTLE_S)
            ball = make_ball(loop.body)
            t = time.perf_counter()
            tr = run_scenario(loop, duration, ball=ball, progress=progress)
            st["wall"] += time.perf_counter() - t
            st["sim"] += tr["t"][-1]
            st["traces"][name] = tr
    out = [_summary(loop, st, CONTROL_DT) for loop, st in zip(loops, state)]
    traces = [st["traces"] for st in state]
    if single:
        return (out[0], traces[0]) if return_traces else out[0]
    return (out, traces) if return_traces else out


def goal_lines(result: dict) -> list[str]:
    """:func:`experiments`'s result as a line per experiment against its goal ("met" or "missed"), and one of
    the loop's speed: what ``python -m warp_vision.sim experiments`` prints (the JSON holds the rest)."""
    def verdict(ok: bool) -> str:
        return "met" if ok else "MISSED"

    sac, verg = result["saccade_20deg"], result["vergence_1m"]
    slowest = sac["time_both_within_1deg_s_max"]
    when = (f"after {slowest:.2f} s at the slowest" if np.isfinite(slowest) else
            "not in every direction within the run")
    lines = [f"saccades to {SACCADE_DEG:g} deg, {len(sac['trials'])} directions: both eyes within "
             f"{SACCADE_WITHIN_DEG:g} deg {when} (goal: by {SACCADE_BY_S:g} s): "
             f"{verdict(sac['all_within_1deg_by_0.3s'])}",
             f"vergence at 1 m: the gaze lines {verg['gaze_line_distance_cm_max']:.2f} cm apart at the most (goal: "
             f"< {VERGENCE_WITHIN_CM:g} cm): {verdict(verg['gaze_line_distance_cm_max'] < VERGENCE_WITHIN_CM)}"]
    for omega in TRACKING_SPEEDS:
        tr = result[f"tracking_{omega:g}deg_s"]
        med, p90 = tr["median_error_deg"], tr["p90_error_deg"]
        lines.append(f"tracking at {omega:g} deg/s: median error {' / '.join(f'{med[s]:.2f}' for s in SIDES)} deg "
                     f"({' / '.join(SIDES)}; p90 {' / '.join(f'{p90[s]:.2f}' for s in SIDES)}; goal: median < "
                     f"{TRACKING_WITHIN_DEG:g} deg): {verdict(max(med.values()) < TRACKING_WITHIN_DEG)}")
    t = result["timing"]
    shares = ", ".join(f"{k} {100 * v:.0f}%" for k, v in sorted(t["share"].items(), key=lambda kv: -kv[1]))
    lines.append(f"the loop: {t['sim_s']:.1f} s simulated in {t['wall_s']:.1f} s ({t['sim_to_wall']:.2f}x real time, "
                 f"{t['frames_per_s']:g} visual frames/s); {shares}")
    return lines


def _summary(loop, st: dict, control_dt: float) -> dict:
    trials = []
    for d in SACCADE_DIRECTIONS_DEG:
        tr = st["traces"][f"saccade_{d}"]
        both = np.maximum(tr["error_left"], tr["error_right"])
        within = both < SACCADE_WITHIN_DEG
        trials.append({"direction_deg": float(d),
                       "time_both_within_1deg_s": float(tr["t"][np.argmax(within)]) if within.any() else None,
                       "error_at_0.3s_deg": float(np.interp(SACCADE_BY_S, tr["t"], both)),
                       "max_error_after_0.3s_deg": float(both[tr["t"] >= SACCADE_BY_S].max()),
                       "gaze_line_distance_cm": 100 * float(max(tr["line_left"][-1], tr["line_right"][-1])),
                       # the eye-head synergy: the eyes' eccentricity in the head falls as the head turns
                       "eye_in_head_deg_peak": float(tr["eye_in_head"].max()),
                       "eye_in_head_deg_end": float(tr["eye_in_head"][-1]),
                       "head_turn_deg_end": float(np.degrees(np.linalg.norm(tr["neck"][-1][:2])))})
    times = [tt["time_both_within_1deg_s"] for tt in trials]
    out = {
        "saccade_20deg": {
            "trials": trials,
            "all_within_1deg_by_0.3s": all(tt is not None and tt <= SACCADE_BY_S for tt in times),
            "time_both_within_1deg_s_max": max(tt if tt is not None else np.inf for tt in times),
            "error_at_0.3s_deg_max": max(tt["error_at_0.3s_deg"] for tt in trials),
            "max_error_after_0.3s_deg_median": float(np.median([tt["max_error_after_0.3s_deg"] for tt in trials])),
        },
        "vergence_1m": {
            "gaze_line_distance_cm_max": max(tt["gaze_line_distance_cm"] for tt in trials),
            "gaze_line_distance_cm_median": float(np.median([tt["gaze_line_distance_cm"] for tt in trials])),
        },
    }
    for omega in TRACKING_SPEEDS:
        trs = [st["traces"][f"tracking_{omega:g}_{way}"] for way in TRACKING_WAYS]
        # after the first saccade onto it, both ways round pooled
        err = {s: np.concatenate([tr[f"error_{s}"][tr["t"] > TRACKING_FROM_S] for tr in trs]) for s in SIDES}
        out[f"tracking_{omega:g}deg_s"] = {"median_error_deg": {s: float(np.median(err[s])) for s in SIDES},
                                           "p90_error_deg": {s: float(np.percentile(err[s], 90)) for s in SIDES}}
    wall = st["wall"]
    share = {k: v / wall for k, v in loop.timing.items()}
    share["other"] = max(0.0, 1.0 - sum(share.values()))  # traces, progress bars, Python between the stages
    out["ball"] = loop.ball
    out["gaze_perception"] = loop.perception
    out["timing"] = {"sim_s": st["sim"], "wall_s": wall, "sim_to_wall": st["sim"] / wall,
                     "frame_every": loop.frame_every, "frames_per_s": 1.0 / (loop.frame_every * control_dt),
                     "share": share}
    return out


def plot_experiments(traces: dict, path: str, title: str | None = None) -> str:
    """The experiments over time, with their goals, in one figure at ``path`` (PNG): the saccades' gaze
    error (the worse eye's) in each direction, the larger of the two gaze lines' distances from the ball
    in the same runs (vergence), and each eye's error while tracking. ``traces``: the second value of
    ``experiments(loop, return_traces=True)``. Returns ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    missing = [name for name, _, _ in _scenarios() if name not in traces]
    if missing:
        raise ValueError(f"traces: missing the scenarios {missing} (expected experiments(..., return_traces=True)'s)")
    fig, (ax_s, ax_v, ax_t) = plt.subplots(1, 3, figsize=(16, 4.6))
    for k, d in enumerate(SACCADE_DIRECTIONS_DEG):
        tr = traces[f"saccade_{d}"]
        both = np.maximum(tr["error_left"], tr["error_right"])
        ax_s.plot(tr["t"], np.maximum(both, 1e-2), color=f"C{k}", label=f"{d} deg")
        ax_v.plot(tr["t"], 100 * np.maximum(tr["line_left"], tr["line_right"]), color=f"C{k}")
    ax_s.axhline(SACCADE_WITHIN_DEG, color="k", ls=":", lw=1)
    ax_s.axvline(SACCADE_BY_S, color="k", ls=":", lw=1)
    ax_s.set(yscale="log", xlabel="time after the ball appears (s)", ylabel="gaze error, worse eye (deg)",
             title=f"saccades to {SACCADE_DEG:g} deg (goal: within {SACCADE_WITHIN_DEG:g} deg by {SACCADE_BY_S:g} s)")
    ax_s.legend(title="direction", fontsize=7, ncol=2)
    ax_v.axhline(VERGENCE_WITHIN_CM, color="k", ls=":", lw=1)
    ax_v.set(yscale="log", xlabel="time after the ball appears (s)",
             ylabel="larger gaze line's distance from the ball (cm)",
             title=f"vergence at 1 m, the same runs (goal: < {VERGENCE_WITHIN_CM:g} cm at the end)")
    for j, (w, way) in enumerate(itertools.product(TRACKING_SPEEDS, TRACKING_WAYS)):
        tr = traces[f"tracking_{w:g}_{way}"]
        for s, ls in zip(SIDES, ("-", "--")):
            ax_t.plot(tr["t"], np.maximum(tr[f"error_{s}"], 1e-2), color=f"C{j}", ls=ls, lw=1,
                      label=f"{w:g} deg/s {way}, {s} eye")
    ax_t.axvspan(0.0, TRACKING_FROM_S, color="0.9", lw=0)
    ax_t.axhline(TRACKING_WITHIN_DEG, color="k", ls=":", lw=1)
    ax_t.set(yscale="log", xlabel="time (s; the shaded start is the saccade onto the ball)", ylabel="gaze error (deg)",
             title=f"tracking a ball circling at 1 m (goal: median < {TRACKING_WITHIN_DEG:g} deg)")
    ax_t.legend(fontsize=6, ncol=2)
    for ax in (ax_s, ax_v, ax_t):
        ax.grid(alpha=0.3, which="both")
        ax.title.set_fontsize(9)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


#: The light-step scenario: the room's light level (``loop.light_scale``) in phases of (duration s,
#: scale): settle, +2 log units, back (-2 log units).
LIGHT_PHASES = ((2.0, 1.0), (2.5, 100.0), (3.0, 1.0))
#: A pupil has settled when it stays within this fraction of the teacher's steady state.
SETTLE_TOLERANCE = 0.05


def light_steps(loop, phases=LIGHT_PHASES, progress: bool = True) -> dict:
    """Fixate a ball straight ahead at 1 m while the room's light level steps through ``phases``; per
    period the pupils (state and command) and the teacher's command (Watson & Yellott for the adapting
    luminance of the last frame). Per step and eye: the steady state (the teacher's command over the last
    0.5 s of the phase), the pupil's distance from it at the phase's end, the settle time (after which it
    stays within ``SETTLE_TOLERANCE`` of it), the latency (until it has moved 5% of the way) and the
    10-90% time."""
    from tqdm import tqdm

    from warp_vision.sim.loop import CONTROL_DT, point_at

    body = loop.body
    body.model.opt.gravity[:] = 0
    light = loop.light_scale  # the loop's own, given back at the end
    loop.light_scale = phases[0][1]
    loop.reset(SETTLE_S)
    ball = point_at(body, 0.0, 0.0, 1.0)
    tr = {"t": [], "light": [], **{f"{k}_{s}": [] for k in ("pupil", "command", "teacher") for s in SIDES}}
    starts = np.cumsum([0.0] + [d for d, _ in phases])
    n = int(round(starts[-1] / CONTROL_DT))
    t0 = body.time
    try:
        for k in tqdm(range(n), desc="light steps", disable=not progress, leave=False):
            t = k * CONTROL_DT
            loop.light_scale = phases[int(np.searchsorted(starts, t, side="right")) - 1][1]
            body.set_ball(ball)
            loop.step()
            tr["t"].append(body.time - t0)
            tr["light"].append(loop.light_scale)
            for s in SIDES:
                tr[f"pupil_{s}"].append(body.intraocular(s)[0])
                tr[f"command_{s}"].append(loop._pupil_command[s])
                tr[f"teacher_{s}"].append(loop.pupil_teacher[s])
    finally:
        loop.light_scale = light
    tr = {k: np.asarray(v) for k, v in tr.items()}
    steps = []
    for i in range(1, len(phases)):
        a, b = starts[i], starts[i + 1]
        for s in SIDES:
            steps.append({"eye": s, "at_s": float(a), "log_units": float(np.log10(phases[i][1] / phases[i - 1][1])),
                          **pupil_step_metrics(tr["t"], tr[f"pupil_{s}"], tr[f"teacher_{s}"], a, b)})
    return {"traces": tr, "steps": steps}


def pupil_step_metrics(t: np.ndarray, pupil: np.ndarray, teacher: np.ndarray, start: float, end: float) -> dict:
    """A pupil's response to a light step at ``start`` (the phase ending at ``end``): see :func:`light_steps`."""
    before = pupil[(t > start - 0.2) & (t <= start)].mean()
    phase = (t > start) & (t <= end)
    tt, p = t[phase] - start, pupil[phase]
    ss = float(teacher[(t > end - 0.5) & (t <= end)].mean())
    off = np.abs(p - ss) / ss > SETTLE_TOLERANCE
    settle = float(tt[np.nonzero(off)[0][-1] + 1]) if off.any() and not off[-1] else (0.0 if not off.any() else None)
    frac = (p - before) / (ss - before)
    moved = lambda f: float(tt[np.argmax(frac >= f)]) if (frac >= f).any() else None  # noqa: E731
    t10, t90 = moved(0.1), moved(0.9)
    return {"from_mm": float(before), "steady_state_mm": ss, "end_mm": float(p[-1]),
            "end_relative_error": float(abs(p[-1] - ss) / ss), "settle_s": settle, "latency_s": moved(0.05),
            "rise_10_90_s": None if t10 is None or t90 is None else t90 - t10,
            "direction": "constrict" if ss < before else "dilate"}


#: The focus-step scenario: the fixated card's distance (m) in phases of (duration s, distance).
FOCUS_PHASES = ((1.5, 2.0), (2.0, 1.0 / 3.0), (2.0, 2.0))
#: Accommodation is in focus within this many dioptres of the card's vergence.
FOCUS_TOLERANCE_D = 0.25
#: The cards' texture seed: none of the lens datasets' (their seeds are 0 and 1000).
FOCUS_CARD_SEED = 2024
#: The goal a focus step is held to (docs/RESULTS.md): in focus (FOCUS_TOLERANCE_D) within this
#: many simulated seconds.
FOCUS_GOAL_S = 1.2


class FixationOracle:
    """Stands in for an eye's foveation net in the focus-step scenario: the true direction of a point
    (``target()``) in the eye frame, so the eyes fixate the card's centre. The foveation nets are trained
    on balls; this scenario measures accommodation alone."""

    def __init__(self, foveator, body, side: str, target):
        self.retina, self.trained_eye = foveator.retina, foveator.trained_eye
        self.samples_per_receptor, self.norm = foveator.samples_per_receptor, foveator.norm
        self.generator = getattr(foveator, "generator", None)
        self.body, self.side, self.target = body, side, target

    def __call__(self, onv):
        from warp_vision.frames import gaze_angles

        T = self.body.eye_pose(self.side)
        d = T[:3, :3].T @ (self.target() - T[:3, 3])
        return np.asarray(gaze_angles(d / np.linalg.norm(d)))[None]


def focus_steps(loop, phases=FOCUS_PHASES, progress: bool = True, snapshots: bool = True,
                card_vertices: int | None = None, card_seed: int = FOCUS_CARD_SEED) -> dict:
    """The eyes fixate a textured card straight ahead while it steps through the distances of
    ``phases`` (a card per distance, sized as the lens data size theirs:
    :func:`warp_vision.data.intraocular.card_size_for`); per period each eye's accommodation, its command, the card's
    vergence from the eye (D) and the defocus (accommodation minus that vergence). Per step and eye: the latency (until
    the accommodation has moved 5% of the way), the time until it is within ``FOCUS_TOLERANCE_D`` of the card's vergence
    for good, and the defocus at the phase's end. With ``snapshots``, the left eye's ONV just after each step and at the
    phase's end (blurred, then sharp). ``card_vertices``: the cards' grid (default the lens data's); ``card_seed``:
    their textures' seed."""
    from tqdm import tqdm

    from warp_vision.sim.loop import CONTROL_DT, point_at

    body = loop.body
    body.model.opt.gravity[:] = 0
    cards = _focus_cards(loop, phases, card_vertices, card_seed)
    loop.reset(SETTLE_S)
    starts = np.cumsum([0.0] + [d for d, _ in phases])
    state = {"centre": None}
    fov = loop.fov
    loop.fov = {s: FixationOracle(fov[s], body, s, lambda: state["centre"]) for s in SIDES}
    H = body.head_pose()
    parked = H[:3, 3] - 1.5 * H[:3, 2]  # the ball is not in this scenario: 1.5 m behind the head, out of sight
    body.set_ball(parked)
    tr = {"t": [], "distance": [],
          **{f"{k}_{s}": [] for k in ("accommodation", "command", "vergence", "defocus") for s in SIDES}}
    shots = []
    n = int(round(starts[-1] / CONTROL_DT))
    t0 = body.time
    try:
        for k in tqdm(range(n), desc="focus steps", disable=not progress, leave=False):
            t = k * CONTROL_DT
            phase = int(np.searchsorted(starts, t, side="right")) - 1
            dist = phases[phase][1]
            if k == 0 or dist != tr["distance"][-1]:  # the card moves at a step, then stays put in the world
                state["centre"] = point_at(body, 0.0, 0.0, dist)
            _show_card(loop, cards, dist, state["centre"])
            body.set_ball(parked)
            loop.step()
            _record_focus(loop, tr, body.time - t0, dist, state["centre"])
            if snapshots and _snapshot_due(loop, t, starts, phase):
                shots.append({"t": float(tr["t"][-1]), "defocus_D": float(tr["defocus_left"][-1]),
                              "onv": loop.onv["left"][0].numpy().copy()})
    finally:
        loop.fov = fov
        for name in cards.values():
            loop.scene.set_visible(name, False)
    tr = {k: np.asarray(v) for k, v in tr.items()}
    steps = []
    for i in range(1, len(phases)):
        a, b = starts[i], starts[i + 1]
        for s in SIDES:
            steps.append({"eye": s, "at_s": float(a), "from_m": phases[i - 1][1], "to_m": phases[i][1],
                          **focus_step_metrics(tr["t"], tr[f"accommodation_{s}"], tr[f"vergence_{s}"], a, b)})
    return {"traces": tr, "steps": steps, "snapshots": shots}


def _focus_cards(loop, phases, card_vertices: int | None, card_seed: int) -> dict:
    """{distance: its card's name in ``loop.scene``}: a card per distance of ``phases``, of the kind the lens nets
    learnt on (the size their data show at that distance, so the pattern's angular scale is theirs) but with a
    texture of its own; each added hidden, once."""
    from warp_vision.data.intraocular import CARD_VERTICES, card_size_for
    from warp_vision.scene import Material
    from warp_vision.scene.textures import textured_card

    cards = {}
    for _dur, dist in phases:
        name = f"focus_card_{card_seed}_{dist:.3f}"
        cards[dist] = name
        if name not in [o.name for o in loop.scene.objects]:
            loop.scene.add(name, textured_card(card_size_for(dist), card_vertices or CARD_VERTICES,
                                               [card_seed, int(dist * 1000)]),
                           Material(vertex_colors=True), np.eye(4))
            loop.scene.set_visible(name, False)
    return cards


def _show_card(loop, cards: dict, dist: float, centre) -> None:
    """The card of ``dist`` alone visible, at ``centre``, its face (+z) toward the eyes (the head's -z)."""
    T = np.eye(4)
    T[:3, :3] = loop.body.head_pose()[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = centre
    for dd, name in cards.items():
        loop.scene.set_visible(name, dd == dist)
    loop.scene.set_transform(cards[dist], T)


def _record_focus(loop, tr: dict, t: float, dist: float, centre) -> None:
    """A period's row of the focus traces ``tr``: the time, the card's distance, and per eye the
    accommodation, the lens command, the card's vergence from the eye (D) and the defocus."""
    body = loop.body
    tr["t"].append(t)
    tr["distance"].append(dist)
    for s in SIDES:
        acc = body.intraocular(s)[1]
        verg = 1.0 / np.linalg.norm(centre - body.eye_pose(s)[:3, 3])
        tr[f"accommodation_{s}"].append(acc)
        tr[f"command_{s}"].append(loop._lens_command.get(s, loop.lens_teacher.get(s, np.nan)))
        tr[f"vergence_{s}"].append(verg)
        tr[f"defocus_{s}"].append(acc - verg)


def _snapshot_due(loop, t: float, starts, phase: int) -> bool:
    """Whether the period at ``t`` rendered a frame just after the step into ``phase`` (not the first) or
    0.1 s before its end."""
    from warp_vision.sim.loop import CONTROL_DT

    if not (loop.period % loop.frame_every == 1 and phase > 0):
        return False
    since = t - starts[phase]
    return (since < loop.frame_every * CONTROL_DT
            or abs(t - (starts[phase + 1] - 0.1)) < loop.frame_every * CONTROL_DT / 2)


def focus_summary(runs: list[list[dict]], goal_s: float = FOCUS_GOAL_S) -> dict:
    """Over the steps of several focus-step runs (``runs``: each a :func:`focus_steps` result's "steps"),
    per direction ("near": to the nearer card, "far"): how many eye-steps came into focus within
    ``goal_s``, the median time to focus (a step never in focus counts as infinitely slow; None if the
    median is such a step) and the median absolute defocus at the phases' ends."""
    out = {}
    for direction in ("near", "far"):
        steps = [st for run in runs for st in run if (st["to_m"] < st["from_m"]) == (direction == "near")]
        if not steps:
            continue
        t = np.array([np.inf if st["in_focus_s"] is None else st["in_focus_s"] for st in steps])
        median = float(np.median(t))
        out[direction] = {"steps": len(steps), "in_focus_within_goal": int((t <= goal_s).sum()), "goal_s": goal_s,
                          "median_in_focus_s": median if np.isfinite(median) else None,
                          "median_abs_end_defocus_D": float(np.median([abs(st["end_defocus_D"]) for st in steps]))}
    return out


def focus_step_metrics(t: np.ndarray, acc: np.ndarray, vergence: np.ndarray, start: float, end: float) -> dict:
    """An eye's accommodation response to a focus step at ``start`` (the phase ending at ``end``)."""
    before = acc[(t > start - 0.2) & (t <= start)].mean()
    phase = (t > start) & (t <= end)
    tt, a, v = t[phase] - start, acc[phase], vergence[phase]
    goal = v[-1]
    frac = (a - before) / (goal - before)
    off = np.abs(a - v) > FOCUS_TOLERANCE_D
    in_focus = float(tt[np.nonzero(off)[0][-1] + 1]) if off.any() and not off[-1] else (0.0 if not off.any() else None)
    return {"from_D": float(before), "to_D": float(goal),
            "latency_s": float(tt[np.argmax(frac >= 0.05)]) if (frac >= 0.05).any() else None, "in_focus_s": in_focus,
            "end_defocus_D": float(a[-1] - v[-1])}
