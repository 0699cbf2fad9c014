"""Data for the intraocular nets (pupil and lens), synthesised by the virtual human itself.

**Pupil** (:class:`PupilDataConfig`, :func:`synthesize_pupil`). Each sample is one ONV of an everyday
scene (generator v8's rooms, lamps, balls, distractors and arms: :mod:`warp_vision.data.foveation_scenes`)
seen through a random current pupil, at a random light level. The teacher is Watson & Yellott's
steady-state pupil for the scene's adapting luminance (:func:`warp_vision.eye.pupil.adapting_luminance`),
which does not depend on the current pupil: the net has to infer the luminance from an ONV whose
brightness grows with the pupil's area.

- The current pupil: one per room block of 16 samples (each block is rendered in one launch, through one
  pupil), drawn from 2-8 mm in steps of ``PUPIL_STEP_MM``, which the loop's renderer also uses.
- The light level: the renderer is linear in every source (lamps, ambient light, emission), so a scene
  whose lights are all k times brighter has an ONV k times brighter. Each sample's adapting luminance is
  drawn log-uniformly over ``luminance_decades`` decades centred on the luminance of a 4 mm pupil
  (75 cd/m^2), and its ONV is the rendered one times the exposure that gives it that luminance. The
  stored ONV is the rendered one (float16); ``exposure`` is stored beside it and applied on loading.
- Held-out rooms (``rooms="heldout"``) come from v8's held-out room family.

**Lens** (:class:`LensDataConfig`, :func:`synthesize_lens`). Each sample is the central field (the
photoreceptors within ``central_deg``) of one eye looking at a textured card
(:func:`warp_vision.scene.textures.textured_card`) at 0.2-5 m, lit by two lamps of random colour, with
the lens at a random state: per block of 16 samples an accommodation (0-6 D) and a pupil (3-6 mm), and
per sample a card distance whose vergence lies within ``defocus_range_D`` of the accommodation (half the
samples near focus, sd 0.5 D). The target is the signed defocus, accommodation minus vergence. Only
the central photoreceptors are rendered and stored. Held-out sets (seed + 1000) have new textures, lamps
and distances.

Each sample's parameters come from generators seeded with (seed, block or index, stream), so a sample
does not depend on the chunk or shard that renders it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass

import numpy as np

from warp_vision.body import SIDES
from warp_vision.errors import require_positive, require_seeds

#: Bump when what a config renders changes (datasets are cached by config + version).
PUPIL_DATA_VERSION = 1
#: The current pupils of the data (and the loop's rendering grid), mm.
PUPIL_STEP_MM = 0.5
PUPIL_GRID_MM = tuple(float(d) for d in np.arange(2.0, 8.0 + 1e-9, PUPIL_STEP_MM))
#: The luminance the data are centred on: Watson & Yellott's for a 4 mm pupil, cd/m^2.
CENTRE_LUMINANCE = 75.17


@dataclass
class PupilDataConfig:
    """What a pupil dataset is; two datasets with equal configs are identical."""

    samples: int = 3000
    photoreceptors: int = 14_400  # P of the eye's retina (the foveation nets' retina)
    eye: str = "left"
    samples_per_receptor: int = 4  # S rays per photoreceptor and channel
    luminance_decades: float = 5.0  # the adapting luminances span this many decades, log-uniformly
    accommodation_D: float = 0.5
    rooms: str = "train"  # v8's room family: "train" or "heldout"
    seed: int = 0
    chunk_size: int = 256

    def validate(self) -> None:
        from warp_vision.data.foveation_scenes import ROOM_FAMILIES

        require_seeds(self)
        if self.eye not in SIDES:
            raise ValueError(f"eye: expected one of {SIDES}, got {self.eye!r}")
        if self.rooms not in ROOM_FAMILIES:
            raise ValueError(f"rooms: expected one of {sorted(ROOM_FAMILIES)}, got {self.rooms!r}")
        require_positive(self, ("samples", "photoreceptors", "samples_per_receptor", "chunk_size"), flags=False)
        if not 0 < self.luminance_decades <= 8:
            raise ValueError(f"luminance_decades: expected decades in (0, 8], got {self.luminance_decades}")
        if not 0 <= self.accommodation_D <= 10:
            raise ValueError(f"accommodation_D: expected 0 to 10 D, got {self.accommodation_D}")

    def manifest(self) -> dict:
        return {"generator": "pupil", "generator_version": PUPIL_DATA_VERSION, **asdict(self)}

    def key(self) -> str:
        """A short hash of the config (dataset cache directory names)."""
        return hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode()).hexdigest()[:12]

    def scene_config(self):
        """The v8 foveation config whose scenes (and retina) the samples show."""
        from warp_vision.data.foveation import FoveationDataConfig

        return FoveationDataConfig(samples=self.samples, photoreceptors=self.photoreceptors, eye=self.eye,
                                   samples_per_receptor=self.samples_per_receptor, generator=8, rooms=self.rooms,
                                   seed=self.seed, accommodation_D=self.accommodation_D)

    def heldout(self, samples: int | None = None) -> PupilDataConfig:
        """The held-out set of this config: held-out rooms, sample seeds offset by 1000."""
        return PupilDataConfig(**{**asdict(self), "rooms": "heldout", "seed": self.seed + 1000,
                                  "samples": samples or max(200, self.samples // 6)})


def block_pupil(cfg: PupilDataConfig, block: int) -> float:
    """The current pupil (mm) room block ``block`` is seen through."""
    return float(np.random.default_rng([cfg.seed, block, 71]).choice(PUPIL_GRID_MM))


def sample_luminance(cfg: PupilDataConfig, index: int) -> float:
    """Sample ``index``'s adapting luminance (cd/m^2), log-uniform around :data:`CENTRE_LUMINANCE`."""
    u = np.random.default_rng([cfg.seed, index, 72]).uniform(-0.5, 0.5)
    return float(CENTRE_LUMINANCE * 10.0 ** (u * cfg.luminance_decades))


def pupil_fields(cfg: PupilDataConfig) -> dict:
    return {"onv": ((3 * cfg.photoreceptors,), "float16"), "exposure": ((), "float32"), "pupil": ((), "float32"),
            "luminance": ((), "float32")}


def render_pupil_samples(cfg: PupilDataConfig, indices, retina, device: str = "cpu") -> dict:
    """Samples ``indices``: the rendered ONV, its exposure, the current pupil (mm), the adapting luminance;
    rendered a room block at a time (each block has its own pupil), the rows in the order of ``indices``."""
    from warp_vision.data.foveation import _render_v8, in_order
    from warp_vision.data.foveation_scenes import ROOM_BLOCK
    from warp_vision.eye.optics import NavarroEye
    from warp_vision.eye.pupil import adapting_luminance

    fcfg = cfg.scene_config()
    out, order = {k: [] for k in pupil_fields(cfg)}, []
    indices = [int(i) for i in indices]
    for block in sorted({i // ROOM_BLOCK for i in indices}):
        idx = [i for i in indices if i // ROOM_BLOCK == block]
        d = block_pupil(cfg, block)
        onv = _render_v8(fcfg, idx, retina, NavarroEye(cfg.accommodation_D, d), device)["onv"]
        raw = np.maximum(onv.astype(np.float64).mean(axis=1), 1e-12)
        lum = np.array([sample_luminance(cfg, i) for i in idx])
        out["onv"].append(onv)
        out["exposure"].append((lum / adapting_luminance(raw, d)).astype(np.float32))
        out["pupil"].append(np.full(len(idx), d, np.float32))
        out["luminance"].append(lum.astype(np.float32))
        order += idx
    return in_order(out, order, indices)


def synthesize_pupil(out_dir, cfg: PupilDataConfig, shard=(0, 1), batch: int = 16, device: str = "cpu",
                     progress: bool = True, log=print):
    """Render the pupil dataset ``cfg`` into ``out_dir`` (this shard's part), resuming what is there."""
    from warp_vision.data.foveation import make_retina
    from warp_vision.data.synth import open_store, pending, render_missing

    cfg.validate()
    retina = make_retina(cfg.scene_config())
    store = open_store(out_dir, cfg.manifest(), cfg.samples, cfg.chunk_size, pupil_fields(cfg), shard, retina, batch)
    todo, mine = pending(store)
    if todo:
        log(f"synthesising {todo:,} of {mine:,} pupil ONVs ({cfg.eye} eye, {cfg.rooms} rooms, "
            f"P={cfg.photoreceptors:,}, S={cfg.samples_per_receptor}) into {out_dir}")
        render_missing(store, lambda r: render_pupil_samples(cfg, r, retina, device), batch, progress, log)
    return store


def read_pupil_store(store) -> dict:
    """A pupil store's samples: ``onv`` [N, 3P] float32 with its exposure applied, ``pupil`` and
    ``luminance`` [N], and ``teacher`` [N], Watson & Yellott's diameter (mm) for the luminance."""
    import torch

    from warp_vision.eye.pupil import pupil_diameter_mm

    d = store.load(["onv", "exposure", "pupil", "luminance"])
    onv = torch.as_tensor(d["onv"]).float().mul_(torch.as_tensor(d["exposure"])[:, None])
    return {"onv": onv, "pupil": torch.as_tensor(d["pupil"]), "luminance": torch.as_tensor(d["luminance"]),
            "teacher": torch.as_tensor(np.asarray(pupil_diameter_mm(d["luminance"].astype(np.float64)), np.float32))}


# --- the lens ------------------------------------------------------------------------------------------

#: Bump when what a lens config renders changes (4: every set through the eye's own rays, EYE_RAY_SEED).
LENS_DATA_VERSION = 4
#: The seed of the eye's ray sampling through the pupil (which S points of the pupil each photoreceptor's
#: rays cross): part of the eye, like its retina, so every lens set, held-out ones included, and the loop
#: (``render_onv(..., seed=0)`` in sim/loop.py) use the same one; held-out sets differ in their scenes.
EYE_RAY_SEED = 0
#: Textured cards: CARD_SIZES_M (each in CARD_TEXTURES textures of CARD_VERTICES^2 vertices). A sample
#: at distance d shows the largest card whose third subtends at most CARD_MAX_RAD there (the whole card
#: 17-26 deg across), and looks at a random point of it, at least FILL_RAD from its edges: the card always
#: covers the central field the lens net reads, each sample sees its own patch of the pattern (so the
#: net cannot learn a few textures by heart), and the pattern's angular scale varies with the card. A new
#: set of textures (same geometry, so the cards' BVHs are built once) every TEXTURE_SET_BLOCKS blocks of
#: 16 samples: the default 16,000 samples see 400 textures. The texel's angular size (card size / CARD_VERTICES / d)
#: tells the distance within a size bin; the nets are therefore not given the accommodation, which with
#: the distance would give the defocus away (docs/RESULTS.md, "The pupil and the lens: the intraocular nets").
CARD_SIZES_M = tuple(float(s) for s in 3 * 0.021 * 1.58 ** np.arange(8))
CARD_TEXTURES = 2
CARD_VERTICES = 384
CARD_MAX_RAD = 0.154
TEXTURE_SET_BLOCKS = 40
FILL_RAD = np.radians(3.2)
#: The share of samples whose defocus is drawn near focus (normal, sd 0.5 D) rather than uniformly.
NEAR_FOCUS_SHARE = 0.5


@dataclass
class LensDataConfig:
    """What a lens dataset is: the central field of one eye's retina looking at a textured card at
    0.2-5 m, the lens at a random state near it; the target is the signed defocus (D)."""

    samples: int = 4000
    photoreceptors: int = 14_400  # P of the eye's retina (the foveation nets' retina)
    eye: str = "left"
    #: S rays per photoreceptor and channel: the loop renders the lens net's central field at its data's S.
    #: With the foveation ONV's 4, a blurred image is sampled at too few pupil points to tell its blur
    #: apart (docs/RESULTS.md: 0.28 D held-out against 0.16 D at 8)
    samples_per_receptor: int = 8
    central_deg: float = 2.0  # only photoreceptors within this eccentricity are rendered and read
    defocus_range_D: float = 2.5  # |accommodation - the card's vergence| up to this
    pupil_range_mm: tuple = (3.0, 6.0)  # the current pupil, per room block of 16
    card_vertices: int = CARD_VERTICES  # per side of each card's grid (fewer: coarser patterns, for tests)
    seed: int = 0
    chunk_size: int = 256

    def validate(self) -> None:
        require_seeds(self)
        if self.card_vertices < 8:
            raise ValueError(f"card_vertices: expected at least 8, got {self.card_vertices}")
        if self.eye not in SIDES:
            raise ValueError(f"eye: expected one of {SIDES}, got {self.eye!r}")
        require_positive(self, ("samples", "photoreceptors", "samples_per_receptor", "chunk_size"), flags=False)
        if not 0.5 <= self.central_deg <= 10:
            raise ValueError(f"central_deg: expected 0.5 to 10 degrees, got {self.central_deg}")
        if not 0 < self.defocus_range_D <= 5:
            raise ValueError(f"defocus_range_D: expected dioptres in (0, 5], got {self.defocus_range_D}")
        lo, hi = self.pupil_range_mm
        if not 2 <= lo <= hi <= 8:
            raise ValueError(f"pupil_range_mm: expected 2 <= low <= high <= 8, got {self.pupil_range_mm}")

    def manifest(self) -> dict:
        d = asdict(self)
        d["pupil_range_mm"] = list(d["pupil_range_mm"])
        if d["card_vertices"] == CARD_VERTICES:  # as before the field existed: cached datasets are found again
            del d["card_vertices"]
        return {"generator": "lens", "generator_version": LENS_DATA_VERSION, **d}

    def key(self) -> str:
        return hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode()).hexdigest()[:12]

    def heldout(self, samples: int | None = None) -> LensDataConfig:
        """The held-out set: new card textures, lamps and distances (seed + 1000)."""
        return LensDataConfig(**{**asdict(self), "seed": self.seed + 1000,
                                 "samples": samples or max(200, self.samples // 6)})


def central_photoreceptors(retina, central_deg: float) -> np.ndarray:
    """Indices of the photoreceptors within ``central_deg`` of the fovea (ascending)."""
    return np.nonzero(np.degrees(np.asarray(retina.rho)) <= central_deg)[0]


def lens_fields(cfg: LensDataConfig, n_central: int) -> dict:
    return {"onv": ((3 * n_central,), "float16"), "defocus": ((), "float32"), "accommodation": ((), "float32"),
            "distance": ((), "float32"), "pupil": ((), "float32")}


_CARDS: dict = {}


def card_scene(seed: int, texture_set: int = 0, vertices: int = CARD_VERTICES):
    """Texture set ``texture_set`` of dataset seed ``seed``: every card size in CARD_TEXTURES textures
    (hidden), and two lamps. The last one built is kept for the next call."""
    from warp_vision.scene import Material, Scene
    from warp_vision.scene.textures import textured_card

    if _CARDS.get("key") != (seed, texture_set, vertices):
        sc = Scene(ambient=(0.02, 0.02, 0.02))
        for k, size in enumerate(CARD_SIZES_M):
            for t in range(CARD_TEXTURES):
                sc.add(f"card{k}_{t}", textured_card(size, vertices, [seed, texture_set, k, t, 73]),
                       Material(vertex_colors=True), np.eye(4))
                sc.set_visible(f"card{k}_{t}", False)
        sc.add_light((0.0, 0.0, 0.0))
        sc.add_light((0.0, 0.0, 0.0))
        _CARDS.update(key=(seed, texture_set, vertices), scene=sc)
    return _CARDS["scene"]


def card_size_for(distance_m: float) -> float:
    """The size (m) of the card a lens sample at ``distance_m`` shows (the largest of CARD_SIZES_M whose
    third subtends at most CARD_MAX_RAD)."""
    return CARD_SIZES_M[max(i for i, s in enumerate(CARD_SIZES_M) if s / 3 <= CARD_MAX_RAD * distance_m or i == 0)]


def block_optics(cfg: LensDataConfig, block: int) -> tuple[float, float]:
    """(accommodation D, pupil mm) of room block ``block``: the accommodation uniform in 0-6 D (0.05 D
    steps), the pupil in ``pupil_range_mm`` (0.5 mm steps)."""
    rng = np.random.default_rng([cfg.seed, block, 74])
    acc = round(rng.uniform(0.0, 6.0) / 0.05) * 0.05
    lo, hi = cfg.pupil_range_mm
    return float(acc), float(rng.choice(np.arange(lo, hi + 1e-9, 0.5)))


def lens_sample(cfg: LensDataConfig, index: int, accommodation: float) -> dict:
    """Sample ``index``'s card (distance, size, texture, pose) and lamps, for a lens at ``accommodation``."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng([cfg.seed, index, 75])
    r = cfg.defocus_range_D
    for _ in range(1000):
        dd = np.clip(rng.normal(0, 0.5), -r, r) if rng.uniform() < NEAR_FOCUS_SHARE else rng.uniform(-r, r)
        vergence = accommodation - dd
        if 0.2 <= vergence <= 5.0:
            break
    else:  # pragma: no cover - accommodation within 0-6 D always finds one
        raise RuntimeError("no card distance found")
    d = 1.0 / vergence
    size = card_size_for(d)
    k = CARD_SIZES_M.index(size)
    # the line of sight meets the card at a random point (u, v) of it, at least FILL_RAD (at d) from its
    # edges, within 0.3 deg of the fovea; the card is turned up to 25 deg from facing the eye
    half = max(size / 2 - d * np.tan(FILL_RAD), 0.0)
    uv = rng.uniform(-half, half, 2)
    off = np.radians(0.3) * np.sqrt(rng.uniform()) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a)])
    sight = d * np.array([np.tan(off[0]), np.tan(off[1]), 1.0])
    tilt = Rotation.from_rotvec(np.append(rng.normal(0, 1, 2) * np.radians(25) / 2, rng.uniform(0, 2 * np.pi)))
    T = np.eye(4)
    T[:3, :3] = (Rotation.from_euler("y", np.pi) * tilt).as_matrix()  # +z (the card's face) toward the eye
    T[:3, 3] = sight - T[:3, :3] @ np.array([uv[0], uv[1], 0.0])
    lamps = []
    for _ in range(2):
        v = rng.normal(size=3)
        v[2] = -abs(v[2]) - 0.3  # on the eye's side of the card
        dist = d * rng.uniform(0.5, 1.5)
        lamps.append((sight + dist * v / np.linalg.norm(v), 1.0 + rng.uniform(-0.2, 0.2, 3),
                      dist**2 * rng.uniform(0.3, 1.5)))
    return {"distance": d, "defocus": accommodation - vergence, "card": f"card{k}_{rng.integers(CARD_TEXTURES)}",
            "transform": T, "lamps": lamps, "ambient": rng.uniform(0.0, 0.05) * np.ones(3)}


def render_lens_samples(cfg: LensDataConfig, indices, positions_mm: np.ndarray, device: str = "cpu") -> dict:
    """Samples ``indices``: the central ONV (float16), defocus (D), accommodation, distance, pupil."""
    from warp_vision.data.foveation_scenes import ROOM_BLOCK
    from warp_vision.eye.optics import NavarroEye
    from warp_vision.kernels.render import render_onv

    out = {k: [] for k in ("onv", "defocus", "accommodation", "distance", "pupil")}
    indices = [int(i) for i in indices]
    for block in sorted({i // ROOM_BLOCK for i in indices}):
        idx = [i for i in indices if i // ROOM_BLOCK == block]
        sc = card_scene(cfg.seed, block // TEXTURE_SET_BLOCKS, cfg.card_vertices)
        names = [o.name for o in sc.objects if o.name.startswith("card")]
        acc, pupil = block_optics(cfg, block)
        ps = [lens_sample(cfg, i, acc) for i in idx]
        B = len(ps)
        for name in names:
            sc.set_visible(name, np.array([p["card"] == name for p in ps]))
            sc.set_transform(name, np.stack([p["transform"] for p in ps]))
        for j, light in enumerate(sc.lights):
            light.position = np.stack([p["lamps"][j][0] for p in ps])
            light.color = np.stack([p["lamps"][j][1] for p in ps])
            light.intensity = np.array([p["lamps"][j][2] for p in ps])
        sc.set_ambient(np.stack([p["ambient"] for p in ps]))
        onv = render_onv(sc, positions_mm, NavarroEye(acc, pupil), np.tile(np.eye(4), (B, 1, 1)),
                         cfg.samples_per_receptor, seed=EYE_RAY_SEED, device=device)
        out["onv"].append(onv.cpu().numpy().astype(np.float16))
        out["defocus"].append(np.array([p["defocus"] for p in ps], np.float32))
        out["accommodation"].append(np.full(B, acc, np.float32))
        out["distance"].append(np.array([p["distance"] for p in ps], np.float32))
        out["pupil"].append(np.full(B, pupil, np.float32))
    return {k: np.concatenate(v) for k, v in out.items()}


def synthesize_lens(out_dir, cfg: LensDataConfig, shard=(0, 1), batch: int = 16, device: str = "cpu",
                    progress: bool = True, log=print):
    """Render the lens dataset ``cfg`` into ``out_dir`` (this shard's part), resuming what is there."""
    from warp_vision.data.foveation import FoveationDataConfig, make_retina
    from warp_vision.data.synth import open_store, pending, render_missing

    cfg.validate()
    retina = make_retina(FoveationDataConfig(photoreceptors=cfg.photoreceptors, eye=cfg.eye))
    central = central_photoreceptors(retina, cfg.central_deg)
    store = open_store(out_dir, cfg.manifest(), cfg.samples, cfg.chunk_size, lens_fields(cfg, len(central)), shard,
                       retina, batch)
    todo, mine = pending(store)
    if todo:
        log(f"synthesising {todo:,} of {mine:,} lens ONVs ({cfg.eye} eye, the {len(central):,} photoreceptors within "
            f"{cfg.central_deg:g} deg, S={cfg.samples_per_receptor}) into {out_dir}")
        pos = np.asarray(retina.positions_optical_mm)[central]
        render_missing(store, lambda r: render_lens_samples(cfg, r, pos, device), batch, progress, log)
    return store
