"""``python -m warp_vision.data foveation --samples N --out DIR [--shard I/N]``: build a dataset alone.

N processes (or machines sharing a directory) given --shard 0/N .. N-1/N build disjoint chunks of one
dataset, which then reads as one. An interrupted run resumes where it stopped when run again.
"""

from __future__ import annotations

import argparse
import dataclasses

from warp_vision.data.foveation import FoveationDataConfig, synthesize


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m warp_vision.data", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="kind", required=True)
    f = sub.add_parser("foveation", help="ONVs of a white ball in a room, with the eye rotation that foveates it")
    defaults = FoveationDataConfig()
    for fld in dataclasses.fields(FoveationDataConfig):
        f.add_argument(f"--{fld.name.replace('_', '-')}", type=type(getattr(defaults, fld.name)), default=getattr(defaults, fld.name),
                       help=f"(default {getattr(defaults, fld.name)!r})")
    f.add_argument("--out", required=True, help="dataset directory")
    f.add_argument("--shard", default="0/1", help="I/N: build only shard I of N (default 0/1, everything)")
    f.add_argument("--batch", type=int, default=16, help="ONVs rendered per launch (default 16)")
    f.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    a = p.parse_args(argv)
    from warp_vision.data.store import parse_shard

    cfg = FoveationDataConfig(**{fld.name: getattr(a, fld.name) for fld in dataclasses.fields(FoveationDataConfig)})
    try:
        store = synthesize(a.out, cfg, shard=parse_shard(a.shard), batch=a.batch, device=a.device)
    except ValueError as e:
        print(f"error: {e}")
        return 2
    left = len(store.missing_chunks())
    print(f"{a.out}: shard {a.shard} done; dataset {'complete' if store.complete else 'still missing other shards'}"
          f"{'' if not left else f' ({left} chunks of this shard missing)'}")
    return 0
