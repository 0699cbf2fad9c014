"""liNet torch modules: the locally-connected irregular layer, the liNet backbone and the FC baseline.

A liNet (paper, IV.A) is H locally-connected ReLU layers: unit n of layer h reads the R_h units of
layer h - 1 listed in row n of its connectivity matrix C_h, with its own weights and bias (no sharing):

    y_h[b, n] = ReLU(bias_h[n] + sum_r W_h[n, r] * y_{h-1}[b, C_h[n, r]])

The layer runs on the Warp kernels of :mod:`warp_vision.kernels.linet`; the connectivity comes from
:func:`warp_vision.nn.connectivity.build_connectivity`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from warp_vision.kernels.linet import locally_connected
from warp_vision.nn.connectivity import LayerConnectivity, _receptive_fields, build_connectivity

__all__ = ["FullyConnected", "LiNet", "LocallyConnected", "fc_param_count", "linet_param_count"]

_FLOATS = (torch.float32, torch.float64)


def _check_size(name: str, value: object, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, got {value!r}")
    return int(value)


class LocallyConnected(nn.Module):
    """One locally-connected irregular layer: ``y[b, n] = bias[n] + sum_r weight[n, r] * x[b, index[n, r]]``.

    Buffers and parameters:
        index:  [N, R] int32 (the kernels' index type: half the memory of int64, and the op's plan
                keeps its private copy in the same dtype), values in [0, in_features); a buffer, so it
                is saved in ``state_dict`` and moves with ``.to(device)``.
        weight: [N, R] one weight per connection; He-initialised, Normal(0, sqrt(2 / R)).
        bias:   [N] zeros at initialisation.
    """

    def __init__(
        self,
        index: Tensor | np.ndarray,
        in_features: int,
        relu: bool = False,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        """
        Args:
            index:       [N, R] integer connectivity, values in [0, in_features).
            in_features: N_in, the width of the input x [B, N_in].
            relu:        apply a (fused) ReLU to the output.
            dtype:       torch.float32 or torch.float64, the dtype of weight and bias.

        Raises:
            ValueError: on a bad shape, dtype or index range, naming the argument.
        """
        super().__init__()
        in_features = _check_size("in_features", in_features)
        if dtype not in _FLOATS:
            raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
        idx = torch.as_tensor(np.asarray(index) if not isinstance(index, Tensor) else index)
        if idx.dtype.is_floating_point or idx.dtype.is_complex or idx.dtype == torch.bool:
            raise ValueError(f"index: expected an integer dtype, got {idx.dtype}")
        if idx.dim() != 2 or idx.shape[0] < 1 or idx.shape[1] < 1:
            raise ValueError(f"index: expected shape [N, R] with N, R >= 1, got shape {tuple(idx.shape)}")
        lo, hi = int(idx.min()), int(idx.max())
        if lo < 0 or hi >= in_features:
            raise ValueError(
                f"index: expected values in [0, {in_features}) (in_features={in_features}), got values in [{lo}, {hi}]"
            )
        self.in_features = in_features
        self.relu = bool(relu)
        if in_features >= 2**31:
            raise ValueError(f"in_features: expected fewer than 2^31 inputs (int32 indices), got {in_features}")
        self.register_buffer("index", idx.detach().to(torch.int32, copy=True).contiguous())
        n, r = idx.shape
        self.weight = nn.Parameter(torch.empty(n, r, dtype=dtype, device=idx.device))
        self.bias = nn.Parameter(torch.empty(n, dtype=dtype, device=idx.device))
        self.folds_input = False
        self.reset_parameters()

    def fold_input_standardisation(self) -> None:
        """Make the layer read its input unstandardised: it computes what it would from
        ``(x - input_mean) / input_std`` (two 0-d buffers, 0 and 1 until set) by folding them into its
        weight and bias, ``w / std`` and ``b - (mean / std) sum_r w``, so a half-precision batch goes to
        the kernels as it is, with no standardised float32 copy."""
        if not self.folds_input:
            self.register_buffer("input_mean", torch.zeros((), dtype=self.weight.dtype, device=self.weight.device))
            self.register_buffer("input_std", torch.ones((), dtype=self.weight.dtype, device=self.weight.device))
            self.folds_input = True

    @property
    def out_features(self) -> int:
        """N, the number of units."""
        return int(self.index.shape[0])

    @property
    def receptive_field(self) -> int:
        """R, the inputs per unit."""
        return int(self.index.shape[1])

    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """He initialisation for ReLU nets (fan_in = R): weight ~ Normal(0, sqrt(2 / R)), bias = 0."""
        with torch.no_grad():
            self.weight.normal_(0.0, math.sqrt(2.0 / self.receptive_field), generator=generator)
            self.bias.zero_()

    def forward(self, x: Tensor) -> Tensor:
        """x [B, in_features] (the parameters' dtype, or float16/bfloat16 with float32 parameters) -> y
        [B, out_features] in the parameters' dtype, on their device."""
        if not isinstance(x, Tensor):  # a numpy batch is told how to convert, not given a shape error
            hint = " (torch.from_numpy(x))" if isinstance(x, np.ndarray) else ""
            raise ValueError(f"x: expected a torch tensor [B, {self.in_features}], got a {type(x).__name__}{hint}")
        if x.dim() != 2 or x.shape[1] != self.in_features:
            raise ValueError(f"x: expected shape [B, {self.in_features}], got {tuple(x.shape)}")
        w, b = self.weight, self.bias
        if self.folds_input:
            w = self.weight / self.input_std
            b = self.bias - (self.input_mean / self.input_std) * self.weight.sum(1)
        return locally_connected(x, w, b, self.index, relu=self.relu)

    def extra_repr(self) -> str:
        return (
            f"in_features={self.in_features}, out_features={self.out_features}, "
            f"receptive_field={self.receptive_field}, relu={self.relu}"
        )


class LiNet(nn.Module):
    """The liNet backbone: H locally-connected ReLU layers over an irregular, foveated input.

    Attributes:
        in_features:     N_0, the input width (3P for an ONV).
        out_features:    N_H.
        layer_sizes:     [N_0, N_1, ..., N_H], N_h = floor(N_{h-1} / f).
        receptive_fields: [R_1, ..., R_H].
        layers:          ``nn.ModuleList`` of H :class:`LocallyConnected` (relu=True); layer h - 1 of
                         the list holds C_h as its ``index`` buffer.

    Buffers ``positions_0`` .. ``positions_H`` ([N_h, 2] float32: plenty for figures, and half the memory
    of float64 at 3P = 1.28e7, where positions_0 alone is 100 MB; retinal domain, the units of
    ``in_positions``) hold each layer's unit positions; they and the index buffers are in
    ``state_dict``, so loading a state dict restores the connectivity as well as the weights.
    """

    def __init__(
        self,
        in_positions: np.ndarray | Tensor,
        layers: int = 4,
        receptive_field: int | Sequence[int] = 20,
        reduction: float = 5,
        seed: int = 0,
    ) -> None:
        """
        Args:
            in_positions:    [N_0, 2] input positions in the retinal domain (for an ONV input,
                             ``onv_positions(photoreceptor_xy)``).
            layers:          H, the number of hidden layers.
            receptive_field: R_h, an int for all layers or H ints.
            reduction:       f, N_h = floor(N_{h-1} / f).
            seed:            the connectivity seed (see :func:`build_connectivity`). Weights are drawn
                             from torch's global generator, like ``torch.nn`` layers; see
                             :meth:`reset_parameters` for a seeded draw.

        Raises:
            ValueError: from :func:`build_connectivity` on bad arguments.
        """
        super().__init__()
        if isinstance(in_positions, Tensor):
            in_positions = in_positions.detach().cpu().numpy()
        conns = build_connectivity(in_positions, layers, receptive_field, reduction, seed)
        pos0 = np.asarray(in_positions, dtype=np.float64)
        self.layer_sizes: list[int] = [len(pos0)] + [c.num_units for c in conns]
        self.receptive_fields: list[int] = [c.receptive_field for c in conns]
        self.in_features = self.layer_sizes[0]
        self.out_features = self.layer_sizes[-1]
        self.layers = nn.ModuleList(
            LocallyConnected(c.index, n_in, relu=True) for c, n_in in zip(conns, self.layer_sizes[:-1])
        )
        for h, pos in enumerate([pos0] + [c.positions for c in conns]):
            self.register_buffer(f"positions_{h}", torch.from_numpy(np.array(pos, dtype=np.float32)))

    @property
    def num_layers(self) -> int:
        """H, the number of hidden layers."""
        return len(self.layers)

    def layer_positions(self, h: int) -> Tensor:
        """[N_h, 2] float32 positions of layer h's units (h = 0: the inputs), retinal domain."""
        if isinstance(h, bool) or not isinstance(h, (int, np.integer)) or not 0 <= h <= self.num_layers:
            raise ValueError(f"h: expected an int in [0, {self.num_layers}], got {h!r}")
        return getattr(self, f"positions_{h}")

    def connectivity(self) -> list[LayerConnectivity]:
        """The current connectivity (from the buffers, so it reflects a loaded state dict), layers 1..H."""
        return [
            LayerConnectivity(
                index=layer.index.detach().cpu().numpy().astype(np.int64),
                positions=self.layer_positions(h).detach().cpu().numpy().astype(np.float64),
            )
            for h, layer in enumerate(self.layers, start=1)
        ]

    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Re-draw every layer's weights (He) and zero the biases, optionally from ``generator``."""
        for layer in self.layers:
            layer.reset_parameters(generator)

    def forward(self, x: Tensor) -> Tensor:
        """x [B, N_0] (e.g. ONVs [B, 3P]) -> [B, N_H] activations of the last hidden layer (post-ReLU)."""
        for layer in self.layers:
            x = layer(x)
        return x

    def num_parameters(self) -> int:
        """Trainable parameters: sum_h N_h R_h + N_h."""
        return sum(p.numel() for p in self.parameters())

    def extra_repr(self) -> str:
        return f"layer_sizes={self.layer_sizes}, receptive_fields={self.receptive_fields}"


class FullyConnected(nn.Module):
    """The fully-connected baseline: Linear + ReLU per layer, He-initialised, biases zero.

    Attributes:
        in_features, out_features: the input width and the last layer's width.
        layer_sizes: [in_features, *hidden].
    """

    def __init__(self, in_features: int, hidden: Sequence[int], dtype: torch.dtype = torch.float32) -> None:
        """
        Args:
            in_features: N_0.
            hidden:      [N_1, ..., N_H], at least one layer.
            dtype:       torch.float32 or torch.float64.
        """
        super().__init__()
        in_features = _check_size("in_features", in_features)
        if isinstance(hidden, (str, bytes)) or not isinstance(hidden, Sequence) or len(hidden) < 1:
            raise ValueError(f"hidden: expected a non-empty sequence of ints, got {hidden!r}")
        sizes = [in_features] + [_check_size("hidden", n) for n in hidden]
        if dtype not in _FLOATS:
            raise ValueError(f"dtype: expected torch.float32 or torch.float64, got {dtype}")
        self.layer_sizes: list[int] = sizes
        self.in_features = sizes[0]
        self.out_features = sizes[-1]
        self.layers = nn.ModuleList(nn.Linear(a, b, dtype=dtype) for a, b in zip(sizes[:-1], sizes[1:]))
        self.reset_parameters()

    @classmethod
    def like(cls, linet: LiNet, dtype: torch.dtype = torch.float32) -> FullyConnected:
        """A fully-connected network with the same layer sizes as ``linet``."""
        return cls(linet.layer_sizes[0], linet.layer_sizes[1:], dtype=dtype)

    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """weight ~ Normal(0, sqrt(2 / fan_in)) (He), bias = 0."""
        with torch.no_grad():
            for layer in self.layers:
                layer.weight.normal_(0.0, math.sqrt(2.0 / layer.in_features), generator=generator)
                layer.bias.zero_()

    def forward(self, x: Tensor) -> Tensor:
        """x [B, in_features] -> [B, out_features] (post-ReLU)."""
        for layer in self.layers:
            x = torch.relu(layer(x))
        return x

    def num_parameters(self) -> int:
        """Trainable parameters: sum_h N_{h-1} N_h + N_h."""
        return sum(p.numel() for p in self.parameters())


def linet_param_count(layer_sizes: Sequence[int], receptive_fields: int | Sequence[int]) -> int:
    """Trainable parameters of a liNet: sum_{h=1..H} N_h R_h + N_h.

    Args:
        layer_sizes:      [N_0, ..., N_H] (N_0 has no parameters).
        receptive_fields: R_h, one int or H ints.
    """
    sizes = [int(n) for n in layer_sizes]
    rfs = _receptive_fields(receptive_fields, len(sizes) - 1)
    return sum(n * r + n for n, r in zip(sizes[1:], rfs))


def fc_param_count(layer_sizes: Sequence[int]) -> int:
    """Trainable parameters of a fully-connected net: sum_{h=1..H} N_{h-1} N_h + N_h."""
    sizes = [int(n) for n in layer_sizes]
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))
