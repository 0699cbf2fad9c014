"""What a ``python -m warp_vision.sim`` command runs on: the nets it needs, provided (trained where
missing, :mod:`warp_vision.sim.provision`), and the body and closed loop built from them. Used by the
commands of :mod:`warp_vision.sim.cli` and by ``intercept`` (:mod:`warp_vision.sim.intercept_trials`)."""

from __future__ import annotations

import os

from warp_vision.body import SIDES, Body, BodyConfig
from warp_vision.fileio import write_json
from warp_vision.sim.scenarios import SETTLE_S


def net_specs(args) -> list:
    """The nets a command's loop needs (:class:`warp_vision.sim.provision.NetSpec`, in
    :func:`warp_vision.sim.provision.plan`'s order, then for ``intercept`` the arm's and the limb vision
    nets), from its parsed arguments: the run directories given, or the default (or ``--quick``) ones."""
    from warp_vision.sim.provision import default_runs, plan

    runs = default_runs(args.quick)
    left = getattr(args, "left", None) or runs["left"]
    right = getattr(args, "right", None) or runs["right"]
    nets = getattr(args, "intraocular", "analytic") == "nets"
    specs = plan(left, right, args.oculomotor or runs["oculomotor"], quick=args.quick,
                 pupil=(getattr(args, "pupil", None) or runs["pupil"]) if nets else None,
                 lens=(getattr(args, "lens", None) or runs["lens"]) if nets else None)
    if args.command == "search" or getattr(args, "gaze_perception", "nets") == "search":
        from warp_vision.sim.provision import search_plan

        specs += search_plan(getattr(args, "verify", None) or runs["verify"], quick=args.quick)
    if args.command == "intercept":
        from warp_vision.sim.provision import strike_plan

        specs += strike_plan(args.side, args.arm or runs["arm"],
                             (args.limb or runs["limb"]) if args.perception == "vision" else None, quick=args.quick)
    return specs


def refuse_unused_given(args) -> None:
    """A run directory named for nets the command will not run is a ValueError, not an option left unread:
    ``--pupil`` or ``--lens`` with ``--intraocular analytic`` (intercept's default), ``--limb`` with an
    intercept whose ``--perception`` is not vision."""
    unused = []
    if getattr(args, "intraocular", "nets") == "analytic":
        unused += [f"--{flag} {getattr(args, flag)}: the {flag} nets run with --intraocular nets; this command's is "
                   "analytic"
                   for flag in ("pupil", "lens") if getattr(args, flag, None) is not None]
    if getattr(args, "limb", None) is not None and getattr(args, "perception", "vision") != "vision":
        unused.append(f"--limb {args.limb}: the limb vision nets run with --perception vision; "
                      f"this command's is {args.perception}")
    if unused:
        raise ValueError("; ".join(unused) + " (leave the flag out, or choose the mode that runs them)")


def refuse_missing_given(args, specs: list) -> None:
    """A run directory named on the command line that holds no run (neither ``best.pt`` nor a stopped run's
    ``latest.pt``) is a ValueError, raised before anything is trained: a mistyped path would otherwise cost
    a training run into it. Only the default directories are trained into when missing."""
    missing = []
    for spec in specs:
        flag = spec.eye if spec.kind == "foveation" else spec.kind  # --left / --right, else the kind's flag
        given = getattr(args, flag, None)
        if given is not None and not spec.ready() and not os.path.isfile(os.path.join(spec.run, "latest.pt")):
            missing.append(f"--{flag} {given}: no {spec.what} in {spec.run} (train it with python -m warp_vision.train "
                           f"{' '.join(spec.command())})")
    if missing:
        raise ValueError("; ".join(missing) + "; or leave the flag out for the default nets, trained first where "
                                              "missing")


def setup_loop(args):
    """Provide the nets (training the default ones where missing), build the body and the loop; once they have loaded,
    writes nets.json to --out. Returns (body, loop)."""
    from warp_vision.sim.loop import Foveator, VisuomotorLoop, load_lens, load_pupil
    from warp_vision.sim.oculomotor import load_oculomotor
    from warp_vision.sim.provision import manifest, provide

    specs = net_specs(args)
    refuse_missing_given(args, specs)
    provide(specs, progress=not args.no_progress)
    body = Body(BodyConfig(arms=not args.no_arms))
    body.step(int(SETTLE_S / body.model.opt.timestep))
    fov = {s: Foveator(spec.run, eye=s) for s, spec in zip(SIDES, specs[:2])}
    old = [spec.run for s, spec in zip(SIDES, specs[:2]) if fov[s].generator < 8]
    if old and args.ball == "ordinary":
        print(f"note: {', '.join(old)} learnt on generator v7 (a glowing ball in a dim room); with --ball ordinary "
              "it will not find the ball. Retrain it (python -m warp_vision.train --eye EYE --overwrite) or use --ball "
              "glowing.")
    ocu_root = os.path.dirname(specs[2].run)
    runs = {(spec.kind, spec.eye): spec.run for spec in specs}
    pupil = {s: load_pupil(runs["pupil", s], eye=s) for s in SIDES} if ("pupil", "left") in runs else None
    lens = {s: load_lens(runs["lens", s], eye=s) for s in SIDES} if ("lens", "left") in runs else None
    perception = getattr(args, "gaze_perception", "nets")
    search = None
    if perception == "search":
        from warp_vision.sim.search import ActiveSearch, Verifier

        search = ActiveSearch({s: Verifier(runs["verify", s], eye=s) for s in SIDES})
    loop = VisuomotorLoop(body, fov, load_oculomotor(ocu_root), seed=args.seed, frame_every=args.frame_every,
                          ball=args.ball, pupil_nets=pupil, lens_nets=lens, perception=perception, search=search)
    os.makedirs(args.out, exist_ok=True)  # recorded once every net has loaded: a failed start leaves the last record
    write_json(os.path.join(args.out, "nets.json"), manifest(specs))
    return body, loop
