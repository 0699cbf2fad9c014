"""``python -m warp_vision.sim search``'s trials: the seated body in a held-out room, a static ball 10 to 35
degrees from the starting gaze, and look-alikes in view; the eyes find the ball (or not).

A trial (:func:`sample_trial`, seeded; training seeds and held-out seeds are disjoint ranges, as the
cannon's :data:`warp_vision.sim.cannon.SPLITS`) draws:

- its room: :func:`warp_vision.sim.loop.body_scene`'s room of a seed drawn from (the split, the trial's
  seed); trials share a room in blocks of :data:`ROOM_BLOCK`;
- the ball (the body's ordinary ball), 10 to 35 degrees from the head's straight-ahead gaze in a random
  direction, 0.8 to 3 m from the eyes, in sight of both eyes;
- look-alikes: the cannon's muzzle, which faces the head end-on 24 degrees to the left (in view in every
  trial), and one or two of: a decoy (a barrel end-on, a drum or a plate, :data:`warp_vision.data.
  foveation_decoys.DECOYS`, about the ball's apparent size), a luminous lamp panel, a raised hand (an arm
  posed, and held there, so the hand is in front of the face).

:func:`run_trial` runs one trial for ``TRIAL_S`` seconds under a perception mode ("search": the active
search; "nets": the foveation nets' single answer) and scores it: the first time both eyes are within
``WITHIN_DEG`` of the ball and stay so to the end (``hold``), the saccades, the search's events.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from warp_vision.body import SIDES

SPLITS = {"train": range(0, 1_000_000), "heldout": range(1_000_000, 2_000_000)}
ROOM_BLOCK = 4
ECCENTRICITY_DEG = (10.0, 35.0)
DISTANCE_M = (0.8, 3.0)
TRIAL_S = 1.3
BY_S = 1.0  # the ball must be held from this time at the latest
WITHIN_DEG = 1.0
LOOK_ALIKES = ("muzzle", "decoy", "lamp", "hand")
LAMP_PANEL = (0.3, 0.3)  # m
#: m: a raised arm's posture is drawn again while any contact of the body lies deeper than this (an arm through
#: the torso would be pushed out by MuJoCo, or fail its penetration check)
POSTURE_DEPTH_M = 0.005


@dataclass
class Trial:
    seed: int
    split: str
    room_seed: int
    ball: tuple  # (eccentricity deg, polar angle deg, distance m) from the head's rest gaze
    decoy: dict | None = None  # {"name", "ecc", "polar", "distance", "end_on"}
    lamp: dict | None = None  # {"ecc", "polar", "distance", "emission"}
    hand: dict | None = None  # {"side", "qpos": {joint: value}}


def trial_seeds(n: int, seed: int = 0, split: str = "heldout") -> list[int]:
    """``n`` consecutive trial seeds of ``split`` from its ``seed``-th."""
    if split not in SPLITS:
        raise ValueError(f"split: expected one of {sorted(SPLITS)}, got {split!r}")
    r = SPLITS[split]
    if not (1 <= n and 0 <= seed and seed + n <= len(r)):
        raise ValueError(f"trials: expected 1..{len(r) - seed:,} trials from seed {seed:,} of the {split} split, got "
                         f"{n:,}")
    return [r[seed + k] for k in range(n)]


def _direction(ecc_deg: float, polar_deg: float) -> tuple[float, float]:
    """(yaw, pitch) deg of the direction ``ecc_deg`` from straight ahead, at polar angle ``polar_deg``."""
    from warp_vision.frames import gaze_angles

    e, p = np.radians(ecc_deg), np.radians(polar_deg)
    return tuple(float(np.degrees(a)) for a in gaze_angles(np.array([np.sin(e) * np.cos(p), np.sin(e) * np.sin(p),
                                                                     np.cos(e)])))


def sample_trial(seed: int, split: str | None = None) -> Trial:
    """The trial of ``seed`` (its split from the seed's range unless given)."""
    split = split or ("heldout" if seed in SPLITS["heldout"] else "train")
    if seed not in SPLITS[split]:
        raise ValueError(f"seed: {seed:,} is not in the {split} split's range")
    rng = np.random.default_rng([64, seed])
    block = (seed - SPLITS[split][0]) // ROOM_BLOCK
    room_seed = int(np.random.default_rng([64, 1 if split == "heldout" else 0, block]).integers(2**31))
    polar = float(rng.uniform(-120, 300))  # not straight down, where the body is
    ball = (float(rng.uniform(*ECCENTRICITY_DEG)), polar, float(np.exp(rng.uniform(*np.log(DISTANCE_M)))))
    kinds = list(rng.choice(["decoy", "lamp", "hand"], size=1 + int(rng.uniform() < 0.4), replace=False))
    t = Trial(seed, split, room_seed, ball)
    if "decoy" in kinds:
        from warp_vision.data.foveation_decoys import DECOYS

        names = list(DECOYS)
        t.decoy = {"name": names[int(rng.integers(len(names)))], "ecc": float(rng.uniform(3, 40)),
                   "polar": float(rng.uniform(-150, 330)), "distance": float(rng.uniform(0.8, 3.0)),
                   "end_on": bool(rng.uniform() < 0.75), "size": float(rng.uniform(0.7, 1.5))}
    if "lamp" in kinds:
        t.lamp = {"ecc": float(rng.uniform(5, 40)), "polar": float(rng.uniform(-150, 330)),
                  "distance": float(rng.uniform(1.5, 3.5)), "emission": float(rng.uniform(0.5, 2.0))}
    if "hand" in kinds:
        t.hand = {"side": "r" if rng.uniform() < 0.5 else "l", "seed": int(rng.integers(2**31))}
    return t


def look_alikes(trial: Trial) -> list[str]:
    return ["muzzle"] + [k for k in ("decoy", "lamp", "hand") if getattr(trial, k) is not None]


# ----------------------------------------------------------------------------------------------
# the scene


def add_look_alike_objects(scene) -> None:
    """The decoys and a lamp panel, hidden until a trial places them."""
    import trimesh

    from warp_vision.data.foveation_decoys import add_decoy_objects
    from warp_vision.scene import Material

    add_decoy_objects(scene)
    scene.add("lamp_panel", trimesh.creation.box((*LAMP_PANEL, 0.02)), Material((0.9, 0.9, 0.9)), np.eye(4))
    scene.set_visible("lamp_panel", False)


def _at(body, ecc: float, polar: float, distance: float) -> np.ndarray:
    from warp_vision.sim.loop import point_at

    return point_at(body, *_direction(ecc, polar), distance)


def place_look_alikes(scene, body, trial: Trial) -> None:
    """Pose and show the trial's decoy and lamp (the arm is posed on the body: :func:`hand_posture`)."""
    from warp_vision.data.foveation_decoys import DECOYS
    from warp_vision.frames import look_rotation
    from warp_vision.scene import Material

    mid = 0.5 * (body.eye_pose("left")[:3, 3] + body.eye_pose("right")[:3, 3])
    for name in DECOYS:
        scene.set_visible(name, trial.decoy is not None and trial.decoy["name"] == name)
    if trial.decoy is not None:
        d = trial.decoy
        r_dec, length = DECOYS[d["name"]]
        ball_r = body.model.geom_size[body.model.geom("ball").id, 0]
        dist = r_dec / (d["size"] * ball_r / trial.ball[2])  # about the ball's apparent size times size
        dist = float(np.clip(dist, 0.8, 4.0))
        face = _at(body, d["ecc"], d["polar"], dist)
        u = (face - mid) / np.linalg.norm(face - mid)
        axis = u if d["end_on"] else np.cross(u, [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(u, [0.0, 0.0, 1.0]))
        T = np.eye(4)
        T[:3, :3] = look_rotation(axis, up=(0.0, 1.0, 0.0) if abs(axis[2]) > 0.9 else (0.0, 0.0, 1.0))
        T[:3, 3] = face + axis * length / 2
        scene.set_transform(d["name"], T)
        scene.set_material(d["name"], Material((0.35, 0.33, 0.3), specular=0.2, shininess=24.0))
    scene.set_visible("lamp_panel", trial.lamp is not None)
    if trial.lamp is not None:
        lp = trial.lamp
        p = _at(body, lp["ecc"], lp["polar"], lp["distance"])
        T = np.eye(4)
        T[:3, :3] = look_rotation(p - mid)
        T[:3, 3] = p
        scene.set_transform("lamp_panel", T)
        scene.set_material("lamp_panel", Material((0.8, 0.8, 0.8), emission=(lp["emission"],) * 3))


def hand_posture(body, trial: Trial) -> dict | None:
    """{qpos address: value} of the trial's raised arm: its joints drawn (from the trial's seed) until the hand
    is within 30 degrees of straight ahead, 0.3 to 0.7 m from the eyes, and no contact of the body is deeper
    than POSTURE_DEPTH_M; None without a hand."""
    import mujoco

    from warp_vision.data.foveation_scenes import _apply_joint_couplings, draw_arm_joints

    m = body.model
    side = trial.hand["side"] if trial.hand is not None else "r"
    if trial.hand is None or f"lunate_{side}" not in [m.body(b).name for b in range(m.nbody)]:
        return None  # no hand in this trial, or a body without arms
    d = mujoco.MjData(m)
    d.qpos[:] = body.data.qpos
    rng = np.random.default_rng(trial.hand["seed"])
    head = body.head_pose()
    adrs = [m.jnt_qposadr[j] for j in range(m.njnt) if m.joint(j).name.endswith(f"_{side}")]
    for _ in range(500):
        draw_arm_joints(m, d, side, rng)
        _apply_joint_couplings(m, d)
        mujoco.mj_forward(m, d)
        v = d.xpos[m.body(f"lunate_{side}").id] - head[:3, 3]
        dist = np.linalg.norm(v)
        deepest = min((float(d.contact[i].dist) for i in range(d.ncon)), default=0.0)
        if 0.3 <= dist <= 0.7 and v @ head[:3, 2] > np.cos(np.radians(30)) * dist and deepest > -POSTURE_DEPTH_M:
            return {int(a): float(d.qpos[a]) for a in adrs}
    return None


def pin(body, posture: dict | None) -> None:
    """Hold the raised arm at its posture (joint angles set, velocities zero)."""
    if not posture:
        return
    m = body.model
    for a, v in posture.items():
        body.data.qpos[a] = v
    for j in range(m.njnt):
        if m.jnt_qposadr[j] in posture:
            body.data.qvel[m.jnt_dofadr[j]] = 0.0


def ball_point(body, trial: Trial) -> np.ndarray:
    return _at(body, *trial.ball)


def in_sight(scene, body, point: np.ndarray) -> bool:
    """Whether both eyes' lines of sight reach the ball at ``point`` first (the scene synced to the body)."""
    from warp_vision.kernels.render import closest_hit

    ball = scene.index("mj_ball")
    for s in SIDES:
        o = body.eye_pose(s)[:3, 3]
        d = (point - o) / np.linalg.norm(point - o)
        _, obj, _ = closest_hit(scene, o[None], d[None])
        if int(obj[0]) != ball:
            return False
    return True


# ----------------------------------------------------------------------------------------------
# a trial


def run_trial(loop, trial: Trial, scene, perception: str, search=None, record=None, settle_s: float = 0.2) -> dict:
    """Run ``trial`` in ``scene`` (its room, :func:`add_look_alike_objects` added) under ``perception``
    ("search" with ``search``, or "nets") and score it (module docstring)."""
    from warp_vision.sim.gaze import CONTROL_DT
    from warp_vision.sim.loop import gaze_error_deg, set_eye_view, sync_scene

    body = loop.body
    loop.scene = scene
    loop.perception, loop.search = perception, search
    loop.reset(settle_s=settle_s)
    posture = hand_posture(body, trial)
    point = ball_point(body, trial)
    body.set_ball(point)
    pin(body, posture)
    place_look_alikes(scene, body, trial)
    sync_scene(scene, body)
    set_eye_view(scene, True)
    visible = in_sight(scene, body, point)
    t0 = body.time
    errors = []
    saccades = {s: 0 for s in SIDES}
    for _ in range(int(round(TRIAL_S / CONTROL_DT))):
        body.set_ball(point)
        pin(body, posture)
        quiet = {s: loop.eyes[s].quiet_from for s in SIDES}
        loop.step()
        for s in SIDES:
            saccades[s] += int(loop.eyes[s].quiet_from != quiet[s])
        errors.append([gaze_error_deg(body, s, point) for s in SIDES])
        if record is not None:
            record(loop)
    err = np.asarray(errors)
    t = (np.arange(len(err)) + 1) * CONTROL_DT
    both = err.max(1) <= WITHIN_DEG
    held_from = None
    if both[-1]:
        k = len(both) - 1
        while k > 0 and both[k - 1]:
            k -= 1
        held_from = float(t[k])
    shown = [k for k in look_alikes(trial) if k != "hand" or posture]
    return {"seed": trial.seed, "perception": perception, "ball_in_sight": visible, "look_alikes": shown,
            "ball": list(trial.ball), "found": held_from is not None and held_from <= BY_S, "held_from_s": held_from,
            "final_error_deg": err[-1].tolist(), "saccades": int(max(saccades.values())),
            "events": [(tm - t0, kind, p.tolist()) for tm, kind, p in (search.log if search is not None else [])],
            "errors_deg": err.round(3).tolist()}
