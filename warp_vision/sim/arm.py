"""Arm motor control the body learns from itself: postures the arm's muscles hold, and the arm's nets.

Each arm of myo-sim's ``myoarms`` has 38 hinge joints and 63 Hill-type muscles. Ten shoulder-girdle joints
(clavicle, scapula and their "phantom" frames) and ``shoulder1_r2`` follow the shoulder's elevation and
elevation plane through MuJoCo joint equalities (polynomials, ``q_dep - q_dep0 = sum_k c_k (q_ind - q_ind0)^k``),
so the arm's independent coordinates are the seven of :data:`MAIN_JOINTS` (elevation plane, elevation,
humeral rotation, elbow flexion, pronation-supination, wrist deviation and flexion) and the 20 of the
thumb and fingers, which every posture here keeps at one relaxed pose (:data:`FINGER_POSE`).

**Holding activations.** At a posture with zero velocities the muscles' joint torques are ``A a + tau0``
(:func:`warp_vision.sim.oculomotor.muscle_torques`, over the arm's 38 dofs). The equality constraints'
forces do no work along motions that keep the constraints, so the posture is still when the torques
projected onto the independent coordinates vanish: ``J^T (A a + tau0 + tau_passive - tau_bias) = 0`` with
``J = dq/dq_ind`` [38, 27] (1 for an independent joint, the polynomial's derivative for a dependent one).
:func:`holding_activations` solves it for the least-effort activations in [0, 1] (scipy's bounded least
squares, as for the eyes) and returns the residual (N m): a posture whose residual exceeds
``ArmDataConfig.max_residual`` is one the muscles cannot hold, and the training drops it.

**Postures.** :meth:`ArmDataConfig.sample_posture` draws the main joints uniformly inside their ranges
(the wrist in a narrower band, :data:`SAMPLE_RANGES`), applies the couplings, and keeps a posture only when
the hand is 0.2-0.6 m in front of the shoulder (world -y; where a ball flying at the body is intercepted)
and no geom of the arm touches anything (contact forces are no part of the static solve). Sample k is
drawn from its own seed (dataset seed, side, k), so chunks are solved independently and resumably.

**The hand** is myo-sim's grasp site ``S_grasp_l`` / ``S_grasp_r`` (on the trapezium, 6 cm distal of the
wrist: the palm). Its position is recorded in the world frame, which is the torso's: the scaffold is fixed
to the world (no free or torso joint), and the head turning on the neck moves neither. The body faces -y,
its left is +x, z is up; metres.

**The nets** (:mod:`warp_vision.nn.arm`, trained by ``python -m warp_vision.train arm --side left|right``,
:mod:`warp_vision.train.arm`): the posture (reflex) net maps the seven main joint angles and velocities to
the 63 activations that hold the arm there and damp its motion; the voluntary net maps (desired hand
displacement, current 63 activations, current main joint angles and velocities) to the next 63
activations, trained on transitions between held postures (:func:`reach_pairs`).

**Why feedback.** The least-effort holding activations of a posture hold it (the hand drifts by tens of
micrometres in a second for most postures), but they are a poor command for *reaching* it: with so little
co-contraction the arm has almost no stiffness, and from another posture it swings past and settles
elsewhere (how far: docs/RESULTS.md, "Figures behind the code's constants"). So what both nets learn is the static
optimisation of a torque beyond holding (:func:`demanded_torque`): a saturating spring toward the goal
posture's joints and a damper, which, solved exactly on the body every 10 ms, reaches to a few cm. The
nets learn it from each posture's torque balance (A, b, stored with the dataset) without solving it per
sample. :func:`evaluate_on_body` measures the nets and both teachers on the body.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass

import mujoco
import numpy as np
import torch

from warp_vision.body import SIDES, Body, SimulationError
from warp_vision.sim.oculomotor import least_effort, muscle_torques

#: The independent joints of an arm that the postures vary (myo-sim's names without the side suffix).
MAIN_JOINTS = ("elv_angle", "shoulder_elv", "shoulder_rot", "elbow_flexion", "pro_sup", "deviation", "flexion")
#: rad: where the main joints are drawn from (inside myo-sim's ranges, 0.05 rad off the limits; the elevation
#: stops at 2.6 rad, the wrist in a narrow band: its angles barely move the hand and would only add redundancy).
SAMPLE_RANGES = {"elv_angle": (-1.0, 2.2), "shoulder_elv": (0.05, 2.6), "shoulder_rot": (-1.5, 2.0),
                 "elbow_flexion": (0.05, 2.2), "pro_sup": (-1.2, 1.2), "deviation": (-0.1, 0.3), "flexion": (-0.4, 0.4)}
#: rad: the relaxed hand every posture keeps: fingers' MCP, PIP and DIP flexion, thumb straight.
FINGER_POSE = {"mcp": 0.3, "pm": 0.3, "md": 0.2}
#: The hand point: myo-sim's grasp site (in the palm).
HAND_SITE = "S_grasp"
#: Effort weight of the holding solve: small next to the torque residual (N m), so a posture the muscles
#: can hold is held exactly and the effort only picks the least-effort activations among those that do.
EFFORT = 1e-6
#: m: the hand's distance in front of the shoulder (along -y) where postures are drawn.
FRONT_M = (0.2, 0.6)
#: The generator's version: bump it when the postures or their solves change.
ARM_DATA_VERSION = 2
#: s: the nets' control period in the closed loop.
CONTROL_PERIOD = 0.01
#: The torque the nets are trained to produce beyond holding (:func:`demanded_torque`): a saturating
#: spring toward the goal posture's main joints (N m/rad, saturating at SATURATION_RAD) and a damper (N m s/rad).
#: Measured with the exact static optimisation in closed loop on 30 held-out reaches (median error at 0.6 s):
#: 60 N m/rad, 0.3 rad, 8 N m s/rad: 5.9 cm; 150, 0.6, 15: 3.1 cm; 300, 0.5, 25: 2.3 cm.
STIFFNESS = 300.0
SATURATION_RAD = 0.5
DAMPING = 25.0


def demanded_torque(dq, velocities, stiffness: float = STIFFNESS, damping: float = DAMPING,
                    saturation: float = SATURATION_RAD, xp=np):
    """[..., 27] torque (N m) on the independent coordinates (main joints first, fingers zero) that moves the
    main joints by ``dq`` [..., 7] rad and damps their ``velocities`` [..., 7] rad/s: ``stiffness *
    saturation * tanh(dq / saturation) - damping * velocities``. ``xp``: numpy or torch."""
    main = stiffness * saturation * xp.tanh(dq / saturation) - damping * velocities
    zeros = xp.zeros(main.shape[:-1] + (20,), dtype=main.dtype) if xp is np else main.new_zeros(main.shape[:-1] + (20,))
    return xp.concatenate([main, zeros], -1) if xp is np else xp.cat([main, zeros], -1)


def _suffix(side: str) -> str:
    if side not in SIDES:
        raise ValueError(f"side: expected one of {SIDES}, got {side!r}")
    return "_l" if side == "left" else "_r"


class Arm:
    """One arm of the body: its muscles, joints, couplings, hand site and shoulder.

    ``actuators`` [63] (muscle ids), ``joints`` [38] (every hinge of the arm), ``main`` [7] and
    ``fingers`` [20] (the independent joints), ``dofs`` [38], ``qadr`` [38] (qpos addresses of
    ``joints``), ``couplings`` (dependent joint, master joint, polynomial coefficients)."""

    def __init__(self, body: Body, side: str):
        from warp_vision.sim.cannon import arm_actuators

        suf = _suffix(side)
        m = body.model
        self.body, self.side, self.model = body, side, m
        names = {int(a): m.actuator(int(a)).name for a in arm_actuators(body)}
        left = [a for a, n in names.items() if n.endswith("_l")]
        self.actuators = np.array(left if side == "left" else [a for a in names if a not in left])
        if len(self.actuators) != 63:
            raise ValueError(f"{side} arm: expected 63 muscles, found {len(self.actuators)}")
        self.actadr = m.actuator_actadr[self.actuators]
        root = m.body(f"myoarm{suf}_root").id

        def under(b: int) -> bool:
            while b > 0:
                if b == root:
                    return True
                b = int(m.body_parentid[b])
            return False

        self.joints = np.array([j for j in range(m.njnt) if under(int(m.jnt_bodyid[j]))])
        self.qadr = m.jnt_qposadr[self.joints]
        self.dofs = m.jnt_dofadr[self.joints]
        self.main = np.array([m.joint(f"{n}{suf}").id for n in MAIN_JOINTS])
        self.couplings = []
        for e in range(m.neq):
            if m.eq_type[e] == mujoco.mjtEq.mjEQ_JOINT and int(m.eq_obj1id[e]) in set(self.joints.tolist()):
                self.couplings.append((int(m.eq_obj1id[e]), int(m.eq_obj2id[e]), m.eq_data[e][:5].copy()))
        dep = {c[0] for c in self.couplings}
        self.fingers = np.array([j for j in self.joints if j not in dep and j not in set(self.main.tolist())])
        self.independent = np.concatenate([self.main, self.fingers])
        self.hand_site = m.site(f"{HAND_SITE}{suf}").id
        self.shoulder_body = m.body(f"humerus{suf}").id
        self.geoms = np.array([g for g in range(m.ngeom) if under(int(m.geom_bodyid[g]))])
        self.finger_q = np.array([self._finger_angle(m.joint(int(j)).name) for j in self.fingers])
        lo, hi = m.jnt_range[self.main].T
        self.main_range = np.stack([lo, hi], 1)

    @staticmethod
    def _finger_angle(name: str) -> float:
        for key, v in FINGER_POSE.items():
            if name.startswith(key) and "flexion" in name:
                return v
        return 0.0

    def qpos(self, angles, base=None) -> np.ndarray:
        """The body's qpos (``base``, default the model's qpos0) with this arm's main joints at ``angles``
        [7] rad, the fingers at :data:`FINGER_POSE` and the coupled joints where their equalities put them."""
        m = self.model
        q = (m.qpos0 if base is None else base).copy()
        q[m.jnt_qposadr[self.main]] = angles
        q[m.jnt_qposadr[self.fingers]] = self.finger_q
        for dep, master, c in self.couplings:
            x = q[m.jnt_qposadr[master]] - m.qpos0[m.jnt_qposadr[master]]
            q[m.jnt_qposadr[dep]] = m.qpos0[m.jnt_qposadr[dep]] + sum(c[k] * x**k for k in range(5))
        return q

    def coupling_jacobian(self, q) -> np.ndarray:
        """J = dq_arm/dq_independent [38, 27] at qpos ``q`` (rows in ``joints`` order, columns ``independent``)."""
        m = self.model
        row = {int(j): r for r, j in enumerate(self.joints)}
        col = {int(j): c for c, j in enumerate(self.independent)}
        J = np.zeros((len(self.joints), len(self.independent)))
        for j, c in col.items():
            J[row[j], c] = 1.0
        for dep, master, coef in self.couplings:
            x = q[m.jnt_qposadr[master]] - m.qpos0[m.jnt_qposadr[master]]
            J[row[dep], col[master]] = sum(k * coef[k] * x ** (k - 1) for k in range(1, 5))
        return J

    def hand(self, data: mujoco.MjData) -> np.ndarray:
        """The hand point (the grasp site) in the world (= torso) frame, m."""
        return data.site_xpos[self.hand_site].copy()

    def shoulder(self, data: mujoco.MjData) -> np.ndarray:
        """The shoulder (the humerus body's origin, the glenohumeral centre) in the world frame, m."""
        return data.xpos[self.shoulder_body].copy()

    def angles(self, data: mujoco.MjData) -> np.ndarray:
        """The main joints' angles [7] rad."""
        return data.qpos[self.model.jnt_qposadr[self.main]].copy()

    def velocities(self, data: mujoco.MjData) -> np.ndarray:
        """The main joints' velocities [7] rad/s."""
        return data.qvel[self.model.jnt_dofadr[self.main]].copy()

    def touching(self, data: mujoco.MjData) -> bool:
        """Whether any geom of this arm is in contact (after ``mj_forward`` or ``mj_collision``)."""
        g = set(self.geoms.tolist())
        return any(int(data.contact.geom1[i]) in g or int(data.contact.geom2[i]) in g for i in range(data.ncon))


def projected_torques(arm: Arm, q, data: mujoco.MjData | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(A [27, 63], b [27]) at qpos ``q`` with zero velocities: the arm is still when ``A a = b``. A: each
    muscle's torque at full activation beyond its passive one, on the independent coordinates (N m per unit
    activation); b: the torque the muscles must supply there (gravity minus passive forces, N m)."""
    A, tau0, rest = muscle_torques(arm.body, arm.actuators, arm.dofs, q, data)
    J = arm.coupling_jacobian(q)
    return J.T @ A, -J.T @ (tau0 + rest)


def holding_activations(arm: Arm, q, effort: float = EFFORT, data: mujoco.MjData | None = None,
                        tone: float = 0.0) -> tuple[np.ndarray, float]:
    """Least-effort activations [63] in [0, 1] that hold ``arm`` still at qpos ``q`` against gravity, the
    passive forces and the couplings, and the residual torque norm (N m) over the 27 independent coordinates."""
    return least_effort(*projected_torques(arm, q, data), effort, tone)


@dataclass
class ArmDataConfig:
    """The static-optimisation dataset of one arm: postures with the hand in front and their holding activations."""

    side: str = "left"
    postures: int = 4000  # postures whose holding activations are solved
    seed: int = 0
    chunk_size: int = 500

    def validate(self) -> None:
        _suffix(self.side)
        if self.postures < 8 or self.chunk_size < 1:
            raise ValueError(f"postures: expected at least 8, got {self.postures}")

    def manifest(self) -> dict:
        return {"generator": "arm_holding", "generator_version": ARM_DATA_VERSION, "main_joints": list(MAIN_JOINTS),
                "sample_ranges": {k: list(v) for k, v in SAMPLE_RANGES.items()}, "finger_pose": FINGER_POSE,
                "front_m": list(FRONT_M), "hand_site": HAND_SITE, "effort": EFFORT, **asdict(self)}

    def key(self) -> str:
        """A short hash of the config (dataset cache directory names)."""
        return hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode()).hexdigest()[:12]

    def sample_posture(self, arm: Arm, k: int, data: mujoco.MjData, tries: int = 2000) -> np.ndarray:
        """Posture ``k``'s qpos: main angles drawn from :data:`SAMPLE_RANGES` (seeded by (seed, side, k)) until
        the hand is :data:`FRONT_M` in front of the shoulder and the arm touches nothing."""
        rng = np.random.default_rng([self.seed, SIDES.index(self.side), k])
        lo, hi = np.array([SAMPLE_RANGES[n] for n in MAIN_JOINTS]).T
        m = arm.model
        for _ in range(tries):
            q = arm.qpos(rng.uniform(lo, hi))
            data.qpos[:] = q
            mujoco.mj_kinematics(m, data)
            front = arm.shoulder(data)[1] - arm.hand(data)[1]
            if not FRONT_M[0] <= front <= FRONT_M[1]:
                continue
            mujoco.mj_comPos(m, data)
            mujoco.mj_collision(m, data)
            if not arm.touching(data):
                return q
        raise RuntimeError(f"posture {k}: no posture with the hand in front in {tries} draws")


def solve_postures(arm: Arm, cfg: ArmDataConfig, r: range) -> dict:
    """Postures ``r`` of ``cfg``: fields ``angles`` [7], ``qpos`` [38] (the arm's joints), ``act`` [63],
    ``hand`` [3] (m, world), ``residual`` (N m), and the posture's static torque balance ``torque_A`` [27, 63],
    ``torque_b`` [27] (:func:`projected_torques`: the nets' activations are scored by ``|A a - b|``)."""
    d = mujoco.MjData(arm.model)
    n = len(r)
    out = {"angles": np.empty((n, 7)), "qpos": np.empty((n, len(arm.joints))), "act": np.empty((n, 63)),
           "hand": np.empty((n, 3)), "residual": np.empty(n)}
    out["torque_A"], out["torque_b"] = np.empty((n, 27, 63), np.float32), np.empty((n, 27), np.float32)
    for i, k in enumerate(r):
        q = cfg.sample_posture(arm, k, d)
        Ap, bp = projected_torques(arm, q, d)
        out["act"][i], out["residual"][i] = least_effort(Ap, bp, EFFORT)
        out["torque_A"][i], out["torque_b"][i] = Ap, bp
        d.qpos[:] = q
        mujoco.mj_kinematics(arm.model, d)
        out["angles"][i], out["qpos"][i], out["hand"][i] = q[arm.model.jnt_qposadr[arm.main]], q[arm.qadr], arm.hand(d)
    return out


def synthesize_arm(out_dir, cfg: ArmDataConfig, shard=(0, 1), progress: bool = True, log=print,
                   body: Body | None = None):
    """Solve the holding activations of ``cfg``'s postures into a chunked store in ``out_dir`` (resuming
    what is there); fields as :func:`solve_postures`. Returns the store."""
    from warp_vision.data.store import ChunkedStore
    from warp_vision.data.synth import pending, render_missing

    cfg.validate()
    body_arm_joints = 38
    fields = {"angles": ((7,), "float64"), "qpos": ((body_arm_joints,), "float64"), "act": ((63,), "float64"),
              "hand": ((3,), "float64"), "residual": ((), "float64"), "torque_A": ((27, 63), "float32"),
              "torque_b": ((27,), "float32")}
    store = ChunkedStore.create_or_resume(out_dir, cfg.manifest(), cfg.postures, cfg.chunk_size, fields,
                                          shard=tuple(shard))
    todo, mine = pending(store)
    if todo:
        log(f"solving the holding activations of {todo:,} of {mine:,} postures ({cfg.side} arm) into {out_dir}")
        arm = Arm(body or Body(), cfg.side)
        render_missing(store, lambda r: solve_postures(arm, cfg, r), batch=50, progress=progress, log=log,
                       what="postures")
    return store


def reach_pairs(idx: np.ndarray, n: int, rng, hand: np.ndarray, angles: np.ndarray, k: int = 12,
                near_m: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """``n`` (current, next) posture index pairs among ``idx`` for the voluntary net.

    A hand position has many postures (seven joints, three coordinates); the pairs resolve the redundancy
    by the least joint motion: for a start i and a goal drawn as another posture's hand, the next posture
    is, of the ``k`` postures whose hands are nearest that goal (i excluded), the one whose main joints
    are nearest i's. Of the goals, a tenth are i itself (hold still), three tenths lie within ``near_m`` of i's hand
    (small corrections) and the rest anywhere (reaches)."""
    from scipy.spatial import cKDTree

    idx = np.asarray(idx)
    tree = cKDTree(hand[idx])
    i = rng.choice(idx, n)
    goal = hand[rng.choice(idx, n)]
    near = rng.uniform(size=n) < 0.3
    step = rng.normal(size=(n, 3))
    step *= (near_m * rng.uniform(size=(n, 1)) ** (1 / 3)) / np.linalg.norm(step, axis=1, keepdims=True)
    goal[near] = hand[i[near]] + step[near]
    kk = min(k, len(idx))
    _, nb = tree.query(goal, kk)
    nb = idx[np.asarray(nb).reshape(n, kk)]
    joint_dist = np.linalg.norm(angles[nb] - angles[i][:, None], axis=-1)
    joint_dist[nb == i[:, None]] = np.inf  # a move goes elsewhere (unless every candidate is i itself)
    j = nb[np.arange(n), joint_dist.argmin(1)]
    same = rng.uniform(size=n) < 0.1
    j[same] = i[same]
    return i, j


# --------------------------------------------------------------------------------------------------
# on the body


def hold_start(body: Body, arm: Arm, qpos_arm, act) -> None:
    """Reset ``body`` and put ``arm`` at its joints' ``qpos_arm`` [38], at rest, its muscles' activations and
    controls at ``act`` [63] (as if held there)."""
    body.reset()
    d = body.data
    d.qpos[arm.qadr] = qpos_arm
    d.act[arm.actadr] = act
    d.ctrl[arm.actuators] = act
    mujoco.mj_forward(body.model, d)


def run_arm(body: Body, arm: Arm, seconds_marks, controller=None) -> np.ndarray:
    """Step ``body`` until each time of ``seconds_marks`` (s, increasing) and return the hand there [len, 3];
    ``controller(t)`` (optional) is called every :data:`CONTROL_PERIOD` before stepping and may set controls.
    A simulation failure leaves NaN for the marks not reached."""
    dt = body.model.opt.timestep
    per = int(round(CONTROL_PERIOD / dt))
    out = np.full((len(seconds_marks), 3), np.nan)
    steps = 0
    try:
        for k, t in enumerate(seconds_marks):
            target = int(round(t / dt))
            while steps < target:
                if controller is not None and steps % per == 0:
                    controller(steps * dt)
                n = min(target - steps, per - steps % per)
                body.step(n)
                steps += n
            out[k] = arm.hand(body.data)
    except SimulationError:
        pass
    return out


def _stats(x: np.ndarray, name: str) -> dict:
    """Median and 90th percentile of distances ``x`` (a failed simulation counts as 10 m; none: None)."""
    if not len(x):
        return {f"{name}_median_m": None, f"{name}_p90_m": None}
    x = np.where(np.isfinite(x), x, 10.0)
    return {f"{name}_median_m": float(np.median(x)), f"{name}_p90_m": float(np.percentile(x, 90))}


def evaluate_on_body(net, body: Body, side: str, data: dict, held_out: np.ndarray, n: int = 60, seed: int = 7,
                     teacher_feedback: bool = True, gain: float = 1.0, modes=None, hold: bool = True,
                     torque: dict | None = None) -> dict:
    """Held-out accuracy of the arm's nets on the body (metres). Every run starts at rest at a held-out
    posture with its muscles at the activations that hold it.

    - reach: toward the hand of another held-out posture j (:func:`reach_pairs` among the held-out
      postures, moves of more than 5 cm), the hand's distance to the target after 0.3 s and 0.6 s, under
      the voluntary net in closed loop (every 10 ms, on the remaining displacement from the true hand, the
      true joint angles and velocities, and as its "current activations" the posture net's holding
      activations for the current angles: the efference copy of the hold command, which is what it was
      trained on; the muscles' true activation state, which carries the last command's drive, makes it
      reach far worse; the displacement times ``gain``) and in open loop (its output at the start, applied throughout);
    - the teachers: the exact holding activations of j applied throughout (open loop), and, with
      ``teacher_feedback``, the exact static optimisation of the torque the nets learn (holding plus
      :func:`demanded_torque` toward j's joints, with ``torque``'s stiffness, damping and saturation: those
      the nets were trained with) solved on the body every 10 ms;
    - posture hold: the posture net in closed loop (every 10 ms from the true joint angles and
      velocities); the hand's drift after 0.3, 0.6 and 1 s; and the same under the exact holding activations."""
    arm = Arm(body, side)
    scratch = mujoco.MjData(body.model)
    rng = np.random.default_rng(seed)
    te = np.asarray(held_out)
    hand, angles, qpos, act = data["hand"], data["angles"], data["qpos"], data["act"]
    i, j = reach_pairs(te, 4 * n, rng, hand, angles)
    dist = np.linalg.norm(hand[j] - hand[i], axis=1)
    keep = np.nonzero(dist > 0.05)[0][:n]  # reaches, not corrections (any move where the held-out set is tiny)
    keep = keep if len(keep) else np.nonzero(dist > 0)[0][:n]
    i, j = i[keep], j[keep]
    marks = (0.3, 0.6)

    def reach(k, mode):
        hold_start(body, arm, qpos[i[k]], act[i[k]])
        control = _reach_control(net, arm, body.data, scratch, data, i[k], j[k], mode, gain, torque)
        return np.linalg.norm(run_arm(body, arm, marks, control) - hand[j[k]], axis=1)

    out = {"reach_pairs": int(len(i)), "reach_distance_median_m": float(np.median(dist[keep])) if len(keep) else None}
    names = {"closed": "reach_closed_loop", "open": "reach_open_loop", "teacher_hold": "reach_teacher_hold",
             "teacher_feedback": "reach_teacher_feedback"}
    for mode in modes or (names if teacher_feedback else ("closed", "open", "teacher_hold")):
        e = np.array([reach(k, mode) for k in range(len(i))]).reshape(-1, len(marks))
        for c, t in enumerate(marks):
            out.update(_stats(e[:, c], f"{names[mode]}_error_{int(t * 1000)}ms"))
    hold_marks = (0.3, 0.6, 1.0)
    starts = rng.choice(te, min(n, len(te)), replace=False)
    for mode in ("posture_net", "teacher") if hold else ():
        drift = []
        for s in starts:
            hold_start(body, arm, qpos[s], act[s])
            control = _hold_control(net, arm, body.data, act[s], mode)
            drift.append(np.linalg.norm(run_arm(body, arm, hold_marks, control) - hand[s], axis=1))
        drift = np.array(drift)
        name = "hold_posture_net" if mode == "posture_net" else "hold_teacher"
        for c, t in enumerate(hold_marks):
            out.update(_stats(drift[:, c], f"{name}_drift_{int(t * 1000)}ms"))
    out["hold_postures"] = int(len(starts))
    return out


def _f32(x) -> torch.Tensor:
    """A batch of one float32 row: what the nets read."""
    return torch.as_tensor(np.asarray(x), dtype=torch.float32)[None]


def _reach_control(net, arm: Arm, d, scratch, data: dict, start: int, goal: int, mode: str, gain: float,
                   torque: dict | None):
    """The controller ``(t) -> None`` of :func:`evaluate_on_body`'s reach from posture ``start`` to ``goal``
    under ``mode`` ("closed", "open", "teacher_hold", "teacher_feedback"), setting the arm's muscles in ``d``."""
    hand, angles, act = data["hand"], data["angles"], data["act"]
    target = hand[goal]

    def control(t):
        if mode == "teacher_hold":
            a = act[goal]
        elif mode == "teacher_feedback":
            Ap, bp = projected_torques(arm, d.qpos.copy(), scratch)
            a = least_effort(Ap, bp + demanded_torque(angles[goal] - arm.angles(d), arm.velocities(d),
                                                      **(torque or {})), EFFORT)[0]
        elif mode == "open" and t > 0:
            return
        elif mode == "open":
            with torch.no_grad():
                a = net.voluntary(_f32(target - hand[start]), _f32(act[start]), _f32(angles[start]))[0].double().numpy()
        else:
            with torch.no_grad():
                q = _f32(arm.angles(d))
                a = net.voluntary(_f32(gain * (target - arm.hand(d))), net.posture(q), q,
                                  _f32(arm.velocities(d)))[0].double().numpy()
        d.ctrl[arm.actuators] = np.clip(a, 0, 1)

    return control


def _hold_control(net, arm: Arm, d, act_s, mode: str):
    """The controller ``(t) -> None`` of :func:`evaluate_on_body`'s hold: the posture net in closed loop, or
    (``mode`` "teacher") the exact holding activations ``act_s`` throughout."""
    def control(t):
        if mode == "teacher":
            a = act_s
        else:
            with torch.no_grad():
                a = net.posture(_f32(arm.angles(d)), _f32(arm.velocities(d)))[0].double().numpy()
        d.ctrl[arm.actuators] = np.clip(a, 0, 1)

    return control


def load_arm(run_dir, side: str | None = None):
    """The arm's nets (:class:`warp_vision.nn.arm.ArmNets`) from a run of ``python -m warp_vision.train arm``; with
    ``side``, refused unless they are that arm's."""
    from warp_vision.nn.trained import load_net

    return load_net(run_dir, expect={"task": "arm", "side": side})[0]
