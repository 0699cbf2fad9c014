"""Torch modules: liNet connectivity, the locally-connected layer, the liNet backbone, the FC baseline."""

from warp_vision.nn.connectivity import (
    LayerConnectivity,
    build_connectivity,
    onv_positions,
    receptive_field_radius,
)
from warp_vision.nn.linet import (
    FullyConnected,
    LiNet,
    LocallyConnected,
    fc_param_count,
    linet_param_count,
)

__all__ = [
    "FullyConnected",
    "LayerConnectivity",
    "LiNet",
    "LocallyConnected",
    "build_connectivity",
    "fc_param_count",
    "linet_param_count",
    "onv_positions",
    "receptive_field_radius",
]
