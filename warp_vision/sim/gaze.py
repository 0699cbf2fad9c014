"""The gaze controller: each eye's estimate of the target's direction in, each eye's change of commanded
gaze out, every control period.

Per eye it keeps:

- where the eye is: an internal model (efference copy through a first-order lag of ``EYE_MODEL_TAU``)
  of the commanded gaze, so the target's direction in the head is that belief plus the retinal error,
  also while the eye is moving;
- a saccade when the retinal error exceeds ``SACCADE_DEG``: the command jumps to the target's direction;
- pursuit otherwise: the command follows the target's direction led by its estimated angular velocity
  times ``LEAD``, and a slow integrator of the retinal error (``BIAS_GAIN`` per period) takes out the
  muscles' static error;
- the vestibulo-ocular reflex: the head's rotation since the last period is taken off the believed
  eye-in-head gaze, so the target's estimated direction, and with it the command, stays put in the world
  while the head turns;
- between frames: the last frame's estimate of the target's direction in the head, turned with the head
  and moved at the estimated angular velocity, stands in for a new one (no saccade is decided and nothing
  is learned without a frame).

Who picks the target (the foveation nets' single answer, the active search of :mod:`warp_vision.sim.search`,
or the true ball) is the caller's business: :meth:`GazeController.update` takes each eye's retinal error.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from warp_vision.body import SIDES

CONTROL_DT = 0.01  # s
SACCADE_DEG = 2.0
EYE_MODEL_TAU = 0.03  # s
LEAD = 0.03  # s
#: The bias integrator's gain per period: a time constant of 0.5 s. It takes out the muscles' static error,
#: which changes slowly with the gaze. A faster integrator also integrates the foveation nets' frame-to-frame
#: error and sets the gaze oscillating about the ball (docs/RESULTS.md, "The closed loop's speed").
BIAS_GAIN = 0.02
VELOCITY_SMOOTHING = 0.15  # weight of the newest velocity sample in its running estimate
MAX_TARGET_SPEED = np.radians(90.0)  # rad/s: the velocity estimate is clipped to this
POST_SACCADE = 0.08  # s after a saccade's command during which the eye is still moving: no velocity or bias learning
MAX_GAZE_DEG = 35.0


@dataclass
class EyeState:
    command: np.ndarray = field(default_factory=lambda: np.zeros(2))  # commanded gaze in the head, rad
    activations: np.ndarray = field(default_factory=lambda: np.zeros(6))
    believed: np.ndarray = field(default_factory=lambda: np.zeros(2))  # the internal model's gaze, rad
    bias: np.ndarray = field(default_factory=lambda: np.zeros(2))  # learned static offset, rad
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))  # the target's, rad/s in the head
    last_target: np.ndarray | None = None  # the estimate of the last frame that learned the velocity
    target: np.ndarray | None = None  # the target's direction in the head, rad: the last frame's estimate, carried
    quiet_from: float = 0.0  # time the last saccade's movement ends


def clamp_gaze(g: np.ndarray) -> np.ndarray:
    """``g`` (yaw, pitch) rad, shortened to at most MAX_GAZE_DEG from the centre."""
    r = np.linalg.norm(g)
    lim = np.radians(MAX_GAZE_DEG)
    return g if r <= lim else g * (lim / r)


class GazeController:
    """Both eyes' saccades, pursuit, bias learning and vestibulo-ocular reflex (see the module docstring).
    ``eyes`` holds each eye's :class:`EyeState`; ``frame_every`` is the number of control periods per visual
    frame."""

    def __init__(self, frame_every: int):
        self.frame_every = int(frame_every)
        self.eyes = {s: EyeState() for s in SIDES}

    def reset(self) -> None:
        self.eyes = {s: EyeState() for s in SIDES}

    def update(self, err: dict | None, head_turn: np.ndarray, now: float) -> dict:
        """One control period: ``err`` is each eye's retinal error (yaw, pitch) rad of the target on a visual
        frame, or None between frames; ``head_turn`` the head's (yaw, pitch) rotation since the last period,
        rad; ``now`` the body's time, s. Returns each eye's change of commanded gaze (rad) and applies it."""
        changes = {}
        k = 1 - np.exp(-CONTROL_DT / EYE_MODEL_TAU)
        for s in SIDES:
            e = self.eyes[s]
            self._turn_with_head(e, head_turn)
            if err is None:
                new = self._carry(e, now)
            elif np.degrees(np.linalg.norm(err[s])) > SACCADE_DEG:
                new = self._saccade(e, e.believed + err[s], now)
            else:
                new = self._pursue(e, e.believed + err[s], err[s], now)
            changes[s] = clamp_gaze(new) - e.command
            e.command = e.command + changes[s]
            e.believed = e.believed + k * (e.command - e.bias - e.believed)
        return changes

    @staticmethod
    def _turn_with_head(e: EyeState, head_turn: np.ndarray) -> None:
        """The vestibulo-ocular reflex: the head turned under the eye, so the believed gaze and every estimate of
        the target's direction in the head (fixed in the world) turn back by as much. The velocity's reference
        turns too, so the velocity is the target's own and the head's turn is not counted twice."""
        e.believed = e.believed - head_turn
        if e.target is not None:
            e.target = e.target - head_turn
        if e.last_target is not None:
            e.last_target = e.last_target - head_turn

    @staticmethod
    def _carry(e: EyeState, now: float) -> np.ndarray:
        """No new frame: the last estimate carried forward at its estimated velocity. (A controller's first
        period is a frame, so ``e.target`` is set.)"""
        if e.target is None:
            return e.command.copy()
        if now >= e.quiet_from:
            e.target = e.target + e.velocity * CONTROL_DT
        return e.target + e.velocity * LEAD + e.bias

    @staticmethod
    def _saccade(e: EyeState, target: np.ndarray, now: float) -> np.ndarray:
        """A saccade to ``target`` (the head frame): the velocity estimate starts again once the eye is quiet."""
        e.target = target
        e.velocity[:] = 0
        e.last_target = None
        e.quiet_from = now + POST_SACCADE
        return target + e.bias

    def _pursue(self, e: EyeState, target: np.ndarray, err: np.ndarray, now: float) -> np.ndarray:
        """Pursuit of ``target``: once the eye is quiet, the target's velocity (a running estimate whose time
        constant does not depend on the frame rate) and the static bias are learned from the frame."""
        e.target = target
        if now >= e.quiet_from:
            if e.last_target is not None:
                v = (target - e.last_target) / (self.frame_every * CONTROL_DT)
                w = 1 - (1 - VELOCITY_SMOOTHING) ** self.frame_every
                e.velocity = (1 - w) * e.velocity + w * v
                speed = np.linalg.norm(e.velocity)
                if speed > MAX_TARGET_SPEED:
                    e.velocity *= MAX_TARGET_SPEED / speed
            e.last_target = target
            e.bias = e.bias + BIAS_GAIN * self.frame_every * err
        return target + e.velocity * LEAD + e.bias
