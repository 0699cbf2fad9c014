"""``python -m warp_vision.sim``: the virtual human's closed-loop demos and measurements.

  demo         the cannon scenario: a ball flies into the periphery; both eyes saccade, converge and track
               it, the head follows. Writes an MP4 (640x480 third-person view with the gaze lines beside
               both eyes' retina images, simulated time on every frame; --gif for a GIF too), the left
               retina at four moments (Fig. 7) and the gaze error over time.
  experiments  saccades to a ball appearing at 20 deg in eight directions, vergence at 1 m, tracking a
               ball moving at 15 and 30 deg/s both ways round, the loop's time shares. Writes experiments.json and
               figures/experiments.png (the runs over time against their goals).
  intraocular  light steps of +2 and -2 log units, and focus steps (a textured card from 2 m to 0.33 m and
               back, fixated): the pupils and lenses under their nets and, in the same run, under the
               analytic laws (their teachers); --cards N repeats the focus steps with the lens nets on N textures.
               Writes intraocular.json and figures/light_steps.png,
               focus_steps.png and focus_retina.png.
  oculomotor   both eyes' oculomotor nets only: trains the missing ones.
  search       active search: --trials N static trials in held-out rooms, the ball 10-35 deg from the starting
               gaze among look-alikes (the cannon's muzzle end-on, a decoy, a lamp panel, a raised hand); each
               under the active search (both eyes' candidates, foveal verification nets, inhibition of return)
               and under the foveation nets' single answer. Writes search.json, figures/search.png and
               scanpath figures (figures/scanpath_SEED.png).
  intercept    the paper's Fig. 8: the cannon shoots a held-out shot, the eyes and head track the ball, both eyes'
               limb vision nets see it and the left arm (--side) strikes it. One shot: intercept.gif (the
               third-person view with the gaze lines and the hand's path beside the left retina), the hand-ball
               distance over time (true and as the limb vision nets saw it) and shot.json. --shots N: N held-out
               shots several ways (limb vision and the eyes' fixation in the closed loop, the true ball
               state, also off by --perception-error-cm, passive arms): intercept_stats.json and figures
               of the deflected fraction by speed and by target, and of the closest approaches.

Demo, experiments and intraocular work from a fresh clone: each net the loop needs (both eyes' foveation
nets, the train command's default preset's retina CNNs; oculomotor nets; unless --intraocular analytic,
pupil and lens nets) that is missing is trained first, after a plan with time estimates, and cached
(``runs/foveation_left``, ``runs/foveation_right``, ``runs/oculomotor/<eye>``, ``runs/pupil/<eye>``,
``runs/lens/<eye>``;
intercept also the arm's motor nets, ``runs/arm/<side>``, and both eyes' limb vision nets,
``runs/limb/<eye>``; with --quick, smaller nets in ``runs/quick/``). Each output
directory gets ``nets.json``: the nets used, with their training configs and checksums.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from warp_vision.body import SIDES, Body, BodyConfig
from warp_vision.errors import ArgumentParser, add_debug_flag, guarded, long_options
from warp_vision.fileio import require_output, write_json
from warp_vision.limits import COUNT, PIXELS, SEED, VIDEO_FPS, Range, integer, number, video_bytes
from warp_vision.provenance import software
from warp_vision.resources import require_memory
from warp_vision.sim.build import net_specs, refuse_missing_given, refuse_unused_given, setup_loop
from warp_vision.sim.demo import demo, demo_lines
from warp_vision.sim.intercept_trials import intercept, pick_shots
from warp_vision.sim.scenarios import SETTLE_S, experiments, goal_lines, plot_experiments


def _secs(t) -> str:
    """A measured time for the command's lines: "0.34 s", or "never" (None or infinite)."""
    return "never" if t is None or not np.isfinite(t) else f"{t:.2f} s"


def intraocular(args) -> dict:
    """Light steps of +2 and -2 log units and focus steps (a textured card from 2 m to 0.33 m and back),
    with the pupil and lens nets and, in the same run, with their teachers (the analytic laws): the
    measures of :func:`warp_vision.sim.scenarios.light_steps` and :func:`~warp_vision.sim.scenarios.focus_steps`,
    and figures of the responses over time and of the left retina blurred, then sharp."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warp_vision.sim.loop import VisuomotorLoop
    from warp_vision.sim.scenarios import (
        FOCUS_CARD_SEED,
        FOCUS_PHASES,
        LIGHT_PHASES,
        focus_steps,
        focus_summary,
        light_steps,
    )

    args.intraocular = "nets"
    _body, nets_loop = setup_loop(args)
    body = Body(BodyConfig(arms=not args.no_arms))
    body.step(int(SETTLE_S / body.model.opt.timestep))
    analytic_loop = VisuomotorLoop(body, nets_loop.fov, nets_loop.ocu, seed=args.seed, frame_every=args.frame_every,
                                   ball=args.ball)
    loops = {"nets": nets_loop, "analytic": analytic_loop}
    light = {m: light_steps(lp, progress=not args.no_progress) for m, lp in loops.items()}
    focus = {m: focus_steps(lp, progress=not args.no_progress) for m, lp in loops.items()}
    # the nets on more cards (the vergence law does not look at the card): how often the near and far steps focus
    more = [{"card_seed": c,
             "steps": focus_steps(nets_loop, progress=not args.no_progress, snapshots=False, card_seed=c)["steps"]}
            for c in range(FOCUS_CARD_SEED + 1, FOCUS_CARD_SEED + args.cards)]
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
    out["nets"]["more_cards"] = more
    for mode in loops:
        cards = [focus[mode]["steps"]] + ([m["steps"] for m in more] if mode == "nets" else [])
        out[mode]["focus_summary"] = focus_summary(cards)
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
    fig.suptitle("left retina, central 3 deg, lens nets in the loop: after each step (blurred) and at its end (sharp)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _net_flags(g, name: str) -> None:
    """The nets the loop runs, and where it finds them (``--help``'s "the nets")."""
    g.add_argument("--quick", action="store_true",
                   help="smaller nets (runs/quick/..., trained in a few minutes when missing) for a first look")
    if name != "oculomotor":
        g.add_argument("--left", default=None, help="the left eye's foveation run (default runs/foveation_left, or "
                                                    "runs/quick/foveation_left, trained there if missing; a directory "
                                                    "given must hold a run)")
        g.add_argument("--right", default=None, help="the right eye's foveation run (likewise)")
    g.add_argument("--oculomotor", default=None,
                   help="the oculomotor runs' directory: <dir>/left, <dir>/right (default runs/oculomotor, or "
                        "runs/quick/oculomotor with --quick, trained there if missing; a directory given must "
                        "hold the runs)")
    if name == "oculomotor":
        return
    if name != "intraocular":  # that command runs both, nets and teachers
        from warp_vision.sim.loop import INTRAOCULAR

        default = "analytic" if name in ("intercept", "search") else "nets"
        g.add_argument("--intraocular", choices=INTRAOCULAR, default=default,
                       help=f"nets{' (default)' if default == 'nets' else ''}: each eye's pupil and lens nets command "
                            "its iris and lens from the ONV (trained into runs/pupil/<eye> and runs/lens/<eye> if "
                            f"missing); analytic{' (default)' if default == 'analytic' else ''}: their teachers, "
                            "Watson & Yellott's pupil for the adapting luminance and accommodation to where the gaze "
                            "lines converge")
    g.add_argument("--pupil", default=None, help="the pupil runs' directory: <dir>/left, <dir>/right (default "
                                                 "runs/pupil, or runs/quick/pupil with --quick)")
    g.add_argument("--lens", default=None, help="the lens runs' directory (likewise: runs/lens, runs/quick/lens)")
    if name in ("demo", "experiments"):
        from warp_vision.sim.loop import PERCEPTION

        g.add_argument("--gaze-perception", choices=PERCEPTION, default="nets",
                       help="where the gaze controller learns the ball's direction: nets (default), each eye's "
                            "foveation net's single answer from its ONV; search: active search over both eyes' "
                            "candidates with foveal verification nets (--verify); oracle: the ball's true direction in "
                            "each eye frame (the eyes still render), which separates perception's errors from the "
                            "controller's and oculomotor nets'")
    if name in ("demo", "experiments", "search"):
        g.add_argument("--verify", default=None,
                       help="the foveal verification runs' directory: <dir>/left, <dir>/right (default runs/verify, or "
                            "runs/quick/verify with --quick, trained there if missing), read by the active search")
    if name == "intercept":
        g.add_argument("--perception", choices=("vision", "fixation", "oracle"), default="vision",
                       help="how the arm knows the ball: vision (default), both eyes' limb vision nets (trained into "
                            "runs/limb/<eye> if missing; with --shots the loop then also runs with fixation); "
                            "fixation: where the two eyes' foveation nets see the ball (the gaze lines' crossing; no "
                            "limb nets); oracle: the simulation's true ball state (no limb nets; with --shots the "
                            "closed-loop mode then runs on it too, as 'loop_oracle')")
        g.add_argument("--arm", default=None, help="the arm runs' directory: <dir>/<side> (default runs/arm, or "
                                                   "runs/quick/arm with --quick, trained there if missing)")
        g.add_argument("--limb", default=None, help="the limb vision runs' directory: <dir>/left, <dir>/right "
                                                    "(default runs/limb, or runs/quick/limb with --quick)")


def _scene_flags(g, name: str) -> None:
    """The body, the room, the ball and the loop's pace (``--help``'s "the scene")."""
    from warp_vision.sim.intercept import INTERCEPT_FRAME_EVERY
    from warp_vision.sim.loop import BALLS, FRAME_EVERY

    if name == "search":  # a raised hand is one of the look-alikes
        g.set_defaults(no_arms=False)
        g.add_argument("--trials", type=integer(COUNT), default=200,
                       help="the number of trials (default 200), each run under the active search and under the "
                            "foveation nets' single answer")
        g.add_argument("--seed", type=integer(SEED), default=0,
                       help="the first trial: seed 1,000,000 + --seed of the held-out split, or --seed of the training "
                            "split (default 0)")
        g.add_argument("--split", choices=("heldout", "train"), default="heldout",
                       help="held-out trials (default: rooms, balls and look-alikes never used to tune the search) or "
                            "training ones")
        g.add_argument("--scanpaths", type=integer(Range(0, 1000, "figures")), default=4,
                       help="scanpath figures of the first N trials (default 4)")
        g.add_argument("--no-baseline", action="store_true", help="skip the single-answer runs of the same trials")
        g.add_argument("--cannon", type=integer(Range(0, 10_000, "shots")), default=50,
                       help="also N cannon shots of the split (seeds as sim intercept's, default 50; 0: none) in the "
                            "trials' rooms, arms passive: the share of shots with both eyes within 2 deg of the ball "
                            "for 90%% of the flight after its first 0.15 s, under each perception")
    elif name == "intercept":  # the arms strike
        g.set_defaults(no_arms=False)
        g.add_argument("--seed", type=integer(SEED), default=0,
                       help="the room's seed, and the first held-out shot: seed 1,000,000 + --seed (default 0)")
    else:
        g.add_argument("--no-arms", action="store_true", help="a bare torso instead of myo-sim's arms (faster)")
        g.add_argument("--seed", type=integer(SEED), default=0, help="the room's seed (default 0)")
    if name == "search":
        g.set_defaults(ball="ordinary", frame_every=FRAME_EVERY)
        return
    g.add_argument("--ball", choices=BALLS, default="ordinary",
                   help="ordinary (default): a grey-white ball lit by the room's lamps, in a room at its everyday "
                        "albedos (generators v8 and v9's kind of scene, what the default foveation nets learn); "
                        "glowing: a white ball that glows, in the room dimmed (generator v7's scene: use it with v7 "
                        "nets, python -m warp_vision.train --generator 7 --model linet ...)"
                        + ("; the limb vision nets must have learnt the same ball (train limb --ball)"
                           if name == "intercept" else ""))
    every = INTERCEPT_FRAME_EVERY if name == "intercept" else FRAME_EVERY
    g.add_argument("--frame-every", type=integer(PERIODS), default=every,
                   help=f"the eyes render (and the foveation nets run) every N control periods of 10 ms "
                        f"(default {every}: {100 // every} frames a second"
                        + ("; a ball at 12 m/s moves 0.24 m between two" if name == "intercept" else "")
                        + "; 1 renders every period)")
    if name == "intraocular":
        g.add_argument("--cards", type=integer(CARDS), default=1,
                       help="the focus steps with the lens nets on N cards of different textures (default 1; the "
                            "vergence law, blind to the texture, runs on the first): how often each step comes into "
                            "focus within 1.2 s")
    if name == "demo":
        g.add_argument("--duration", type=number(DURATION), default=0.8, help="simulated seconds (default 0.8)")
        g.add_argument("--flight", type=number(FLIGHT), default=0.9,
                       help="s of flight to the point --stop m before the face (default 0.9)")
        g.add_argument("--stop", type=number(STOP), default=1.0,
                       help="m from the head where the ball's flight is aimed (default 1)")
    if name == "intercept":
        g.add_argument("--side", choices=SIDES, default="left",
                       help="the striking arm: left (default) or right (the other hangs)")
        g.add_argument("--shots", type=integer(COUNT), default=None,
                       help="N held-out shots (seeds 1,000,000 + --seed ...), each run several ways: the closed loop "
                            "with the chosen --perception (with vision also with the eyes' fixation), the true ball "
                            "state (no rendering; also off by each --perception-error-cm), passive arms; writes "
                            "intercept_stats.json and figures. Default: one shot with its video")
        g.add_argument("--shot-seed", type=integer(SEED), default=None,
                       help="one shot: the shot of this seed (training seeds 0-999,999, held-out 1,000,000-1,999,999; "
                            "default the first held-out one, 1,000,000 + --seed)")
        g.add_argument("--perception-error-cm", type=float, nargs="*", default=[],
                       help="with --shots, also run the shots with the true ball state off by each of these errors "
                            "(cm; a fixed offset per shot in a random direction, no rendering): how accurate the limb "
                            "vision nets must be for the interception")


def _output_flags(g, name: str) -> None:
    """What is written where, and shown (``--help``'s "the output")."""
    g.add_argument("--no-progress", action="store_true", help="no progress bars")
    if name == "oculomotor":  # (it writes the nets' runs alone)
        return
    g.add_argument("--out", default=None,
                   help=f"output directory (default runs/sim_{name}, or runs/quick/sim_{name} with --quick)")
    if name not in ("demo", "intercept"):
        return
    retina = "the left retina beside it is" if name == "intercept" else "the retina images beside it are"
    g.add_argument("--width", type=integer(PIXELS), default=640, help="third-person view width (pixels; default 640)")
    g.add_argument("--height", type=integer(PIXELS), default=480,
                   help=f"third-person view height (pixels; default 480); {retina} half as high")
    if name == "demo":
        g.add_argument("--video-every", type=integer(PERIODS), default=1,
                       help="a video frame every N control periods (10 ms; default 1)")
    g.add_argument("--slow-motion", type=number(SLOW_MOTION), default=4.0,
                   help="the video plays this many times slower than simulated time (default 4)")
    if name == "intercept":
        g.add_argument("--video-format", choices=("gif", "mp4"), default="gif",
                       help="intercept.gif (default) or intercept.mp4 (H.264)")
    else:
        g.add_argument("--gif", action="store_true", help="also write demo.gif (same frames)")
        g.add_argument("--viewer", action="store_true",
                       help="open MuJoCo's passive viewer on the running loop (skipped, with a note, without a "
                            "display)")


def parser() -> argparse.ArgumentParser:
    """The simulation's command line: a subcommand each, its --help in sections (the nets, the scene, the output)."""
    ap = ArgumentParser(prog="python -m warp_vision.sim", description=__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        p = sub.add_parser(name)
        _net_flags(p.add_argument_group("the nets"), name)
        if name != "oculomotor":
            _scene_flags(p.add_argument_group("the scene"), name)
        _output_flags(p.add_argument_group("the output"), name)
        add_debug_flag(p)
    return ap


def main(argv=None) -> int:
    p = parser()
    args = p.parse_args(argv)
    return guarded(lambda: _run(args), args.debug, options=long_options(p))


def _run(args) -> None:
    """Refuse bad settings (before any net is trained), then run the command."""
    if getattr(args, "out", "") is None:
        args.out = os.path.join("runs", "quick", f"sim_{args.command}") if args.quick else f"runs/sim_{args.command}"
    _refuse_bad_settings(args)
    COMMANDS[args.command](args)


#: The ranges of the simulation's own settings (beside :mod:`warp_vision.limits`' shared ones): a period count
#: (frames, video frames), the focus steps' cards, demo's simulated seconds (each control period keeps the left
#: eye's ONV for the figure), its flight time and aim, and the video's pace.
PERIODS = Range(1, 1000, "control periods")
CARDS = Range(1, 100, "cards")
DURATION = Range(0.01, 60.0, "simulated seconds")
FLIGHT = Range(0.05, 10.0, "s")
STOP = Range(0.05, 10.0, "m")
SLOW_MOTION = Range(0.001, 1000.0)
#: the simulated seconds of one intercept shot's video, at the most (its flight and the strike after)
SHOT_SECONDS = 3.0


def _refuse_bad_settings(args) -> None:
    """A ValueError naming the first flag out of range, or given where the command does not use it, and a video
    whose frame rate no player shows or whose frames would not fit in memory; all before any net is trained."""
    if hasattr(args, "slow_motion"):
        from warp_vision.sim.loop import CONTROL_DT

        every = getattr(args, "video_every", 1)
        fps = 1.0 / (every * CONTROL_DT * args.slow_motion)
        if not VIDEO_FPS.lo <= fps <= VIDEO_FPS.hi:
            raise ValueError(f"--slow-motion: {args.slow_motion:g} with a frame every {every} period(s) makes a video "
                             f"of {fps:.3g} frames a second; expected {VIDEO_FPS.words()}")
        seconds = getattr(args, "duration", SHOT_SECONDS)
        gif = getattr(args, "gif", False) or getattr(args, "video_format", "mp4") == "gif"
        frames = int(seconds / (CONTROL_DT * every)) + 1
        require_memory(video_bytes(args.width, args.height, frames, kept=gif),
                       f"the video ({frames} frames of a {args.width} x {args.height} "
                       f"view{', kept for the GIF' if gif else ''})",
                       "--width, --height" + (", --duration or --video-every" if hasattr(args, "duration") else ""))
    if getattr(args, "out", None) is not None:
        require_output(args.out, "--out")
    refuse_unused_given(args)


def _oculomotor(args) -> None:
    """``sim oculomotor``: train (or find) both eyes' oculomotor nets; one line each."""
    from warp_vision.sim.provision import provide

    specs = net_specs(args)[2:]
    refuse_missing_given(args, specs)
    provide(specs, progress=not args.no_progress)
    for spec in specs:  # (it printed both summaries whole, some 60 lines of JSON)
        print(oculomotor_line(spec.eye, spec.run, json.loads(Path(spec.run, "summary.json").read_text())))


def _intercept(args) -> None:
    """``sim intercept``, its own settings refused before any net is trained."""
    pick_shots(args)
    bad = [e for e in args.perception_error_cm if not (np.isfinite(e) and 0 <= e <= 500)]
    if bad or (args.perception_error_cm and args.shots is None):
        raise ValueError("--perception-error-cm: expected distances of 0-500 cm with --shots, got "
                         f"{args.perception_error_cm}")
    if args.height < 8:
        raise ValueError(f"--height: expected >= 8, got {args.height}")
    intercept(args)


def _demo(args) -> None:
    """``sim demo``: the video and figures; the gaze error in a line (it printed its JSON, 50-60 lines)."""
    result = demo(args)
    write_json(os.path.join(args.out, "demo.json"), {**result, "software": software()})
    print("\n".join(demo_lines(result, args.out)))


def _intraocular(args) -> None:
    """``sim intraocular``: each light and focus step of the nets and of the analytic controllers, a line each."""
    result = intraocular(args)
    for mode in ("nets", "analytic"):
        for st in result[mode]["light_steps"]:
            print(f"{mode:8s} {st['eye']:5s} eye, {st['log_units']:+.0f} log units at {st['at_s']:.1f} s "
                  f"({st['direction']}): {st['from_mm']:.2f} -> {st['end_mm']:.2f} mm (steady state "
                  f"{st['steady_state_mm']:.2f}, off by {100 * st['end_relative_error']:.1f}%), latency "
                  f"{_secs(st['latency_s'])}, 10-90% {_secs(st['rise_10_90_s'])}, settled within 5% after "
                  f"{_secs(st['settle_s'])}")
        for st in result[mode]["focus_steps"]:
            print(f"{mode:8s} {st['eye']:5s} eye, card {st['from_m']:.2f} -> {st['to_m']:.2f} m at {st['at_s']:.1f} s: "
                  f"{st['from_D']:.2f} -> {st['to_D']:.2f} D, latency {_secs(st['latency_s'])}, in focus (0.25 D) "
                  f"after {_secs(st['in_focus_s'])}, defocus at the end {st['end_defocus_D']:+.3f} D")
        for direction, f in result[mode]["focus_summary"].items():
            print(f"{mode:8s} {direction} steps ({f['steps']} eye-steps): in focus within {f['goal_s']} s: "
                  f"{f['in_focus_within_goal']}/{f['steps']}, median time to focus {_secs(f['median_in_focus_s'])}, "
                  f"median |defocus| at the end {f['median_abs_end_defocus_D']:.3f} D")
    write_json(os.path.join(args.out, "intraocular.json"), {**result, "software": software()})
    print(f"wrote {os.path.join(args.out, 'intraocular.json')} and figures in {os.path.join(args.out, 'figures')}")


def _experiments(args) -> None:
    """``sim experiments``: saccades, vergence and tracking on the closed loop; each goal in a line, a figure."""
    _body, loop = setup_loop(args)
    result, traces = experiments(loop, progress=not args.no_progress, return_traces=True)
    os.makedirs(os.path.join(args.out, "figures"), exist_ok=True)
    figure = plot_experiments(traces, os.path.join(args.out, "figures", "experiments.png"),
                              title=f"the {loop.ball} ball, gaze perception: {loop.perception}; "
                                    f"foveation nets {loop.fov['left'].run_dir} and {loop.fov['right'].run_dir}")
    write_json(os.path.join(args.out, "experiments.json"), {**result, "software": software()})
    print("\n".join(goal_lines(result)))
    print(f"wrote {os.path.join(args.out, 'experiments.json')} and {figure}")


def _search(args) -> None:
    """``sim search``: the trials under the active search and the single answer; a line each, search.json, figures."""
    from warp_vision.sim.search_report import report_lines, search_command

    report = search_command(args)
    print("\n".join(report_lines(report)))
    print(f"wrote {os.path.join(args.out, 'search.json')} and figures in {os.path.join(args.out, 'figures')}")


#: Each command and its work, in the order --help lists them.
COMMANDS = {"demo": _demo, "experiments": _experiments, "intraocular": _intraocular, "oculomotor": _oculomotor,
            "intercept": _intercept, "search": _search}


def oculomotor_line(eye: str, run: str, summary: dict) -> str:
    """What ``sim oculomotor`` prints of an eye's net: its check on the body (held-out gazes), and where the
    rest lies."""
    s = summary
    return (f"{eye} eye, {run}: on the body, {s['transitions']} held-out saccades land "
            f"{s['gaze_error_deg_median']:.2f} deg from their gazes (median; p90 {s['gaze_error_deg_p90']:.2f}), "
            f"pursuits of 30 of its steps end {s['pursuit_chain_error_deg_median']:.2f} deg off (p90 "
            f"{s['pursuit_chain_error_deg_p90']:.2f}); the rest in {os.path.join(run, 'summary.json')}")
