"""``python -m warp_vision.train``: the foveation training job (see train/cli.py)."""
