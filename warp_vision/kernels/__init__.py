"""Warp kernels, grouped by stage along the data path (see docs/ARCHITECTURE.md).

- :mod:`~warp_vision.kernels.launch`: Warp initialisation, devices and the CPU thread-split launch
  shared by every kernel;
- :mod:`~warp_vision.kernels.render`: the ray tracer that renders ONVs (eye rays, BVHs, packet
  traversal, shading) and its numpy reference;
- :mod:`~warp_vision.kernels.linet`: the locally-connected liNet layer, its feature-major layout and
  its plain-torch reference.
"""
