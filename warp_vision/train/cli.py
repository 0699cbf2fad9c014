"""Command line of ``python -m warp_vision.train``, each line below after ``python -m warp_vision.train``:

    [--preset smoke|quick|default|paper] [--flag value ...]           train (the default task, foveation)
    --resume RUN_DIR [--epochs N]                                     continue a stopped run
    faces [--preset smoke|default|paper] [--flag value ...]           active face recognition
    faces --resume RUN_DIR [--epochs N]                               continue a stopped AFR run
    oculomotor --eye left|right [--preset smoke|quick|default]        an eye's oculomotor net
    arm --side left|right [--preset smoke|quick|default]              an arm's motor nets
    limb|pupil|lens|verify --eye left|right [--preset ...]            an eye's limb vision, pupil, lens or
                                                                      foveal verification net
    evaluate RUN_DIR [--split test|val|train]                         re-evaluate a run (any task)
    evaluate RUN_DIR --misses                                         where a foveation net's misses lie
    evaluate RUN_DIR --misses --signal                                ... and how much of each ball the ONV holds
    evaluate RUN_DIR [RUN_DIR ...] --conditions                       foveation nets on held-out conditions
    evaluate RUN_DIR RUN_DIR [...] --agreement                        do foveation nets miss the same balls?
    compare RUN_DIR [RUN_DIR ...] --out FIG.png                       loss curves together
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import fields
from pathlib import Path

from warp_vision.errors import ArgumentParser, guarded, long_options, not_a_command
from warp_vision.errors import add_debug_flag as _debug_flag
from warp_vision.train import config as C
from warp_vision.train import config_body as body
from warp_vision.train import config_intraocular as intraocular
from warp_vision.train import config_verify


def _run_flags(p: argparse.ArgumentParser, groups: dict) -> argparse.ArgumentParser:
    """The flags every training command has besides its config's, in its "the run" group (``groups``:
    :func:`config.add_arguments`'s)."""
    run = groups.get("the run", p)
    run.add_argument("--resume", metavar="RUN_DIR", default=None,
                     help="continue the stopped run in RUN_DIR exactly, with the settings of its config.json (other "
                          "settings are refused; one stopped before its first epoch ended starts "
                          "again); with --epochs N, under a new epoch cap (N = the epochs done ends it now: the best "
                          "checkpoint is evaluated, figures written; fewer is refused). A run that early stopping "
                          "ended trains further only under a higher cap, its patience counted afresh")
    run.add_argument("--overwrite", action="store_true", help="replace the run already in --out (default: refuse)")
    run.add_argument("--no-progress", action="store_true", help="no progress bars")
    run.add_argument("--workers", type=_workers, default="auto", metavar="N",
                     help="processes that synthesise a missing dataset (foveation and limb runs; the dataset is the "
                          "same for any N); default auto: one per CPU core, at most 8, for a dataset of 1,000 samples "
                          "or more (else 1; 1 on a GPU; under torchrun each rank renders its own shard)")
    _debug_flag(run)
    return p


def _workers(text: str):
    """--workers: a positive integer or "auto"."""
    if text == "auto":
        return text
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'auto', got {text!r}")
    return n


def _train_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="python -m warp_vision.train",
        description=(
            "Train a foveation net: synthesise (or reuse) a dataset of ONVs of a ball in a room (the default "
            "preset: generator v9's ordinary balls among distractors and decoys, and the retina CNN; --generator 7 "
            "--model linet: v7's glowing ball and the paper's liNet), train the net to predict the eye rotation (yaw, "
            "pitch) that foveates the ball, evaluate, and "
            "write config, checkpoints, metrics and figures to --out. "
            "Also: 'python -m warp_vision.train faces ...' (active face recognition), 'oculomotor --eye left|right' "
            "(an eye's oculomotor net), 'arm --side left|right' (an arm's motor nets), 'limb|pupil|lens|verify --eye "
            "left|right' (an eye's limb vision, pupil, lens or foveal verification net), 'evaluate RUN_DIR' and "
            "'compare RUN_DIR ... --out FIG'. Runs under torchrun unchanged."
        ),
    )
    p.siblings = lambda: _siblings("foveation")
    return _run_flags(p, C.add_arguments(p))


#: how the hint for a flag of another command names the foveation task, which has no word on the command line
FOVEATION = "the foveation task"


def _siblings(name: str) -> dict:
    """The parsers of train's commands other than ``name`` ("foveation", a task of TASKS, "evaluate" or
    "compare"), by name: a flag a command lacks is named as theirs (``train faces --samples 5``)."""
    makers = {"foveation": _train_parser, **{t: (lambda t=t: _task_parser(t)) for t in TASKS},
              "evaluate": _eval_parser, "compare": _compare_parser}
    return {FOVEATION if other == "foveation" else other: make() for other, make in makers.items() if other != name}


#: the commands that train a task besides the default (foveation):
#: name -> (module, config class, its presets, description)
TASKS = {
    "faces": ("faces", C.FaceTrainConfig, C.FACE_PRESETS,
              "Active face recognition (the paper's Section VI.B): build identities with anny, synthesise (or reuse) "
              "ONVs of each face across yaw and pitch poses, train the two-headed liNet (identity and pose), evaluate, "
              "and write config, checkpoints, metrics and figures to --out. Runs under torchrun unchanged."),
    "oculomotor": ("oculomotor", body.OculomotorTrainConfig, body.OCULOMOTOR_PRESETS,
                   "An eye's oculomotor net: solve (or reuse) the least-effort activations that hold gazes in a disc "
                   "on the MuJoCo body, train the net from (change of gaze, current activations) to the next "
                   "activations on transitions between them, check it on the body, and write config, checkpoints, "
                   "metrics and summary to --out (default runs/oculomotor/<eye>)."),
    "arm": ("arm", body.ArmTrainConfig, body.ARM_PRESETS,
            "An arm's motor nets (the paper's Fig. 8): solve (or reuse) the least-effort activations of its 63 muscles "
            "that hold postures with the hand 0.2-0.6 m in front of the shoulder on the MuJoCo body, train the posture "
            "net (joint angles and velocities to activations that hold and damp) and the voluntary net (hand "
            "displacement, current activations, joint angles and velocities to the next activations), check both "
            "on the body, and write config, checkpoints, metrics and summary to --out (default runs/arm/<side>)."),
    "limb": ("limb", body.LimbTrainConfig, body.LIMB_PRESETS,
             "An eye's limb vision net (the paper's nets 3-10): synthesise (or reuse) ONVs of the closed loop's world "
             "with the body's arms at random postures and the cannon's ball near a hand or on a shot's path, the eye "
             "tracking it; train the ranging net (default: the ball's distance from its apparent size, for balls near "
             "the line of sight; the loop adds the foveation net's direction and the hand's proprioception) or, with "
             "--model linet|fc|cnn, a net from the ONV to each arm's hand-to-ball discrepancy (eye frame, m); "
             "measure it on rooms and shots training never saw, and write config, checkpoints, metrics, summary and "
             "figures to --out (default runs/limb/<eye>)."),
    "pupil": ("pupil", intraocular.PupilTrainConfig, intraocular.PUPIL_PRESETS,
              "An eye's pupil net (the paper's SNNs for the iris): synthesise (or reuse) ONVs of everyday scenes seen "
              "through random pupils at light levels over five decades, train the net from (ONV, current pupil) to "
              "Watson & Yellott's pupil for the scene's adapting luminance, measure it on rooms training never saw, "
              "and write config, checkpoints, metrics, summary and figures to --out (default runs/pupil/<eye>)."),
    "lens": ("lens", intraocular.LensTrainConfig, intraocular.LENS_PRESETS,
             "An eye's lens net (the paper's SNNs for accommodation): synthesise (or reuse) central-field ONVs of "
             "textured cards at 0.2-5 m with the lens at random states near them, train the net from (ONV, current "
             "pupil) to the signed defocus (read from the colour channels' unequal blur), measure it on new "
             "textures, lamps and distances, and write config, checkpoints, metrics, summary and figures to --out "
             "(default runs/lens/<eye>)."),
    "verify": ("verify", config_verify.VerifyTrainConfig, config_verify.VERIFY_PRESETS,
               "An eye's foveal verification net (active search): synthesise (or reuse) central-field ONVs of "
               "generator-v9 scenes fixating the ball or a look-alike (a decoy's face, the muzzle end-on, a hand, a "
               "bright object, a lamp's patch, the ball's shadow, furniture), 0-2 deg off; train the net (default "
               "the CNN; --model linet: the paper's liNet) to say whether the ball is at the fovea and how far off; "
               "fit the threshold that rejects 1% of the balls; measure false accepts per look-alike class on rooms "
               "training never saw, and write config, checkpoints, metrics, summary and the ROC figure to --out "
               "(default runs/verify/<eye>)."),
}


def _task_parser(name: str) -> argparse.ArgumentParser:
    _, cls, presets, description = TASKS[name]
    p = ArgumentParser(prog=f"python -m warp_vision.train {name}", description=description)
    p.siblings = lambda: _siblings(name)
    return _run_flags(p, C.add_arguments(p, cls, presets))


def _eval_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="python -m warp_vision.train evaluate",
                       description="Re-evaluate a run's best (or last) checkpoint: for a foveation run the angular "
                                   "error (median, 90th percentile, degrees), for a faces run the identity accuracy "
                                   "and the pose error.")
    p.add_argument("run_dirs", nargs="+", metavar="RUN_DIR",
                   help="training run directories (with best.pt; latest.pt for --checkpoint latest)")
    p.add_argument("--split", choices=["test", "val", "train"], default="test", help="which split (default test)")
    p.add_argument("--conditions", action="store_true",
                   help="foveation runs: render (or reuse) one held-out set per test condition (v8 scenes in rooms "
                        "training never saw: glowing ball in a dim room, lit white ball, coloured matte ball, a lamp "
                        "or brighter object in view, the body's arm in view; v9's: a round decoy in view) and print "
                        "one table with every run side by side (median / 90th percentile, degrees, and the share more "
                        "than 5 degrees off); writes RUN_DIR/conditions.json and "
                        "RUN_DIR/figures/conditions.png")
    p.add_argument("--misses", action="store_true",
                   help="foveation runs: also print where the balls more than 5 degrees off lie (the share off per "
                        "eccentricity band, apparent-radius band and scene flag: occluded, glowing, distractor, arm, "
                        "decoy), drawn in RUN_DIR/figures/misses_<split>.png")
    p.add_argument("--signal", action="store_true",
                   help="with --misses, v8 and v9 runs: render the split again with and without its balls (about 0.1 s "
                        "an ONV on a 2-core CPU) and add the share off per band of photoreceptors that see the ball "
                        "and of its contrast with its surround, and what the estimates land on (the ball, a decoy by "
                        "kind, a bright object, the arm, the panel, a box or cylinder of the furniture, a wall, the "
                        "floor or the ceiling), beside what each class would get by chance (each scene probed along "
                        "another ball's direction)")
    p.add_argument("--agreement", action="store_true",
                   help="two or more foveation runs on one dataset: whether they miss the same balls of the split (per "
                        "pair: both more than 5 degrees off, against what independent nets would give; the share of "
                        "one's misses the other shares; both on the same wrong thing), and the share off if the best "
                        "net were taken for every ball")
    p.add_argument("--samples", type=int, default=None,
                   help=f"with --conditions: ONVs per held-out condition (default {C.CONDITION_SAMPLES})")
    p.add_argument("--views", type=int, default=None, metavar="N",
                   help="foveation CNN runs: read the net out by the consensus of N turned and mirrored views instead "
                        "of its own (default: its spec's, 8; 1: the plain image alone)")
    # = nn.trained.CHECKPOINTS (a test checks)
    p.add_argument("--checkpoint", choices=["best", "latest"], default="best",
                   help="the weights read (on the run's split or, with --conditions, the held-out sets): the best "
                        "validation epoch's (best.pt) or the last epoch's (latest.pt: what a run that memorises its "
                        "training set has learnt by its end; --conditions then writes conditions_latest.json) "
                        "(default best)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.siblings = lambda: _siblings("evaluate")
    return _debug_flag(p)


def _module(task: str):
    import importlib

    return importlib.import_module(f"warp_vision.train.{'foveation' if task == 'foveation' else TASKS[task][0]}")


def _compare_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(prog="python -m warp_vision.train compare",
                       description="Plot several foveation (or face) runs' training and validation MSE curves in one "
                                   "figure.")
    p.add_argument("runs", nargs="+", help="run directories (with metrics.jsonl)")
    p.add_argument("--out", required=True, help="figure path; its suffix picks the format (.png, .pdf, .svg, ...; "
                                                 "none: PNG)")
    p.add_argument("--title", default="training and validation MSE", help="the figure's title (default: %(default)r)")
    p.siblings = lambda: _siblings("compare")
    return _debug_flag(p)


def _compare(argv: list[str]) -> int:
    p = _compare_parser()
    a = p.parse_args(argv)

    def job():
        from warp_vision.fileio import atomic_write, require_output
        from warp_vision.nn.trained import not_a_run, read_run_config, saved_task
        from warp_vision.train.figures import plot_curves
        from warp_vision.train.rundir import a_run, read_metrics

        require_output(a.out, "--out", kind="file")
        fmt = figure_format(a.out)
        hists = {}
        names = [Path(r).name for r in a.runs]
        for i, r in enumerate(a.runs):
            m = Path(r) / "metrics.jsonl"
            if not m.exists():
                raise not_a_run(r, m.name)
            cfg = read_run_config(r) or {}
            task = saved_task(r, cfg)
            if task not in ("foveation", "faces"):
                raise ValueError(f"runs: {r} is {a_run(task)}; compare plots foveation and face runs' MSE curves")
            # the directory's name, its path where names repeat
            name = names[i] if names.count(names[i]) == 1 else str(r)
            p = cfg.get("photoreceptors")
            # (linet: before the choice)
            label = f"{name} ({cfg.get('model', 'linet')}{f', P={p:,}' if isinstance(p, int) else ''})"
            if label in hists:
                raise ValueError(f"runs: {r} is given twice")
            hists[label] = read_metrics(m, need=("epoch", "train_mse", "val_mse"))
        fig = plot_curves(hists, a.title)
        atomic_write(a.out, lambda f: fig.savefig(f, format=fmt, dpi=120, bbox_inches="tight"))
        print(f"wrote {a.out}")

    return _guarded(job, a.debug, p)


def figure_format(path) -> str:
    """The figure format a path's suffix names (png where it has none); a ValueError naming the formats
    matplotlib writes for any other suffix (it wrote a PNG under ``curves.pdf``)."""
    from matplotlib.backend_bases import FigureCanvasBase

    suffix = Path(path).suffix.lower().lstrip(".")
    if not suffix:
        return "png"
    formats = FigureCanvasBase.get_supported_filetypes()
    if suffix not in formats:
        raise ValueError(f"--out {path}: .{suffix} is not a figure format matplotlib writes; "
                         f"expected one of {', '.join('.' + f for f in sorted(formats))}, or no suffix (PNG)")
    return suffix


def _refuse_unwritable_runs(run_dirs, flag: str) -> None:
    """An OSError naming the first run directory (or its figures/) where nothing can be written: evaluate
    ``flag`` writes its results there (it rendered the held-out sets, evaluated, and then failed to write)."""
    from warp_vision.fileio import probe_writable

    for run in run_dirs:
        if not (Path(run) / "config.json").exists():
            continue  # (not a run: refused by name where it is read)
        for d in (Path(run), Path(run) / "figures"):
            try:
                probe_writable(d)
            except OSError as e:
                raise OSError(e.errno, f"evaluate {flag} writes its results into the run directory, and nothing can be "
                                       f"written there ({e.strerror}); evaluate a copy of the run", str(d)) from None


def _evaluate(argv: list[str]) -> int:
    from warp_vision.nn.trained import saved_task
    from warp_vision.train.rundir import a_run

    p = _eval_parser()
    a = p.parse_args(argv)
    if a.views is not None and a.agreement:
        p.error("--views: with --conditions or a run's own split, not with --agreement")
    if a.checkpoint != "best" and a.agreement:
        p.error("--checkpoint: with --conditions or a run's own split; --agreement reads the best checkpoint")
    if a.misses and a.conditions:
        p.error("--misses: of a run's own split (--split), not with --conditions")
    if a.signal and not a.misses:
        p.error("--signal: a part of --misses")
    if a.agreement and (a.misses or a.conditions or len(a.run_dirs) < 2):
        p.error("--agreement: of two or more runs' own split, not with --misses or --conditions")
    if a.samples is not None and not a.conditions:  # refused, not ignored: it sizes --conditions' sets only
        p.error("--samples: the ONVs of each held-out set of --conditions; a run's own split has its own")
    if a.split != "test" and a.conditions:
        p.error(f"--split {a.split}: of a run's own split; --conditions measures held-out sets of its own")

    def job():
        if a.conditions or a.misses:  # (their table and figure go into each run: refused now, not after the renders)
            _refuse_unwritable_runs(a.run_dirs, "--conditions" if a.conditions else "--misses")
        if a.conditions:
            from warp_vision.train.conditions import evaluate_conditions

            evaluate_conditions(a.run_dirs, samples=C.CONDITION_SAMPLES if a.samples is None else a.samples,
                                progress=not a.no_progress, views=a.views, checkpoint=a.checkpoint)
            return
        if a.agreement:
            from warp_vision.train.foveation import evaluate_agreement

            evaluate_agreement(a.run_dirs, a.split)
            return
        tasks = [saved_task(run_dir) for run_dir in a.run_dirs]
        for run_dir, task in zip(a.run_dirs, tasks):  # every run checked before the first is evaluated
            for flag, given, only in (("--misses", a.misses, "foveation runs"), ("--views", a.views is not None,
                                                                               "foveation CNN runs")):
                if given and task != "foveation":
                    raise ValueError(f"{flag}: {only} only; {run_dir} is {a_run(task)}")
        for run_dir, task in zip(a.run_dirs, tasks):
            kw = {"misses": True, "signal": a.signal} if a.misses else {}
            if task == "foveation":
                kw["progress"] = not a.no_progress
            if a.views is not None:
                kw["views"] = a.views
            _module(task).evaluate_run(run_dir, a.split, checkpoint=a.checkpoint, **kw)

    return _guarded(job, a.debug, p)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "compare":
        return _compare(argv[1:])
    if argv and argv[0] == "evaluate":
        return _evaluate(argv[1:])
    name, cls, a, make, p = parse_training(argv)
    argv = argv[1:] if argv and argv[0] in TASKS else argv
    run = _module(name).run
    if a.resume:
        def resume():
            _refuse_settings_on_resume(a, cls, argv)
            return run(resume=a.resume, progress=not a.no_progress, epochs=a.epochs, workers=a.workers)

        return _guarded(resume, a.debug, p)
    return _guarded(lambda: run(make(), progress=not a.no_progress, overwrite=a.overwrite, workers=a.workers),
                    a.debug, p)


def parse_training(argv: list[str]):
    """A training command line (``[TASK] --flag ...``, no ``compare`` or ``evaluate``) as ``(task, config
    class, parsed flags, make, the parser)``: ``make()`` builds its config, refusing what
    :func:`config.from_args` refuses. Exits as argparse does on unknown flags."""
    if argv and argv[0] in TASKS:
        name = argv[0]
        p = _task_parser(name)
        a = p.parse_args(argv[1:])
        _, cls, presets, _ = TASKS[name]
        return name, cls, a, lambda: C.from_args(a, cls, presets), p
    p = _train_parser()
    if argv and not argv[0].startswith("-"):  # a mistyped task or command: argparse called it an unknown argument
        p.error(f"{not_a_command(argv[0], [*TASKS, 'evaluate', 'compare'], 'a task or command')}, "
                f"or the foveation task's flags alone")
    a = p.parse_args(argv)
    return "foveation", C.TrainConfig, a, lambda: C.from_args(a), p


def _refuse_settings_on_resume(a: argparse.Namespace, cls, argv: list[str]) -> None:
    """A ValueError for settings given with ``--resume``: a resumed run continues as its config.json says,
    under a new epoch cap at most, so a setting given with it (``--resume RUN --lr 0.1``) is refused rather than
    left unread."""
    given = [f"--{f.name.replace('_', '-')}" for f in fields(cls)
             if f.name not in ("preset", "task", "epochs") and getattr(a, f.name, None) is not None]
    given += [flag for flag in ("--preset", "--overwrite") if any(x == flag or x.startswith(flag + "=") for x in argv)]
    if given:
        raise ValueError(f"--resume {a.resume} continues the run as its config.json says; {', '.join(given)} "
                         f"{'does' if len(given) == 1 else 'do'} not apply (--epochs does: a new epoch cap). To train "
                         f"with other settings, start a new run in another --out")


def _guarded(job, debug: bool, parser: argparse.ArgumentParser) -> int:
    """Run a job (:func:`warp_vision.errors.guarded`), its errors naming ``parser``'s options; a non-finite
    loss exits with code 3."""
    from warp_vision.train.harness import NonFiniteLoss

    return guarded(job, debug, {NonFiniteLoss: 3}, long_options(parser))
