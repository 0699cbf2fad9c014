"""Generator v8's scenes: ordinary balls in everyday rooms, among distractors, with the body's arms in view.

v7 (:mod:`warp_vision.data.foveation`) shows a glowing white ball in one dim room; a net trained on it
finds the glowing blob and nothing else (issue 17: 45.6 deg median on a lit white ball that does not
glow). v8 draws every sample from a family:

- **Rooms**: each block of :data:`ROOM_BLOCK` consecutive samples shares a room built from its own seed
  (size 5-10 m by 5-10 m by 2.6-4 m, 3-8 pieces of furniture, walls, floor and ceiling of albedo 0.2-0.8
  with a mild tint). Training rooms and held-out rooms come from disjoint seed families
  (``FoveationDataConfig.rooms``: "train" or "heldout"), so a held-out set shows rooms training never saw.
- **Lighting**: 1-3 point lamps under the ceiling, of random colour and intensity, and an ambient level,
  all scaled by a per-sample brightness factor spanning two orders of magnitude (10^-1 to 10^1). The
  exposure is what the config's pupil gives; the net normalises.
- **The ball** (the only sphere in view; sizes and distances as v7): albedo from dark grey to white
  (0.15-1), neutral or coloured, matte or glossy. A minority glows (v7's emission), some of those in a
  room dimmed as v7's (:data:`DIM_ALBEDO`).
- **Distractors**: in a share of the samples, a luminous panel (a lamp or window) and/or a bright box or
  cylinder in the field of view, each brighter than the ball (emission a random 1.5-4 times the ball's
  estimated radiance), never in front of it.
- **The body's arms**: in a share of the samples, the MuJoCo body's arms (myo-sim meshes) and torso at a
  random arm posture, the eye where the body's eye is, looking near the hand or forearm, the body set down
  at a random place and heading in the room.
- **Occlusion** as v7: a panel partly hides the ball in a share of the samples; every sample's ball is
  visible (a hidden one is redrawn).

``FoveationDataConfig.condition`` picks the mixture: "mixed" (training) or one held-out test condition
("glow_dim": v7's glowing ball in a dim room; "white": a lit white ball; "matte": a coloured matte ball;
"distractor": a lamp or brighter object in view; "arm": the body's arm in view; "decoy", generator v9's: a round decoy
in view, :mod:`warp_vision.data.foveation_decoys`). Every sample's parameters come from a generator seeded with (dataset
seed, sample index, attempt) and its room's from (family, dataset seed, block), so a sample never depends on how it is
batched.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from warp_vision.frames import gaze_angles, look_rotation, translation

#: Consecutive samples that share a room (one scene build each).
ROOM_BLOCK = 16
#: The seed families of training and held-out rooms (disjoint by construction: the family is the first
#: word of every room's seed).
ROOM_FAMILIES = {"train": 0, "heldout": 1}
#: "decoy" (round things that are not the ball in view) is generator v9's (warp_vision.data.foveation_decoys).
CONDITIONS = ("mixed", "glow_dim", "white", "matte", "distractor", "arm", "decoy")
#: The training mixture: shares of samples with a glowing ball in a dim room (v7's condition), with a
#: glowing ball in an ordinary room, with distractors in view, with the body's arms in view.
MIX = {"glow_dim": 0.10, "glow": 0.05, "distractor": 0.30, "arm": 0.25}
LAMPS = 3
#: v7's dim room and glowing ball (glow samples): room albedos x DIM_ALBEDO, ball emission GLOW.
DIM_ALBEDO = 0.1
GLOW = 2.0
BRIGHTNESS_DECADES = (-1.0, 1.0)
_HIDDEN = np.array([0.0, 0.0, -10.0])
#: Distractor meshes (object frame, m): a luminous panel facing the eye, a box and a cylinder.
DISTRACTORS = ("lamp_panel", "bright_box", "bright_cylinder")
_ARM_JOINTS = ("elv_angle", "shoulder_elv", "shoulder_rot", "elbow_flexion", "pro_sup", "deviation", "flexion")


def room_layout(family: int, seed: int, block: int) -> dict:
    """The room of ``block``: its size (m), furniture count, surface albedos and furniture seed."""
    rng = np.random.default_rng([8, family, seed, block])
    size = (float(rng.uniform(5, 10)), float(rng.uniform(5, 10)), float(rng.uniform(2.6, 4.0)))
    tint = lambda: rng.uniform(0.2, 0.8) * (1 + rng.uniform(-0.15, 0.15, 3))  # noqa: E731
    surfaces = {n: np.clip(tint(), 0.0, 1.0) for n in ("floor", "ceiling", "wall_north", "wall_south", "wall_east",
                                                       "wall_west")}
    return {"size": size, "objects": int(rng.integers(3, 9)), "surfaces": surfaces,
            "furniture_seed": int(rng.integers(2**31))}


@lru_cache(maxsize=1)
def _ball_meshes(radii: tuple) -> tuple:
    import trimesh

    return tuple(trimesh.creation.icosphere(subdivisions=3, radius=r) for r in radii)


@lru_cache(maxsize=1)
def _distractor_meshes() -> dict:
    import trimesh

    return {"lamp_panel": trimesh.creation.box((0.5, 0.3, 0.03)), "bright_box": trimesh.creation.box((0.3, 0.3, 0.3)),
            "bright_cylinder": trimesh.creation.cylinder(radius=0.12, height=0.5, sections=24)}


@dataclass
class ArmKit:
    """The body's arms and torso as meshes, and random arm postures (its MuJoCo model, posed by kinematics)."""

    body: object
    meshes: dict  # name -> trimesh (arm parts in their anchor body's frame, the torso in the body's world frame)
    anchors: dict  # name -> MuJoCo body id (0 for the torso)

    @staticmethod
    @lru_cache(maxsize=1)
    def load() -> ArmKit:
        import trimesh

        from warp_vision.body import ARM_PARTS, HIDDEN_FROM_EYES, Body, visible_parts

        body = Body()
        m = body.model
        parts = visible_parts(body, ARM_PARTS["right"] + ARM_PARTS["left"] + HIDDEN_FROM_EYES, exclude=("ball",))
        meshes, anchors = {}, {}
        for b, ms in parts.items():
            name = m.body(b).name if b else "torso"
            if name in HIDDEN_FROM_EYES:
                continue
            meshes[f"arm_{name}"] = trimesh.util.concatenate(ms)
            anchors[f"arm_{name}"] = b
        return ArmKit(body, meshes, anchors)

    def pose(self, rng: np.random.Generator, eye: str):
        """A random posture of both arms: ({part: [4, 4] body-frame pose}, the eye's centre, a point on a hand
        or forearm in front of the head to look near), body frame (m)."""
        import mujoco

        b = self.body
        m, d = b.model, b.data
        for _ in range(50):
            d.qpos[:] = m.qpos0
            for side in ("r", "l"):
                draw_arm_joints(m, d, side, rng)
            _apply_joint_couplings(m, d)
            mujoco.mj_kinematics(m, d)
            centre = b.eye_pose(eye)[:3, 3]
            fwd = b.head_pose()[:3, 2]
            side = "r" if rng.uniform() < 0.5 else "l"
            part = ("lunate" if rng.uniform() < 0.6 else "radius") + f"_{side}"
            target = d.xpos[m.body(part).id].copy()
            v = target - centre
            if np.dot(v, fwd) > np.cos(np.radians(70)) * np.linalg.norm(v):
                return {n: b.pose(a) if a else np.eye(4) for n, a in self.anchors.items()}, centre, target
        return None


def draw_arm_joints(m, d, side: str, rng: np.random.Generator) -> None:
    """Each independent joint of arm ``side`` ("r" or "l") drawn uniformly in its range, into ``d.qpos`` (the
    coupled joints follow with :func:`_apply_joint_couplings`)."""
    for j in _ARM_JOINTS:
        jid = m.joint(f"{j}_{side}").id
        lo, hi = m.jnt_range[jid]
        d.qpos[m.jnt_qposadr[jid]] = rng.uniform(lo, hi)


def _apply_joint_couplings(m, d) -> None:
    """Set the joints that myo-sim's joint equalities tie to others (the shoulder rhythm): MuJoCo's
    polynomial, q1 - q1_0 = c0 + c1 (q2 - q2_0) + ... + c4 (q2 - q2_0)^4 (a constant where q2 is absent)."""
    import mujoco

    for e in range(m.neq):
        if m.eq_type[e] != mujoco.mjtEq.mjEQ_JOINT or not m.eq_active0[e]:
            continue
        j1, j2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])
        c = m.eq_data[e, :5]
        a1 = m.jnt_qposadr[j1]
        x = d.qpos[m.jnt_qposadr[j2]] - m.qpos0[m.jnt_qposadr[j2]] if j2 >= 0 else 0.0
        d.qpos[a1] = m.qpos0[a1] + c[0] + c[1] * x + c[2] * x**2 + c[3] * x**3 + c[4] * x**4


def _kind(condition: str, rng: np.random.Generator) -> dict:
    """Which features a sample has, by the condition's rules."""
    if condition == "mixed":
        u = rng.uniform()
        glow_dim = u < MIX["glow_dim"]
        glow = glow_dim or u < MIX["glow_dim"] + MIX["glow"]
        return {"glow": glow, "dim": glow_dim, "coloured": rng.uniform() < 0.5, "glossy": rng.uniform() < 0.5,
                "distractor": (not glow_dim) and rng.uniform() < MIX["distractor"],
                "arm": (not glow_dim) and rng.uniform() < MIX["arm"], "white": False}
    base = {"glow": False, "dim": False, "coloured": rng.uniform() < 0.5, "glossy": rng.uniform() < 0.5,
            "distractor": False, "arm": False, "white": False}
    if condition == "glow_dim":
        base.update(glow=True, dim=True)
    elif condition == "white":
        base.update(white=True, coloured=False)
    elif condition == "matte":
        base.update(coloured=True, glossy=False)
    elif condition == "distractor":
        base.update(distractor=True)
    elif condition == "arm":
        base.update(arm=True)
    return base


def _ball_material(kind: dict, rng: np.random.Generator) -> dict:
    if kind["glow"]:
        return {"diffuse": np.ones(3), "specular": 0.4, "shininess": 32.0, "emission": np.full(3, GLOW)}
    level = rng.uniform(0.8, 1.0) if kind["white"] else rng.uniform(0.15, 1.0)
    if kind["coloured"]:
        hue = rng.uniform(0, 2 * np.pi)
        sat = rng.uniform(0.4, 0.9)
        rgb = 1 + sat * np.cos(hue - np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3]))
        colour = level * rgb / rgb.max()
    else:
        colour = np.full(3, level)
    spec = (float(rng.uniform(0.2, 0.6)), float(rng.uniform(16, 64))) if kind["glossy"] else (0.0, 32.0)
    return {"diffuse": np.clip(colour, 0, 1), "specular": spec[0], "shininess": spec[1], "emission": np.zeros(3)}


def _lighting(kind: dict, size, rng: np.random.Generator) -> dict:
    pos = np.tile(_HIDDEN, (LAMPS, 1))
    colour = np.ones((LAMPS, 3))
    intensity = np.zeros(LAMPS)
    if kind["dim"]:  # v7's lamp and ambient light
        pos[0] = [0.0, 0.0, size[2] - 0.6]
        colour[0] = rng.uniform(0.6, 1.0, 3)
        intensity[0] = rng.uniform(3.0, 15.0)
        return {"pos": pos, "colour": colour, "intensity": intensity, "ambient": np.full(3, 0.06), "brightness": 1.0}
    brightness = 10 ** rng.uniform(*BRIGHTNESS_DECADES)
    n = int(rng.integers(1, LAMPS + 1))
    for i in range(n):
        pos[i] = [rng.uniform(-size[0] / 2 + 0.4, size[0] / 2 - 0.4),
                  rng.uniform(-size[1] / 2 + 0.4, size[1] / 2 - 0.4), size[2] - rng.uniform(0.2, 0.9)]
        colour[i] = rng.uniform(0.6, 1.0, 3)
        intensity[i] = brightness * rng.uniform(2.0, 10.0) / n ** 0.5
    ambient = brightness * rng.uniform(0.01, 0.08) * rng.uniform(0.8, 1.0, 3)
    return {"pos": pos, "colour": colour, "intensity": intensity, "ambient": ambient, "brightness": float(brightness)}


def ball_radiance(light: dict, mat: dict, ball) -> float:
    """A rough upper estimate of the ball's brightest radiance: its albedo (and specular peak) under the
    lamps' irradiance at its centre (no shadows, normal incidence) and the ambient light, plus its emission."""
    d2 = np.sum((light["pos"] - ball) ** 2, axis=1)
    E = float(np.max(light["ambient"])) + float(
        np.sum(light["intensity"] * light["colour"].max(axis=1) / np.maximum(d2, 1e-4))
    )
    return float(np.max(mat["diffuse"]) * E / np.pi * (1 + mat["specular"]) + np.max(mat["emission"]))


def _room_bounds(size, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The room's box (floor at z = 0, centred in x and y), shrunk by ``margin`` m: (lo, hi)."""
    half = np.array([size[0] / 2, size[1] / 2, 0.0])
    return -half + margin, half + [0.0, 0.0, size[2]] - margin


def _in_room(p, size, margin: float) -> bool:
    lo, hi = _room_bounds(size, margin)
    return bool(np.all(p > lo) and np.all(p < hi))


def _room_exit(p, d, size, margin: float) -> float:
    """How far (m) from ``p`` along unit ``d`` the room, shrunk by ``margin``, reaches."""
    lo, hi = _room_bounds(size, margin)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - p) / d, np.where(d < 0, (lo - p) / d, np.inf))
    return float(max(0.0, t.min()))


def field_direction(rng, max_field_deg: float) -> tuple[np.ndarray, float, float]:
    """A direction uniform over the solid angle within ``max_field_deg`` of the eye's axis (eye frame),
    with its cos(eccentricity) and azimuth."""
    ct = rng.uniform(np.cos(np.radians(max_field_deg)), 1.0)
    st = np.sqrt(1 - ct * ct)
    phi = rng.uniform(0, 2 * np.pi)
    return np.array([st * np.cos(phi), st * np.sin(phi), ct]), float(ct), float(phi)


def _distractors(kind, R, eye, u_ball, ball_angle, size, light, mat, ball, rng) -> dict:
    """Poses, visibility and emission of the distractors: one or two, in view, away from the ball."""
    out = {n: {"pose": translation(_HIDDEN), "visible": False, "emission": np.zeros(3),
               "diffuse": np.full(3, 0.5)} for n in DISTRACTORS}
    if not kind["distractor"]:
        return out
    L = ball_radiance(light, mat, ball)
    chosen = [DISTRACTORS[0]] if rng.uniform() < 0.5 else []
    if not chosen or rng.uniform() < 0.5:
        chosen.append(DISTRACTORS[1 + int(rng.integers(2))])
    for name in chosen:
        for _ in range(100):
            u, _, _ = field_direction(rng, 40.0)
            room_left = _room_exit(eye, R @ u, size, 0.3)  # how far the room reaches that way
            if room_left < 0.5:
                continue
            dist = float(rng.uniform(0.5, min(4.0, room_left)))
            reach = 0.35 / dist  # about the object's apparent radius (rad)
            if np.arccos(np.clip(u @ u_ball, -1, 1)) < ball_angle + reach + np.radians(3):
                continue
            p = eye + dist * (R @ u)
            T = np.eye(4)
            T[:3, :3] = look_rotation(p - eye) if name == "lamp_panel" else _yaw(rng.uniform(0, np.pi))
            T[:3, 3] = p
            tint = rng.uniform(0.7, 1.0, 3)
            out[name] = {"pose": T, "visible": True, "emission": rng.uniform(1.5, 4.0) * L * tint / tint.max(),
                         "diffuse": rng.uniform(0.3, 0.9, 3)}
            break
    return out


def occluder_pose(rng, eye, ball, R, phi: float, radius: float, occluded: bool) -> np.ndarray:
    """The occluding panel's [4, 4] pose (v7's rule, shared by v8): between the eye and the ball, its near
    edge crossing the ball's disc from 0.2 of its apparent radius beyond the centre to 0.8 short of it (so
    it hides about 5% to 60% of the ball); face-on to the eye (its thin local z along the line of sight:
    edge-on, it would hide at most a 2 cm strip), its local x along the side direction so its
    near edge runs straight past the ball. Parked out of sight when not ``occluded`` (the same two draws
    from ``rng`` either way)."""
    side = R @ np.array([np.cos(phi + np.pi / 2), np.sin(phi + np.pi / 2), 0.0])
    frac = rng.uniform(0.4, 0.7)
    panel = eye + frac * (ball - eye) + side * frac * radius * rng.uniform(-0.2, 0.8) + side * 0.125
    Tp = np.eye(4)
    z = (ball - eye) / np.linalg.norm(ball - eye)
    x = side - (side @ z) * z
    x /= np.linalg.norm(x)
    Tp[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    Tp[:3, 3] = panel if occluded else _HIDDEN
    return Tp


def _yaw(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def sample_params(cfg, index: int, attempt: int, radii, diameter_limits) -> dict:
    """The random scene of v8 sample ``index`` of ``cfg`` (a FoveationDataConfig; ``attempt`` > 0: a redraw
    after attempt - 1 hid the ball). ``radii``: the balls' radii (m); ``diameter_limits(eccentricity)``:
    the least and the most apparent diameter (rad) a ball may have there (v7's rules)."""
    rng = np.random.default_rng([cfg.seed, index, attempt, 8])
    block = index // ROOM_BLOCK
    room = room_layout(ROOM_FAMILIES[cfg.rooms], cfg.seed, block)
    size = room["size"]
    kind = _kind(cfg.condition, rng)
    arm = None
    for _ in range(1000):
        if kind["arm"]:
            kit = ArmKit.load()
            posed = kit.pose(rng, cfg.eye)
            if posed is None:
                continue
            parts, centre, look = posed
            # the body set down at a random place and heading, the eye at least 0.8 m inside the walls
            Tw = np.eye(4)
            Tw[:3, :3] = _yaw(rng.uniform(-np.pi, np.pi))
            spot = np.array([rng.uniform(-size[0] / 2 + 0.8, size[0] / 2 - 0.8),
                             rng.uniform(-size[1] / 2 + 0.8, size[1] / 2 - 0.8)])
            Tw[:2, 3] = spot - (Tw[:3, :3] @ centre)[:2]
            eye = Tw[:3, :3] @ centre + Tw[:3, 3]
            fwd = Tw[:3, :3] @ (look - centre)
            # look near the hand or forearm: its direction turned by up to 20 deg
            fwd = fwd / np.linalg.norm(fwd) + np.tan(np.radians(rng.uniform(0, 20))) * _unit_perp(fwd, rng)
            arm = {n: Tw @ T for n, T in parts.items()}
        else:
            eye = np.array([rng.uniform(-size[0] / 2 + 0.6, size[0] / 2 - 0.6),
                            rng.uniform(-size[1] / 2 + 0.6, size[1] / 2 - 0.6), rng.uniform(0.9, 1.8)])
            yaw0, pitch0 = rng.uniform(-np.pi, np.pi), rng.uniform(-0.35, 0.35)
            fwd = np.array([np.cos(pitch0) * np.cos(yaw0), np.cos(pitch0) * np.sin(yaw0), np.sin(pitch0)])
        R = look_rotation(fwd)
        u_eye, ct, phi = field_direction(rng, cfg.max_field_deg)
        size_k = int(rng.integers(len(radii)))
        radius = radii[size_k]
        lo, hi = diameter_limits(np.arccos(ct))
        far = min(5.0, radius / np.sin(lo / 2))
        near = max(0.3, radius / np.sin(hi / 2))
        if near >= far:
            continue
        dist = float(np.exp(rng.uniform(np.log(near), np.log(far))))
        ball = eye + dist * (R @ u_eye)
        if dist > radius + 0.05 and _in_room(ball, size, radius + 0.05):
            break
    else:  # pragma: no cover - every direction admits a ball (FoveationDataConfig._check_field) and the rooms are large
        raise RuntimeError("could not place the ball inside the room")
    occluded = bool(rng.uniform() < cfg.occluded_fraction)
    Tp = occluder_pose(rng, eye, ball, R, phi, radius, occluded)
    light = _lighting(kind, size, rng)
    mat = _ball_material(kind, rng)
    ball_angle = np.arcsin(min(1.0, radius / dist))
    distract = _distractors(kind, R, eye, u_eye, ball_angle, size, light, mat, ball, rng)
    panel_albedo = rng.uniform(0.2, 0.8) * rng.uniform(0.8, 1.0, 3) * (DIM_ALBEDO if kind["dim"] else 1.0)
    Te = np.eye(4)
    Te[:3, :3] = R
    Te[:3, 3] = eye
    yaw, pitch = (float(a) for a in gaze_angles(u_eye))
    return {
        "block": block, "room": room, "kind": kind, "eye_pose": Te, "ball": ball, "radius": radius, "size": size_k,
        "panel_pose": Tp, "panel_albedo": panel_albedo, "light": light, "ball_material": mat, "distractors": distract,
        "arm": arm,
        "target": np.array([yaw, pitch], dtype=np.float32),
        "meta": np.array([dist, radius, float(occluded), float(kind["glow"]), float(kind["distractor"]),
                          float(arm is not None), light["brightness"]], dtype=np.float32),
    }


def _unit_perp(v, rng) -> np.ndarray:
    """A random unit vector perpendicular to ``v``."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    a = rng.normal(size=3)
    a -= (a @ v) * v
    return a / np.linalg.norm(a)


def make_scene(family: int, seed: int, block: int, radii, with_arms: bool = True):
    """The scene of one room: the room (static), a ball of each of ``radii``, the occluding panel, the
    distractors and the body's arms and torso (dynamic, hidden until placed), and LAMPS lamps."""
    from warp_vision.scene import Material
    from warp_vision.scene.room import make_room

    room = room_layout(family, seed, block)
    sc = make_room(size=room["size"], n_objects=room["objects"], seed=room["furniture_seed"], ball_centre=_HIDDEN)
    for o in sc.objects:
        if o.name in room["surfaces"]:
            o.material.diffuse = tuple(float(v) for v in room["surfaces"][o.name])
    sc.set_visible("ball", False)
    for k, mesh in enumerate(_ball_meshes(tuple(radii))):
        sc.add(f"ball_{k}", mesh, Material((1.0, 1.0, 1.0), specular=0.4, shininess=32, smooth=True),
               translation(_HIDDEN))
    sc.add("occluder", _occluder_mesh(), Material((0.5, 0.5, 0.5)), translation(_HIDDEN))
    for name, mesh in _distractor_meshes().items():
        sc.add(name, mesh, Material((0.8, 0.8, 0.8)), translation(_HIDDEN))
    sc.set_visible("occluder", False)
    for name in DISTRACTORS:
        sc.set_visible(name, False)
    if with_arms:
        for name, mesh in ArmKit.load().meshes.items():
            sc.add(name, mesh, Material(vertex_colors=True), translation(_HIDDEN))
            sc.set_visible(name, False)
    sc.lights = []
    for _ in range(LAMPS):
        sc.add_light(_HIDDEN, intensity=0.0)
    return sc


def place(scene, ps: list) -> None:
    """Set up ``scene`` (:func:`make_scene`, the samples' room) for the samples ``ps``, one per batch element:
    the room's albedos (dimmed in dim samples), the ball, panel, distractors and arms with their poses,
    visibility and materials, the lamps and the ambient light."""
    from warp_vision.scene import Material

    for o in scene.objects:  # the room: its own materials (a per-batch list never replaces them), dimmed in dim samples
        if not o.static:
            continue
        m = o.material
        if any(p["kind"]["dim"] for p in ps):
            dim = Material(tuple(DIM_ALBEDO * np.asarray(m.diffuse)), m.specular, m.shininess, 0.0)
            scene.set_material(o.name, [dim if p["kind"]["dim"] else m for p in ps])
        else:
            scene.set_material(o.name, m)
    balls = [Material(tuple(p["ball_material"]["diffuse"]), p["ball_material"]["specular"],
                      p["ball_material"]["shininess"], emission=tuple(p["ball_material"]["emission"]),
                      smooth=True) for p in ps]
    for k in range(sum(o.name.startswith("ball_") for o in scene.objects)):
        scene.set_transform(f"ball_{k}", np.stack([translation(p["ball"] if p["size"] == k else _HIDDEN) for p in ps]))
        scene.set_visible(f"ball_{k}", [p["size"] == k for p in ps])
        scene.set_material(f"ball_{k}", balls)
    scene.set_transform("occluder", np.stack([p["panel_pose"] for p in ps]))
    scene.set_visible("occluder", [bool(p["meta"][2]) for p in ps])
    scene.set_material("occluder", [Material(tuple(p["panel_albedo"])) for p in ps])
    for name in DISTRACTORS:
        ds = [p["distractors"][name] for p in ps]
        scene.set_transform(name, np.stack([d["pose"] for d in ds]))
        scene.set_visible(name, [d["visible"] for d in ds])
        scene.set_material(name, [Material(tuple(d["diffuse"]), emission=tuple(d["emission"])) for d in ds])
    arm_names = [o.name for o in scene.objects if o.name.startswith("arm_")]
    for name in arm_names:
        scene.set_transform(name, np.stack([p["arm"][name] if p["arm"] else translation(_HIDDEN) for p in ps]))
        scene.set_visible(name, [p["arm"] is not None for p in ps])
    for i, lamp in enumerate(scene.lights):
        lamp.position = np.stack([p["light"]["pos"][i] for p in ps])
        lamp.color = np.stack([p["light"]["colour"][i] for p in ps])
        lamp.intensity = np.array([p["light"]["intensity"][i] for p in ps])
    scene.set_ambient(np.stack([p["light"]["ambient"] for p in ps]))


@lru_cache(maxsize=1)
def _occluder_mesh():
    import trimesh

    return trimesh.creation.box((0.25, 0.25, 0.02))
