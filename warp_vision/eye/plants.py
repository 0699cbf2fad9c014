"""The iris and the lens as plants with human dynamics: a latency, then first-order movement.

Both plants take a command (the pupil diameter in mm, the accommodation in dioptres) and move their
state toward the command they received one latency ago, exponentially with a time constant:

    state(t + dt) = command(t - latency) + (state(t) - command(t - latency)) exp(-dt / tau)

**Pupil** (:class:`PupilPlant`, 2-8 mm).
- Latency falls with luminance, from about 0.30 s in dim light to 0.20 s in bright light: Lee, Cohen &
  Boynton (1969), "Latency variation in human pupil contraction due to stimulus luminance and/or
  adaptation level", JOSA 59(1):97-100, found the latency to be primarily a function of the luminance
  during the step; Pamplona, Oliveira & Baranoski (2009), "Photorealistic models for pupil light reflex
  and iridal pattern deformation", ACM TOG 28(4):106, model the same fall over the photopic range. Here
  the luminance is the one the command stands for (the luminance whose Watson & Yellott diameter is the
  command): ``latency = clip(0.25 - 0.025 log10(L / 1 cd m^-2), 0.20, 0.30)`` s.
- Constriction is faster than dilation: time constants 0.15 s and 0.45 s (dilation 3 times slower;
  Ellis (1981), "The pupillary light reflex in normal subjects", Br J Ophthalmol 65:754-759, reports
  constriction velocities about three times the redilation velocities).

**Lens** (:class:`LensPlant`, 0-10 D at this age).
- Latency 0.3 s and time constant 0.25 s: Kasthurirangan & Glasser (2005), "Characteristics of pupil
  responses during far-to-near and near-to-far accommodation", Ophthalmic Physiol Opt 25:328-339, and
  Kasthurirangan, Vilupuru & Glasser (2003), "Amplitude dependent accommodative dynamics in humans",
  Vision Res 43:2945-2956 (latencies about 0.3 s, time constants about 0.2-0.3 s); Bharadwaj & Schor
  (2005), "Acceleration characteristics of human ocular accommodation", Vision Res 45:17-28.
- Peak velocity grows with amplitude: for a first-order movement it is amplitude / tau, linear in the
  amplitude, as Kasthurirangan et al. (2003) found (the "main sequence" of accommodation).

Plain numpy; one plant per eye and quantity, stepped by the body each control period.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

PUPIL_RANGE_MM = (2.0, 8.0)
PUPIL_LATENCY_S = (0.20, 0.30)  # bright, dim
PUPIL_TAU_S = {"constrict": 0.15, "dilate": 0.45}
LENS_RANGE_D = (0.0, 10.0)
LENS_LATENCY_S = 0.30
LENS_TAU_S = 0.25


def pupil_latency_s(luminance_cd_m2) -> np.ndarray:
    """The pupil's latency (s) for a step to ``luminance_cd_m2``: 0.25 s at 1 cd/m^2, 0.025 s less per
    decade brighter, within 0.20-0.30 s (Lee, Cohen & Boynton 1969; module docstring)."""
    L = np.asarray(luminance_cd_m2, dtype=np.float64)
    if not np.all(np.isfinite(L)) or np.any(L < 0):
        raise ValueError(f"luminance_cd_m2: expected finite values >= 0, got {luminance_cd_m2!r}")
    return np.clip(0.25 - 0.025 * np.log10(np.maximum(L, 1e-12)), *PUPIL_LATENCY_S)


class _Plant:
    """A latency followed by a first-order lag with a time constant that may depend on the direction."""

    name = "plant"
    unit = ""

    def __init__(self, state: float, limits: tuple[float, float]):
        self.limits = limits
        self.state = self._check(state, "state")
        self.time = 0.0
        self._commands: deque = deque([(-math.inf, self.state)])  # (time it takes effect, command)

    def _check(self, v, name: str) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not math.isfinite(v):
            raise ValueError(f"{self.name} {name}: expected a finite number ({self.unit}), got {v!r}")
        return float(np.clip(float(v), *self.limits))

    def latency(self, command: float) -> float:
        raise NotImplementedError

    def tau(self, state: float, target: float) -> float:
        raise NotImplementedError

    def command(self, value) -> None:
        """Command ``value`` now (clipped to the range); it takes effect one latency later."""
        v = self._check(value, "command")
        if v != self._commands[-1][1]:
            self._commands.append((self.time + self.latency(v), v))

    def reset(self, state: float) -> None:
        self.state = self._check(state, "state")
        self._commands = deque([(-math.inf, self.state)])

    def _effective(self, t: float) -> float:
        while len(self._commands) > 1 and self._commands[1][0] <= t:
            self._commands.popleft()
        return self._commands[0][1]

    def advance(self, dt: float, substep: float = 0.005) -> float:
        """Move ``dt`` s forward (in substeps of at most ``substep`` s, so a command that takes effect
        inside the interval does so on time); returns the new state."""
        if not (np.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt: expected a finite duration >= 0, got {dt!r}")
        n = max(1, math.ceil(dt / substep - 1e-9))
        h = dt / n
        for _ in range(n):
            target = self._effective(self.time)
            self.state = target + (self.state - target) * math.exp(-h / self.tau(self.state, target))
            self.time += h
        return self.state


class PupilPlant(_Plant):
    """The iris: pupil diameter (mm), latency by luminance, constriction faster than dilation."""

    name = "pupil"
    unit = "mm"

    def __init__(self, state: float = 4.0):
        super().__init__(state, PUPIL_RANGE_MM)

    def latency(self, command: float) -> float:
        from warp_vision.eye.pupil import luminance_for_diameter

        return float(pupil_latency_s(luminance_for_diameter(command)))

    def tau(self, state: float, target: float) -> float:
        return PUPIL_TAU_S["constrict"] if target < state else PUPIL_TAU_S["dilate"]


class LensPlant(_Plant):
    """The lens: accommodation (D), latency 0.3 s, time constant 0.25 s."""

    name = "lens"
    unit = "D"

    def __init__(self, state: float = 1.0):
        super().__init__(state, LENS_RANGE_D)

    def latency(self, command: float) -> float:
        return LENS_LATENCY_S

    def tau(self, state: float, target: float) -> float:
        return LENS_TAU_S
