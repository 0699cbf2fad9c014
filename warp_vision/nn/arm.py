"""The arm's motor nets: a posture (reflex) net and a voluntary net, for one arm's 63 muscles.

Both are trained on postures the body solves for itself (:mod:`warp_vision.sim.arm`: least-effort
activations that hold the arm still against gravity and passive forces) by ``python -m warp_vision.train
arm --side left|right`` (:mod:`warp_vision.train.arm`).

- :class:`PostureNet` (the reflex): the seven main joint angles (rad: elevation plane, elevation, humeral
  rotation, elbow flexion, pronation-supination, wrist deviation and flexion,
  :data:`warp_vision.sim.arm.MAIN_JOINTS`) and their velocities (rad/s) -> the 63 activations in [0, 1]
  that hold the arm there against gravity and damp its motion.
- :class:`VoluntaryNet`: the paper's form (as the oculomotor net's): (desired hand displacement [3] m in
  the world/torso frame, current 63 activations, current joint angles and velocities) -> the next 63
  activations, which drive the hand toward the displacement (applied every control period on the
  remaining displacement, they bring it there and hold it).

Both read out through a sigmoid (offset so an untrained net starts near 0.05, where most holding
activations are). What they are trained to do is defined in torque (:mod:`warp_vision.train.arm`).
:class:`ArmNets` holds both (one checkpoint per arm). Every forward checks its inputs' shapes and that
they are finite (a ``ValueError`` naming the input otherwise).
"""

from __future__ import annotations

import torch
from torch import nn

#: muscles per arm, main joints per arm
MUSCLES = 63
JOINTS = 7
#: m: the voluntary net's displacement unit; s/rad: the velocities' scale at the input
DISPLACEMENT_UNIT = 0.1
VELOCITY_SCALE = 0.5


def _check(name: str, x, width: int) -> torch.Tensor:
    if not torch.is_tensor(x):
        raise ValueError(f"{name}: expected a tensor [B, {width}], got {type(x).__name__}")
    if x.dim() != 2 or x.shape[-1] != width:
        raise ValueError(f"{name}: expected shape [B, {width}], got {tuple(x.shape)}")
    if not torch.isfinite(x).all():
        raise ValueError(f"{name}: expected finite values")
    return x


def _batch(*xs) -> None:
    if len({int(x.shape[0]) for x in xs}) != 1:
        raise ValueError(f"inputs: expected one batch size, got {[tuple(x.shape) for x in xs]}")


def _mlp(n_in: int, hidden: int, n_out: int, layers: int = 3) -> nn.Sequential:
    mods, w = [], n_in
    for _ in range(layers - 1):
        mods += [nn.Linear(w, hidden), nn.SiLU()]
        w = hidden
    return nn.Sequential(*mods, nn.Linear(w, n_out))


def _velocities(velocities, angles: torch.Tensor) -> torch.Tensor:
    if velocities is None:
        return torch.zeros_like(angles)
    _check("velocities", velocities, JOINTS)
    _batch(angles, velocities)
    return velocities


class PostureNet(nn.Module):
    """(joint angles [B, 7] rad, joint velocities [B, 7] rad/s or None: at rest) -> activations [B, 63] in [0, 1]
    that hold the arm there and damp its motion."""

    def __init__(self, hidden: int = 256):
        super().__init__()
        self.mlp = _mlp(2 * JOINTS, hidden, MUSCLES)

    def forward(self, angles: torch.Tensor, velocities: torch.Tensor | None = None) -> torch.Tensor:
        _check("angles", angles, JOINTS)
        v = _velocities(velocities, angles)
        return torch.sigmoid(self.mlp(torch.cat([angles, VELOCITY_SCALE * v], -1)) - 3.0)  # starts near 0.05


class VoluntaryNet(nn.Module):
    """(displacement [B, 3] m, activations [B, 63] in [0, 1], angles [B, 7] rad, velocities [B, 7] rad/s or
    None: at rest) -> next activations [B, 63] in [0, 1]."""

    def __init__(self, hidden: int = 256):
        super().__init__()
        self.mlp = _mlp(3 + MUSCLES + 2 * JOINTS, hidden, MUSCLES)

    def forward(self, displacement: torch.Tensor, activations: torch.Tensor, angles: torch.Tensor,
                velocities: torch.Tensor | None = None) -> torch.Tensor:
        _check("displacement", displacement, 3)
        _check("activations", activations, MUSCLES)
        _check("angles", angles, JOINTS)
        _batch(displacement, activations, angles)
        v = _velocities(velocities, angles)
        if activations.min() < 0 or activations.max() > 1:
            raise ValueError(f"activations: expected values in [0, 1], got {float(activations.min()):.3g} to "
                             f"{float(activations.max()):.3g}")
        x = torch.cat([displacement / DISPLACEMENT_UNIT, 4 * activations - 1, angles, VELOCITY_SCALE * v], -1)
        return torch.sigmoid(self.mlp(x) - 3.0)


class ArmNets(nn.Module):
    """One arm's posture net (``posture``) and voluntary net (``voluntary``); ``side`` is recorded in the spec."""

    def __init__(self, hidden: int = 256):
        super().__init__()
        self.posture = PostureNet(hidden)
        self.voluntary = VoluntaryNet(hidden)

    def forward(self, displacement: torch.Tensor, activations: torch.Tensor, angles: torch.Tensor,
                velocities: torch.Tensor | None = None) -> torch.Tensor:
        """The voluntary net (the posture net is ``self.posture``)."""
        return self.voluntary(displacement, activations, angles, velocities)
