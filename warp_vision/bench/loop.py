"""``python -m warp_vision.bench loop``: the closed loop's speed and accuracy at several visual frame rates.

For each setting (the eyes render every N control periods of 10 ms; N = 1 renders every
period), one run of :func:`warp_vision.sim.scenarios.experiments` on the same nets (trained first
when missing, as ``python -m warp_vision.sim`` does): simulated/wall, the wall time's shares (render, nets,
MuJoCo, control, other) and the experiments' accuracy (saccade settle time in eight directions, tracking
errors, vergence). The settings share one process and take turns scenario by scenario, so they meet the
same machine (a drift in its speed falls on all alike); the eye-ray cache is shared too, so a setting
rarely aims its rays itself (the loop's steady state; the first visit of an optical state costs about
0.17 s per eye). The summary compares each setting with the first: the speed-up
and the relative change of the saccade settle time and of the tracking median.
"""

from __future__ import annotations

import numpy as np

from warp_vision.body import SIDES


def _accuracy(res: dict) -> dict:
    sac = res["saccade_20deg"]
    settle = [t["time_both_within_1deg_s"] for t in sac["trials"]]
    track = {k: float(np.mean(list(res[k]["median_error_deg"].values()))) for k in res if k.startswith("tracking_")}
    return {
        "saccade_settle_s_median": float(np.median([np.inf if s is None else s for s in settle])),
        "saccade_settle_s_max": sac["time_both_within_1deg_s_max"],
        "saccades_within_1deg_by_0.3s": sac["all_within_1deg_by_0.3s"],
        "vergence_gaze_line_distance_cm_max": res["vergence_1m"]["gaze_line_distance_cm_max"],
        **{f"{k}_median_error_deg": v for k, v in track.items()},
    }


def run(frame_every=(1, None), quick: bool = False, progress: bool = True, log=print) -> dict:
    """Measure the loop at each of ``frame_every`` (None: the loop's default, ``FRAME_EVERY``)."""
    from warp_vision.body import Body, BodyConfig
    from warp_vision.sim.loop import FRAME_EVERY, Foveator, VisuomotorLoop
    from warp_vision.sim.oculomotor import load_oculomotor
    from warp_vision.sim.provision import default_runs, manifest, plan, provide
    from warp_vision.sim.scenarios import SETTLE_S, experiments

    settings = [FRAME_EVERY if n is None else int(n) for n in frame_every]
    if not settings or any(n < 1 for n in settings):
        raise ValueError(f"frame_every: expected whole numbers of control periods >= 1, got {list(frame_every)}")
    runs = default_runs(quick)
    specs = plan(runs["left"], runs["right"], runs["oculomotor"], quick=quick)
    provide(specs, progress=progress, log=log)
    fov = {s: Foveator(spec.run, eye=s) for s, spec in zip(SIDES, specs[:2])}
    ocu = load_oculomotor(runs["oculomotor"])
    out = {"nets": manifest(specs), "settings": []}
    loops = []
    for n in settings:
        body = Body(BodyConfig())
        body.step(int(SETTLE_S / body.model.opt.timestep))
        loops.append(VisuomotorLoop(body, fov, ocu, frame_every=n))
        loops[-1].step()  # compiles what the first frame needs (kernels, eye rays) outside the measurement
    results = experiments(loops, progress=progress)
    for n, res in zip(settings, results):
        row = {"frame_every": n, "frames_per_s": res["timing"]["frames_per_s"],
               "sim_to_wall": res["timing"]["sim_to_wall"], "share": res["timing"]["share"],
               "wall_s": res["timing"]["wall_s"], "sim_s": res["timing"]["sim_s"], "accuracy": _accuracy(res),
               "experiments": res}
        log(f"frame every {n} period(s) ({row['frames_per_s']:.0f} Hz): simulated/wall {row['sim_to_wall']:.3f}; "
            + ", ".join(f"{k} {100 * v:.0f}%" for k, v in row["share"].items())
            + f"; saccade settle median {row['accuracy']['saccade_settle_s_median']:.3f} s, tracking 30 deg/s median "
            f"{row['accuracy'].get('tracking_30deg_s_median_error_deg', float('nan')):.2f} deg")
        out["settings"].append(row)
    base = out["settings"][0]
    out["versus_first"] = []
    for row in out["settings"][1:]:
        a, b = row["accuracy"], base["accuracy"]
        out["versus_first"].append({
            "frame_every": row["frame_every"],
            "speedup": row["sim_to_wall"] / base["sim_to_wall"],
            "saccade_settle_relative_change": a["saccade_settle_s_median"] / b["saccade_settle_s_median"] - 1,
            "tracking_30_relative_change": (a["tracking_30deg_s_median_error_deg"]
                                            / b["tracking_30deg_s_median_error_deg"] - 1),
            "tracking_15_relative_change": (a["tracking_15deg_s_median_error_deg"]
                                            / b["tracking_15deg_s_median_error_deg"] - 1),
        })
    return out
