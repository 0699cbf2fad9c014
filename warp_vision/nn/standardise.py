"""The targets' standardisation that every regression net carries: ``target_mean`` and ``target_std``
buffers (saved with the weights) and :meth:`StandardisedTargets.set_target_norm`."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class StandardisedTargets(nn.Module):
    """A net whose outputs are its targets standardised with the training set's mean and std."""

    def init_target_norm(self, outputs: int) -> None:
        """Register the ``outputs``-long buffers (mean 0, std 1 until :meth:`set_target_norm`)."""
        self.register_buffer("target_mean", torch.zeros(outputs))
        self.register_buffer("target_std", torch.ones(outputs))

    def set_target_norm(self, mean: Tensor, std: Tensor) -> None:
        """The targets' mean and std (the training set's): the net's outputs are standardised with them."""
        with torch.no_grad():
            self.target_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
            self.target_std.copy_(torch.as_tensor(std, dtype=torch.float32))
