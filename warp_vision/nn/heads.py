"""Task heads on a backbone: the foveation net (ONV -> eye yaw and pitch)."""

from __future__ import annotations

import torch
from torch import nn

from warp_vision.nn.linet import FullyConnected, LiNet


class FoveationNet(nn.Module):
    """A backbone (liNet or its fully-connected twin) and a linear output layer to (yaw, pitch).

    forward: onv [B, 3P] float32 -> [B, outputs] (standardised targets during training).
    """

    def __init__(self, backbone: nn.Module, outputs: int = 2):
        super().__init__()
        self.backbone = backbone
        self.head = nn.Linear(backbone.out_features, outputs)

    def forward(self, onv: torch.Tensor) -> torch.Tensor:
        return self.head(self.backbone(onv))


def foveation_net(model: str, in_positions, layers: int = 4, receptive_field: int = 20, reduction: int = 5,
                  seed: int = 0) -> FoveationNet:
    """``model`` "linet" or "fc" (same hidden sizes as the liNet), on inputs at ``in_positions`` [3P, 2]."""
    torch.manual_seed(seed)
    linet = LiNet(in_positions, layers=layers, receptive_field=receptive_field, reduction=reduction, seed=seed)
    if model == "linet":
        return FoveationNet(linet)
    if model == "fc":
        return FoveationNet(FullyConnected.like(linet))
    raise ValueError(f"model: expected 'linet' or 'fc', got {model!r}")
