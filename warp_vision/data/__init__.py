"""Dataset synthesis and the on-disk dataset store (``warp_vision.data.store``)."""
