"""Foveation data the virtual human synthesises itself: ONVs of a ball in a room, and the eye rotation
that would bring the ball onto the fovea.

Three generators, chosen by ``FoveationDataConfig.generator``: 8 is
:mod:`warp_vision.data.foveation_scenes` (ordinary balls in a family of everyday rooms, distractors, the
body's arms); 9 is v8 plus decoys, round things that are not the ball (:mod:`warp_vision.data.foveation_decoys`);
7, described here and the config's default (the training presets choose 9), is a glowing white ball in
one dim room.

Each v7 sample: the eye stands somewhere in a dim room looking in a random direction; a glowing white ball
of random size lies at 0.3 to 5 m, at a distance where it looks between :func:`min_apparent_diameter`
(1.5 deg, or 3 photoreceptor spacings where it lies) and ``MAX_APPARENT_DIAMETER_DEG`` (30 deg) across,
within ``max_field_deg`` of the optical axis, sometimes half hidden
behind a panel, never wholly hidden (a sample whose ball no line of sight reaches is redrawn); the lights
change colour and intensity. The target is (yaw, pitch) in radians, eye frame:
``yaw = atan2(x, z)`` (turning about the eye's +y axis, toward +x) and ``pitch = atan2(y, hypot(x, z))``
(elevation) of the ball centre's direction (:func:`warp_vision.frames.gaze_angles`). Every sample's
parameters come from its own generator, seeded with (dataset seed, sample index, attempt), so a sample
does not depend on the batch, chunk or shard that renders it: the same seed gives the same ONVs.

ONVs are stored as float16, which halves the dataset: the relative rounding error is at most 2^-11
(4.9e-4), which moves the net's standardised inputs by at most 0.003 of their spread, and a trained
foveation net's predictions by far less than its error (docs/RESULTS.md has the measurement).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from warp_vision.data.foveation_scenes import field_direction, occluder_pose
from warp_vision.data.store import ChunkedStore
from warp_vision.errors import require_positive, require_seeds
from warp_vision.frames import gaze_angles, gaze_directions, look_rotation

#: The scene generators (bump the newest when a generator changes what a config renders: datasets are
#: cached by config + version), each reproducible by ``FoveationDataConfig.generator``: 7 is the glowing
#: white ball in one dim room; 8 (:mod:`warp_vision.data.foveation_scenes`) ordinary balls in a family of
#: everyday rooms, among distractors, with the body's arms in view; 9 (:mod:`warp_vision.data.foveation_decoys`)
#: v8 plus decoys (cylinders seen end-on, such as a cannon's muzzle), each v9 sample v8's with decoys added.
GENERATORS = (7, 8, 9)
#: The generator a config uses unless it says otherwise: v7, so configs saved before the field existed
#: read as v7's; the training presets choose v9 (warp_vision.train.config.PRESETS).
GENERATOR_VERSION = 7


def generator_flag(text: str) -> int:
    """``--generator``'s value: a version as the docs name it, ``9`` or ``v9`` (a plain int type refuses ``v9``)."""
    import argparse

    t = text.strip()
    t = t[1:] if t[:1] in ("v", "V") else t
    if not t.isdigit():
        raise argparse.ArgumentTypeError(f"expected a generator version, one of {', '.join(map(str, GENERATORS))} "
                                          f"(or v{GENERATORS[0]} ...), got {text!r}")
    return int(t)


#: The dataset each training preset trains on (``python -m warp_vision.train --preset NAME``), as the settings
#: it changes from :class:`FoveationDataConfig`'s defaults: ``warp_vision.train.config.PRESETS`` is built on
#: these, and ``python -m warp_vision.data foveation --preset NAME`` builds the same dataset.
PRESET_DATA: dict[str, dict] = {
    "smoke": dict(samples=160, photoreceptors=400, samples_per_receptor=1),
    "quick": dict(samples=2000, generator=9),
    "default": dict(samples=12_000, generator=9),
    "paper": dict(samples=25_000, samples_per_receptor=8, generator=9),
}
#: Seeds of the two eyes' retinas: each eye has its own photoreceptor layout, hence its own net.
RETINA_SEEDS = {"left": 1, "right": 2}
ROOM_SIZE = (10.0, 10.0, 4.0)
#: Ball radii (m). Transforms are rigid, so each size is its own sphere; a sample shows one of them and
#: parks the others under the floor.
BALL_RADII = tuple(float(r) for r in np.geomspace(0.04, 0.2, 8))
#: The room's surfaces are dimmed to this fraction of make_room's albedos, and the white ball glows with
#: BALL_EMISSION (radiance, on top of the light it reflects), so the ball is the brightest thing in view
#: as in the paper's set-up (Fig. 7: a white ball on a dark retina) rather than one grey among many: a
#: point lamp's inverse-square fall-off otherwise makes a wall near the lamp brighter than a lit ball
#: far from it. With the room's full albedo and no emission the brightest photoreceptor missed the ball
#: in most samples; with these values it nearly always lies on it (docs/RESULTS.md has the measurement).
ROOM_ALBEDO = 0.1
BALL_EMISSION = 2.0
_HIDDEN = np.array([0.0, 0.0, -10.0])


@dataclass
class FoveationDataConfig:
    """What a foveation dataset is; two datasets with equal configs are identical."""

    samples: int = 4000  # number of ONVs
    photoreceptors: int = 14_400  # P per retina
    eye: str = "left"  # which eye's retina (left/right have different layouts)
    samples_per_receptor: int = 4  # S rays per photoreceptor and channel
    max_field_deg: float = 45.0  # the ball lies within this angle of the optical axis
    occluded_fraction: float = 0.2  # samples with a panel partly hiding the ball
    accommodation_D: float = 0.5  # the lens's accommodation (dioptres)
    pupil_diameter_mm: float = 4.0  # the pupil's diameter (mm)
    seed: int = 0  # seed of the scenes (the training command's --data-seed)
    chunk_size: int = 256  # ONVs per stored chunk (a shard's unit)
    generator: int = GENERATOR_VERSION  # 7 (glowing ball, dim room), 8 (ordinary
                                        # balls: foveation_scenes) or 9 (v8 + decoys)
    rooms: str = "train"  # v8: the room family, "train" or "heldout" (disjoint seeds)
    condition: str = "mixed"  # v8: "mixed" (training) or one held-out test condition

    def validate(self) -> None:
        from warp_vision.data.foveation_scenes import CONDITIONS, ROOM_FAMILIES

        require_seeds(self)
        require_positive(self, ("samples", "photoreceptors", "samples_per_receptor", "chunk_size"), flags=False)
        if self.eye not in RETINA_SEEDS:
            raise ValueError(f"eye: expected one of {sorted(RETINA_SEEDS)}, got {self.eye!r}")
        if not 0 < self.max_field_deg <= 80:
            raise ValueError(f"max_field_deg: expected degrees in (0, 80], got {self.max_field_deg}")
        if not 0 <= self.occluded_fraction <= 1:
            raise ValueError(f"occluded_fraction: expected 0 to 1, got {self.occluded_fraction}")
        if self.generator not in GENERATORS:
            raise ValueError(f"generator: expected one of {GENERATORS}, got {self.generator!r}")
        if self.rooms not in ROOM_FAMILIES:
            raise ValueError(f"rooms: expected one of {sorted(ROOM_FAMILIES)}, got {self.rooms!r}")
        if self.condition not in CONDITIONS:
            raise ValueError(f"condition: expected one of {list(CONDITIONS)}, got {self.condition!r}")
        if self.generator == 7 and (self.rooms, self.condition) != ("train", "mixed"):
            raise ValueError("rooms and condition belong to generators 8 and 9; generator 7 has one room and one "
                             "condition")
        if self.generator == 8 and self.condition == "decoy":
            raise ValueError("condition 'decoy' belongs to generator 9 (v8 has no decoys)")
        self._check_field()

    def _check_field(self) -> None:
        """Every direction of the field must admit a ball: a retina with too few photoreceptors sees, far
        out, only balls larger than the largest allowed, and synthesis would redraw the ball's direction
        (no longer uniform over the field) or never place it. One retina's visual angles, cached, and
        built by synthesis anyway."""
        ecc = np.radians(np.append(np.arange(0.0, self.max_field_deg, 0.5), self.max_field_deg))
        least = np.array([min_apparent_diameter(self, e) for e in ecc])
        too_big = np.flatnonzero(least >= np.radians(MAX_APPARENT_DIAMETER_DEG))
        if len(too_big):
            e = float(np.degrees(ecc[too_big[0]]))
            raise ValueError(
                f"photoreceptors: {self.photoreceptors:,} are too few for balls out to "
                f"max_field_deg={self.max_field_deg:g}: from {e:.1f} deg out they lie so far apart that the smallest "
                f"ball seen there ({np.degrees(least[too_big[0]]):.0f} deg across, {MIN_RECEPTORS_ACROSS:g} spacings) "
                f"is larger than the largest allowed ({MAX_APPARENT_DIAMETER_DEG:g} deg); use more photoreceptors or a "
                "smaller --max-field-deg")

    @classmethod
    def saved(cls, d: dict) -> FoveationDataConfig:
        """The config recorded as ``d`` (a checkpoint's ``data``); one saved before ``generator`` existed is v7's."""
        return cls(**{"generator": 7, **d})

    def key(self) -> str:
        """A short hash of the config (dataset cache directory names)."""
        return hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode()).hexdigest()[:12]

    def manifest(self) -> dict:
        """The config as the dataset store records it (with the generator's version). A v7 config's
        manifest is what v7 wrote (without v8's fields), so its cached datasets are found again."""
        d = dataclasses.asdict(self)
        version = d.pop("generator")
        if version == 7:
            del d["rooms"], d["condition"]
        return {"generator_version": version, **d}


def make_eye(cfg: FoveationDataConfig):
    """The eye the dataset is rendered with (its accommodation and pupil)."""
    from warp_vision.eye.optics import NavarroEye

    return NavarroEye(cfg.accommodation_D, cfg.pupil_diameter_mm)


def make_retina(cfg: FoveationDataConfig):
    from warp_vision.eye.retina import Retina

    return Retina.log_polar(cfg.photoreceptors, seed=RETINA_SEEDS[cfg.eye], eye=make_eye(cfg))


def make_scene(seed: int):
    """The room (fixed per dataset seed), the ball and an occluding panel (both moved per sample)."""
    import trimesh

    from warp_vision.scene import Material
    from warp_vision.scene.room import make_room

    sc = make_room(size=ROOM_SIZE, n_objects=6, seed=seed, ball_centre=_HIDDEN)
    for o in sc.objects:
        if o.static:
            o.material.diffuse = tuple(ROOM_ALBEDO * np.asarray(o.material.diffuse))
            o.material.reflectivity = 0.0
    for k, r in enumerate(BALL_RADII):
        sc.add_sphere(f"ball_{k}", r, _HIDDEN, Material((1.0, 1.0, 1.0), specular=0.4, shininess=32, smooth=True,
                                                              emission=(BALL_EMISSION,) * 3))
    sc.set_visible("ball", False)  # the room's own ball: the sized ones above replace it
    # 25 x 25 cm, 2 cm thick along its local z: posed face-on to the eye (z along the line of sight)
    panel = trimesh.creation.box((0.25, 0.25, 0.02))
    # as dim as the room: with the undimmed albedo it would outshine the room beside the ball
    sc.add("occluder", panel, Material(tuple(ROOM_ALBEDO * np.array([0.35, 0.3, 0.25]))))
    sc.lights[0].position = np.array([0.0, 0.0, ROOM_SIZE[2] - 0.6])  # a hanging lamp, not a hot spot on the ceiling
    return sc


#: The ball's apparent diameter is at least this (deg), and at least MIN_RECEPTORS_ACROSS times the
#: photoreceptor spacing where it lies (v7): a smaller ball falls between the periphery's photoreceptors
#: and leaves no trace in the ONV, making its target noise: such balls far in the periphery, under a flat
#: 1.5 deg floor alone, were most of a trained net's worst training errors (docs/RESULTS.md, "Figures behind
#: the code's constants").
MIN_APPARENT_DIAMETER_DEG = 1.5
MIN_RECEPTORS_ACROSS = 3.0
#: ... and at most this (deg, v7): a ball near the eye fills much of the field, mostly half hidden, and its
#: centre is where nothing of it is seen; such balls were the rest of the worst errors (the same entry).
MAX_APPARENT_DIAMETER_DEG = 30.0


@lru_cache(maxsize=4)
def _spacing_profile(photoreceptors: int, eye: str, accommodation_D: float, pupil_diameter_mm: float):
    """(eccentricity [rad] bin centres, median angular spacing [rad] of the photoreceptors' visual
    directions there): how far apart neighbouring photoreceptors look in the field, by eccentricity."""
    from scipy.spatial import cKDTree

    cfg = FoveationDataConfig(photoreceptors=photoreceptors, eye=eye, accommodation_D=accommodation_D,
                              pupil_diameter_mm=pupil_diameter_mm)
    ang = make_retina(cfg).visual_angles(make_eye(cfg))
    ang = ang[np.all(np.isfinite(ang), axis=1)]
    d = gaze_directions(ang)
    if len(d) < 2:
        return np.array([0.0, np.pi]), np.array([np.pi, np.pi])
    chord, _ = cKDTree(d).query(d, k=2)
    spacing = 2 * np.arcsin(np.clip(chord[:, 1] / 2, 0, 1))
    ecc = np.arccos(np.clip(d[:, 2], -1, 1))
    edges = np.radians(np.arange(0.0, 90.01, 2.5))
    centres, med = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (ecc >= lo) & (ecc < hi)
        if m.any():
            centres.append(0.5 * (lo + hi))
            med.append(np.median(spacing[m]))
    return np.array(centres), np.array(med)


def min_apparent_diameter(cfg: FoveationDataConfig, eccentricity: float) -> float:
    """The smallest apparent diameter (rad) a ball may have at ``eccentricity`` rad from the axis."""
    ecc, spacing = _spacing_profile(cfg.photoreceptors, cfg.eye, cfg.accommodation_D, cfg.pupil_diameter_mm)
    return max(np.radians(MIN_APPARENT_DIAMETER_DEG),
               MIN_RECEPTORS_ACROSS * float(np.interp(eccentricity, ecc, spacing)))


def sample_params(cfg: FoveationDataConfig, index: int, attempt: int = 0) -> dict:
    """The random scene parameters of sample ``index`` (independent of batching); ``attempt`` > 0 draws
    a replacement when attempt - 1 hid the ball (see :func:`ball_visible`)."""
    rng = np.random.default_rng([cfg.seed, index, attempt])
    half = np.array(ROOM_SIZE[:2]) / 2 - 0.6
    for _ in range(1000):
        eye = np.array([*rng.uniform(-half, half), rng.uniform(0.9, 1.8)])
        yaw0 = rng.uniform(-np.pi, np.pi)
        pitch0 = rng.uniform(-0.35, 0.35)
        fwd = np.array([np.cos(pitch0) * np.cos(yaw0), np.cos(pitch0) * np.sin(yaw0), np.sin(pitch0)])
        R = look_rotation(fwd)
        u_eye, ct, phi = field_direction(rng, cfg.max_field_deg)  # uniform over the solid angle of the field
        size = int(rng.integers(len(BALL_RADII)))
        radius = BALL_RADII[size]
        far = min(5.0, radius / np.sin(min_apparent_diameter(cfg, np.arccos(ct)) / 2))
        near = max(0.3, radius / np.sin(np.radians(MAX_APPARENT_DIAMETER_DEG / 2)))
        if near >= far:  # this size cannot be seen there within the limits: draw again
            continue
        dist = float(np.exp(rng.uniform(np.log(near), np.log(far))))
        ball = eye + dist * (R @ u_eye)
        lo = np.array([-ROOM_SIZE[0] / 2, -ROOM_SIZE[1] / 2, 0.0]) + radius + 0.05
        hi = np.array([ROOM_SIZE[0] / 2, ROOM_SIZE[1] / 2, ROOM_SIZE[2]]) - radius - 0.05
        if dist > radius + 0.05 and np.all(ball > lo) and np.all(ball < hi):
            break
    else:  # pragma: no cover - every direction admits a ball (FoveationDataConfig._check_field) and the room is large
        raise RuntimeError("could not place the ball inside the room")
    occluded = bool(rng.uniform() < cfg.occluded_fraction)
    Tp = occluder_pose(rng, eye, ball, R, phi, radius, occluded)
    light_colour = rng.uniform(0.6, 1.0, 3)
    light_intensity = float(rng.uniform(3.0, 15.0))
    yaw, pitch = (float(a) for a in gaze_angles(u_eye))
    Te = np.eye(4)
    Te[:3, :3] = R
    Te[:3, 3] = eye
    return {
        "eye_pose": Te,
        "ball": ball,
        "radius": radius,
        "size": size,
        "panel_pose": Tp,
        "light_colour": light_colour,
        "light_intensity": light_intensity,
        "target": np.array([yaw, pitch], dtype=np.float32),
        "meta": np.array([dist, radius, float(occluded)], dtype=np.float32),
    }


def _place(scene, ps: list) -> None:
    """Move the balls, the panel and the lamp of ``scene`` to the samples ``ps`` (one per batch element)."""
    B = len(ps)
    for k in range(len(BALL_RADII)):
        T = np.broadcast_to(np.eye(4), (B, 4, 4)).copy()
        T[:, :3, 3] = [p["ball"] if p["size"] == k else _HIDDEN for p in ps]
        scene.set_transform(f"ball_{k}", T)
        scene.set_visible(f"ball_{k}", [p["size"] == k for p in ps])
    scene.set_transform("occluder", np.stack([p["panel_pose"] for p in ps]))
    scene.set_visible("occluder", [bool(p["meta"][2]) for p in ps])
    light = scene.lights[0]
    light.color = np.stack([p["light_colour"] for p in ps])
    light.intensity = np.array([p["light_intensity"] for p in ps])


def ball_sight_fraction(scene, p: dict, batch: int, rings=(0.8,), per_ring: int = 8, device: str = "cpu") -> float:
    """Share of lines of sight from the eye that reach the ball first in batch element ``batch`` of the
    placed ``scene``: one to the ball's centre and ``per_ring`` to points at each of ``rings`` (fractions of
    its apparent radius)."""
    from warp_vision.kernels.render import closest_hit

    eye = p["eye_pose"][:3, 3]
    fwd = p["ball"] - eye
    R = look_rotation(fwd)
    a = np.linspace(0, 2 * np.pi, per_ring, endpoint=False)
    circle = np.stack([np.cos(a), np.sin(a), np.zeros(per_ring)], 1) @ R.T
    d = np.concatenate([fwd[None]] + [fwd + f * p["radius"] * circle for f in rings])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, obj, _ = closest_hit(scene, np.tile(eye, (len(d), 1)), d, batch=batch, device=device)
    return float(np.mean(obj == scene.index(f"ball_{p['size']}")))


def ball_visible(scene, p: dict, batch: int, device: str = "cpu") -> bool:
    """Whether any of 9 lines of sight from the eye (to the ball's centre and to 8 points at 0.8 of its
    apparent radius) reaches the ball first in batch element ``batch`` of the placed ``scene``."""
    return ball_sight_fraction(scene, p, batch, device=device) > 0


def render_samples(cfg: FoveationDataConfig, indices, scene, retina, eye, device: str = "cpu") -> dict:
    """Render samples ``indices`` of ``cfg`` (v7 in one batch of ``scene``; v8 and v9 per room, building each
    room's scene, ``scene`` unused):
    {"onv": [B, 3P] float16, "target": [B, 2], "meta": [B, 3 (v7), 7 (v8) or 8 (v9)]}."""
    if cfg.generator >= 8:
        return _render_v8(cfg, indices, retina, eye, device)
    return _render_v7(cfg, indices, scene, retina, eye, device)


def _render_v7(cfg: FoveationDataConfig, indices, scene, retina, eye, device: str = "cpu") -> dict:
    """Render samples ``indices`` in one batch: {"onv": [B, 3P] float16, "target": [B, 2], "meta": [B, 3]}.

    A sample whose ball no line of sight reaches (behind a piece of furniture, or the panel) is redrawn
    (``attempt`` + 1) until one does: a hidden ball has no place to foveate, and its target would be noise.
    """
    from warp_vision.kernels.render import render_onv

    attempts = [0] * len(indices)
    ps = [sample_params(cfg, int(i)) for i in indices]
    todo = list(range(len(ps)))
    while todo:
        _place(scene, ps)
        todo = [k for k in todo if not ball_visible(scene, ps[k], k, device)]
        for k in todo:
            attempts[k] += 1
            if attempts[k] > 50:  # pragma: no cover - the room is mostly empty; never seen
                raise RuntimeError(f"sample {indices[k]}: no visible ball in 50 draws")
            ps[k] = sample_params(cfg, int(indices[k]), attempts[k])
    onv = render_onv(scene, retina, eye, np.stack([p["eye_pose"] for p in ps]), cfg.samples_per_receptor, seed=cfg.seed,
                     device=device)
    return {
        "onv": onv.cpu().numpy().astype(np.float16),
        "target": np.stack([p["target"] for p in ps]),
        "meta": np.stack([p["meta"] for p in ps]),
    }


#: v8's meta columns (v7 has the first three)
META_V8 = ("distance_m", "radius_m", "occluded", "glow", "distractor", "arm", "brightness")
#: v9's: v8's and whether a decoy is in view
META_V9 = META_V8 + ("decoy",)


def meta_columns(generator: int) -> tuple[str, ...]:
    """The names of a generator's meta columns (the dataset's ``meta`` field, in order)."""
    return {7: META_V8[:3], 8: META_V8, 9: META_V9}[generator]


def _render_placed(cfg: FoveationDataConfig, scene, ps: list, retina, eye, device: str = "cpu") -> np.ndarray:
    """The ONVs [B, 3P] float32 of a room's scene placed for the samples ``ps`` (:func:`_placed_v8`)."""
    from warp_vision.kernels.render import render_onv

    poses = np.stack([p["eye_pose"] for p in ps])
    return render_onv(scene, retina, eye, poses, cfg.samples_per_receptor, seed=cfg.seed, device=device).cpu().numpy()


def _render_v8(cfg: FoveationDataConfig, indices, retina, eye, device: str = "cpu") -> dict:
    """v8 and v9: the samples grouped by room (:func:`_placed_v8`), each room's batch rendered at once; the
    rows come back in the order of ``indices``."""
    out, order = {"onv": [], "target": [], "meta": []}, []
    for scene, idx, ps in _placed_v8(cfg, indices, device):
        out["onv"].append(_render_placed(cfg, scene, ps, retina, eye, device).astype(np.float16))
        out["target"].append(np.stack([p["target"] for p in ps]))
        out["meta"].append(np.stack([p["meta"] for p in ps]))
        order += idx
    return in_order(out, order, indices)


def in_order(parts: dict, order: list, indices) -> dict:
    """``parts`` ({field: [row blocks]}) rendered group by group, their rows the samples ``order``, as one
    array per field whose rows follow ``indices`` (each of them in ``order``)."""
    row = {i: r for r, i in enumerate(order)}
    take = [row[int(i)] for i in indices]
    return {k: np.concatenate(v)[take] for k, v in parts.items()}


def _placed_v8(cfg: FoveationDataConfig, indices, device: str = "cpu"):
    """Yield ``(scene, idx, ps)`` per room: the room's scene (built once; the last one is kept for the next
    call) placed for its samples ``idx`` (in the order given), whose parameters are ``ps``. A sample whose ball no
    line of sight reaches (or, condition "decoy", with no decoy in sight) is redrawn. v9 adds each
    sample's decoys to v8's sample."""
    from warp_vision.data import foveation_decoys as D
    from warp_vision.data import foveation_scenes as V

    indices = [int(i) for i in indices]
    decoys = cfg.generator >= 9
    limits = lambda ecc: (min_apparent_diameter(cfg, ecc), np.radians(MAX_APPARENT_DIAMETER_DEG))  # noqa: E731

    def draw(i: int, attempt: int) -> dict:
        p = V.sample_params(cfg, i, attempt, BALL_RADII, limits)
        return D.add_decoys(cfg, p, i, attempt) if decoys else p

    for block in sorted({i // V.ROOM_BLOCK for i in indices}):
        idx = [i for i in indices if i // V.ROOM_BLOCK == block]
        key = (V.ROOM_FAMILIES[cfg.rooms], cfg.seed, block)
        with_arms = cfg.condition in ("mixed", "arm")
        if _SCENE_V8.get("key") != (key, with_arms, decoys):
            scene = V.make_scene(*key, BALL_RADII, with_arms=with_arms)
            if decoys:
                D.add_decoy_objects(scene)
            _SCENE_V8.update(key=(key, with_arms, decoys), scene=scene)
        scene = _SCENE_V8["scene"]
        attempts = [0] * len(idx)
        ps = [draw(i, 0) for i in idx]
        todo = list(range(len(ps)))
        while todo:
            V.place(scene, ps)
            if decoys:  # and the decoy column: one in sight (a "decoy" sample without one is redrawn)
                D.place_decoys(scene, ps)
                for k in todo:
                    ps[k]["meta"][-1] = D.decoy_in_sight(scene, ps[k], k, device)
            todo = [k for k in todo if not ball_visible(scene, ps[k], k, device)
                    or (cfg.condition == "decoy" and not ps[k]["meta"][-1])]
            for k in todo:
                attempts[k] += 1
                if attempts[k] > 50:  # pragma: no cover - never seen
                    raise RuntimeError(f"sample {idx[k]}: no visible ball (or, condition decoy, no decoy in sight) in "
                                       "50 draws")
                ps[k] = draw(idx[k], attempts[k])
        yield scene, idx, ps


#: What a line of sight from the eye can reach first, by class (:func:`ball_signal`'s ``landed_on``).
LANDED_ON = ("ball", "decoy: barrel", "decoy: drum", "decoy: plate", "bright object", "arm", "panel", "furniture: box",
             "furniture: cylinder", "wall, floor or ceiling", "nothing")
#: :func:`ball_signal`'s disc: the photoreceptors within this many apparent radii of the ball's centre.
DISC_RADII = 1.1
#: The ring :func:`ball_signal` compares the ball with: beyond the disc, out to this many apparent radii
#: plus RING_MARGIN_DEG.
RING_RADII = 2.0
RING_MARGIN_DEG = 1.0


def _landed_class(name: str | None) -> str:
    from warp_vision.data.foveation_decoys import DECOYS
    from warp_vision.data.foveation_scenes import DISTRACTORS
    from warp_vision.scene.room import furniture_shape

    if name is None:
        return "nothing"
    if name.startswith("ball_"):
        return "ball"
    if name in DECOYS:
        return f"decoy: {name.removeprefix('decoy_')}"
    if name in DISTRACTORS:
        return "bright object"
    if name.startswith("arm_"):
        return "arm"
    if name == "occluder":
        return "panel"
    return f"furniture: {furniture_shape(name)}" if name.startswith("object_") else "wall, floor or ceiling"


def ball_signal(cfg: FoveationDataConfig, indices, retina, eye, directions=None, device: str = "cpu",
                with_onv: bool = False, progress: bool = False, chance_directions=None) -> dict:
    """How much of each sample's ball its ONV holds: samples ``indices`` of ``cfg`` (v8 or v9) are rendered
    room by room as the dataset has them and again, everything placed alike, with the ball hidden. Per
    sample, in the order of ``indices``:

    - ``"receptors"`` [N] int: the photoreceptors that see the ball: those within :data:`DISC_RADII`
      apparent radii of its centre whose response the ball changes (a partly hidden ball counts its
      visible part);
    - ``"contrast"`` [N] float: how far the ball's mean colour on those photoreceptors lies from the mean
      colour of the ring around the disc (out to :data:`RING_RADII` apparent radii plus
      :data:`RING_MARGIN_DEG`), relative to the ring's: ``|rgb_ball - rgb_ring| / |rgb_ring|`` (0 where no
      photoreceptor sees the ball, NaN where none sees the ring);
    - ``"landed_on"`` [N] str, with ``directions`` ([N, 2] yaw, pitch in the eye frame, radians; a net's
      estimates): the class (:data:`LANDED_ON`) of what each direction from the eye reaches first;
    - ``"chance_landed_on"`` [N] str, with ``chance_directions`` (the same form): the same for directions that
      owe nothing to the ONV (for example other samples' targets), what an estimate would land on by chance;
    - ``"onv"`` [N, 3P] float32, with ``with_onv``: the ONVs as rendered (the dataset stores them as float16).

    ``progress``: a progress bar over the samples.
    """
    from tqdm import tqdm

    from warp_vision.kernels.render import closest_hit

    if cfg.generator < 8:
        raise ValueError(f"ball_signal: generator {cfg.generator}: v8 and v9 only (v7's balls glow in a fixed room)")
    indices = [int(i) for i in indices]
    if len(set(indices)) != len(indices):
        raise ValueError("ball_signal: indices must be distinct")
    probes = {}  # out key -> [N, 2] directions followed from the eye
    for key, name, v in (("landed_on", "directions", directions),
                         ("chance_landed_on", "chance_directions", chance_directions)):
        if v is not None:
            probes[key] = np.asarray(v, dtype=np.float64)
            if probes[key].shape != (len(indices), 2):
                raise ValueError(f"{name}: expected [{len(indices)}, 2] (yaw, pitch), got {probes[key].shape}")
    where = {i: n for n, i in enumerate(indices)}
    P = retina.P
    seen = gaze_directions(retina.visual_angles(eye))  # [P, 3]; NaN where the chief ray is blocked
    cols = {c: k for k, c in enumerate(meta_columns(cfg.generator))}
    out = {"receptors": np.zeros(len(indices), np.int64), "contrast": np.zeros(len(indices))}
    if with_onv:
        out["onv"] = np.zeros((len(indices), 3 * P), np.float32)
    for key in probes:
        out[key] = np.empty(len(indices), dtype=object)
    bar = tqdm(total=len(indices), desc="rendering with and without the balls", unit="ONV", disable=not progress)
    for scene, idx, ps in _placed_v8(cfg, indices, device):
        with_ball = _render_placed(cfg, scene, ps, retina, eye, device)
        for key, dirs in probes.items():
            for k, (i, p) in enumerate(zip(idx, ps)):
                d = p["eye_pose"][:3, :3] @ gaze_directions(dirs[where[i]])
                _, obj, _ = closest_hit(scene, p["eye_pose"][:3, 3][None], d[None], batch=k, device=device)
                out[key][where[i]] = _landed_class(scene.objects[int(obj[0])].name if obj[0] >= 0 else None)
        for name in (o.name for o in scene.objects if o.name.startswith("ball_")):  # place() shows them again
            scene.set_visible(name, False)
        without = _render_placed(cfg, scene, ps, retina, eye, device)
        for k, (i, p) in enumerate(zip(idx, ps)):
            n = where[i]
            rgb, rgb0 = with_ball[k].reshape(P, 3), without[k].reshape(P, 3)
            cos = seen @ gaze_directions(np.asarray(p["target"], np.float64))
            radius = np.arcsin(min(1.0, p["meta"][cols["radius_m"]] / p["meta"][cols["distance_m"]]))
            on_disc = cos > np.cos(DISC_RADII * radius)  # the disc's edge photoreceptors sample it in part
            ball = on_disc & (np.abs(rgb - rgb0).sum(1) > 0)
            ring = ~on_disc & (cos > np.cos(RING_RADII * radius + np.radians(RING_MARGIN_DEG)))
            if with_onv:
                out["onv"][n] = with_ball[k]
            out["receptors"][n] = int(ball.sum())
            if ball.any():
                ring_rgb = rgb[ring].mean(0) if ring.any() else np.full(3, np.nan)
                with np.errstate(divide="ignore", invalid="ignore"):  # a black ring: infinite contrast
                    out["contrast"][n] = float(np.linalg.norm(rgb[ball].mean(0) - ring_rgb) / np.linalg.norm(ring_rgb))
        bar.update(len(idx))
    bar.close()
    return out


_SCENE_V8: dict = {}


def dataset_fields(cfg: FoveationDataConfig) -> dict:
    meta = len(meta_columns(cfg.generator))
    return {"onv": ((3 * cfg.photoreceptors,), "float16"), "target": ((2,), "float32"), "meta": ((meta,), "float32")}


def synthesize(out_dir, cfg: FoveationDataConfig, shard=(0, 1), batch: int = 16, device: str = "cpu",
               progress: bool = True, log=print) -> ChunkedStore:
    """Render the dataset ``cfg`` into ``out_dir`` (or this shard's part of it), resuming what is there.

    Chunks already written (and recorded) are kept; the rest are rendered ``batch`` samples per launch.
    Returns the store. ``out_dir/retina.npz`` holds the retina the ONVs were rendered with.
    """
    from warp_vision.data.synth import open_store, pending, render_missing

    cfg.validate()
    retina = make_retina(cfg)
    store = open_store(out_dir, cfg.manifest(), cfg.samples, cfg.chunk_size, dataset_fields(cfg), shard, retina, batch)
    todo, mine = pending(store)
    if not todo:
        return store
    log(f"synthesising {todo:,} of {mine:,} ONVs (P={cfg.photoreceptors:,}, S={cfg.samples_per_receptor}) into "
        f"{out_dir}")
    eye = make_eye(cfg)
    scene = make_scene(cfg.seed) if cfg.generator == 7 else None
    render_missing(store, lambda r: render_samples(cfg, r, scene, retina, eye, device), batch, progress, log)
    return store
