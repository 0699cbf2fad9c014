"""Intercepting the cannon's ball with one arm: perception of the ball, an interception point on its
predicted path, and the arm's motor nets driving the hand there.

- :class:`ArmInterceptor` (made by :func:`arm_interceptor`): a controller for
  :func:`warp_vision.sim.cannon.run_shot`. Every :data:`~warp_vision.sim.arm.CONTROL_PERIOD` (10 ms) it
  (a) asks its *perception* for the ball's position and velocity: ``"oracle"`` reads the simulation's true
  state; any callable ``(body, t) -> (position [3], velocity [3])`` or None (nothing seen yet: hold) can
  stand in for it, as the limb vision nets do (:class:`warp_vision.sim.limb.LimbVision`); (b) predicts the ball's
  ballistic path under gravity (no drag, no spin: ``p(tau) = p + v tau + g tau^2 / 2``) and picks an interception point
  on it with :func:`intercept_point`; (c) feeds the arm's voluntary net (:class:`warp_vision.nn.arm.ArmNets`) the
  desired hand displacement, ``gain`` x (point - hand), as :func:`warp_vision.sim.arm.evaluate_on_body` runs it in
  closed loop (the true main joint angles and velocities, and the posture net's holding activations at the current
  angles as the "current activations"), and sets the arm's 63 muscle controls from its output. Without a reachable
  point on the path (the ball gone past, or flying wide) it holds the arm with the posture net.
  Before the launch (:meth:`ArmInterceptor.ready`, ``run_shot``'s ``ready``) it puts the arm at a *ready
  posture*: main joint angles found by :func:`ready_angles` (least squares on the arm's kinematics) that
  put the hand at ``ready_hand`` (by default :data:`READY_OFFSET` from the shoulder: the centre of the
  cannon's reach envelope, :data:`warp_vision.sim.cannon.ENVELOPE`), and holds it there with the posture
  net. The other arm stays passive (zero activation; it hangs).
  Defaults (``aim="plane"``, the plane :data:`PLANE_FRONT` in front of the shoulder, ``gain`` :data:`GAIN`)
  are the best of the variants tried on 50 held-out left shots
  (``sample_shots(50, seed=0, split="heldout", side="left")``, the default left arm nets; the figures:
  docs/RESULTS.md, "Figures behind the code's constants").
- :func:`intercept_point`: where on the predicted path to put the hand. ``aim="plane"``: where the path
  crosses a frontal plane (y = const; the controller's: :data:`PLANE_FRONT` in front of the shoulder), if
  that point is within reach;
  ``"closest"``: the reachable path point nearest the current hand; ``"soonest"``: the earliest reachable
  path point the hand can get to in time under a crude model of the arm (a latency plus a constant hand
  speed). "Reachable": within ``reach_fraction`` x :data:`~warp_vision.sim.cannon.ARM_REACH` of the
  shoulder and at least ``min_front`` m in front of it. ``"plane"`` falls back to ``"closest"`` when the
  crossing is out of reach.
- :func:`intercept_stats`: runs shots with a controller (or passive arms) and returns each shot's result
  and the aggregates: the deflected fraction, the median closest approach of the misses, by launch speed.

Frames and units: the world frame of :mod:`warp_vision.body`, which is the torso's (the body faces -y, its
left is +x, +z up); the voluntary net was trained on hand displacements in that frame. SI units: m, s,
m/s, rad; activations in [0, 1].
"""

from __future__ import annotations

import time

import mujoco
import numpy as np
import torch
from scipy.optimize import least_squares

from warp_vision.body import SIDES, Body
from warp_vision.sim.arm import CONTROL_PERIOD, MAIN_JOINTS, SAMPLE_RANGES, Arm
from warp_vision.sim.cannon import ARM_REACH, GRAVITY, SETTLE_S, SHOULDER_LEFT, run_shot, shoulder

#: Perceptions :func:`arm_interceptor` knows by name (any callable ``(body, t) -> (position, velocity)`` also works).
PERCEPTIONS = ("oracle",)
#: Ways of choosing the interception point (:func:`intercept_point`).
AIMS = ("plane", "closest", "soonest")
#: m: the ready hand relative to the shoulder, (outward, forward, up): the centre of the cannon's envelope
#: (:data:`warp_vision.sim.cannon.ENVELOPE`: outward -0.15..0.25, forward 0.25..0.5, up -0.45..0.2).
READY_OFFSET = (0.05, 0.375, -0.125)
#: Fraction of ARM_REACH the interception point may lie from the shoulder (the envelope's targets lie within 0.85).
REACH_FRACTION = 0.85
#: m: the interception point lies at least this far in front of the shoulder (-y).
MIN_FRONT = 0.15
#: s: how far ahead the path is predicted, and its sampling step.
HORIZON_S = 0.8
PATH_STEP_S = 0.002
#: m: the default plane of ``aim="plane"``: this far in front of the hanging shoulder (the envelope's
#: nearest targets): it leaves the arm more time to reach than the ready hand's plane, 0.375 m, and deflects
#: more shots (docs/RESULTS.md, "Figures behind the code's constants").
PLANE_FRONT = 0.25
#: The default displacement gain: the net is asked for twice the remaining displacement (at gain 1 the arm
#: is too slow for the 0.2-0.55 s flights: docs/RESULTS.md, "Figures behind the code's constants").
GAIN = 2.0
#: m: the largest displacement the voluntary net is fed (its training reaches: hands 0.2-0.6 m in front).
MAX_DISPLACEMENT = 0.6
#: "soonest": the crude arm the timing is judged with: a latency (s) and a hand speed (m/s).
ARM_LATENCY_S = 0.1
ARM_SPEED = 1.5


def _mirror(offset, side: str) -> np.ndarray:
    x, f, u = offset
    return np.array([x if side == "left" else -x, -f, u])


def ballistic_path(position, velocity, taus, gravity=GRAVITY) -> np.ndarray:
    """[len(taus), 3] the ball's centre (m) ``taus`` s ahead from ``position`` (m) with ``velocity`` (m/s)."""
    taus = np.asarray(taus, float)[:, None]
    return np.asarray(position, float) + np.asarray(velocity, float) * taus + 0.5 * np.asarray(gravity) * taus**2


def intercept_point(position, velocity, shoulder, hand, aim: str = "plane", plane_y: float | None = None,
                    reach_fraction: float = REACH_FRACTION, min_front: float = MIN_FRONT,
                    horizon: float = HORIZON_S, step: float = PATH_STEP_S, latency: float = ARM_LATENCY_S,
                    hand_speed: float = ARM_SPEED) -> tuple[np.ndarray, float] | None:
    """(point [3] m, tau s) on the ball's predicted path where the hand should meet it, or None when no
    point of the next ``horizon`` s is reachable (within ``reach_fraction`` x ARM_REACH of ``shoulder`` and
    ``min_front`` m in front of it). ``aim`` as the module docstring says; ``plane_y`` (m, world y) the
    plane of ``"plane"`` (default: the hand's y)."""
    if aim not in AIMS:
        raise ValueError(f"aim: expected one of {AIMS}, got {aim!r}")
    taus = np.arange(0.0, horizon + step / 2, step)
    path = ballistic_path(position, velocity, taus)
    shoulder, hand = np.asarray(shoulder, float), np.asarray(hand, float)
    ok = (np.linalg.norm(path - shoulder,
                         axis=1) <= reach_fraction * ARM_REACH) & (path[:, 1] <= shoulder[1] - min_front)
    if not ok.any():
        return None
    if aim == "plane":
        y = hand[1] if plane_y is None else float(plane_y)
        ahead = path[:, 1] - y
        cross = np.nonzero((ahead[:-1] < 0) & (ahead[1:] >= 0))[0]  # the ball flies toward +y
        if len(cross):
            k = int(cross[0])
            w = -ahead[k] / (ahead[k + 1] - ahead[k])
            tau = float(taus[k] + w * step)
            p = ballistic_path(position, velocity, [tau])[0]
            if ok[k] or ok[k + 1]:
                return p, tau
        elif ahead[0] == 0 and ok[0]:
            return path[0].copy(), 0.0
        aim = "closest"
    idx = np.nonzero(ok)[0]
    dist = np.linalg.norm(path[idx] - hand, axis=1)
    if aim == "closest":
        k = int(idx[np.argmin(dist)])
    else:  # soonest: the earliest point the hand gets to in time; else the one it misses by least
        slack = taus[idx] - (latency + dist / hand_speed)
        k = int(idx[np.argmax(slack >= 0)]) if (slack >= 0).any() else int(idx[np.argmax(slack)])
    return path[k].copy(), float(taus[k])


def ready_angles(arm: Arm, hand_target, data: mujoco.MjData | None = None, regularise: float = 0.02) -> np.ndarray:
    """Main joint angles [7] rad (within :data:`~warp_vision.sim.arm.SAMPLE_RANGES`) that put ``arm``'s hand
    at ``hand_target`` (m, world), found by least squares on the kinematics, with a small pull
    (``regularise`` m/rad) toward the middle of the sampled ranges so the posture is a typical one."""
    m = arm.model
    d = data if data is not None else mujoco.MjData(m)
    lo, hi = np.array([SAMPLE_RANGES[n] for n in MAIN_JOINTS]).T
    mid = (lo + hi) / 2
    target = np.asarray(hand_target, float)

    def residual(q):
        d.qpos[:] = arm.qpos(q)
        mujoco.mj_kinematics(m, d)
        return np.concatenate([arm.hand(d) - target, regularise * (q - mid)])

    best = None
    for start in (mid, np.r_[0.5, 1.2, 0.0, 1.2, 0.0, 0.1, 0.0], np.r_[0.0, 0.8, 0.5, 1.5, 0.0, 0.1, 0.0]):
        sol = least_squares(residual, np.clip(start, lo, hi), bounds=(lo, hi))
        if best is None or sol.cost < best.cost:
            best = sol
    return best.x


def oracle_perception(body: Body, t: float) -> tuple[np.ndarray, np.ndarray]:
    """The ball's true position (m) and velocity (m/s) in the world frame."""
    v = body.model.jnt_dofadr[body.ball_joint]
    return body.ball_position(), body.data.qvel[v:v + 3].copy()


class OffsetOracle:
    """The true ball state with a fixed position error: ``error_m`` metres in a direction drawn per shot
    (uniform on the sphere, from ``seed`` and the shot's count), the velocity true. A perception with the
    accuracy of an imperfect limb vision net, to measure how accurate the nets must be for the
    interception (``python -m warp_vision.sim intercept --shots N --perception-error-cm ...``). Call
    :meth:`new_shot` before each shot (:func:`intercept_stats` does, through the controller's ``ready``)."""

    def __init__(self, error_m: float, seed: int = 0):
        if not (np.isfinite(error_m) and error_m >= 0):
            raise ValueError(f"error_m: expected a finite distance >= 0 m, got {error_m}")
        self.error_m, self._rng = float(error_m), np.random.default_rng([17, seed])
        self.offset = np.zeros(3)
        self.new_shot()

    def new_shot(self) -> None:
        v = self._rng.normal(size=3)
        self.offset = self.error_m * v / np.linalg.norm(v)

    def __call__(self, body: Body, t: float) -> tuple[np.ndarray, np.ndarray]:
        p, v = oracle_perception(body, t)
        return p + self.offset, v


class ArmInterceptor:
    """A :func:`~warp_vision.sim.cannon.run_shot` controller that intercepts the ball with one arm (see
    the module docstring); :meth:`ready` is ``run_shot``'s ``ready``. After a shot, ``log`` holds one
    (t s, interception point [3] or None, hand [3]) per control update."""

    def __init__(self, body: Body, nets, side: str, perception="oracle", aim: str = "plane", gain: float = GAIN,
                 ready_hand=None, plane_y: float | None = None, reach_fraction: float = REACH_FRACTION,
                 min_front: float = MIN_FRONT, max_displacement: float = MAX_DISPLACEMENT,
                 period: float = CONTROL_PERIOD, hold_before_launch: bool = True):
        if side not in SIDES:
            raise ValueError(f"side: expected one of {SIDES}, got {side!r}")
        if isinstance(perception, str):
            if perception not in PERCEPTIONS:
                raise ValueError(f"perception: expected one of {PERCEPTIONS} or a callable, got {perception!r}")
            perception = oracle_perception
        elif not callable(perception):
            raise ValueError(f"perception: expected one of {PERCEPTIONS} or a callable, got {perception!r}")
        if aim not in AIMS:
            raise ValueError(f"aim: expected one of {AIMS}, got {aim!r}")
        if not gain > 0 or not max_displacement > 0 or not period > 0:
            raise ValueError(f"gain, max_displacement, period: expected > 0, got {gain}, {max_displacement}, {period}")
        self.body, self.nets, self.side, self.perceive = body, nets, side, perception
        self.aim, self.gain, self.max_displacement = aim, float(gain), float(max_displacement)
        self.reach_fraction, self.min_front = float(reach_fraction), float(min_front)
        self.arm = Arm(body, side)
        self.shoulder = shoulder(side)
        self.ready_hand = self.shoulder + _mirror(READY_OFFSET,
                                                  side) if ready_hand is None else np.asarray(ready_hand, float)
        self.plane_y = float(self.shoulder[1] - PLANE_FRONT) if plane_y is None else float(plane_y)
        self._scratch = mujoco.MjData(body.model)
        self.ready_q = ready_angles(self.arm, self.ready_hand, self._scratch)
        dt = body.model.opt.timestep
        self._per = max(1, int(round(period / dt)))
        self._dt = dt
        self.hold_before_launch = hold_before_launch
        self.log: list = []

    # --- nets --------------------------------------------------------------------------------------
    @staticmethod
    def _f32(x) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x), dtype=torch.float32)[None]

    def _hold(self) -> np.ndarray:
        d = self.body.data
        with torch.no_grad():
            a = self.nets.posture(self._f32(self.arm.angles(d)), self._f32(self.arm.velocities(d)))
        return a[0].double().numpy()

    def _reach(self, displacement) -> np.ndarray:
        d = self.body.data
        with torch.no_grad():
            q = self._f32(self.arm.angles(d))
            a = self.nets.voluntary(self._f32(displacement), self.nets.posture(q), q, self._f32(self.arm.velocities(d)))
        return a[0].double().numpy()

    def _set(self, a) -> None:
        self.body.data.ctrl[self.arm.actuators] = np.clip(a, 0.0, 1.0)

    # --- run_shot hooks ----------------------------------------------------------------------------
    def ready(self, body: Body, t: float) -> None:
        """Before the launch (``t`` s since the reset): at t = 0 put the arm at the ready posture, at rest,
        its muscles at the posture net's holding activations; then hold it there with the posture net."""
        k = int(round(t / self._dt))
        if k == 0:
            self.log = []
            getattr(self.perceive, "new_shot", lambda: None)()  # e.g. an OffsetOracle's error for this shot
            d = body.data
            q = self.arm.qpos(self.ready_q, d.qpos)
            d.qpos[self.arm.qadr] = q[self.arm.qadr]
            d.qvel[self.arm.dofs] = 0.0
            mujoco.mj_forward(body.model, d)
            a = np.clip(self._hold(), 0, 1)
            d.act[self.arm.actadr] = a
            self._set(a)
        elif self.hold_before_launch and k % self._per == 0:
            self._set(self._hold())

    def __call__(self, body: Body, t: float) -> None:
        if int(round(t / self._dt)) % self._per:
            return
        seen = self.perceive(body, t)
        hand = self.arm.hand(body.data)
        if seen is None:  # nothing perceived yet: hold
            self._set(self._hold())
            self.log.append((t, None, hand))
            return
        position, velocity = seen
        hit = intercept_point(position, velocity, self.arm.shoulder(body.data), hand, self.aim, self.plane_y,
                              self.reach_fraction, self.min_front)
        if hit is None:
            self._set(self._hold())
            self.log.append((t, None, hand))
            return
        point = hit[0]
        disp = self.gain * (point - hand)
        n = np.linalg.norm(disp)
        if n > self.max_displacement:
            disp *= self.max_displacement / n
        self._set(self._reach(disp))
        self.log.append((t, point, hand))


def arm_interceptor(body: Body, nets, side: str, perception="oracle", **kw) -> ArmInterceptor:
    """The interception controller of ``side``'s arm driven by ``nets`` (:class:`~warp_vision.nn.arm.ArmNets`,
    e.g. :func:`warp_vision.sim.arm.load_arm`), with ``perception`` ("oracle" or a callable ``(body, t) ->
    (position, velocity)``); keywords as :class:`ArmInterceptor`. ValueError on an unknown side,
    perception or aim."""
    return ArmInterceptor(body, nets, side, perception, **kw)


# --------------------------------------------------------------------------------------------------
SPEED_BINS = (6.0, 8.0, 10.0, 12.0)


def _summary(rows: list[dict]) -> dict:
    miss = [r["closest"] for r in rows if not r["deflected"]]
    return {"n": len(rows), "deflected_fraction": float(np.mean([r["deflected"] for r in rows])) if rows else None,
            "median_closest_miss_m": float(np.median(miss)) if miss else None,
            "median_closest_m": float(np.median([r["closest"] for r in rows])) if rows else None}


def intercept_stats(shots, controller_factory=None, body: Body | None = None, settle: float = SETTLE_S,
                    frontal_y: float | None = SHOULDER_LEFT[1], speed_bins=SPEED_BINS, runner=None,
                    progress: bool = False, desc: str = "shots") -> dict:
    """Run ``shots`` (:func:`warp_vision.sim.cannon.run_shot`) with ``controller_factory(body)`` (a
    controller; its ``ready`` attribute, if any, is ``run_shot``'s ``ready``) or passive arms (None).
    ``frontal_y``: the detector's frontal plane (default the hanging shoulders' y, the same for every
    controller: a raised arm moves the shoulder). Returns ``{"shots": [per shot: seed, speed, flight_time,
    deflected, closest (m), arm_contact, error (a SimulationError's text or None), wall_s], **aggregate,
    "by_speed": {"6-8": aggregate, ...}, "wall_s_per_shot": mean}``; a shot whose simulation fails counts
    as a miss at 10 m. ``runner(shot) -> ShotResult`` (optional) runs each shot instead of ``run_shot``
    (e.g. :func:`run_vision_shot` in the closed loop); ``progress``: a progress bar named ``desc``."""
    from tqdm import tqdm

    from warp_vision.body import SimulationError

    if runner is None:
        body = body or Body()
        ctrl = controller_factory(body) if controller_factory is not None else None

        def runner(shot):
            return run_shot(body, shot, ctrl, settle, frontal_y, ready=getattr(ctrl, "ready", None))

    rows = []
    for shot in tqdm(shots, desc=desc, unit="shot", disable=not progress, dynamic_ncols=True):
        t0 = time.perf_counter()
        try:
            r = runner(shot)
            row = {"deflected": r.deflected, "closest": r.closest, "arm_contact": r.arm_contact, "error": None}
        except SimulationError as e:
            row = {"deflected": False, "closest": 10.0, "arm_contact": None, "error": str(e)}
        rows.append({"seed": shot.seed, "speed": shot.speed, "flight_time": shot.flight_time, **row,
                     "direction": [float(x) for x in shot.direction], "wall_s": time.perf_counter() - t0})
    out = {"shots": rows, **_summary(rows)}
    edges = list(speed_bins)
    out["by_speed"] = {
        f"{lo:g}-{hi:g}": _summary([r for r in rows if lo <= r["speed"] < hi or (hi == edges[-1] and r["speed"] == hi)])
        for lo, hi in zip(edges, edges[1:])
    }
    out["wall_s_per_shot"] = float(np.mean([r["wall_s"] for r in rows])) if rows else None
    return out


# --------------------------------------------------------------------------------------------------
# the closed loop: eyes and head track the ball, the limb vision nets see it, the arm strikes

#: s: before the launch the ball rests at the muzzle this long while the eyes find and fixate it
FIXATE_S = 0.4
#: ``sim intercept`` renders every INTERCEPT_FRAME_EVERY control periods: 50 frames a second. A fast shot
#: leaves the ranging gate after about 0.13 s of its 0.2-0.3 s flight; at 25 frames a second that is
#: four observations, too few for the ballistic fit (docs/RESULTS.md, "The arms: ...", what made the
#: difference)
INTERCEPT_FRAME_EVERY = 2


def run_vision_shot(loop, shot, interceptor: ArmInterceptor | None, vision=None, settle: float = SETTLE_S,
                    fixate: float = FIXATE_S, frontal_y: float | None = SHOULDER_LEFT[1], record=None):
    """Fire ``shot`` in the closed loop and return the deflection detector's
    :class:`~warp_vision.sim.cannon.ShotResult`.

    ``loop`` (:class:`warp_vision.sim.loop.VisuomotorLoop`) owns the body, the eyes, their foveation and
    oculomotor nets and the neck. The body is reset; for ``settle`` s the interceptor's arm goes to its
    ready posture and is held there (the other arm hangs; ``interceptor`` None: both hang); then for
    ``fixate`` s the ball is held at the muzzle while the loop runs, so the eyes find it. At the launch
    the detector starts and every control period (10 ms): the interceptor acts on its perception (its
    last state: the frame before), then the loop runs one period (renders on its visual frames, tracks,
    steps MuJoCo with the detector after every step); on a visual frame ``vision``
    (:class:`warp_vision.sim.limb.LimbVision` or :class:`~warp_vision.sim.limb.FixationVision`, or None
    when the interceptor's perception is the oracle) observes what the loop just rendered and estimated,
    with the eye poses and the hand of that moment.
    ``record(loop, detector)`` (optional) is called after every period. The loop's ``timing`` gains
    "limb_vision" (the limb nets) and "arm" (the interceptor: aim and motor nets)."""
    from warp_vision.sim.cannon import TAIL_S, DeflectionDetector
    from warp_vision.sim.loop import CONTROL_DT

    body = loop.body
    muzzle = body.data.site_xpos[body.model.site("muzzle").id]
    if not np.allclose(muzzle, shot.muzzle, atol=1e-6):
        raise ValueError(f"shot: drawn for a muzzle at {shot.muzzle}, the body's is at {muzzle.round(3).tolist()}")
    for k in ("limb_vision", "arm"):
        loop.timing.setdefault(k, 0.0)
    loop.reset(0.0)
    dt = body.model.opt.timestep
    for k in range(int(round(settle / dt))):
        if interceptor is not None:
            interceptor.ready(body, k * dt)
        body.step()
    for _ in range(int(round(fixate / CONTROL_DT))):
        body.set_ball(shot.muzzle)
        if interceptor is not None:
            interceptor.ready(body, body.time)
        loop.step()
    body.fire_cannon(shot.target, shot.flight_time)
    det = DeflectionDetector(body, frontal_y)
    if vision is not None:
        vision.reset()
    loop.substep = det.update
    end = shot.flight_time + TAIL_S
    try:
        while det.t < end and not det.landed and not det.passed:
            frame = loop.period % loop.frame_every == 0
            if frame and vision is not None:
                poses = {s: body.eye_pose(s) for s in SIDES}
                hand, t_frame = interceptor.arm.hand(body.data), det.t
            if interceptor is not None:
                t0 = time.perf_counter()
                interceptor(body, det.t)
                loop.timing["arm"] += time.perf_counter() - t0
            loop.step()
            if frame and vision is not None:
                t0 = time.perf_counter()
                vision.observe(loop, poses, hand, t_frame)
                loop.timing["limb_vision"] += time.perf_counter() - t0
            if record is not None:
                record(loop, det)
    finally:
        loop.substep = None
    return det.result()
