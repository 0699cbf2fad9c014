"""The cannon scenario of the paper's Fig. 8: seeded shots at the seated body and a detector that says
whether an arm deflected the ball.

- :class:`Shot` and :func:`sample_shots`: shots drawn from seeds within an envelope of shots a hand can
  reach (:data:`ENVELOPE`): the ball passes through a target point in front of a shoulder, within the
  arm's reach, at a launch speed of 6-12 m/s. Training and held-out shots come from disjoint seed ranges
  (:data:`SPLITS`).
- :class:`DeflectionDetector`: stepped alongside the simulation, it records the first contact of the ball
  with each body part (hand, forearm, upper arm of either side; torso; head), the ball's velocity change
  in contacts with a hand or forearm, and the closest approach of the ball to a hand or forearm.
- :func:`run_shot`: fires one shot at a body whose arms are passive (zero activation) or moved by a
  controller, and returns the detector's :class:`ShotResult`.

Frames and units: the world frame of :mod:`warp_vision.body` (+z up, the body faces -y, its left is +x);
SI units (m, s, m/s). The body's frontal plane is y = the shoulders' mean y (the glenohumeral joints'
centres, 0.101 m with the arms hanging): "in front of the body" is y below it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from warp_vision.body import BODY_CONTYPE, SIDES, Body, BodyConfig

#: The arm's parts the detector tells apart (per side; the torso and head are parts too).
ARM_PARTS = ("hand", "forearm", "upper_arm")
#: Parts whose touch can deflect the ball (and whose distance to it is the closest approach).
DEFLECTING_PARTS = ("hand", "forearm")
#: A hand or forearm contact deflects the ball when the ball's velocity changes by more than this (m/s),
#: beyond gravity, over the steps in which it touches them.
DEFLECTION_DV = 1.0
#: The left shoulder (glenohumeral joint centre, the ``humerus_l`` body's origin, m) with the pelvis on the
#: stool and the arms hanging: read off the model (``tests/test_cannon.py`` checks it); the right is the
#: mirror image (x -> -x).
SHOULDER_LEFT = (0.170, 0.101, 1.095)
#: The arm's reach (m): shoulder -> elbow (0.291) -> wrist (0.258) -> third knuckle (0.081) along
#: myo-sim's bones (``humerus``, ``ulna``, ``lunate``, ``3proxph`` origins), read off the model; the
#: fingertips reach 0.08 m further.
ARM_REACH = 0.630

#: The envelope of reachable shots (the ball's centre passes through the target at the flight time), per
#: side, relative to that side's shoulder: ``forward`` m in front of it (-y), ``outward`` m away from the
#: midline (negative: across it), ``up`` m above it; within ``reach_fraction`` x ``ARM_REACH`` of the
#: shoulder. Launch speed uniform in ``speed`` m/s from the muzzle (the flatter of the two ballistic paths
#: at that speed); the flight times it gives are 0.2-0.55 s.
ENVELOPE = {"forward": (0.25, 0.50), "outward": (-0.15, 0.25), "up": (-0.45, 0.20), "reach_fraction": 0.85,
            "speed": (6.0, 12.0)}
#: Seed ranges of the splits: a shot's seed picks its target and speed. Disjoint, so no held-out shot is
#: ever trained on.
SPLITS = {"train": range(0, 1_000_000), "heldout": range(1_000_000, 2_000_000)}
TRAIN_SEEDS = SPLITS["train"]
HELDOUT_SEEDS = SPLITS["heldout"]
GRAVITY = np.array([0.0, 0.0, -9.81])  # m/s^2, the model's (MuJoCo's default)

#: run_shot: passive arms hang still after about 1 s (they swing forward under gravity first)
SETTLE_S = 1.0
#: run_shot stops this long after the flight time at the latest (s), or earlier when the ball lands or is
#: this far behind the frontal plane (m): past the body.
TAIL_S = 0.3
BEHIND_M = 0.35


@dataclass(frozen=True)
class Shot:
    """One cannon shot: the ball leaves ``muzzle`` with ``launch_velocity`` and, in flight, passes through
    ``target`` after ``flight_time`` s. ``side``: the arm whose reach envelope drew the target."""

    seed: int | None  # None: aimed by hand (make_shot)
    side: str
    target: tuple  # m, world
    speed: float  # m/s at launch
    flight_time: float  # s from the muzzle to the target
    muzzle: tuple  # m, world (BodyConfig.cannon_position)
    launch_velocity: tuple  # m/s, world

    @property
    def direction(self) -> np.ndarray:
        """Unit launch direction."""
        v = np.asarray(self.launch_velocity)
        return v / np.linalg.norm(v)


def shoulder(side: str) -> np.ndarray:
    """A shoulder's centre at rest (m, world): :data:`SHOULDER_LEFT` or its mirror image."""
    if side not in SIDES:
        raise ValueError(f"side: expected one of {SIDES}, got {side!r}")
    x, y, z = SHOULDER_LEFT
    return np.array([x if side == "left" else -x, y, z])


def flight_time(muzzle, target, speed: float, gravity=GRAVITY) -> float:
    """Flight time (s) of the flatter ballistic path from ``muzzle`` through ``target`` at launch speed
    ``speed`` (m/s); ValueError when the speed cannot reach it. With D = target - muzzle, the launch
    velocity v = (D - g T^2 / 2) / T has |v| = speed where
    |g|^2 T^4 / 4 - (speed^2 + D.g) T^2 + |D|^2 = 0; the smaller root is the flatter path."""
    D = np.asarray(target, float) - np.asarray(muzzle, float)
    g = np.asarray(gravity, float)
    a, b, c = g @ g / 4, -(speed**2 + D @ g), D @ D
    disc = b * b - 4 * a * c
    if disc < 0:
        raise ValueError(f"speed: {speed} m/s cannot reach {np.round(target, 3).tolist()} from the muzzle")
    return float(np.sqrt((-b - np.sqrt(disc)) / (2 * a)))


def make_shot(target, speed: float, seed: int | None = None, side: str = "left",
              muzzle=BodyConfig.cannon_position) -> Shot:
    """The shot from ``muzzle`` through ``target`` (m) at launch speed ``speed`` (m/s), on the flatter
    path. ``seed`` and ``side`` are recorded (None: a shot aimed by hand, drawn from no seed)."""
    if side not in SIDES:
        raise ValueError(f"side: expected one of {SIDES}, got {side!r}")
    if not speed > 0:
        raise ValueError(f"speed: expected > 0 m/s, got {speed}")
    target, muzzle = np.asarray(target, float), np.asarray(muzzle, float)
    T = flight_time(muzzle, target, speed)
    v = (target - muzzle - 0.5 * GRAVITY * T**2) / T
    return Shot(seed, side, _floats(target), float(speed), T, _floats(muzzle), _floats(v))


def shot_from_seed(seed: int, side: str = "left", muzzle=BodyConfig.cannon_position) -> Shot:
    """The shot of ``seed``: a target drawn uniformly in the :data:`ENVELOPE` box of ``side``'s shoulder
    (redrawn until it lies within the reach), a speed uniformly in its range."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed!r}")
    s = shoulder(side)
    out = 1.0 if side == "left" else -1.0
    rng = np.random.default_rng(int(seed))
    while True:
        f, o, u = (rng.uniform(*ENVELOPE[k]) for k in ("forward", "outward", "up"))
        offset = np.array([out * o, -f, u])
        if np.linalg.norm(offset) <= ENVELOPE["reach_fraction"] * ARM_REACH:
            break
    return make_shot(s + offset, float(rng.uniform(*ENVELOPE["speed"])), int(seed), side, muzzle)


def _floats(v) -> tuple:
    return tuple(float(x) for x in v)


def sample_shots(n: int, seed: int = 0, split: str = "train", side: str = "left") -> list[Shot]:
    """``n`` shots of ``split`` (:data:`SPLITS`): those of seeds ``start + seed`` ... ``start + seed + n - 1``
    of the split's range. Reproducible: the same arguments give the same shots."""
    if split not in SPLITS:
        raise ValueError(f"split: expected one of {sorted(SPLITS)}, got {split!r}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n <= 0:
        raise ValueError(f"n: expected an integer > 0, got {n!r}")
    seeds = SPLITS[split]
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0 or seed + n > len(seeds):
        raise ValueError(f"seed: expected an integer in [0, {len(seeds) - n}] for n={n}, got {seed!r}")
    return [shot_from_seed(seeds[seed + k], side) for k in range(n)]


# --- body parts ------------------------------------------------------------------------------------
_ARM_BONES = {"humerus": "upper_arm", "ulna": "forearm", "radius": "forearm"}


def geom_parts(model: mujoco.MjModel) -> dict[int, tuple[str, str | None]]:
    """{geom id: (part, side)} for the body's collision geoms (contype ``BODY_CONTYPE``): ``humerus_l``'s
    are the left upper arm's, ``ulna_l``'s and ``radius_l``'s the left forearm's, those of bodies below
    ``radius_l`` (carpals, metacarpals, fingers) the left hand's; those on or below ``neck`` the head's
    (side None), the rest the torso's (side None)."""
    out = {}
    for g in range(model.ngeom):
        if not model.geom_contype[g] & BODY_CONTYPE:
            continue
        out[g] = _part_of_body(model, int(model.geom_bodyid[g]))
    return out


def _part_of_body(model: mujoco.MjModel, b: int) -> tuple[str, str | None]:
    chain = []  # b and its ancestors' names, b first
    while b:
        chain.append(model.body(b).name)
        b = int(model.body_parentid[b])
    for k, name in enumerate(chain):
        bone, _, suffix = name.rpartition("_")
        if bone in _ARM_BONES and suffix in ("l", "r"):
            side = "left" if suffix == "l" else "right"
            return ("hand" if k > 0 else _ARM_BONES[bone]), side  # below the radius: the hand
        if name == "neck":
            return "head", None
    return "torso", None


def part_name(part: str, side: str | None) -> str:
    """``"hand_left"``, ..., ``"torso"``, ``"head"``."""
    return part if side is None else f"{part}_{side}"


# --- the detector ----------------------------------------------------------------------------------
@dataclass
class Contact:
    """A first touch of the ball on a body part."""

    t: float  # s since the detector started (the launch)
    geom: str  # the body's collision geom
    ball: tuple  # m, the ball's centre
    ball_speed: float  # m/s, just before the step of the touch


@dataclass
class ShotResult:
    """What a shot did. ``first_contacts``: {part name (:func:`part_name`): :class:`Contact`};
    ``arm_contact``: the first hand or forearm one (None: none); ``before_frontal_plane``: the ball's centre
    was in front of the frontal plane (y < ``frontal_y``) then; ``arm_dv``: the ball's velocity change
    (m/s, vector) in the steps it touched a hand or forearm, gravity's taken out; ``deflected``: a hand or
    forearm touched it before the frontal plane and changed its velocity by more than
    ``threshold``; ``closest``: the least distance (m) from the ball's surface to a hand or forearm
    collision geom (negative: overlapping), at ``closest_t`` s, on ``closest_part``; ``landed``: the ball
    touched the floor; ``passed``: it went past the body (``BEHIND_M`` behind the frontal plane)."""

    deflected: bool
    first_contacts: dict
    arm_contact: str | None
    before_frontal_plane: bool
    arm_dv: np.ndarray
    closest: float
    closest_t: float
    closest_part: str | None
    landed: bool
    passed: bool
    frontal_y: float
    threshold: float
    duration: float  # s simulated after the launch
    ball_end: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m, the ball's centre at the end
    max_penetration: float = 0.0  # m, the deepest ball contact seen

    @property
    def speed_change(self) -> float:
        """|arm_dv| (m/s)."""
        return float(np.linalg.norm(self.arm_dv))


class DeflectionDetector:
    """Watches the ball in a :class:`~warp_vision.body.Body`: call :meth:`update` after every
    ``body.step()`` (one MuJoCo step each: the contacts it reads are those of the last step), then
    :meth:`result`. It starts at construction: times are from then (the launch).

    ``frontal_y``: the frontal plane (m; default the shoulders' mean y now); ``threshold``: the velocity
    change (m/s) that makes a hand or forearm touch a deflection (default :data:`DEFLECTION_DV`)."""

    def __init__(self, body: Body, frontal_y: float | None = None, threshold: float = DEFLECTION_DV):
        if not threshold > 0:
            raise ValueError(f"threshold: expected > 0 m/s, got {threshold}")
        m, d = body.model, body.data
        self.body, self.threshold = body, float(threshold)
        self.parts = geom_parts(m)
        if not any(p in DEFLECTING_PARTS for p, _ in self.parts.values()):
            raise ValueError("body: no hand or forearm collision geoms (a body built with arms=False?)")
        self.ball_geom = m.geom("ball").id
        self.floor_geom = m.geom("floor").id
        self._dof = int(m.jnt_dofadr[body.ball_joint])
        if frontal_y is None:
            frontal_y = float(np.mean([d.xpos[m.body(f"humerus_{s}").id][1] for s in ("l", "r")]))
        self.frontal_y = float(frontal_y)
        self._arm_geoms = np.array([g for g, (p, _) in self.parts.items() if p in DEFLECTING_PARTS])
        self._t0 = body.time
        self._v = self._ball_velocity()
        self.first: dict[str, Contact] = {}
        self.arm_contact: str | None = None
        self.before_plane = False
        self.arm_dv = np.zeros(3)
        self.closest, self.closest_t, self.closest_part = np.inf, np.nan, None
        self.landed = self.passed = False
        self.max_penetration = 0.0
        self._closest_approach()

    def _ball_velocity(self) -> np.ndarray:
        return self.body.data.qvel[self._dof:self._dof + 3].copy()

    @property
    def t(self) -> float:
        return self.body.time - self._t0

    def update(self) -> None:
        """Read the last step: the ball's contacts, its velocity change, its distance to the arms."""
        d = self.body.data
        v_prev, v = self._v, self._ball_velocity()
        self._v = v
        dv = v - v_prev - GRAVITY * self.body.model.opt.timestep  # what contacts did this step
        p = self.body.ball_position()
        touched_arm = False
        for i in range(d.ncon):
            c = d.contact[i]
            g1, g2 = int(c.geom[0]), int(c.geom[1])
            if self.ball_geom not in (g1, g2) or c.exclude:
                continue
            other = g2 if g1 == self.ball_geom else g1
            if other == self.floor_geom:
                self.landed = True
                continue
            if other not in self.parts:
                continue
            self.max_penetration = max(self.max_penetration, -float(c.dist))
            part, side = self.parts[other]
            name = part_name(part, side)
            if name not in self.first:
                self.first[name] = Contact(self.t, self.body.model.geom(other).name, _floats(p),
                                           float(np.linalg.norm(v_prev)))
            if part in DEFLECTING_PARTS:
                touched_arm = True
                if self.arm_contact is None:
                    self.arm_contact = name
                    self.before_plane = bool(p[1] < self.frontal_y)
        if touched_arm:
            self.arm_dv += dv
        if p[1] > self.frontal_y + BEHIND_M:
            self.passed = True
        self._closest_approach()

    def _closest_approach(self) -> None:
        """The least distance from the ball to a hand or forearm geom now: geoms in order of a lower bound
        (centre distance less both bounding radii), exact (``mj_geomDistance``) until the bound passes the best."""
        m, d = self.body.model, self.body.data
        gs = self._arm_geoms
        centre = d.geom_xpos[self.ball_geom]
        lower = np.linalg.norm(d.geom_xpos[gs] - centre, axis=1) - m.geom_rbound[gs] - m.geom_rbound[self.ball_geom]
        best, best_g = np.inf, None
        for k in np.argsort(lower):
            if lower[k] >= best:
                break
            dist = mujoco.mj_geomDistance(m, d, self.ball_geom, int(gs[k]), 10.0, None)
            if dist < best:
                best, best_g = dist, int(gs[k])
        if best < self.closest:
            self.closest, self.closest_t = float(best), self.t
            self.closest_part = part_name(*self.parts[best_g])

    def result(self) -> ShotResult:
        deflected = self.arm_contact is not None and self.before_plane and np.linalg.norm(self.arm_dv) > self.threshold
        return ShotResult(bool(deflected), dict(self.first), self.arm_contact, self.before_plane, self.arm_dv.copy(),
                          self.closest, self.closest_t, self.closest_part, self.landed, self.passed, self.frontal_y,
                          self.threshold, self.t, self.body.ball_position(), self.max_penetration)


# --- one shot --------------------------------------------------------------------------------------
def arm_actuators(body: Body) -> np.ndarray:
    """Ids of the arms' muscles: myo-sim's actuators (not the eyes', neck's, pupils' or lenses')."""
    skip = {int(i) for s in SIDES for i in body.eye_muscles[s]} | {int(i) for i in body.neck_muscles}
    skip |= set(body.pupil.values()) | set(body.accommodation.values())
    return np.array([i for i in range(body.model.nu) if i not in skip])


def run_shot(body: Body, shot: Shot, controller=None, settle: float = SETTLE_S, frontal_y: float | None = None,
             threshold: float = DEFLECTION_DV, ready=None) -> ShotResult:
    """Fire ``shot`` at ``body`` and simulate until the ball lands, passes the body (``BEHIND_M`` behind
    its frontal plane) or ``TAIL_S`` after the shot's flight time. The body is reset first and its passive
    arms settle for ``settle`` s. ``controller(body, t)`` (optional) is called before every step with t s
    since the launch and may set the arms' controls (:func:`arm_actuators`); without one the arms stay
    passive (zero activation). ``ready(body, t)`` (optional) is called before every step of the settle
    phase with t s since the reset (0 first) and may place and hold the arms at a ready posture; without
    one they settle passively. Raises :class:`~warp_vision.body.SimulationError` as ``body.step`` does."""
    muzzle = body.data.site_xpos[body.model.site("muzzle").id]
    if not np.allclose(muzzle, shot.muzzle, atol=1e-6):
        raise ValueError(f"shot: drawn for a muzzle at {shot.muzzle}, the body's is at {muzzle.round(3).tolist()}")
    body.reset()
    dt = body.model.opt.timestep
    if ready is None:
        body.step(int(round(settle / dt)))
    else:
        for k in range(int(round(settle / dt))):
            ready(body, k * dt)
            body.step()
    body.fire_cannon(shot.target, shot.flight_time)
    det = DeflectionDetector(body, frontal_y, threshold)
    end = shot.flight_time + TAIL_S
    while det.t < end and not det.landed and not det.passed:
        if controller is not None:
            controller(body, det.t)
        body.step()
        det.update()
    return det.result()
