"""The liNet layer in Warp: the locally-connected irregular op and what it is built from.

- :mod:`~warp_vision.kernels.linet.op`: the public op :func:`locally_connected` (re-exported here),
  its connectivity plan and the host side of forward and backward;
- :mod:`~warp_vision.kernels.linet.kernels`: the Warp forward and backward kernels;
- :mod:`~warp_vision.kernels.linet.layout`: feature-major activations (64-lane vectors, transposes);
- :mod:`~warp_vision.kernels.linet.reference`: the same maths in plain torch, for tests and benchmarks.
"""

from warp_vision.kernels.linet.op import locally_connected

__all__ = ["locally_connected"]
