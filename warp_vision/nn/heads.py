"""Task heads: the foveation net (ONV -> eye yaw and pitch), the face-recognition net (ONV -> identity and
pose) on a liNet backbone, and the oculomotor net (change of gaze, activations -> next activations).

Two read-outs of a backbone's hidden layers are available:

- ``"linear"``: the paper's Fig. 5, one fully-connected layer from the last hidden layer to
  (yaw, pitch). It learns localisation slowly: a ReLU net must divide by the target's total response
  to turn "which units fire" into an angle that does not depend on the ball's size and brightness, and
  a ball's localised response shrinks layer by layer under random weights.
- ``"softargmax"`` (liNet only): every layer h = 0..H (0: the ONV itself) votes for a gaze direction,
  the softmax-weighted mean of its units' visual directions (spatial soft-argmax), with weights
  ``softmax_n(exp(log_temperature_h) * a_h[n] + bias_h[n])``; a unit's visual direction is the mean of
  its receptive field's, starting from the photoreceptors' chief rays (:meth:`Retina.visual_angles`),
  as the paper gives each unit the mean position of its receptive field, and its bias starts at the
  log of the solid angle it covers. The same fully-connected output layer then reads the last hidden
  layer and the H + 1 votes (standardised like the targets); it starts as the ONV's vote alone, a
  bright-spot detector, and training adds the rest. The softmax is the normalisation the linear
  read-out lacks.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

from warp_vision.nn.linet import FullyConnected, LiNet
from warp_vision.nn.standardise import StandardisedTargets

HEADS = ("linear", "softargmax")


def unit_directions(linet: LiNet, input_angles: np.ndarray | Tensor) -> list[Tensor]:
    """Visual directions [N_h, 2] of each layer's units, h = 0..H: ``input_angles`` [N_0, 2] (the ONV's),
    then for each hidden unit the mean over its receptive field of the previous layer's."""
    a = torch.as_tensor(np.asarray(input_angles, dtype=np.float64))
    if a.shape != (linet.in_features, 2) or not torch.isfinite(a).all():
        raise ValueError(
            f"input_angles: expected finite values of shape ({linet.in_features}, 2), got {tuple(a.shape)}"
        )
    out = [a]
    for layer in linet.layers:
        a = a[layer.index.cpu().long()].mean(1)
        out.append(a)
    return out


def log_solid_angle_share(directions: Tensor, k: int = 4) -> Tensor:
    """[N] log of each unit's share of the field, estimated as the squared distance to its k-th nearest
    neighbour in (yaw, pitch), relative to the mean (float32; zeros when N <= k)."""
    from scipy.spatial import cKDTree

    d = np.asarray(directions.detach().cpu().numpy(), dtype=np.float64)
    if len(d) <= k:
        return torch.zeros(len(d))
    dist, _ = cKDTree(d).query(d, k=k + 1)
    area = np.maximum(dist[:, k], 1e-9) ** 2
    return torch.from_numpy(np.log(area / area.mean()).astype(np.float32))


class FoveationNet(StandardisedTargets):
    """A backbone (liNet or its fully-connected twin) and a fully-connected output layer to (yaw, pitch).

    forward: onv [B, 3P] float32 -> [B, outputs] (standardised targets: ``(angle - target_mean) /
    target_std``, the buffers set by :meth:`set_target_norm`).
    """

    def __init__(self, backbone: nn.Module, outputs: int = 2, head: str = "linear",
                 directions: list[Tensor] | None = None):
        """
        Args:
            backbone:   a :class:`LiNet` or :class:`FullyConnected`.
            head:       "linear" or "softargmax" (needs a liNet and ``directions``).
            directions: for "softargmax", each layer's unit directions [N_h, 2], h = 0..H (radians, the
                        targets' units), from :func:`unit_directions`.
        """
        super().__init__()
        if head not in HEADS:
            raise ValueError(f"head: expected one of {HEADS}, got {head!r}")
        self.backbone = backbone
        self.head_kind = head
        self.init_target_norm(outputs)
        extra = 0
        if head == "softargmax":
            if not isinstance(backbone, LiNet):
                raise ValueError("head: 'softargmax' needs a liNet backbone (its units have retinal positions)")
            H = backbone.num_layers
            if outputs != 2 or directions is None or len(directions) != H + 1:
                raise ValueError("directions: expected one [N_h, 2] tensor per layer h = 0..H (0: the inputs), and "
                                 "outputs=2")
            for h, (d, n) in enumerate(zip(directions, backbone.layer_sizes)):
                if tuple(d.shape) != (n, 2):
                    raise ValueError(f"directions[{h}]: expected shape ({n}, 2), got {tuple(d.shape)}")
                self.register_buffer(f"directions_{h}", d.detach().to(torch.float32).clone())
            # temperature 3: an input 1 (one std) above its neighbours gets e^3 = 20x their weight
            self.log_temperature = nn.Parameter(torch.full((H + 1,), math.log(3.0)))
            # each unit's vote starts weighted by the solid angle it covers (the fovea's many small units
            # would otherwise pull every vote toward the fovea); the biases then learn
            self.vote_bias = nn.ParameterList(nn.Parameter(log_solid_angle_share(d)) for d in directions)
            extra = 2 * (H + 1)
        self.head = nn.Linear(backbone.out_features + extra, outputs)
        if head == "softargmax":
            with torch.no_grad():  # start as the inputs' vote (a bright-spot detector); the rest learns
                self.head.weight.zero_()
                self.head.bias.zero_()
                self.head.weight[:, backbone.out_features : backbone.out_features + 2] = torch.eye(2)

    def _vote(self, h: int, x: Tensor, scale: Tensor | None = None) -> Tensor:
        t = self.log_temperature[h].exp()
        if scale is None:
            logits = x * t + self.vote_bias[h]
        else:  # a half-precision x: widened element by element, no float32 copy of it
            logits = torch.addcmul(self.vote_bias[h], x, t * scale)
        w = torch.softmax(logits, dim=1)
        return w @ getattr(self, f"directions_{h}")

    def votes(self, onv: Tensor) -> tuple[Tensor, list[Tensor]]:
        """(last hidden layer [B, N_H], gaze votes [B, 2] in radians of layers h = 0..H) for the
        soft-argmax head (h = 0: the net's input, one vote per ONV element).

        A backbone whose first layer standardises its (half-precision) input itself gets the same layer-0
        vote as one fed standardised input: the temperature is divided by the input's std, and the mean,
        a shift common to every element, cancels in the softmax."""
        first = self.backbone.layers[0]
        if getattr(first, "folds_input", False):
            votes = [self._vote(0, onv, 1.0 / first.input_std)]
        else:
            votes = [self._vote(0, onv)]
        x = onv
        for h, layer in enumerate(self.backbone.layers, start=1):
            x = layer(x)
            votes.append(self._vote(h, x))
        return x, votes

    def forward(self, onv: Tensor) -> Tensor:
        if self.head_kind == "linear":
            return self.head(self.backbone(onv))
        x, votes = self.votes(onv)
        z = [(v - self.target_mean) / self.target_std for v in votes]
        return self.head(torch.cat([x, *z], dim=1))


def foveation_net(model: str, in_positions, layers: int = 4, receptive_field: int = 20, reduction: int = 5,
                  seed: int = 0, head: str = "linear", input_angles=None, outputs: int = 2) -> FoveationNet:
    """``model`` "linet" or "fc" (same hidden sizes as the liNet), on inputs at ``in_positions`` [3P, 2],
    ``outputs`` values read out (the linear head; 2: yaw and pitch).

    ``head`` "softargmax" (liNet only) needs ``input_angles`` [3P, 2], each input's visual direction
    (yaw, pitch) in radians (e.g. ``Retina.visual_angles`` repeated per channel).
    """
    if head not in HEADS:
        raise ValueError(f"head: expected one of {HEADS}, got {head!r}")
    torch.manual_seed(seed)
    linet = LiNet(in_positions, layers=layers, receptive_field=receptive_field, reduction=reduction, seed=seed)
    if model == "linet":
        if head == "softargmax":
            if input_angles is None:
                raise ValueError("input_angles: the softargmax head needs each input's visual direction")
            return FoveationNet(linet, outputs, head=head, directions=unit_directions(linet, input_angles))
        return FoveationNet(linet, outputs)
    if model == "fc":
        if head != "linear":
            raise ValueError(f"head: the fc baseline has only the linear head, got {head!r}")
        return FoveationNet(FullyConnected.like(linet), outputs)
    raise ValueError(f"model: expected 'linet' or 'fc', got {model!r}")


def limb_vision_net(model: str, in_positions, layers: int = 3, receptive_field: int = 20, reduction: int = 5,
                    seed: int = 0) -> FoveationNet:
    """A limb vision net (the paper's nets 3-10, one per eye): :func:`foveation_net` with a linear read-out
    of six values, the hand-to-ball discrepancy of the left and of the right arm (m, eye frame;
    standardised by the target buffers)."""
    return foveation_net(model, in_positions, layers, receptive_field, reduction, seed, outputs=6)


class AFRNet(nn.Module):
    """The paper's active-face-recognition net (Section VI.B): a liNet backbone and two single-layer
    fully-connected heads on its last hidden layer, FC1 to identity logits and FC2 to the pose angles
    (standardised: ``(angle - pose_mean) / pose_std``, buffers set by :meth:`set_pose_norm`).

    forward: onv [B, 3P] -> (logits [B, identities], pose [B, 2] standardised).
    """

    def __init__(self, backbone: nn.Module, identities: int, pose_outputs: int = 2):
        super().__init__()
        if identities < 2:
            raise ValueError(f"identities: expected at least 2 classes, got {identities}")
        self.backbone = backbone
        self.fc1 = nn.Linear(backbone.out_features, identities)
        self.fc2 = nn.Linear(backbone.out_features, pose_outputs)
        self.register_buffer("pose_mean", torch.zeros(pose_outputs))
        self.register_buffer("pose_std", torch.ones(pose_outputs))

    def set_pose_norm(self, mean: Tensor, std: Tensor) -> None:
        with torch.no_grad():
            self.pose_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
            self.pose_std.copy_(torch.as_tensor(std, dtype=torch.float32))

    def forward(self, onv: Tensor) -> tuple[Tensor, Tensor]:
        x = self.backbone(onv)
        return self.fc1(x), self.fc2(x)

    def pose_degrees(self, z: Tensor) -> Tensor:
        """Standardised pose outputs -> angles in the labels' units."""
        return z * self.pose_std + self.pose_mean


def afr_net(in_positions, identities: int, layers: int = 5, receptive_field: int = 20, reduction: int = 2,
            seed: int = 0, model: str = "linet") -> AFRNet:
    """The AFR net on inputs at ``in_positions`` [3P, 2]; ``model`` "fc" swaps in the fully-connected twin."""
    torch.manual_seed(seed)
    linet = LiNet(in_positions, layers=layers, receptive_field=receptive_field, reduction=reduction, seed=seed)
    if model == "linet":
        return AFRNet(linet, identities)
    if model == "fc":
        return AFRNet(FullyConnected.like(linet), identities)
    raise ValueError(f"model: expected 'linet' or 'fc', got {model!r}")


class OculomotorNet(nn.Module):
    """(desired change of gaze [B, 2] rad, current activations [B, 6]) -> next activations [B, 6] in [0, 1].

    The MLP predicts a [6, 2] matrix J from the change and the activations, and the activations change by
    J times the change of gaze: no change asks for none, a small change is met by the local Jacobian of the
    activations that hold a gaze (a smooth function of them), and a saccade by a secant. Applied to its own
    output every control period it does not drift, as a net that predicts the activations outright does
    (:func:`warp_vision.sim.oculomotor.evaluate_on_body` measures such pursuit chains).
    """

    def __init__(self, hidden: int = 256):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(8, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
                                 nn.Linear(hidden, 12))

    def forward(self, change: torch.Tensor, activations: torch.Tensor) -> torch.Tensor:
        if change.shape[-1] != 2 or activations.shape[-1] != 6 or change.shape[:-1] != activations.shape[:-1]:
            raise ValueError(f"change [B, 2] and activations [B, 6] expected, got {tuple(change.shape)} and "
                             f"{tuple(activations.shape)}")
        c = change * (180 / np.pi / 10)  # in units of 10 deg
        J = 0.1 * self.mlp(torch.cat([c, 4 * activations - 1], -1)).unflatten(-1, (6, 2))
        return (activations + (J @ c.unsqueeze(-1)).squeeze(-1)).clamp(0.0, 1.0)
