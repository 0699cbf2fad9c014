"""The foveal verification dataset: "is the ball at my fovea, and how far off?"

After a saccade the candidate sits at the fovea, within the saccade's landing error. Each sample is one
eye's central field (the photoreceptors within ``central_deg`` of the fovea, the foveation retina's own,
rendered at the foveation data's rays per photoreceptor, so the loop can read the field out of the ONV it
has rendered anyway) looking at one thing in a generator-v9 scene (its rooms, lighting, materials, arms,
distractors and decoys; :mod:`warp_vision.data.foveation_scenes`):

- with probability ``positive_share`` the ball;
- otherwise a look-alike, by class (:data:`LOOK_ALIKES`): a decoy's face (the barrel end-on is the
  cannon's muzzle as the eyes see it), a point on a hand or forearm, a bright object or luminous panel,
  the bright patch a lamp throws on the floor, the ball's shadow, a piece of furniture, or anything in
  view;

with the eye turned so the fixated point lies 0 to ``max_offset_deg`` from the optical axis (the landing
error). The label is 1 when the ball's centre lies within :data:`ACCEPT_DEG` of the axis and a line of sight
reaches it, else 0; the offset target is the ball's direction in the eye frame. Training rooms and held-out
rooms are v8's disjoint families (``rooms``). Every draw comes from a generator seeded with (seed, sample
index), so a sample does not depend on how it is batched.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass

import numpy as np

from warp_vision.data.foveation_scenes import _unit_perp
from warp_vision.data.intraocular import central_photoreceptors
from warp_vision.errors import require_positive, require_seeds

VERIFY_DATA_VERSION = 1
#: The label: the ball's centre within this angle of the optical axis (and in sight).
ACCEPT_DEG = 2.5
#: What the eye fixates in a sample: the ball, or one look-alike class. The class is stored per sample
#: (``cls``, an index into this tuple) so the false accepts can be counted per class.
CLASSES = ("ball", "decoy: barrel", "decoy: drum", "decoy: plate", "hand or forearm", "bright object", "lamp patch",
           "shadow", "furniture", "anything")
LOOK_ALIKES = CLASSES[1:]
#: The look-alikes' draw weights (a class a scene lacks, e.g. no decoy placed, is drawn again among the rest).
WEIGHTS = {"decoy": 0.30, "hand or forearm": 0.2, "bright object": 0.12, "lamp patch": 0.08, "shadow": 0.1,
           "furniture": 0.15, "anything": 0.05}
_ROOMS = ("train", "heldout")
#: deg: the range of the ball's apparent radius (log-uniform) in the samples
BALL_RADIUS_DEG = (0.3, 3.0)
#: the balls of the samples: the BALL_SIZES smallest of generator v8's radii (4 to 8 cm)
BALL_SIZES = 4
#: Fixations per placed scene: the eye looks at this many things (ball or look-alikes) in each v9 scene sample.
FIXATIONS = 4


@dataclass
class VerifyDataConfig:
    """What a verification dataset is; equal configs give identical datasets."""

    samples: int = 6000
    photoreceptors: int = 14_400  # P of the eye's retina (the foveation nets' retina)
    eye: str = "left"
    samples_per_receptor: int = 4  # S: the foveation ONV's, so the loop reads the field out of its ONV
    central_deg: float = 5.0  # the field: photoreceptors within this eccentricity
    positive_share: float = 0.4  # the eye aims at the ball (a look-alike next to it may bring it in, too)
    max_offset_deg: float = 2.0  # the fixation error after a saccade: 0 to this
    rooms: str = "train"  # generator v8/v9's room family: "train" or "heldout"
    seed: int = 0
    chunk_size: int = 256

    def validate(self) -> None:
        from warp_vision.body import SIDES

        require_seeds(self)
        require_positive(self, ("samples", "photoreceptors", "samples_per_receptor", "chunk_size"), flags=False)
        if self.eye not in SIDES:
            raise ValueError(f"eye: expected one of {SIDES}, got {self.eye!r}")
        if not 1.0 <= self.central_deg <= 15.0:
            raise ValueError(f"central_deg: expected 1 to 15 degrees, got {self.central_deg}")
        if not 0.0 < self.positive_share < 1.0:
            raise ValueError(f"positive_share: expected a share in (0, 1), got {self.positive_share}")
        if not 0.0 <= self.max_offset_deg < self.central_deg:
            raise ValueError(f"max_offset_deg: expected 0 to central_deg ({self.central_deg:g}), got "
                             f"{self.max_offset_deg}")
        if self.rooms not in _ROOMS:
            raise ValueError(f"rooms: expected one of {_ROOMS}, got {self.rooms!r}")

    def scene_config(self):
        """The generator-v9 foveation config whose scenes (rooms, lighting, objects) the samples look into."""
        from warp_vision.data.foveation import FoveationDataConfig

        return FoveationDataConfig(samples=-(-self.samples // FIXATIONS), photoreceptors=self.photoreceptors,
                                   eye=self.eye, samples_per_receptor=self.samples_per_receptor, seed=self.seed,
                                   generator=9, rooms=self.rooms, condition="mixed")

    def manifest(self) -> dict:
        return {"generator": "verify", "generator_version": VERIFY_DATA_VERSION, **asdict(self)}

    def key(self) -> str:
        return hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode()).hexdigest()[:12]

    def heldout(self, samples: int | None = None) -> VerifyDataConfig:
        """The held-out set: rooms of the held-out family (never trained on), other scenes (seed + 1000)."""
        return VerifyDataConfig(**{**asdict(self), "rooms": "heldout", "seed": self.seed + 1000,
                                   "samples": samples or max(200, self.samples // 6)})


def verify_fields(n_central: int) -> dict:
    return {"onv": ((3 * n_central,), "float16"), "label": ((), "float32"), "offset": ((2,), "float32"),
            "cls": ((), "int64"), "ball_ecc_deg": ((), "float32"), "ball_radius_deg": ((), "float32")}


def dataset_fields(cfg: VerifyDataConfig) -> dict:
    from warp_vision.data.foveation import make_retina

    return verify_fields(len(central_photoreceptors(make_retina(cfg.scene_config()), cfg.central_deg)))


def _first_hit(scene, origin, point, batch: int, device: str):
    """(object name or None, hit point) of the line of sight from ``origin`` toward ``point``."""
    from warp_vision.kernels.render import closest_hit

    d = np.asarray(point, float) - origin
    d /= np.linalg.norm(d)
    t, obj, _ = closest_hit(scene, origin[None], d[None], batch=batch, device=device)
    if obj[0] < 0:
        return None, None
    return scene.objects[int(obj[0])].name, origin + float(t[0]) * d


def _look_alike_points(scene, p: dict, batch: int, rng, device: str) -> dict:
    """Candidate points (world, m) of each look-alike kind that sample ``p``'s scene holds: {kind: point}."""
    eye = p["eye_pose"][:3, 3]
    out = {}
    shown = [n for n, d in p.get("decoys", {}).items() if d["visible"]]
    if shown:
        name = shown[int(rng.integers(len(shown)))]
        out["decoy"] = p["decoys"][name]["pose"][:3, 3]
    if p["arm"] is not None:
        names = [n for n in p["arm"] if any(k in n for k in ("lunate", "radius", "ulna"))]
        name = names[int(rng.integers(len(names)))]
        mesh = scene.objects[scene.index(name)].mesh
        v = np.asarray(mesh.vertices)[int(rng.integers(len(mesh.vertices)))]
        out["hand or forearm"] = p["arm"][name][:3, :3] @ v + p["arm"][name][:3, 3]
    bright = [n for n, d in p["distractors"].items() if d["visible"]]
    if bright:
        out["bright object"] = p["distractors"][bright[int(rng.integers(len(bright)))]]["pose"][:3, 3]
    lit = [i for i, s in enumerate(p["light"]["intensity"]) if s > 0]
    if lit:
        lamp = np.asarray(p["light"]["pos"][lit[int(rng.integers(len(lit)))]], float)
        out["lamp patch"] = np.array([lamp[0], lamp[1], 0.0]) + np.append(rng.normal(0, 0.15, 2), 0.0)
        # the ball's shadow: where the lamp's ray past the ball lands
        ball = np.asarray(p["ball"], float)
        d = ball - lamp
        d /= np.linalg.norm(d)
        name, hit = _first_hit(scene, ball + d * (p["radius"] * 1.05 + 0.01), ball + 2 * d, batch, device)
        if hit is not None:
            out["shadow"] = hit
    furniture = [o for o in scene.objects if o.name.startswith("object_")]
    if furniture:
        o = furniture[int(rng.integers(len(furniture)))]
        v = np.asarray(o.mesh.vertices)
        out["furniture"] = o.transform[0][:3, :3] @ v[int(rng.integers(len(v)))] + o.transform[0][:3, 3]
    R = p["eye_pose"][:3, :3]
    u = rng.normal(size=3)
    u[2] = abs(u[2]) + 2.0  # within about 40 deg of the sample's own gaze
    out["anything"] = eye + R @ (u / np.linalg.norm(u))
    return out


def _ball_in_sight(scene, eye, ball, radius: float, batch: int, device: str) -> bool:
    """Whether a line of sight reaches the ball: toward its centre or one of four points at 0.7 of its radius
    (a panel may hide part of it)."""
    from warp_vision.kernels.render import closest_hit

    u = (ball - eye) / np.linalg.norm(ball - eye)
    a = np.cross(u, [0.0, 0.0, 1.0]) if abs(u[2]) < 0.99 else np.cross(u, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    pts = ball + 0.7 * radius * np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]]) @ np.stack([a, b])
    d = pts - eye
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, obj, _ = closest_hit(scene, np.tile(eye, (len(d), 1)), d, batch=batch, device=device)
    return any(o >= 0 and scene.objects[int(o)].name.startswith("ball_") for o in obj)


def fixation(cfg: VerifyDataConfig, scene, p: dict, index: int, batch: int, device: str = "cpu") -> dict:
    """Sample ``index``'s fixation in its placed v9 scene ``p`` (batch element ``batch`` of ``scene``):
    {"pose": the eye's [4, 4] pose, "cls": index into CLASSES, "label", "offset": the ball's (yaw, pitch) in
    the eye frame, rad, "ball_ecc_deg", "ball_radius_deg"}."""
    from warp_vision.data.foveation import _landed_class
    from warp_vision.frames import gaze_angles, look_rotation

    rng = np.random.default_rng([cfg.seed, index, 64])
    eye = p["eye_pose"][:3, 3]
    ball = np.asarray(p["ball"], float)
    if rng.uniform() < cfg.positive_share:
        kind, point = "ball", ball
    else:
        points = _look_alike_points(scene, p, batch, rng, device)
        kinds = [k for k in WEIGHTS if k in points]
        w = np.array([WEIGHTS[k] for k in kinds])
        kind = kinds[int(rng.choice(len(kinds), p=w / w.sum()))]
        point = points[kind]
    u = point - eye
    u /= np.linalg.norm(u)
    off = np.radians(cfg.max_offset_deg) * np.sqrt(rng.uniform())
    axis = np.cos(off) * u + np.sin(off) * _unit_perp(u, rng)
    R = look_rotation(axis)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, eye
    hit, _ = _first_hit(scene, eye, point, batch, device)
    landed = _landed_class(hit)
    if kind == "ball":
        cls = "ball"
    elif kind == "decoy":
        cls = landed if landed.startswith("decoy") else "anything"
    else:
        cls = kind
    to_ball = R.T @ (ball - eye)
    ecc = float(np.degrees(np.arccos(np.clip(to_ball[2] / np.linalg.norm(to_ball), -1, 1))))
    in_sight = _ball_in_sight(scene, eye, ball, p["radius"], batch, device)
    label = float(in_sight and ecc <= ACCEPT_DEG)
    if label and cls != "ball":
        cls = "ball"  # a look-alike next to the ball (its shadow, a decoy behind it): the ball is at the fovea
    return {"pose": T, "cls": CLASSES.index(cls), "label": label, "offset": gaze_angles(to_ball).astype(np.float32),
            "ball_ecc_deg": ecc,
            "ball_radius_deg": float(np.degrees(np.arcsin(min(1.0, p["radius"] / np.linalg.norm(ball - eye)))))}


def _ball_at_loop_size(cfg: VerifyDataConfig, p: dict, index: int) -> dict:
    """Scene sample ``p`` with its ball moved along its line of sight so that its apparent radius is drawn
    log-uniformly from BALL_RADIUS_DEG (the sizes the loop's ball has at arm's length and beyond; v9's
    balls can fill the whole central field); the ball stays where it was if the room has no such place."""
    from warp_vision.data.foveation import BALL_RADII
    from warp_vision.data.foveation_scenes import _in_room, _room_exit

    rng = np.random.default_rng([cfg.seed, index, 65])
    size = int(rng.integers(BALL_SIZES))  # one of the smallest balls: the loop's has a radius of 4 cm
    eye, ball, radius = p["eye_pose"][:3, 3], np.asarray(p["ball"], float), BALL_RADII[size]
    u = (ball - eye) / np.linalg.norm(ball - eye)
    reach = _room_exit(eye, u, p["room"]["size"], radius + 0.05)  # the farthest the ball can be that way
    lo, hi = np.radians(BALL_RADIUS_DEG)
    least = np.arcsin(min(1.0, radius / max(0.98 * reach, radius)))
    a = np.exp(rng.uniform(np.log(max(lo, least)), np.log(max(hi, least))))
    moved = eye + u * radius / np.sin(a)
    if not _in_room(moved, p["room"]["size"], radius + 0.05) or np.linalg.norm(moved - eye) < radius + 0.3:
        return p
    return {**p, "ball": moved, "size": size, "radius": radius}


def render_verify_samples(cfg: VerifyDataConfig, indices, positions_mm: np.ndarray, device: str = "cpu") -> dict:
    """Samples ``indices`` of ``cfg``: the central ONV (float16) and the fields of :func:`fixation`, in order.
    Sample i looks into v9 scene sample ``i // FIXATIONS`` (each placed scene serves FIXATIONS fixations)."""
    from warp_vision.data import foveation_decoys as D
    from warp_vision.data import foveation_scenes as V
    from warp_vision.data.foveation import _placed_v8, in_order, make_eye
    from warp_vision.kernels.render import render_onv

    fcfg = cfg.scene_config()
    wanted = {int(i) for i in indices}
    out, order = {k: [] for k in ("onv", "label", "offset", "cls", "ball_ecc_deg", "ball_radius_deg")}, []
    for scene, idx, ps in _placed_v8(fcfg, sorted({i // FIXATIONS for i in wanted}), device):
        mine = [(i, k) for k, s in enumerate(idx) for i in range(s * FIXATIONS, (s + 1) * FIXATIONS) if i in wanted]
        ps = [_ball_at_loop_size(cfg, p, s) for p, s in zip(ps, idx)]
        V.place(scene, ps)
        D.place_decoys(scene, ps)
        fx = [fixation(cfg, scene, ps[k], i, k, device) for i, k in mine]  # (on the scene as placed for ps)
        rep = [ps[k] for _, k in mine]
        V.place(scene, rep)
        D.place_decoys(scene, rep)
        onv = render_onv(scene, positions_mm, make_eye(fcfg), np.stack([f["pose"] for f in fx]),
                         cfg.samples_per_receptor, seed=cfg.seed, device=device)
        out["onv"].append(onv.cpu().numpy().astype(np.float16))
        for key in ("label", "ball_ecc_deg", "ball_radius_deg"):
            out[key].append(np.array([f[key] for f in fx], np.float32))
        out["offset"].append(np.stack([f["offset"] for f in fx]))
        out["cls"].append(np.array([f["cls"] for f in fx], np.int64))
        order += [i for i, _ in mine]
    return in_order(out, order, indices)


def synthesize_verify(out_dir, cfg: VerifyDataConfig, shard=(0, 1), batch: int = 16, device: str = "cpu",
                      progress: bool = True, log=print):
    """Render the verification dataset ``cfg`` into ``out_dir`` (this shard's part), resuming what is there."""
    from warp_vision.data.foveation import make_retina
    from warp_vision.data.synth import open_store, pending, render_missing

    cfg.validate()
    retina = make_retina(cfg.scene_config())
    central = central_photoreceptors(retina, cfg.central_deg)
    store = open_store(out_dir, cfg.manifest(), cfg.samples, cfg.chunk_size, verify_fields(len(central)), shard,
                       retina, batch)
    todo, mine = pending(store)
    if todo:
        log(f"synthesising {todo:,} of {mine:,} verification ONVs ({cfg.eye} eye, the {len(central):,} photoreceptors "
            f"within {cfg.central_deg:g} deg, {cfg.rooms} rooms) into {out_dir}")
        pos = np.ascontiguousarray(np.asarray(retina.positions_optical_mm)[central])
        render_missing(store, lambda r: render_verify_samples(cfg, r, pos, device), batch, progress, log)
    return store
