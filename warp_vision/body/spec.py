"""The body's MuJoCo model, assembled with ``mujoco.MjSpec``: its dimensions, muscles and contact
settings, and :func:`build_spec` (the parts and frames: :mod:`warp_vision.body`)."""


from __future__ import annotations

import contextlib
import warnings
from dataclasses import dataclass
from functools import lru_cache

import mujoco
import numpy as np

from warp_vision.eye.plants import LENS_RANGE_D, PUPIL_RANGE_MM
from warp_vision.frames import fick_rotation, gaze_angles, gaze_direction

EYE_RADIUS = 0.012  # m
EYE_MASS = 0.0075  # kg
INTEROCULAR = 0.063  # m
#: Eye centres in the world at rest with the pelvis at ``PELVIS_HEIGHT``: found in the scaffold's skull
#: mesh (the orbits' centres, 12 mm behind the orbital rim) relative to its head body.
ORBIT_HEIGHT_ABOVE_HEAD = 0.079  # m above the head body's origin (the skull base)
ORBIT_FORWARD_OF_HEAD = 0.068  # m forward (-y) of the head body's origin
PELVIS_HEIGHT = 0.62  # m: the sacrum of a person seated on a 0.5 m stool
STOOL_HEIGHT = 0.5
#: Eye plant: orbital tissue stiffness (N m / rad) and viscosity (N m s / rad) about the eye centre; the
#: time constant viscosity / stiffness is 20 ms.
EYE_STIFFNESS = 0.01
EYE_DAMPING = 2e-4
EYE_RANGE_DEG = 50.0
EYE_MUSCLE_FORCE = 1.0  # N, peak isometric force of each extraocular muscle (about 100 g)
EYE_MUSCLE_TIMECONST = (0.005, 0.02)  # s, activation and deactivation
#: Peak shortening velocity in optimal lengths per second: extraocular fibres are among the fastest; with
#: MuJoCo's default (1.5) the force-velocity curve alone took a 20 deg step 260 ms to settle within 1 deg.
EYE_MUSCLE_VMAX = 10.0
NECK_JOINTS = ("yaw", "pitch", "roll")
NECK_RANGE_DEG = {"yaw": 70.0, "pitch": 40.0, "roll": 30.0}
NECK_STIFFNESS = 2.0  # N m / rad
NECK_DAMPING = 0.4  # N m s / rad
NECK_MOMENT_ARM = 0.03  # m
NECK_MUSCLE_FORCE = 150.0  # N
NECK_MUSCLE_TIMECONST = (0.01, 0.04)
ACCOMMODATION_RANGE_D = LENS_RANGE_D
BALL_RADIUS = 0.04
BALL_MASS = 0.06
#: The ball's contacts (with ``BodyConfig.ball_contacts``). The ball has contype 0 and conaffinity 1
#: (``BODY_CONTYPE``): myo-sim's collision geoms (contype 1, conaffinity 0, so never with one another)
#: touch it; the floor does by an explicit pair with the same settings but no margin. Its priority (1, over
#: everything's 0) makes its solref, solimp, friction and condim the contact's. The settings were chosen with
#: 60 g balls shot at 3-25 m/s at a wall and at the torso, head, upper arm, forearm and hand (1 ms steps,
#: implicitfast), and what they do is in docs/RESULTS.md ("The arms: ...", "Contacts", and "Figures behind the
#: code's constants"):
#: - solref (time constant 4 ms, damping ratio 0.3): as stiff as 1 ms steps allow (MuJoCo holds time
#:   constants at >= 2 steps), with the restitution of a ball on a body. A damping ratio near critical stops
#:   the ball dead; a lower one, or a direct (negative) solref, throws it back faster than it came: a contact
#:   starts a random fraction of a step deep (a 15 m/s ball moves 15 mm a step) and a stiffer spring gives
#:   that depth back as energy.
#: - solimp (0.95, 0.99, 1 mm): impedance near 1 at once, so the ball is stopped within a few steps.
#: - margin 5 mm: the contact acts from 5 mm off the body's surface, which takes 5 mm off the depth at
#:   which a fast ball is first caught, and keeps the deepest penetration of a 25 m/s shot below
#:   ``max_penetration``.
#: - no tunnelling at these speeds: the thinnest collision geom (a fingertip, 2 mm half-thickness) and
#:   the ball (radius 40 mm) overlap along at least 84 mm of path: 5.6 steps at 15 m/s, 4.2 at 20 m/s.
#: - condim 3, sliding friction 0.5 (a ball on skin or clothes): glancing hits take some spin.
BALL_SOLREF = (0.004, 0.3)
BALL_SOLIMP = (0.95, 0.99, 0.001, 0.5, 2.0)
BALL_MARGIN = 0.005  # m
BALL_FRICTION = (0.5, 0.005, 0.0001)
BALL_CONDIM = 3
#: contype of myo-sim's collision geoms (its arms', torso's and head's), the bit the ball's conaffinity adds
BODY_CONTYPE = 1
TIMESTEP = 0.001  # s
SIDES = ("left", "right")

#: Extraocular muscles: name -> (origin, via point, insertion, wrap side, textbook action). Positions are
#: in the eye frame at rest (m from the eye centre) with x measured *nasally* (mirrored per eye): the
#: origin and via point are fixed in the head, the insertion on the globe; the tendon wraps the globe on
#: the side of ``wrap side`` where its straight path would cut through it. The obliques' sides are temporal
#: (above the globe for the superior, below for the inferior): straight up or down, their paths flipped to
#: the globe's far side (40-47 mm longer) over part of the gaze disc, and the superior oblique elevated the
#: eye above 14 deg up (tests/test_sim.py checks every path is continuous over the disc).
_A = np.array([0.007, 0.0, -0.030])  # the annulus of Zinn: the orbit's apex, behind and nasal of the eye
_S60, _C60 = np.sin(np.radians(60)), np.cos(np.radians(60))  # insertions 60 deg from the front pole


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


EYE_MUSCLES = {
    "lateral_rectus": (_A + [-0.004, 0, 0], None, EYE_RADIUS * np.array([-_S60, 0, _C60]), [-1, 0, 0], "abduction"),
    "medial_rectus": (_A + [0.004, 0, 0], None, EYE_RADIUS * np.array([_S60, 0, _C60]), [1, 0, 0], "adduction"),
    "superior_rectus": (_A + [0, 0.004, 0], None, EYE_RADIUS * np.array([0, _S60, _C60]), [0, 1, 0], "elevation"),
    "inferior_rectus": (_A + [0, -0.004, 0], None, EYE_RADIUS * np.array([0, -_S60, _C60]), [0, -1, 0], "depression"),
    "superior_oblique": (_A + [0.002, 0.003, 0], np.array([0.014, 0.012, 0.008]),
                         EYE_RADIUS * _unit([-0.35, 0.75, -0.55]), [-0.5, 0.866, 0], "intorsion"),
    "inferior_oblique": (np.array([0.010, -0.014, 0.004]), None,
                         EYE_RADIUS * _unit([-0.5, -0.8, -0.3]), [-0.5, -0.866, 0], "extorsion"),
}
EYE_MUSCLE_NAMES = tuple(EYE_MUSCLES)
#: Insertion sites sit this far off the globe's surface (the tendon's thickness); see _add_eye.
INSERTION_LIFT = 0.0005  # m
NECK_MUSCLE_NAMES = tuple(f"neck_{j}_{s}" for j in NECK_JOINTS for s in ("pos", "neg"))


@dataclass
class BodyConfig:
    """What the assembled body contains."""

    arms: bool = True  # myo-sim's muscle-driven arms and torso scaffold (False: a bare torso box, for fast tests)
    timestep: float = TIMESTEP  # s
    cannon_position: tuple = (1.2, -2.6, 0.9)  # m, the barrel's muzzle
    #: m: deeper contacts raise SimulationError. myo-sim's rest pose already has each humerus's collision
    #: capsule inside the thorax's (by how much: docs/RESULTS.md, "Figures behind the code's constants"); 2 cm
    #: leaves room above that.
    max_penetration: float = 0.02
    #: The ball collides with the arms, torso and head (myo-sim's collision geoms; the bare torso of
    #: ``arms=False`` has none, so there it flies through). False: only with the floor.
    ball_contacts: bool = True


def _nasal_sign(side: str) -> float:
    """+1 where the eye frame's +x is nasal (the right eye), -1 where it is temporal (the left eye)."""
    return {"left": -1.0, "right": 1.0}[side]


def quat_from_matrix(R) -> np.ndarray:
    """MuJoCo's unit quaternion (w, x, y, z) of a [3, 3] rotation matrix (``mju_mat2Quat``)."""
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(R, float).reshape(9))
    return q


#: World-from-eye rotation at rest: +z forward (-y world), +y up, +x the body's left (+x world).
EYE_REST_ROTATION = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


#: World-from-body rotation of the myo-sim scaffold's head body at rest (its OpenSim frame: x forward, y up,
#: z to the right).
SCAFFOLD_HEAD_ROTATION = np.array([[0.0, 0, -1], [-1, 0, 0], [0, 1, 0]])


#: what MuJoCo warns each time myo-sim attaches an arm with an empty prefix (our names are its names, so
#: the prefix stays empty; we never save the spec as XML, which is what the warning is about)
EMPTY_PREFIX_WARNING = "Attaching a spec with an empty prefix"


@contextlib.contextmanager
def _without_mujoco_warning(known: str):
    """Drop MuJoCo's C-level warnings that contain ``known`` while the block runs; any other warning goes
    to the handler installed before, or, where there is none, to Python's ``warnings`` as a RuntimeWarning.
    MuJoCo's default handler would print it and append it to MUJOCO_LOG.TXT in the working directory."""
    previous = mujoco.get_mju_user_warning()

    def handler(message: str) -> None:
        if known in message:
            return
        if previous is not None:
            previous(message)
        else:
            warnings.warn(f"MuJoCo: {message}", RuntimeWarning, stacklevel=2)

    mujoco.set_mju_user_warning(handler)
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(previous)


def _myo_spec() -> mujoco.MjSpec:
    import myo_sim

    # myo-sim attaches its arms with an empty prefix, and both myo-sim (a UserWarning) and MuJoCo say so
    with warnings.catch_warnings(), _without_mujoco_warning(EMPTY_PREFIX_WARNING):
        warnings.simplefilter("ignore", UserWarning)
        spec = myo_sim.load_spec("myoarms")
    for g in list(spec.worldbody.geoms):  # its floor (at -0.4 m); the room has its own
        spec.delete(g)
    for light in list(spec.worldbody.lights):
        spec.delete(light)
    spec.body("Full Body").pos = [0.0, 0.0, PELVIS_HEIGHT]
    return spec


def _bare_spec() -> mujoco.MjSpec:
    """A stand-in for the scaffold with the same head frame: a torso box and a skull sphere."""
    spec = mujoco.MjSpec()
    torso = spec.worldbody.add_body(name="torso", pos=[0, 0.1, PELVIS_HEIGHT])
    torso.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.16, 0.1, 0.28], pos=[0, 0, 0.28], rgba=[0.8, 0.7, 0.6, 1],
                   contype=0, conaffinity=0)
    head = torso.add_body(name="head", pos=[0, 0.009, 0.601], quat=quat_from_matrix(SCAFFOLD_HEAD_ROTATION))
    head.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.075, 0, 0], pos=[0.03, 0.08, 0], mass=2.1,
                  rgba=[0.9, 0.85, 0.8, 1], contype=0, conaffinity=0, group=0)
    return spec


def _angle(spec: mujoco.MjSpec, radians: float) -> float:
    """A joint range value in the unit the spec's compiler reads (degrees unless the spec says radians)."""
    return float(np.degrees(radians)) if spec.compiler.degree else float(radians)


def _add_eye(spec: mujoco.MjSpec, head, side: str) -> None:
    Rh = SCAFFOLD_HEAD_ROTATION
    n = _nasal_sign(side)
    lat = {"left": 1.0, "right": -1.0}[side] * INTEROCULAR / 2  # world x of the eye centre
    centre_world = np.array([lat, -ORBIT_FORWARD_OF_HEAD, ORBIT_HEIGHT_ABOVE_HEAD])
    # an "orbit" frame in the head, aligned with the eye at rest; the eye body sits at its origin
    orbit = head.add_body(name=f"orbit_{side}", pos=Rh.T @ centre_world,
                          quat=quat_from_matrix(Rh.T @ EYE_REST_ROTATION))
    eye = orbit.add_body(name=f"eye_{side}")
    eye.add_joint(name=f"eye_{side}", type=mujoco.mjtJoint.mjJNT_BALL, stiffness=EYE_STIFFNESS, damping=EYE_DAMPING,
                  range=[0, _angle(spec, np.radians(EYE_RANGE_DEG))], limited=mujoco.mjtLimited.mjLIMITED_TRUE,
                  armature=1e-7)
    eye.add_geom(name=f"globe_{side}", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[EYE_RADIUS, 0, 0], mass=EYE_MASS,
                 rgba=[0.95, 0.95, 0.92, 1], contype=0, conaffinity=0, group=0)
    # the cornea and iris as a dark disc on the front pole, so a third-person view shows where it looks
    eye.add_geom(name=f"iris_{side}", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.006, 0.0015, 0],
                 pos=[0, 0, EYE_RADIUS - 0.001], mass=1e-5, rgba=[0.25, 0.15, 0.08, 1], contype=0, conaffinity=0,
                 group=0)
    mirror = np.array([n, 1.0, 1.0])  # nasal-x table -> eye-frame x
    for name, (origin, via, insertion, wrap_side, _action) in EYE_MUSCLES.items():
        tag = f"{name}_{side}"
        orbit.add_site(name=f"{tag}_origin", pos=origin * mirror, size=[0.001, 0, 0], group=3)
        if via is not None:
            orbit.add_site(name=f"{tag}_trochlea", pos=via * mirror, size=[0.001, 0, 0], group=3)
        orbit.add_site(name=f"{tag}_side", pos=0.02 * np.asarray(wrap_side, float) * mirror, size=[0.001, 0, 0],
                       group=3)
        # half a millimetre off the surface (the tendon's thickness): MuJoCo's sphere wrapping needs its end
        # points outside the sphere, and one on the surface flips between wrapping and not
        eye.add_site(name=f"{tag}_insertion", pos=insertion * mirror * (1 + INSERTION_LIFT / EYE_RADIUS),
                     size=[0.001, 0, 0], group=3)
        t = spec.add_tendon(name=tag, width=0.0008, rgba=[0.8, 0.2, 0.2, 1], group=3)
        t.wrap_site(f"{tag}_origin")
        if via is not None:
            t.wrap_site(f"{tag}_trochlea")
        t.wrap_geom(f"globe_{side}", f"{tag}_side")
        t.wrap_site(f"{tag}_insertion")
        a = spec.add_actuator(name=tag, target=tag, trntype=mujoco.mjtTrn.mjTRN_TENDON, group=1)
        a.set_to_muscle(timeconst=list(EYE_MUSCLE_TIMECONST), tausmooth=0.0, range=[0.75, 1.05], force=EYE_MUSCLE_FORCE,
                        vmax=EYE_MUSCLE_VMAX)
    # intraocular state: force-free filters that mirror the plants (ctrl = act = the plant's state, so
    # MuJoCo's filter holds it; the plants in eye/plants.py move it)
    for quantity, rng in (("pupil", PUPIL_RANGE_MM), ("accommodation", ACCOMMODATION_RANGE_D)):
        a = spec.add_actuator(name=f"{quantity}_{side}", target=f"eye_{side}", trntype=mujoco.mjtTrn.mjTRN_JOINT,
                              group=2)
        a.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
        a.dynprm[0] = 0.1
        a.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        a.gainprm[0] = 0.0
        a.biastype = mujoco.mjtBias.mjBIAS_NONE
        a.ctrlrange = list(rng)
        a.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        a.gear = [0, 0, 0, 0, 0, 0]


def _add_neck(spec: mujoco.MjSpec, head) -> None:
    Rh = SCAFFOLD_HEAD_ROTATION
    axes = {"yaw": [0, 0, 1.0], "pitch": [-1.0, 0, 0], "roll": [0, -1.0, 0]}  # world axes; + = left, up, right ear down
    for j in NECK_JOINTS:
        r = np.radians(NECK_RANGE_DEG[j])
        head.add_joint(name=f"neck_{j}", type=mujoco.mjtJoint.mjJNT_HINGE, axis=Rh.T @ axes[j],
                       range=[_angle(spec, -r), _angle(spec, r)], limited=mujoco.mjtLimited.mjLIMITED_TRUE,
                       stiffness=NECK_STIFFNESS, damping=NECK_DAMPING, armature=0.005)
        for s, sign in (("pos", -1.0), ("neg", 1.0)):  # a muscle shortens as its joint turns its way
            t = spec.add_tendon(name=f"neck_{j}_{s}")
            t.wrap_joint(f"neck_{j}", sign * NECK_MOMENT_ARM)
            a = spec.add_actuator(name=f"neck_{j}_{s}", target=f"neck_{j}_{s}", trntype=mujoco.mjtTrn.mjTRN_TENDON,
                                  group=1)
            a.set_to_muscle(timeconst=list(NECK_MUSCLE_TIMECONST), tausmooth=0.0, range=[0.75, 1.05],
                            force=NECK_MUSCLE_FORCE)


def _add_world(spec: mujoco.MjSpec, cfg: BodyConfig) -> None:
    wb = spec.worldbody
    wb.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[5, 5, 0.1], rgba=[0.5, 0.5, 0.5, 1], group=1,
                contype=4, conaffinity=4)  # the ball lands on it
    wb.add_geom(name="stool", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.18, STOOL_HEIGHT / 2, 0],
                pos=[0, 0.06, STOOL_HEIGHT / 2], rgba=[0.45, 0.3, 0.2, 1], contype=0, conaffinity=0, group=0)
    muzzle = np.asarray(cfg.cannon_position, float)
    aim = _unit(np.array([0, 0, 1.2]) - muzzle)  # the barrel points roughly at the head
    cannon = wb.add_body(name="cannon", pos=muzzle - 0.25 * aim, quat=quat_from_matrix(_frame_z(aim)))
    cannon.add_geom(name="barrel", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.07, 0.25, 0], rgba=[0.2, 0.2, 0.22, 1],
                    contype=0, conaffinity=0, group=0)
    cannon.add_site(name="muzzle", pos=[0, 0, 0.25])
    ball = wb.add_body(name="ball", pos=[0, 3.0, BALL_RADIUS])  # resting on the floor behind the body
    ball.add_freejoint(name="ball")
    geom = ball.add_geom(name="ball", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[BALL_RADIUS, 0, 0], mass=BALL_MASS,
                         rgba=[1, 1, 1, 1], group=0, contype=4, conaffinity=4)  # hits the floor
    if cfg.ball_contacts:  # ... and the body: see BALL_SOLREF
        geom.contype, geom.conaffinity = 0, BODY_CONTYPE
        geom.priority = 1
        geom.solref, geom.solimp = list(BALL_SOLREF), list(BALL_SOLIMP)
        geom.friction, geom.condim = list(BALL_FRICTION), BALL_CONDIM
        geom.margin = BALL_MARGIN
        # the floor by an explicit pair, without the margin (a contact takes the larger of its geoms'
        # margins, and in MuJoCo 3.17 a geom's gap does not offset it): the ball lands on the floor, not
        # 5 mm above it
        spec.add_pair(name="ball_floor", geomname1="floor", geomname2="ball", condim=BALL_CONDIM, margin=0.0,
                      solref=list(BALL_SOLREF), solimp=list(BALL_SOLIMP),
                      friction=[BALL_FRICTION[0], BALL_FRICTION[0], BALL_FRICTION[1], BALL_FRICTION[2],
                                BALL_FRICTION[2]])


def _frame_z(z) -> np.ndarray:
    """A rotation whose third column is ``z``."""
    z = _unit(z)
    x = np.cross([0, 0, 1.0], z) if abs(z[2]) < 0.99 else np.array([1.0, 0, 0])
    x = _unit(x)
    return np.stack([x, np.cross(z, x), z], 1)


def build_spec(cfg: BodyConfig | None = None) -> mujoco.MjSpec:
    """The whole body as an (uncompiled) ``MjSpec``."""
    cfg = cfg or BodyConfig()
    if not cfg.timestep > 0:
        raise ValueError(f"timestep: expected > 0 s, got {cfg.timestep}")
    spec = _myo_spec() if cfg.arms else _bare_spec()
    spec.modelname = "warp_vision_human"
    spec.option.timestep = cfg.timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    head = spec.body("head")
    _add_neck(spec, head)
    for side in SIDES:
        _add_eye(spec, head, side)
    _add_world(spec, cfg)
    _eye_lengthranges(spec)
    return spec


#: Orientations the length ranges are sampled over: gaze within the joint's cone, torsion within this.
_LR_TORSION_DEG = 15.0


@lru_cache(maxsize=1)
def _eye_lengths() -> dict:
    """Each extraocular muscle's (shortest, longest) tendon length (m) over eye orientations sampled
    uniformly in gaze within the joint's cone with torsion within +-``_LR_TORSION_DEG``. Computed on the
    bare body (the eyes and their orbits are the same in every body), once per process."""
    spec = _bare_spec()
    head = spec.body("head")
    for side in SIDES:
        _add_eye(spec, head, side)
    for a in spec.actuators:
        if a.name.split("_")[0] not in ("pupil", "accommodation"):
            a.lengthrange = [0.0, 1.0]
    model = spec.compile()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    n = 3000
    ecc = np.radians(EYE_RANGE_DEG) * 0.98 * np.sqrt(rng.uniform(size=n))
    phi = rng.uniform(0, 2 * np.pi, n)
    tor = np.radians(_LR_TORSION_DEG) * rng.uniform(-1, 1, n)
    out = {}
    for side in SIDES:
        adr = model.jnt_qposadr[model.joint(f"eye_{side}").id]
        tid = [model.tendon(f"{m}_{side}").id for m in EYE_MUSCLE_NAMES]
        L = np.empty((n, len(tid)))
        for k in range(n):
            d = gaze_direction(np.arctan2(np.sin(ecc[k]) * np.cos(phi[k]), np.cos(ecc[k])),
                               np.arcsin(np.sin(ecc[k]) * np.sin(phi[k])))
            yaw, pitch = gaze_angles(d)
            R = fick_rotation(yaw, pitch) @ _rot_z(tor[k])
            data.qpos[adr:adr + 4] = quat_from_matrix(R)
            mujoco.mj_fwdPosition(model, data)
            L[k] = data.ten_length[tid]
        for j, m in enumerate(EYE_MUSCLE_NAMES):
            # percentiles, not extremes: at the cone's rim a path can jump to the globe's far side
            out[f"{m}_{side}"] = tuple(float(v) for v in np.percentile(L[:, j], [1, 99]))
    return out


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _eye_lengthranges(spec: mujoco.MjSpec) -> None:
    """Give the extraocular muscles their length ranges (MuJoCo's own search, which pushes the joint with
    the muscle, does not converge on a ball joint)."""
    for name, (lo, hi) in _eye_lengths().items():
        spec.actuator(name).lengthrange = [lo, hi]
