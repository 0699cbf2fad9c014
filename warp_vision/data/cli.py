"""``python -m warp_vision.data foveation|faces [--preset NAME] [--flag value ...] [--out DIR] [--shard I/N]``:
build a dataset alone.

``--preset`` names a training preset: the dataset built is the one ``python -m warp_vision.train [faces]
--preset NAME`` with the same flags trains on (its settings come from ``PRESET_DATA`` of
:mod:`warp_vision.data.foveation` and :mod:`warp_vision.data.faces`, which the training presets are built on),
and by default it goes where that run looks for it, ``runs/datasets/<kind>-<config hash>``, so the run finds it
without ``--data-dir``. N processes (or machines sharing a directory) given --shard 0/N .. N-1/N build
disjoint chunks of one dataset, which then reads as one. An interrupted run resumes where it stopped when
run again.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from warp_vision.data.foveation import FoveationDataConfig, generator_flag, synthesize
from warp_vision.errors import ArgumentParser, add_debug_flag, field_help, guarded, long_options, preset_defaults, told


def _add_config_flags(parser: argparse.ArgumentParser, cls, presets: dict, choices: dict) -> argparse._ArgumentGroup:
    """The dataset's flags (its config's fields, by the preset's values; ``choices``: the allowed values of those
    that have a fixed set, which the config's validate checks too) in one section of --help, and where and how
    it is built in another, which it returns."""
    data = parser.add_argument_group("the dataset", "the settings of the training run's data (--seed: its --data-seed)")
    data.add_argument("--preset", choices=list(presets), default="default",
                      help="the dataset of this training preset (default: default), under the flags given")
    defaults = cls()
    for fld in dataclasses.fields(cls):
        value = getattr(defaults, fld.name)
        data.add_argument(f"--{fld.name.replace('_', '-')}", default=None,
                          type=generator_flag if fld.name == "generator" else type(value),
                          help=f"{field_help(cls, fld.name)} ({preset_defaults(presets, fld.name, value)})",
                          **({"choices": choices[fld.name]} if fld.name in choices else {}))
    built = parser.add_argument_group("where and how it is built")
    built.add_argument("--out", default=None,
                       help="dataset directory (default: runs/datasets/<kind>-<config hash>, where the training run "
                            "of these settings looks for it)")
    built.add_argument("--shard", default="0/1", help="I/N: build only shard I of N (default 0/1, everything)")
    built.add_argument("--batch", type=int, default=16, help="ONVs rendered per launch (default 16)")
    built.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    built.add_argument("--no-progress", action="store_true", help="no progress bar (as train's and sim's)")
    add_debug_flag(parser)
    return built


def config_of(kind: str, args: argparse.Namespace):
    """The dataset config of a parsed command line: its preset's settings with the flags given over them."""
    from warp_vision.data import faces, foveation

    cls, presets = (FoveationDataConfig,
                    foveation.PRESET_DATA) if kind == "foveation" else (faces.FaceDataConfig, faces.PRESET_DATA)
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if getattr(args, f.name) is not None}
    return cls(**{**presets[args.preset], **given})


def parser() -> argparse.ArgumentParser:
    from warp_vision.data import faces, foveation

    p = ArgumentParser(prog="python -m warp_vision.data", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="kind", required=True)
    fov = sub.add_parser("foveation", help="ONVs of a ball in a room (--generator 7: a glowing white ball; 8: ordinary "
                                           "balls among distractors; 9: and decoys), with the eye rotation that "
                                           "foveates it")
    from warp_vision.data.foveation_scenes import CONDITIONS, ROOM_FAMILIES

    _add_config_flags(fov, FoveationDataConfig, foveation.PRESET_DATA,
                      {"eye": sorted(foveation.RETINA_SEEDS), "generator": list(foveation.GENERATORS),
                       "rooms": sorted(ROOM_FAMILIES), "condition": list(CONDITIONS)})
    fc = sub.add_parser("faces", help="ONVs of anny-built faces across yaw and pitch poses, with identity and pose")
    built = _add_config_flags(fc, faces.FaceDataConfig, faces.PRESET_DATA, {"eye": sorted(faces.RETINA_SEEDS)})
    built.add_argument("--identities-cache", default=None, help="identity meshes' cache file (default runs/faces/...)")
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    a = p.parse_args(argv)
    from warp_vision.data.store import parse_shard

    def job():
        from warp_vision.data.store import ChunkedStore
        from warp_vision.fileio import require_output
        from warp_vision.kernels.launch import require_device

        require_device(a.device)  # before the manifest is written
        cfg = config_of(a.kind, a)
        cfg.validate()
        out = a.out or str(Path("runs/datasets") / f"{a.kind}-{cfg.key()}")
        # a whole dataset may lie on a read-only disk; one still to be rendered needs a directory that can be
        # written, checked before the first mkdir (which would name a missing file, not the option)
        require_output(out, "--out", writable=not ChunkedStore.whole_at(out))
        cache = getattr(a, "identities_cache", None)
        if cache:  # (read where it holds the identities, written where it does not)
            require_output(cache, "--identities-cache", kind="file", writable=not Path(cache).is_file())
        if a.kind == "foveation":
            return out, synthesize(out, cfg, shard=parse_shard(a.shard), batch=a.batch, device=a.device,
                                   progress=not a.no_progress)
        from warp_vision.data import faces as FA

        return out, FA.synthesize(out, cfg, shard=parse_shard(a.shard), batch=a.batch, device=a.device,
                                  progress=not a.no_progress, identities_path=a.identities_cache)

    def report():
        try:
            out, store = job()
        except KeyboardInterrupt as e:
            print("interrupted: the chunks written are kept; the same command carries on from them", file=sys.stderr)
            raise told(e)  # noqa: B904 (told returns e: the caught exception, raised again)
        left = len(store.missing_chunks())
        print(f"{out}: shard {a.shard} done; dataset {'complete' if store.complete else 'still missing other shards'}"
              f"{'' if not left else f' ({left} chunks of this shard missing)'}")

    return guarded(report, a.debug, options=long_options(p))
