"""Generator v9: v8's scenes (:mod:`warp_vision.data.foveation_scenes`) plus decoys, round things that
are not the ball.

v8's nets take a cannon's muzzle seen end-on (a dark disc of about the ball's apparent size) for the ball
(docs/RESULTS.md, "Ordinary objects": in the cannon scenario the right eye fixated the muzzle for 0.45 s). v8
never shows them a round thing that is not a sphere, so nothing in their data tells a disc from a ball.
v9 adds, in a share of the samples, one or two **decoys**: solid cylinders (a cannon-like barrel, a
drum, a thin plate) of everyday albedo, mostly seen end-on (their axis within 25 degrees of the line of
sight, so they look like discs) and of an apparent size near the ball's (0.5 to 2.5 times its radius).
Some stand apart from the ball; some just behind it, so that the ball's disc overlaps theirs, as a cannon
ball does as it leaves the muzzle. The ball stays the only sphere and stays visible (decoys are never in
front of it).

A v9 sample is exactly the v8 sample of the same (config, index, attempt) with the decoys added: they are
drawn from a generator of their own, seeded with (dataset seed, sample index, attempt, 9), so every
other draw, and a sample without decoys, is v8's. Conditions: "mixed" shows decoys in :data:`MIX_DECOY`
of its samples (none in v7's glowing-ball-in-a-dim-room samples); the held-out condition "decoy" in
every sample; the other conditions never.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from warp_vision.data.foveation_scenes import _HIDDEN, _in_room, _room_exit, _unit_perp, field_direction
from warp_vision.frames import look_rotation, translation

#: The decoys (object frame: a cylinder along z centred at the origin): radius, length (m). The barrel is
#: the sim's cannon's (warp_vision.body.spec: radius 70 mm, 0.5 m long).
DECOYS = {"decoy_barrel": (0.07, 0.5), "decoy_drum": (0.15, 0.3), "decoy_plate": (0.10, 0.01)}
#: The share of "mixed" samples with decoys.
MIX_DECOY = 0.30
#: A decoy's apparent radius relative to the ball's: the cannon's muzzle is 1.75 times the ball's radius
#: (70 against 40 mm), so at the launch it looks 1.75 times as large (a first draft with 0.6-1.6 left the
#: muzzle just outside and a net trained on it still fixated the muzzle in the cannon scenario).
APPARENT_RATIO = (0.5, 2.5)
#: Axis tilt from the line of sight of the end-on decoys (deg), and their share.
END_ON_TILT_DEG = 25.0
END_ON_SHARE = 0.75
#: The share of decoys placed just behind the ball (their discs overlapping), the rest apart from it.
BEHIND_SHARE = 0.35


@lru_cache(maxsize=1)
def decoy_meshes() -> dict:
    import trimesh

    return {n: trimesh.creation.cylinder(radius=r, height=h, sections=32) for n, (r, h) in DECOYS.items()}


def has_decoys(cfg, kind: dict, rng: np.random.Generator) -> bool:
    """Whether a v9 sample of ``cfg`` with features ``kind`` shows decoys (its first draw from ``rng``)."""
    u = rng.uniform()
    if cfg.condition == "decoy":
        return True
    return cfg.condition == "mixed" and not kind["dim"] and u < MIX_DECOY


def _parked() -> dict:
    return {"pose": translation(_HIDDEN), "visible": False, "diffuse": np.full(3, 0.5), "specular": 0.0}


def _material(rng: np.random.Generator) -> tuple[np.ndarray, float]:
    level = rng.uniform(0.05, 0.7)
    if rng.uniform() < 0.5:
        colour = np.full(3, level)
    else:
        colour = level * rng.uniform(0.5, 1.0, 3)
    glossy = rng.uniform() < 0.3  # drawn before the specular level: the draws' order fixes every sample
    return np.clip(colour, 0.0, 1.0), (float(rng.uniform(0.0, 0.4)) if glossy else 0.0)


def draw_decoys(cfg, p: dict, index: int, attempt: int, max_tries: int = 200) -> dict:
    """The decoys of v9 sample ``p`` (a v8 sample of ``cfg``, :func:`foveation_scenes.sample_params`, drawn
    for ``index`` and ``attempt``): {name: {"pose", "visible", "diffuse", "specular"}} for every decoy of
    :data:`DECOYS` (hidden ones parked under the floor)."""
    rng = np.random.default_rng([cfg.seed, index, attempt, 9])
    out = {n: _parked() for n in DECOYS}
    if not has_decoys(cfg, p["kind"], rng):
        return out
    eye, R, ball, radius = p["eye_pose"][:3, 3], p["eye_pose"][:3, :3], np.asarray(p["ball"]), p["radius"]
    size = p["room"]["size"]
    d_ball = float(np.linalg.norm(ball - eye))
    u_ball = (ball - eye) / d_ball
    a_ball = float(np.arcsin(min(1.0, radius / d_ball)))  # the ball's apparent radius (rad)
    names = list(DECOYS)
    count = 2 if rng.uniform() < 0.3 else 1
    chosen = [names[int(i)] for i in rng.choice(len(names), size=count, replace=False)]
    placed = []  # (direction, apparent radius) of the decoys placed so far
    for name in chosen:
        r_dec, length = DECOYS[name]
        for _ in range(max_tries):
            a_dec = a_ball * rng.uniform(*APPARENT_RATIO)
            behind = rng.uniform() < BEHIND_SHARE
            # the disc's centre up to 1.5 summed radii from the ball's (0: the ball at the muzzle), farther away
            if behind:
                sep = (a_ball + a_dec) * rng.uniform(0.0, 1.5)
                u = np.cos(sep) * u_ball + np.sin(sep) * _unit_perp(u_ball, rng)
            else:
                u = R @ field_direction(rng, cfg.max_field_deg)[0]
                sep = float(np.arccos(np.clip(u @ u_ball, -1, 1)))
                if sep < a_ball + a_dec + np.radians(3):
                    continue
            dist = r_dec / np.tan(a_dec)
            if behind and dist < d_ball + radius + r_dec + 0.1:
                continue
            if dist < 0.4 or dist + length > _room_exit(eye, u, size, 0.05):
                continue
            if any(np.arccos(np.clip(u @ v, -1, 1)) < a_dec + av + np.radians(2) for v, av in placed):
                continue
            if rng.uniform() < END_ON_SHARE:  # the axis along the line of sight, tilted away from the eye
                tilt = np.radians(rng.uniform(0, END_ON_TILT_DEG))
                axis = np.cos(tilt) * u + np.sin(tilt) * _unit_perp(u, rng)
            else:
                axis = _unit_perp(u, rng) if rng.uniform() < 0.5 else rng.normal(size=3)
                axis /= np.linalg.norm(axis)
                if axis @ u < 0:
                    axis = -axis
            face = eye + dist * u  # the centre of the face toward the eye; the body extends away from it
            centre = face + axis * length / 2
            if not (_in_room(face, size, 0.05) and _in_room(face + axis * length, size, 0.05)):
                continue
            if _in_front_of_ball(centre, np.hypot(r_dec, length / 2), eye, u_ball, d_ball, radius, a_ball):
                continue
            T = np.eye(4)
            T[:3, :3] = look_rotation(axis, up=_unit_perp(axis, rng))
            T[:3, 3] = centre
            diffuse, specular = _material(rng)
            out[name] = {"pose": T, "visible": True, "diffuse": diffuse, "specular": specular}
            placed.append((u, a_dec))
            break
    return out


def _in_front_of_ball(centre, bound: float, eye, u_ball, d_ball: float, radius: float, a_ball: float) -> bool:
    """Whether a decoy whose bounding sphere is (``centre``, ``bound``) may hide part of the ball: it
    overlaps the ball's disc (with a 1 degree margin) and is not wholly behind the ball."""
    v = centre - eye
    dv = float(np.linalg.norm(v))
    if dv - bound > d_ball + radius:
        return False
    reach = np.arcsin(min(1.0, bound / dv)) if dv > bound else np.pi
    return float(np.arccos(np.clip(v @ u_ball / dv, -1, 1))) < a_ball + reach + np.radians(1)


def add_decoys(cfg, p: dict, index: int, attempt: int) -> dict:
    """Make v8 sample ``p`` the v9 sample: its decoys (``p["decoys"]``) and a last meta column, whether a
    decoy was placed (the renderer sets it to whether one is in sight). Returns ``p``."""
    p["decoys"] = draw_decoys(cfg, p, index, attempt)
    shown = any(d["visible"] for d in p["decoys"].values())
    p["meta"] = np.append(p["meta"], np.float32(shown)).astype(np.float32)
    return p


def decoy_in_sight(scene, p: dict, batch: int, device: str = "cpu") -> bool:
    """Whether a line of sight from the eye reaches one of sample ``p``'s decoys first (toward its centre) in
    batch element ``batch`` of the placed ``scene`` (a decoy may stand behind furniture)."""
    from warp_vision.kernels.render import closest_hit

    shown = [n for n, d in p["decoys"].items() if d["visible"]]
    if not shown:
        return False
    eye = p["eye_pose"][:3, 3]
    d = np.stack([p["decoys"][n]["pose"][:3, 3] - eye for n in shown])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, obj, _ = closest_hit(scene, np.tile(eye, (len(d), 1)), d, batch=batch, device=device)
    return bool(np.any(np.asarray(obj) == np.array([scene.index(n) for n in shown])))


def add_decoy_objects(scene) -> None:
    """Add the decoys to a v8 room's scene (hidden until placed)."""
    from warp_vision.scene import Material

    for name, mesh in decoy_meshes().items():
        scene.add(name, mesh, Material((0.5, 0.5, 0.5)), translation(_HIDDEN))
        scene.set_visible(name, False)


def place_decoys(scene, ps: list) -> None:
    """Pose, show and colour the decoys of the v9 samples ``ps``, one per batch element."""
    from warp_vision.scene import Material

    for name in DECOYS:
        ds = [p["decoys"][name] for p in ps]
        scene.set_transform(name, np.stack([d["pose"] for d in ds]))
        scene.set_visible(name, [d["visible"] for d in ds])
        scene.set_material(name, [Material(tuple(d["diffuse"]), specular=d["specular"], shininess=24.0) for d in ds])
