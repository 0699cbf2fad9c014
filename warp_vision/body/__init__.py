"""The virtual human's body in MuJoCo, assembled with ``mujoco.MjSpec`` from parts.

- myo-sim's ``myoarms``: a passive anatomical torso scaffold (pelvis, spine, ribcage, skull) with two
  muscle-driven arms (63 Hill-type muscles each). The pelvis is fixed and sits on a stool (the paper's
  Fig. 8 set-up).
- A head on a neck of three hinges (yaw, pitch, roll about the skull base), each moved by an
  antagonistic pair of Hill-type muscles on fixed tendons (moment arm ``NECK_MOMENT_ARM``), with passive
  ligament stiffness and damping.
- Two eyes in the skull's orbits, 63 mm apart: 12 mm spheres of 7.5 g on ball joints with orbital
  tissue stiffness and damping, each turned by six Hill-type muscles on spatial tendons that wrap the
  globe: the four recti from the annulus of Zinn behind the eye, the superior oblique through a
  trochlea at the upper nasal orbital rim, the inferior oblique from the nasal orbital floor (see
  :data:`~warp_vision.body.spec.EYE_MUSCLES`). Each eye also has an iris and a lens, plants with human dynamics
  (:mod:`warp_vision.eye.plants`: a latency, then a first-order movement): their states, the pupil
  diameter (mm) and the accommodation (dioptres), are the eye's optical state. Two force-free MuJoCo
  actuators per eye mirror them (``ctrl`` = ``act`` = the plant's state), for viewers and state dumps.
- A cannon (a static barrel) and a ball on a free joint that it launches. The ball bounces off the floor
  and, with ``BodyConfig.ball_contacts``, off the arms (hands, forearms, upper arms), torso and head:
  myo-sim's collision geoms (see :data:`~warp_vision.body.spec.BALL_SOLREF` for the contact's settings).

Frames: world +z up (docs/ARCHITECTURE.md); the body faces -y; its left is +x. At rest each eye's body
frame is the eye frame of docs/ARCHITECTURE.md (+z the optical axis, +y up, +x = +y cross +z = the body's
left), so the ball joint's quaternion is the eye-in-head rotation. Gaze angles (yaw, pitch) follow the
foveation data (:mod:`warp_vision.frames`): yaw = atan2(x, z) toward +x, pitch = atan2(y, hypot(x, z))
upward. SI units throughout.
"""

from __future__ import annotations

import warnings

import mujoco
import numpy as np

from warp_vision.body.meshes import ARM_PARTS, HIDDEN_FROM_EYES, geom_mesh, visible_parts
from warp_vision.body.spec import (
    BODY_CONTYPE,
    EYE_MUSCLE_NAMES,
    EYE_REST_ROTATION,
    NECK_JOINTS,
    NECK_MUSCLE_NAMES,
    SCAFFOLD_HEAD_ROTATION,
    SIDES,
    BodyConfig,
    build_spec,
    quat_from_matrix,
)
from warp_vision.eye.plants import LensPlant, PupilPlant
from warp_vision.frames import gaze_angles, torsion_angle

__all__ = ["ARM_PARTS", "BODY_CONTYPE", "Body", "BodyConfig", "EYE_MUSCLE_NAMES", "EYE_REST_ROTATION",
           "HIDDEN_FROM_EYES", "NECK_MUSCLE_NAMES", "SCAFFOLD_HEAD_ROTATION", "SIDES", "SimulationError", "build_spec",
           "geom_mesh", "quat_from_matrix", "visible_parts"]


class SimulationError(RuntimeError):
    """MuJoCo reported a warning or the state became unphysical (NaN, deep penetration)."""

class Body:
    """The compiled body and its state, with named access to eyes, muscles, head and ball.

    Each :meth:`step` advances MuJoCo and raises :class:`SimulationError` on any MuJoCo warning, a
    non-finite state or a contact deeper than ``cfg.max_penetration``.
    """

    def __init__(self, cfg: BodyConfig | None = None):
        self.cfg = cfg or BodyConfig()
        self.spec = build_spec(self.cfg)
        with warnings.catch_warnings():  # myo-sim's empty attach prefix, said again on compiling
            warnings.simplefilter("ignore", UserWarning)
            self.model = self.spec.compile()
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.eye_muscles = {s: np.array([m.actuator(f"{n}_{s}").id for n in EYE_MUSCLE_NAMES]) for s in SIDES}
        self.neck_muscles = np.array([m.actuator(n).id for n in NECK_MUSCLE_NAMES])
        self.pupil = {s: m.actuator(f"pupil_{s}").id for s in SIDES}
        self.accommodation = {s: m.actuator(f"accommodation_{s}").id for s in SIDES}
        self.eye_joint = {s: m.joint(f"eye_{s}").id for s in SIDES}
        self.eye_body = {s: m.body(f"eye_{s}").id for s in SIDES}
        self.neck_joints = np.array([m.joint(f"neck_{j}").id for j in NECK_JOINTS])
        self.head_body = m.body("head").id
        self.ball_joint = m.joint("ball").id
        self._warnings = np.zeros(len(self.data.warning), dtype=int)
        self.reset()

    # --- state ------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Rest pose, zero activations, pupils 4 mm, accommodation 1 D, ball resting on the floor behind the body."""
        mujoco.mj_resetData(self.model, self.data)
        self.plants = {s: {"pupil": PupilPlant(4.0), "lens": LensPlant(1.0)} for s in SIDES}
        self._mirror_plants()
        mujoco.mj_forward(self.model, self.data)
        self._warnings[:] = [w.number for w in self.data.warning]

    def _act(self, actuator: int) -> int:
        return int(self.model.actuator_actadr[actuator])

    @property
    def time(self) -> float:
        return float(self.data.time)

    def step(self, n: int = 1) -> None:
        """Advance ``n`` timesteps with the current controls; raise :class:`SimulationError` on trouble.
        The iris and lens plants advance by the same time, after MuJoCo (they exert no force)."""
        for _ in range(int(n)):
            mujoco.mj_step(self.model, self.data)
            self.check()
        dt = int(n) * self.model.opt.timestep
        for eye in self.plants.values():
            for plant in eye.values():
                plant.advance(dt)
        self._mirror_plants()

    def _mirror_plants(self) -> None:
        for s in SIDES:
            for act, plant in ((self.pupil[s], self.plants[s]["pupil"]),
                               (self.accommodation[s], self.plants[s]["lens"])):
                self.data.ctrl[act] = plant.state
                self.data.act[self._act(act)] = plant.state

    def check(self) -> None:
        d = self.data
        counts = d.warning.number  # one array read (a list of the 8 warning structs costs 0.1 ms a step)
        new = np.nonzero(counts > self._warnings)[0]
        self._warnings[:] = counts
        if len(new):
            names = [mujoco.mjtWarning(int(i)).name for i in new]
            raise SimulationError(f"t={d.time:.4f} s: MuJoCo warned {names} (info "
                                  f"{[d.warning[i].lastinfo for i in new]})")
        if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel)) and np.all(np.isfinite(d.act))):
            raise SimulationError(f"t={d.time:.4f} s: non-finite state")
        if d.ncon:
            depth = -d.contact.dist[: d.ncon].min()
            if depth > self.cfg.max_penetration:
                raise SimulationError(f"t={d.time:.4f} s: contact penetration {depth * 1000:.1f} mm "
                                      f"(limit {self.cfg.max_penetration * 1000:.0f} mm)")

    # --- controls ---------------------------------------------------------------------------------
    def set_eye_activations(self, side: str, a) -> None:
        """Six extraocular activations in [0, 1], in the order of :data:`EYE_MUSCLE_NAMES`."""
        self.data.ctrl[self.eye_muscles[side]] = _check_activations("eye activations", a, 6)

    def set_neck_activations(self, a) -> None:
        """Six neck activations in [0, 1], in the order of :data:`NECK_MUSCLE_NAMES`."""
        self.data.ctrl[self.neck_muscles] = _check_activations("neck activations", a, len(NECK_MUSCLE_NAMES))

    def set_intraocular(self, side: str, pupil_mm: float | None = None, accommodation_D: float | None = None) -> None:
        """Command the pupil diameter (mm) and lens accommodation (D), clipped to their ranges; the plants
        (:mod:`warp_vision.eye.plants`) follow after their latencies. NaN or inf is a
        ValueError (MuJoCo would only complain a step later)."""
        if side not in self.pupil:
            raise ValueError(f"side: expected one of {sorted(self.pupil)}, got {side!r}")
        for name, v in (("pupil_mm", pupil_mm), ("accommodation_D", accommodation_D)):
            if v is not None and (isinstance(v, bool) or not np.isfinite(np.asarray(v, dtype=np.float64)).all()):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
        if pupil_mm is not None:
            self.plants[side]["pupil"].command(float(pupil_mm))
        if accommodation_D is not None:
            self.plants[side]["lens"].command(float(accommodation_D))

    def intraocular(self, side: str) -> tuple[float, float]:
        """(pupil diameter mm, accommodation D): the eye's current optical state."""
        return (self.plants[side]["pupil"].state, self.plants[side]["lens"].state)

    # --- kinematics -------------------------------------------------------------------------------
    def pose(self, body: int) -> np.ndarray:
        """[4, 4] world-from-body transform of MuJoCo body ``body`` (an id; 0 is the world)."""
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[body].reshape(3, 3)
        T[:3, 3] = self.data.xpos[body]
        return T

    def eye_pose(self, side: str) -> np.ndarray:
        """[4, 4] world-from-eye transform (the eye frame of docs/ARCHITECTURE.md)."""
        return self.pose(self.eye_body[side])

    def head_pose(self) -> np.ndarray:
        """[4, 4] world-from-head transform, in the eye-frame convention (+z forward, +y up)."""
        T = self.pose(self.head_body)
        T[:3, :3] = T[:3, :3] @ SCAFFOLD_HEAD_ROTATION.T @ EYE_REST_ROTATION
        return T

    def eye_in_head(self, side: str) -> np.ndarray:
        """[3, 3] eye-in-head rotation (the ball joint's)."""
        q = self.data.qpos[self.model.jnt_qposadr[self.eye_joint[side]]:][:4]
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, q)
        return R.reshape(3, 3)

    def gaze_in_head(self, side: str) -> np.ndarray:
        """(yaw, pitch) of the eye in the head, radians."""
        return gaze_angles(self.eye_in_head(side)[:, 2])

    def torsion(self, side: str) -> float:
        """The eye's rotation about its line of sight beyond the Fick rotation to its gaze (rad, + = about +z)."""
        R = self.eye_in_head(side)
        yaw, pitch = gaze_angles(R[:, 2])
        return float(torsion_angle(R, yaw, pitch))

    def neck_angles(self) -> np.ndarray:
        """(yaw, pitch, roll) of the neck hinges, radians."""
        return self.data.qpos[self.model.jnt_qposadr[self.neck_joints]].copy()

    def ball_position(self) -> np.ndarray:
        return self.data.qpos[self.model.jnt_qposadr[self.ball_joint]:][:3].copy()

    def set_ball(self, position, velocity=(0.0, 0.0, 0.0)) -> None:
        """Place the ball (m) with a linear velocity (m/s) and no spin."""
        a = self.model.jnt_qposadr[self.ball_joint]
        v = self.model.jnt_dofadr[self.ball_joint]
        self.data.qpos[a:a + 3] = position
        self.data.qpos[a + 3:a + 7] = [1, 0, 0, 0]
        self.data.qvel[v:v + 3] = velocity
        self.data.qvel[v + 3:v + 6] = 0
        # the poses only (what a render or a trace reads before the next step, which recomputes the rest
        # from qpos and qvel); a whole mj_forward through the arms' tendons cost 0.3 ms a call
        mujoco.mj_kinematics(self.model, self.data)

    def fire_cannon(self, through, after: float) -> np.ndarray:
        """Launch the ball from the muzzle on the ballistic path that passes ``through`` (m) ``after``
        seconds; returns the launch velocity (m/s)."""
        if not after > 0:
            raise ValueError(f"after: expected > 0 s, got {after}")
        p0 = self.data.site_xpos[self.model.site("muzzle").id].copy()
        g = self.model.opt.gravity
        v = (np.asarray(through, float) - p0 - 0.5 * g * after**2) / after
        self.set_ball(p0, v)
        return v


def _check_activations(name: str, a, n: int) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},), got {a.shape}")
    if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
        raise ValueError(f"{name}: expected values in [0, 1], got min {a.min():.3g}, max {a.max():.3g}")
    return a
