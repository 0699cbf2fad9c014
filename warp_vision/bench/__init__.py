"""Kernel microbenchmarks: ``python -m warp_vision.bench --help``."""
