"""``python -m warp_vision.data foveation|faces [--flag value ...] --out DIR [--shard I/N]``: build a dataset alone.

N processes (or machines sharing a directory) given --shard 0/N .. N-1/N build disjoint chunks of one
dataset, which then reads as one. An interrupted run resumes where it stopped when run again.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from warp_vision.data.foveation import FoveationDataConfig, synthesize
from warp_vision.errors import ArgumentParser, add_debug_flag, guarded


def _add_config_flags(parser: argparse.ArgumentParser, cls) -> None:
    defaults = cls()
    for fld in dataclasses.fields(cls):
        parser.add_argument(f"--{fld.name.replace('_', '-')}", type=type(getattr(defaults, fld.name)),
                            default=getattr(defaults, fld.name), help=f"(default {getattr(defaults, fld.name)!r})")
    parser.add_argument("--out", required=True, help="dataset directory")
    parser.add_argument("--shard", default="0/1", help="I/N: build only shard I of N (default 0/1, everything)")
    parser.add_argument("--batch", type=int, default=16, help="ONVs rendered per launch (default 16)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    add_debug_flag(parser)


def main(argv: list[str] | None = None) -> int:
    from warp_vision.data.faces import FaceDataConfig

    p = ArgumentParser(prog="python -m warp_vision.data", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="kind", required=True)
    fov = sub.add_parser("foveation", help="ONVs of a ball in a room (--generator 7: a glowing white ball; 8: ordinary "
                                           "balls among distractors; 9: and decoys), with the eye rotation that foveates it")
    _add_config_flags(fov, FoveationDataConfig)
    faces = sub.add_parser("faces", help="ONVs of anny-built faces across yaw and pitch poses, with identity and pose")
    _add_config_flags(faces, FaceDataConfig)
    faces.add_argument("--identities-cache", default=None, help="identity meshes' cache file (default runs/faces/...)")
    a = p.parse_args(argv)
    from warp_vision.data.store import parse_shard

    cls = FoveationDataConfig if a.kind == "foveation" else FaceDataConfig
    cfg = cls(**{fld.name: getattr(a, fld.name) for fld in dataclasses.fields(cls)})

    def job():
        from warp_vision.fileio import require_output
        from warp_vision.kernels.launch import require_device

        require_device(a.device)  # before the manifest is written
        require_output(a.out, "--out", writable=False)  # (a complete dataset may be read-only; synthesis probes)
        if a.kind == "foveation":
            return synthesize(a.out, cfg, shard=parse_shard(a.shard), batch=a.batch, device=a.device)
        from warp_vision.data import faces as FA

        return FA.synthesize(a.out, cfg, shard=parse_shard(a.shard), batch=a.batch, device=a.device,
                             identities_path=a.identities_cache)

    def report():
        try:
            store = job()
        except KeyboardInterrupt:
            print("interrupted: the chunks written are kept; the same command carries on from them", file=sys.stderr)
            raise
        left = len(store.missing_chunks())
        print(f"{a.out}: shard {a.shard} done; dataset {'complete' if store.complete else 'still missing other shards'}"
              f"{'' if not left else f' ({left} chunks of this shard missing)'}")

    return guarded(report, a.debug)
