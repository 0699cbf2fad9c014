"""``python -m warp_vision.sim search``: the search trials (:mod:`warp_vision.sim.search_trials`) under the
active search and, on the same trials, under the foveation nets' single answer; search.json, a summary
figure and scanpath figures.

The scanpath figure of a trial is the scene as the head sees it at the start (a pinhole view from the
eyes' midpoint along the head's straight-ahead gaze): the ball and each look-alike named, the search's
targets numbered in order with the time each was chosen, a rejected one crossed out in red, an accepted
one ringed in green, and the gaze (the two eyes' mean axis, 1.5 m out) over the trial as a line.
"""

from __future__ import annotations

import os
import time

import numpy as np

from warp_vision.body import SIDES
from warp_vision.sim.gaze import CONTROL_DT

SCANPATH_FOV_DEG = 90.0
SCANPATH_SIZE = (560, 420)


def summarise(results: list[dict]) -> dict:
    """The share found (both eyes within 1 deg by 1.0 s and holding), the median time to the hold among the
    found, the median saccades per trial, and the share found per look-alike present."""
    found = [r for r in results if r["found"]]
    out = {"trials": len(results), "found": len(found), "found_share": len(found) / max(len(results), 1),
           "simulation_errors": sum("error" in r for r in results),
           "median_time_to_hold_s": float(np.median([r["held_from_s"] for r in found])) if found else None,
           "median_saccades": float(np.median([r["saccades"] for r in results])) if results else None,
           "by_look_alike": {}}
    for kind in ("muzzle", "decoy", "lamp", "hand"):
        rs = [r for r in results if kind in r["look_alikes"]]
        if rs:
            out["by_look_alike"][kind] = {"trials": len(rs), "found_share": float(np.mean([r["found"] for r in rs]))}
    return out


def _trial_scene(body, room_seed: int, cache: dict):
    from warp_vision.sim.loop import body_scene
    from warp_vision.sim.search_trials import add_look_alike_objects

    if cache.get("seed") != room_seed:
        sc = body_scene(body, room_seed, "ordinary")
        add_look_alike_objects(sc)
        cache.update(seed=room_seed, scene=sc)
    return cache["scene"]


def run_all(loop, trials: list, verifiers: dict | None, baseline: bool = True, progress: bool = True,
            scanpaths: int = 0, out: str | None = None) -> dict:
    """Every trial under the active search and (``baseline``) under the single answer; scanpath figures of the
    first ``scanpaths`` trials into ``out/figures``."""
    from tqdm import tqdm

    from warp_vision.body import SimulationError
    from warp_vision.sim.search import ActiveSearch
    from warp_vision.sim.search_trials import run_trial

    modes = ["search"] + (["nets"] if baseline else [])
    results = {m: [] for m in modes}
    cache: dict = {}
    wall = {m: 0.0 for m in modes}
    sim_s = {m: 0.0 for m in modes}
    added = {"candidates": 0.0, "single_answer": 0.0, "pairs": 0.0, "verify": 0.0, "frames": 0}
    for k, trial in enumerate(tqdm(trials, desc="search trials", disable=not progress)):
        scene = _trial_scene(loop.body, trial.room_seed, cache)
        for m in modes:
            search = ActiveSearch(verifiers) if m == "search" else None
            path = [] if (m == "search" and k < scanpaths) else None
            record = (lambda lp, path=path: path.append(_mean_gaze_point(lp.body))) if path is not None else None
            t0 = time.perf_counter()
            try:
                r = run_trial(loop, trial, scene, m, search, record=record)
            except SimulationError as e:  # the body's physics failed its checks: the trial counts as a miss
                r = _failed_trial(trial, m, e)
            wall[m] += time.perf_counter() - t0
            sim_s[m] += len(r["errors_deg"]) * CONTROL_DT
            results[m].append(r)
            if search is not None:
                for key in added:
                    added[key] += search.timing[key]
            if path is not None and out and "error" not in r:
                scanpath_figure(loop, trial, scene, r, path, os.path.join(out, "figures", f"scanpath_{trial.seed}.png"))
    frames = max(added["frames"], 1)
    per_frame = {k: 1e3 * added[k] / frames for k in ("candidates", "pairs", "verify")}
    frame_ms = 1e3 * wall["search"] / frames
    return {"modes": {m: {"summary": summarise(results[m]), "real_time_factor": sim_s[m] / max(wall[m], 1e-9),
                          "trials": results[m]} for m in modes},
            "search_cost": {"ms_per_frame": per_frame, "frame_ms": frame_ms,
                            "single_answer_ms": 1e3 * added["single_answer"] / frames,
                            "share_of_frame": sum(per_frame.values()) / max(frame_ms, 1e-9)}}


#: the cannon shots' measure: from this time after the launch on, the share of the flight with both eyes
#: within CANNON_WITHIN_DEG of the ball
CANNON_FROM_S, CANNON_WITHIN_DEG = 0.15, 2.0


def run_cannon_shot(loop, shot, scene, perception: str, search=None, settle_s: float = 0.2) -> dict:
    """One cannon shot (:mod:`warp_vision.sim.cannon`) under ``perception``: the loop runs from the launch
    for the shot's flight time with the arms passive; per period both eyes' gaze error to the ball."""
    from warp_vision.sim.gaze import CONTROL_DT
    from warp_vision.sim.loop import gaze_error_deg

    body = loop.body
    loop.scene = scene
    loop.perception, loop.search = perception, search
    loop.reset(settle_s=settle_s)
    for name in [o.name for o in scene.objects if o.name.startswith("decoy_") or o.name == "lamp_panel"]:
        scene.set_visible(name, False)
    body.fire_cannon(shot.target, shot.flight_time)
    err = []
    for _ in range(int(round(shot.flight_time / CONTROL_DT))):
        loop.step()
        err.append([gaze_error_deg(body, s, body.ball_position()) for s in SIDES])
    err = np.asarray(err)
    t = (np.arange(len(err)) + 1) * CONTROL_DT
    late = t >= CANNON_FROM_S
    share = float((err[late].max(1) <= CANNON_WITHIN_DEG).mean()) if late.any() else 0.0
    return {"seed": shot.seed, "perception": perception, "flight_s": shot.flight_time, "share_within": share,
            "tracked": share >= 0.9, "median_error_deg": float(np.median(err[late].max(1))) if late.any() else None}


def run_cannon(loop, shots: list, rooms: list, verifiers: dict | None, baseline: bool, progress: bool) -> dict:
    """Every shot under the active search and (``baseline``) the single answer, in the trials' rooms in turn."""
    from tqdm import tqdm

    from warp_vision.sim.search import ActiveSearch

    modes = ["search"] + (["nets"] if baseline else [])
    out = {m: [] for m in modes}
    cache: dict = {}
    for k, shot in enumerate(tqdm(shots, desc="cannon shots", disable=not progress)):
        scene = _trial_scene(loop.body, rooms[k % len(rooms)], cache)
        for m in modes:
            out[m].append(run_cannon_shot(loop, shot, scene, m, ActiveSearch(verifiers) if m == "search" else None))
    return {m: {"shots": len(r), "tracked_share": float(np.mean([x["tracked"] for x in r])) if r else None,
                "median_share_within": float(np.median([x["share_within"] for x in r])) if r else None, "per_shot": r}
            for m, r in out.items()}


def _failed_trial(trial, perception: str, error: Exception) -> dict:
    """A trial the simulation could not finish, scored as not found (its gaze errors infinite), with the error."""
    from warp_vision.sim.search_trials import TRIAL_S, look_alikes

    periods = int(round(TRIAL_S / CONTROL_DT))
    return {"seed": trial.seed, "perception": perception, "ball_in_sight": None, "look_alikes": look_alikes(trial),
            "ball": list(trial.ball), "found": False, "held_from_s": None, "final_error_deg": [float("inf")] * 2,
            "saccades": 0, "events": [], "errors_deg": [[float("inf")] * 2] * periods, "error": str(error)}


def _mean_gaze_point(body) -> np.ndarray:
    mid = 0.5 * (body.eye_pose("left")[:3, 3] + body.eye_pose("right")[:3, 3])
    axis = body.eye_pose("left")[:3, 2] + body.eye_pose("right")[:3, 2]
    return mid + 1.5 * axis / np.linalg.norm(axis)


def scanpath_figure(loop, trial, scene, result: dict, path: list, file: str) -> str:
    """The trial's scanpath drawn on the head's view of the scene (module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mujoco

    from warp_vision.frames import look_at
    from warp_vision.kernels.render import render_camera
    from warp_vision.sim.loop import set_eye_view, sync_scene
    from warp_vision.sim.search_trials import ball_point, hand_posture, look_alikes, pin, place_look_alikes
    from warp_vision.sim.video import project
    from warp_vision.viz import tone_map

    body = loop.body
    w, h = SCANPATH_SIZE
    loop.reset(settle_s=0.2)
    point = ball_point(body, trial)
    body.set_ball(point)
    pin(body, hand_posture(body, trial))  # the raised hand, as in the trial
    mujoco.mj_forward(body.model, body.data)
    place_look_alikes(scene, body, trial)
    mid = 0.5 * (body.eye_pose("left")[:3, 3] + body.eye_pose("right")[:3, 3])
    cam = look_at(mid, mid + body.head_pose()[:3, 2])
    sync_scene(scene, body)
    set_eye_view(scene, True)
    img = tone_map(render_camera(scene, cam, w, h, fov_deg=SCANPATH_FOV_DEG).numpy())
    fig, ax = plt.subplots(figsize=(7.5, 5.8))
    ax.imshow(img)
    xy = [q for q in project(cam, w, h, SCANPATH_FOV_DEG, np.asarray(path)) if q is not None]
    if xy:
        ax.plot(*np.asarray(xy).T, color="yellow", lw=1.2, alpha=0.8, label="gaze")
    b = project(cam, w, h, SCANPATH_FOV_DEG, [point])[0]
    if b:
        ax.plot(*b, "o", mfc="none", mec="cyan", ms=14, mew=2, label="ball")
    muzzle = body.data.site_xpos[body.model.site("muzzle").id]
    m = project(cam, w, h, SCANPATH_FOV_DEG, [muzzle])[0]
    if m:
        ax.annotate("muzzle", m, color="white", fontsize=8)
    n = 0
    for t, kind, p in result["events"]:
        q = project(cam, w, h, SCANPATH_FOV_DEG, [np.asarray(p)])[0]
        if q is None:
            continue
        if kind == "target":
            n += 1
            ax.annotate(f"{n} ({t:.2f} s)", q, color="white", fontsize=8, xytext=(6, -6), textcoords="offset points")
            ax.plot(*q, "w.", ms=6)
        elif kind in ("reject", "lost"):
            ax.plot(*q, "x", color="red", ms=12, mew=2.5)
        elif kind == "accept":
            ax.plot(*q, "o", mfc="none", mec="lime", ms=10, mew=2)
    verdict = f"found, held from {result['held_from_s']:.2f} s" if result["found"] else "not found by 1.0 s"
    ax.set_title(f"trial {trial.seed}: look-alikes {', '.join(look_alikes(trial))}; {verdict}", fontsize=9)
    ax.set_axis_off()
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    os.makedirs(os.path.dirname(file), exist_ok=True)
    fig.savefig(file, dpi=100)
    plt.close(fig)
    return file


def summary_figure(report: dict, file: str) -> str:
    """Per mode: the share of trials whose both eyes are within 1 deg of the ball over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    for m, d in report["modes"].items():
        err = np.array([r["errors_deg"] for r in d["trials"]])  # [trials, periods, 2]
        t = (np.arange(err.shape[1]) + 1) * CONTROL_DT
        ax[0].plot(t, (err.max(2) <= 1.0).mean(0), label=f"{m} ({100 * d['summary']['found_share']:.0f}% found)")
        kinds = list(d["summary"]["by_look_alike"])
        ax[1].bar(np.arange(len(kinds)) + (0.2 if m == "nets" else -0.2),
                  [d["summary"]["by_look_alike"][k]["found_share"]
                                                                          for k in kinds], width=0.4, label=m)
        ax[1].set_xticks(np.arange(len(kinds)), kinds)
    ax[0].axvline(1.0, color="k", lw=0.7, ls="--")
    ax[0].set(xlabel="time (s)", ylabel="share of trials with both eyes within 1 deg", ylim=(0, 1))
    ax[1].set(ylabel="share found", title="by the look-alike in view", ylim=(0, 1))
    for a in ax:
        a.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(file), exist_ok=True)
    fig.savefig(file, dpi=110)
    plt.close(fig)
    return file


def report_lines(report: dict) -> list[str]:
    lines = []
    c = report.get("search_cost")
    if c:
        parts = ", ".join(f"{k} {v:.1f} ms" for k, v in c["ms_per_frame"].items())
        lines.append(f"what the search adds per frame: {parts}; {100 * c['share_of_frame']:.0f}% of the search's "
                     f"{c['frame_ms']:.0f} ms a frame (4 control periods)")
    for m, c in report.get("cannon", {}).items():
        what = "active search" if m == "search" else "single answer"
        lines.append(f"cannon, {what}: both eyes within {CANNON_WITHIN_DEG:g} deg of the ball for 90% of the flight "
                     f"after {CANNON_FROM_S:g} s in {100 * c['tracked_share']:.0f}% of {c['shots']} shots (median "
                     f"share of the flight {100 * c['median_share_within']:.0f}%)")
    for m, d in report["modes"].items():
        s = d["summary"]
        what = "active search" if m == "search" else "single answer (today's foveation nets)"
        t = f"{s['median_time_to_hold_s']:.2f} s" if s["median_time_to_hold_s"] is not None else "-"
        by = ", ".join(f"{k} {100 * v['found_share']:.0f}% of {v['trials']}" for k, v in s["by_look_alike"].items())
        lines.append(f"{what}: both eyes within 1 deg of the ball by 1.0 s and holding it in "
                     f"{s['found']}/{s['trials']} trials ({100 * s['found_share']:.1f}%); median time to the hold {t}, "
                     f"median saccades {s['median_saccades']:.0f}; by look-alike: {by}; real-time factor "
                     f"{d['real_time_factor']:.2f}")
    return lines


def search_command(args) -> dict:
    """``sim search``: provide the nets, run the trials, write search.json and the figures."""
    from warp_vision.fileio import write_json
    from warp_vision.provenance import software
    from warp_vision.sim.build import net_specs, setup_loop
    from warp_vision.sim.search import Verifier
    from warp_vision.sim.search_trials import sample_trial, trial_seeds

    seeds = trial_seeds(args.trials, args.seed, args.split)
    body, loop = setup_loop(args)
    verify_runs = {spec.eye: spec.run for spec in net_specs(args) if spec.kind == "verify"}
    verifiers = {s: Verifier(verify_runs[s], eye=s) for s in SIDES}
    trials = [sample_trial(s, args.split) for s in seeds]
    report = run_all(loop, trials, verifiers, baseline=not args.no_baseline, progress=not args.no_progress,
                     scanpaths=args.scanpaths, out=args.out)
    if args.cannon:
        from warp_vision.sim.cannon import sample_shots

        shots = sample_shots(args.cannon, seed=args.seed, split=args.split, side="left")
        report["cannon"] = run_cannon(loop, shots, sorted({t.room_seed for t in trials}), verifiers,
                                      not args.no_baseline, not args.no_progress)
    report["settings"] = {"trials": args.trials, "cannon_shots": args.cannon, "seed": args.seed, "split": args.split,
                          "verify": verify_runs, "foveation": {s: loop.fov[s].run_dir for s in SIDES}}
    write_json(os.path.join(args.out, "search.json"), {**report, "software": software()})
    summary_figure(report, os.path.join(args.out, "figures", "search.png"))
    return report
