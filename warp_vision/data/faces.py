"""Faces for active face recognition: parametric 3D heads (``anny``), and ONVs of them across poses.

The paper scanned 50 subjects; we draw them from ``anny``, a parametric human model built on
MakeHuman's CC0 assets. Identity ``i`` of seed ``s`` has its own generator, seeded with (s, i), so the
first k identities of a set of 50 are the k identities of a set of k (tests use a few).

- **Shape:** anny's head topology (4,538 vertices with eyes and mouth) under the identity's
  phenotypes: gender, age (adults), muscle, weight, proportions and the african/asian/caucasian
  blend. On top come local changes of the head's regions (cheeks, chin, ears, eyebrows, eyes,
  forehead, head, mouth, neck, nose), each drawn from N(0, 0.4^2) clipped to [-1, 1].
- **Colour:** anny ships no colour texture. Each vertex's albedo is built procedurally from the
  identity's skin tone, lip colour, brow (hair) colour and iris colour. The regions come from anny's
  UV masks (face, lips, eyelids, ears: MPFB2's skin masks, sampled at each vertex's texture
  coordinates) and its part segmentation (eyeballs, eye and mouth cavities, tongue). The brows have
  no mask; they are an arched band above each eye, placed on the identity's own geometry.
- **Frame (anny's):** metres, +z up, the face looking toward -y, the head's left toward +x.

A sample is one identity in one pose. The head turns about its centre (at eye height) by ``yaw``
(about +z; positive turns the face toward +x, its left) and then ``pitch`` (positive lifts the chin).
Both run over ``-max_pose_deg`` to ``max_pose_deg`` in ``pose_step_deg`` steps: with the defaults that
is 30 x 30 poses, each angle one of -29, -27, ..., 29 degrees. The eye stands ``distance_m``
in front of the frontal face's centre (midway between the eyes and the mouth) and fixates that
centre wherever the pose puts it. It is accommodated to that distance. The lighting is fixed: a
warm key light, a cool fill light, ambient light and a grey backdrop. ONVs are stored as float16, as
for the foveation data.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from warp_vision.data.store import ChunkedStore
from warp_vision.errors import require_positive, require_seeds
from warp_vision.fileio import NPY_FORMAT_ERRORS, atomic_write
from warp_vision.frames import look_rotation

#: Bump when identities or renders change for the same config (caches are keyed by it).
GENERATOR_VERSION = 1
#: anny's model: the head topology and rig, every phenotype (with the ethnic blend), default local changes.
ANNY_MODEL = dict(rig="makehuman-head", topology="head", local_changes="default", phenotypes="all")
#: Local changes drawn per identity: those whose region (after an optional l-/r- side prefix) is one of these.
FACE_REGIONS = ("cheek", "chin", "ear", "eyebrows", "eye", "forehead", "head", "mouth", "neck", "nose")
RETINA_SEEDS = {"left": 11, "right": 12}

# albedo palettes (linear RGB); an identity's colour is a random point between two neighbours
SKIN_TONES = np.array([[0.80, 0.60, 0.50], [0.68, 0.48, 0.38], [0.55, 0.37, 0.27], [0.40, 0.25, 0.17],
                       [0.26, 0.16, 0.11], [0.15, 0.09, 0.07]])
HAIR_COLOURS = np.array([[0.03, 0.025, 0.02], [0.10, 0.06, 0.035], [0.25, 0.15, 0.08], [0.55, 0.42, 0.25],
                         [0.45, 0.18, 0.08], [0.55, 0.55, 0.55]])
IRIS_COLOURS = np.array([[0.20, 0.10, 0.04], [0.35, 0.25, 0.10], [0.20, 0.35, 0.55], [0.25, 0.40, 0.25],
                         [0.40, 0.45, 0.50]])
SCLERA = np.array([0.80, 0.78, 0.74])
CAVITY = np.array([0.06, 0.03, 0.03])
TONGUE = np.array([0.55, 0.22, 0.22])


#: The dataset each face training preset trains on (``python -m warp_vision.train faces --preset NAME``), as
#: the settings it changes from :class:`FaceDataConfig`'s defaults (the paper's poses):
#: ``warp_vision.train.config.FACE_PRESETS`` is built on these, and ``python -m warp_vision.data faces --preset
#: NAME`` builds the same dataset.
PRESET_DATA: dict[str, dict] = {
    "smoke": dict(identities=3, pose_step_deg=15.0, photoreceptors=400, samples_per_receptor=1),  # 3 x 4 x 4 poses
    "default": dict(pose_step_deg=4.0),  # 50 identities x 15 x 15 poses: 11,250 ONVs
    "paper": dict(pose_step_deg=2.0),  # the paper's 30 x 30 poses: 45,000 ONVs
}


@dataclass
class FaceDataConfig:
    """What a face dataset is; equal configs give identical datasets."""

    identities: int = 50  # distinct people
    pose_step_deg: float = 2.0  # yaw and pitch step
    max_pose_deg: float = 30.0  # poses span -max to +max degrees in both angles
    photoreceptors: int = 14_400  # P per retina
    eye: str = "left"  # which eye's retina (the recognition is monocular)
    samples_per_receptor: int = 4  # S rays per photoreceptor and channel
    distance_m: float = 0.5  # eye to the face's centre
    pupil_diameter_mm: float = 4.0  # the pupil's diameter (mm)
    identity_seed: int = 0  # seed of the identities (shape and colour)
    seed: int = 0  # seed of the rays (the training command's --data-seed)
    chunk_size: int = 256  # ONVs per stored chunk (a shard's unit)

    def validate(self) -> None:
        require_seeds(self)
        require_positive(self, ("identities", "photoreceptors", "samples_per_receptor", "chunk_size"), flags=False)
        if self.eye not in RETINA_SEEDS:
            raise ValueError(f"eye: expected one of {sorted(RETINA_SEEDS)}, got {self.eye!r}")
        if not 0 < self.pose_step_deg <= 2 * self.max_pose_deg <= 120:
            raise ValueError("pose_step_deg and max_pose_deg: expected 0 < step <= 2 max <= 120 degrees, got "
                             f"{self.pose_step_deg} and {self.max_pose_deg}")
        if not 0.2 <= self.distance_m <= 3.0:
            raise ValueError(f"distance_m: expected 0.2 to 3 m, got {self.distance_m}")

    def pose_values(self) -> np.ndarray:
        """The yaw (and pitch) values in degrees: ``round(2 max / step)`` steps centred on 0."""
        n = max(1, int(round(2 * self.max_pose_deg / self.pose_step_deg)))
        return (np.arange(n) - (n - 1) / 2) * self.pose_step_deg

    @property
    def poses(self) -> int:
        return len(self.pose_values()) ** 2

    @property
    def samples(self) -> int:
        return self.identities * self.poses

    def manifest(self) -> dict:
        import anny

        return {"generator_version": GENERATOR_VERSION, "anny": anny.__version__, **dataclasses.asdict(self)}

    def key(self) -> str:
        return hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode()).hexdigest()[:12]

    def sample_labels(self, index: int) -> tuple[int, float, float]:
        """(identity, yaw_deg, pitch_deg) of sample ``index``: identity-major, then yaw, then pitch."""
        v = self.pose_values()
        ident, k = divmod(int(index), len(v) ** 2)
        return ident, float(v[k // len(v)]), float(v[k % len(v)])


# --------------------------------------------------------------------------------------------------
# identities


@dataclass
class FaceIdentities:
    """N head meshes of one topology with per-vertex albedo, and the landmarks the renderer uses."""

    vertices: np.ndarray  # [N, V, 3] float32, m, anny's frame
    faces: np.ndarray  # [F, 3] int32
    colours: np.ndarray  # [N, V, 3] float32 albedo in [0, 1]
    pivot: np.ndarray  # [N, 3] the head's centre at eye height (the head turns about it)
    face_centre: np.ndarray  # [N, 3] midway between the eyes and the mouth (the eye fixates it)
    params: np.ndarray  # [N, K] float32 the drawn shape and colour parameters
    param_names: list
    seed: int | None = None  # the identity seed they were drawn with (None: a cache written before it was kept)

    def __len__(self) -> int:
        return len(self.vertices)

    def subset(self, n: int) -> FaceIdentities:
        return FaceIdentities(self.vertices[:n], self.faces, self.colours[:n], self.pivot[:n], self.face_centre[:n],
                              self.params[:n], self.param_names, self.seed)

    def mesh(self, i: int):
        import trimesh

        rgba = np.concatenate([np.round(self.colours[i] * 255), np.full((self.vertices.shape[1], 1), 255)], 1)
        return trimesh.Trimesh(self.vertices[i].astype(np.float64), self.faces, vertex_colors=rgba.astype(np.uint8),
                               process=False)

    def save(self, path) -> None:
        """Write the identities to ``path`` (a compressed .npz; its directory is created), atomically."""

        def write(f) -> None:
            np.savez_compressed(f, vertices=self.vertices, faces=self.faces, colours=self.colours.astype(np.float16),
                                pivot=self.pivot, face_centre=self.face_centre, params=self.params,
                                param_names=np.array(self.param_names),
                                **({} if self.seed is None else {"identity_seed": np.int64(self.seed)}))

        atomic_write(path, write)

    @classmethod
    def load(cls, path) -> FaceIdentities:
        """The identities :meth:`save` wrote to ``path``; any other file is a ValueError naming it (it read as
        numpy's "pickled (object) data" error, or a KeyError), and is left as it is."""
        try:
            with np.load(path) as z:
                return cls(z["vertices"], z["faces"], z["colours"].astype(np.float32), z["pivot"], z["face_centre"],
                           z["params"], [str(s) for s in z["param_names"]],
                           int(z["identity_seed"]) if "identity_seed" in z.files else None)
        except (*NPY_FORMAT_ERRORS, KeyError, AttributeError, TypeError) as e:
            raise ValueError(f"{path}: not a cache of face identities ({type(e).__name__}); give --identities-cache "
                             "a new path, or the file a run of this package wrote") from None

    def nearest_neighbour_mm(self) -> np.ndarray:
        """[N] each identity's RMS vertex distance (mm) to its nearest other identity (same topology,
        meshes aligned on their face centres)."""
        v = self.vertices.astype(np.float64) - self.face_centre[:, None, :]
        flat = v.reshape(len(v), -1)
        sq = (flat**2).sum(1)
        d2 = (sq[:, None] + sq[None, :] - 2 * flat @ flat.T) / v.shape[1]
        np.fill_diagonal(d2, np.inf)
        return 1000.0 * np.sqrt(np.maximum(d2.min(1), 0.0))


def _anny_model():
    import anny
    import torch

    return anny.Anny(**ANNY_MODEL).to(dtype=torch.float32)


def _region_masks(model) -> dict:
    """Per-vertex weights in [0, 1] of anny's regions: UV masks (face, lips, eyelids, ears) sampled at
    each vertex's texture coordinates, and part labels (eyeball front/back, cavities, tongue)."""
    from anny.face_segmentation import get_face_segmentation_mask
    from anny.paths import get_anny_root_dir
    from PIL import Image

    faces = model.faces.cpu().numpy()
    V = int(faces.max()) + 1
    tc = model.texture_coordinates.cpu().numpy()
    fti = model.face_texture_coordinate_indices.cpu().numpy()
    # each vertex's texture coordinates: the mean over the face corners that use it (seams average)
    uv = np.zeros((V, 2))
    cnt = np.zeros(V)
    np.add.at(uv, faces.ravel(), tc[fti.ravel()])
    np.add.at(cnt, faces.ravel(), 1)
    uv /= np.maximum(cnt, 1)[:, None]
    out = {}
    tex = get_anny_root_dir() / "data/mpfb2/textures"
    for name in ("face", "lips", "eyelids", "ears"):
        im = np.asarray(Image.open(tex / f"mpfb_{name}.jpg").convert("L"), dtype=np.float32) / 255.0
        h, w = im.shape
        col = np.clip(np.round(uv[:, 0] * (w - 1)), 0, w - 1).astype(int)
        row = np.clip(np.round((1 - uv[:, 1]) * (h - 1)), 0, h - 1).astype(int)
        out[name] = im[row, col]
    for name, labels in {"eye_front": ["eye_front.L", "eye_front.R"], "eye_back": ["eye_back.L", "eye_back.R"],
                         "cavity": ["eye_cavity.L", "eye_cavity.R", "mouth_cavity"], "tongue": ["tongue"],
                         "eye_front_L": ["eye_front.L"], "eye_front_R": ["eye_front.R"]}.items():
        fm = get_face_segmentation_mask(model, labels).cpu().numpy()
        m = np.zeros(V, np.float32)
        m[faces[fm].ravel()] = 1.0
        out[name] = m
    return out


def _palette(rng, palette: np.ndarray) -> np.ndarray:
    t = rng.uniform(0, len(palette) - 1)
    k = min(int(t), len(palette) - 2)
    return (1 - (t - k)) * palette[k] + (t - k) * palette[k + 1]


def _landmarks(v: np.ndarray, masks: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(left eye centre, right eye centre, mouth centre, head centre at eye height) of vertices ``v``."""
    eye_l = v[masks["eye_front_L"] > 0].mean(0)
    eye_r = v[masks["eye_front_R"] > 0].mean(0)
    mouth = v[masks["lips"] > 0.5].mean(0)
    skin = (masks["eye_front"] + masks["eye_back"] + masks["cavity"] + masks["tongue"]) == 0
    lo, hi = v[skin].min(0), v[skin].max(0)
    pivot = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.5 * (eye_l[2] + eye_r[2])])
    return eye_l, eye_r, mouth, pivot


def _colours(rng, v: np.ndarray, masks: dict, eyes) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex albedo [V, 3] of one identity and its colour parameters."""
    skin = _palette(rng, SKIN_TONES) * rng.uniform(0.92, 1.08, 3)
    lips = skin * np.array([0.85, 0.55, 0.55]) * rng.uniform(0.75, 1.05)
    hair = _palette(rng, HAIR_COLOURS)
    iris = _palette(rng, IRIS_COLOURS)
    flush = rng.uniform(0.0, 0.15)  # cheeks' and ears' redness
    c = np.tile(skin, (len(v), 1))
    c *= 1 + flush * (masks["face"] + masks["ears"])[:, None] * np.array([0.5, -0.3, -0.3])
    c *= 1 - 0.15 * masks["eyelids"][:, None]
    c = c + masks["lips"][:, None] * (lips - c)
    # brows: an arched band above each eye on the skin in front
    width, thick, lift = rng.uniform(0.022, 0.03), rng.uniform(0.004, 0.008), rng.uniform(0.012, 0.018)
    front = masks["eye_front"] + masks["eye_back"] + masks["cavity"] == 0
    for e in eyes:
        dx = (v[:, 0] - e[0]) / width
        arch = lift + 0.006 * (1 - dx**2)
        brow = (np.abs(dx) < 1) & (np.abs(v[:, 2] - e[2] - arch) < thick) & (v[:, 1] < e[1] + 0.02) & front
        c[brow] = hair
    # eyeballs: sclera, the iris on the front cap and a dark pupil in its middle
    c[masks["eye_back"] > 0] = SCLERA
    for side, e in zip(("eye_front_L", "eye_front_R"), eyes):
        m = masks[side] > 0
        r = np.hypot(v[m, 0] - e[0], v[m, 2] - e[2])
        c[np.flatnonzero(m)] = np.where((r < 0.35 * r.max())[:, None], 0.03, iris)
    c[masks["cavity"] > 0] = CAVITY
    c[masks["tongue"] > 0] = TONGUE
    params = np.concatenate([skin, lips, hair, iris, [flush, width, thick, lift]])
    return np.clip(c, 0.0, 1.0).astype(np.float32), params


def build_identities(n: int, seed: int = 0, progress: bool = True) -> FaceIdentities:
    """Draw ``n`` identities from anny (identity i from generator (seed, i)). anny's first model build in
    a fresh environment takes a few minutes; then each identity takes well under a second."""
    import torch
    from tqdm import tqdm

    model = _anny_model()
    masks = _region_masks(model)
    pheno = list(model.phenotype_labels)
    local = [k for k in model.local_change_labels
             if k.split("-", 1)[1 if k[:2] in ("l-", "r-") else 0].startswith(FACE_REGIONS)]
    faces = model.faces.cpu().numpy().astype(np.int32)
    V, C, P, F, Cp = [], [], [], [], []
    for i in tqdm(range(n), desc="identities", unit="face", disable=not progress, dynamic_ncols=True):
        rng = np.random.default_rng([seed, i])
        ph = {k: 0.5 for k in pheno}
        ph.update(gender=rng.uniform(0, 1), age=rng.uniform(0.45, 0.95), muscle=rng.uniform(0.2, 0.8),
                  weight=rng.uniform(0.2, 0.8), proportions=rng.uniform(0.3, 0.7))
        race = rng.dirichlet(np.full(3, 0.7))
        ph.update(african=race[0], asian=race[1], caucasian=race[2])
        lc = np.clip(rng.normal(0, 0.4, len(local)), -1, 1)
        with torch.no_grad():
            out = model(phenotype_kwargs={k: torch.tensor([float(x)]) for k, x in ph.items()},
                        local_changes_kwargs={k: torch.tensor([float(x)]) for k, x in zip(local, lc)})
        v = out["vertices"][0].cpu().numpy().astype(np.float64)
        eye_l, eye_r, mouth, pivot = _landmarks(v, masks)
        col, cpar = _colours(rng, v, masks, (eye_l, eye_r))
        centre = np.array([0.5 * (eye_l[0] + eye_r[0]), 0.5 * (eye_l[1] + eye_r[1]),
                           0.5 * (0.5 * (eye_l[2] + eye_r[2]) + mouth[2])])
        V.append(v.astype(np.float32))
        C.append(col)
        P.append(pivot)
        F.append(centre)
        Cp.append(np.concatenate([[ph[k] for k in pheno], lc, cpar]).astype(np.float32))
    names = pheno + local + [f"{k}_{c}" for k in ("skin", "lips", "hair", "iris") for c in "rgb"] + \
        ["flush", "brow_width", "brow_thickness", "brow_lift"]
    return FaceIdentities(np.stack(V), faces, np.stack(C), np.stack(P), np.stack(F), np.stack(Cp), names, int(seed))


def identities_cache(n: int, seed: int) -> Path:
    import anny

    return Path("runs/faces") / f"identities-n{n}-seed{seed}-v{GENERATOR_VERSION}-anny{anny.__version__}.npz"


def load_identities(n: int, seed: int = 0, cache: str | Path | None = None, progress: bool = True,
                    log=print) -> FaceIdentities:
    """The ``n`` identities of ``seed``, from ``cache`` (default runs/faces/identities-...npz) when it
    holds them (a cache of more identities serves fewer), else built with anny and cached."""
    path = Path(cache) if cache else identities_cache(n, seed)
    if path.exists():
        ids = FaceIdentities.load(path)
        if ids.seed is not None and ids.seed != seed:  # (a cache given by name; the default names carry the seed)
            raise ValueError(f"{path}: holds identity seed {ids.seed}'s identities, not seed {seed}'s; "
                             "give --identities-cache another path")
        if len(ids) >= n:
            return ids.subset(n)
    t0 = time.perf_counter()
    log(f"building {n} identities with anny (its first model build in a fresh environment takes minutes)")
    ids = build_identities(n, seed, progress)
    ids.save(path)
    log(f"built {n} identities in {time.perf_counter() - t0:.0f} s; cached in {path} "
        f"({path.stat().st_size / 2**20:.1f} MiB)")
    return ids


# --------------------------------------------------------------------------------------------------
# rendering


def head_pose(ids: FaceIdentities, i: int, yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """[4, 4] world-from-head transform of identity ``i`` turned by (yaw, pitch) about its pivot."""
    y, p = np.radians(yaw_deg), np.radians(pitch_deg)
    Rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(-p), -np.sin(-p)], [0, np.sin(-p), np.cos(-p)]])
    R = Rz @ Rx
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = ids.pivot[i] - R @ ids.pivot[i]
    return T


def eye_pose(cfg: FaceDataConfig, ids: FaceIdentities, i: int, head: np.ndarray) -> np.ndarray:
    """[4, 4] world-from-eye: ``distance_m`` in front of identity i's frontal face centre, fixating the
    centre as ``head`` (its pose) places it."""
    c0 = ids.face_centre[i].astype(np.float64)
    eye = c0 + np.array([0.0, -cfg.distance_m, 0.0])
    c = head[:3, :3] @ c0 + head[:3, 3]
    T = np.eye(4)
    T[:3, :3] = look_rotation(c - eye)
    T[:3, 3] = eye
    return T


def make_eye(cfg: FaceDataConfig):
    """The eye the faces are seen with: accommodated to ``distance_m``."""
    from warp_vision.eye.optics import NavarroEye

    return NavarroEye(1.0 / cfg.distance_m, cfg.pupil_diameter_mm)


def make_retina(cfg: FaceDataConfig):
    from warp_vision.eye.retina import Retina

    return Retina.log_polar(cfg.photoreceptors, seed=RETINA_SEEDS[cfg.eye], eye=make_eye(cfg))


def make_scene(ids: FaceIdentities):
    """A grey backdrop, fixed lights and every identity's head (shown one per batch element)."""
    from warp_vision.scene import Material, Scene

    sc = Scene(ambient=(0.08, 0.08, 0.08), background=(0.0, 0.0, 0.0))
    c = ids.face_centre.mean(0)
    back = np.eye(4)
    back[:3, :3] = look_rotation([0.0, -1.0, 0.0])  # the plane's normal (+z) toward the face
    back[:3, 3] = c + np.array([0.0, 0.6, 0.0])
    sc.add_plane("backdrop", (3.0, 3.0), back, Material((0.25, 0.25, 0.27)), static=True)
    for i in range(len(ids)):
        sc.add(f"head_{i}", ids.mesh(i), Material((0.5, 0.5, 0.5), specular=0.08, shininess=12, smooth=True,
                                                  vertex_colors=True))
        sc.set_visible(f"head_{i}", False)
    sc.add_light(c + np.array([0.5, -0.9, 0.6]), color=(1.0, 0.95, 0.85), intensity=1.6)  # key, upper left
    sc.add_light(c + np.array([-0.8, -0.6, 0.0]), color=(0.8, 0.85, 1.0), intensity=0.5)  # fill, right
    return sc


def render_samples(cfg: FaceDataConfig, indices, ids: FaceIdentities, scene, retina, eye, device: str = "cpu") -> dict:
    """Render samples ``indices`` in one batch: {"onv": [B, 3P] float16, "identity": [B], "pose": [B, 2]
    (yaw, pitch) degrees}."""
    from warp_vision.kernels.render import render_onv

    labels = [cfg.sample_labels(i) for i in indices]
    B = len(labels)
    heads = [head_pose(ids, k, y, p) for k, y, p in labels]
    for i in range(len(ids)):
        name = f"head_{i}"
        shown = np.array([k == i for k, _, _ in labels])
        scene.set_visible(name, shown if B > 1 else bool(shown[0]))
        scene.set_transform(name, np.stack(heads) if B > 1 else heads[0])
    eyes = np.stack([eye_pose(cfg, ids, k, h) for (k, _, _), h in zip(labels, heads)])
    onv = render_onv(scene, retina, eye, eyes, cfg.samples_per_receptor, seed=cfg.seed, device=device)
    return {
        "onv": onv.cpu().numpy().astype(np.float16),
        "identity": np.array([k for k, _, _ in labels], dtype=np.int64),
        "pose": np.array([[y, p] for _, y, p in labels], dtype=np.float32),
    }


def dataset_fields(cfg: FaceDataConfig) -> dict:
    return {"onv": ((3 * cfg.photoreceptors,), "float16"), "identity": ((), "int64"), "pose": ((2,), "float32")}


def synthesize(out_dir, cfg: FaceDataConfig, shard=(0, 1), batch: int = 16, device: str = "cpu", progress: bool = True,
               log=print, identities_path: str | Path | None = None) -> ChunkedStore:
    """Render the face dataset ``cfg`` into ``out_dir`` (or this shard's part), resuming what is there.

    ``out_dir/identities.npz`` holds the identity meshes and ``out_dir/retina.npz`` the retina.
    """
    from warp_vision.data.synth import open_store, pending, render_missing

    cfg.validate()
    retina = make_retina(cfg)
    store = open_store(out_dir, cfg.manifest(), cfg.samples, cfg.chunk_size, dataset_fields(cfg), shard, retina, batch)
    todo, mine = pending(store)
    if not todo:
        return store
    ids = load_identities(cfg.identities, cfg.identity_seed, identities_path, progress, log)
    if not (Path(out_dir) / "identities.npz").exists():
        ids.save(Path(out_dir) / "identities.npz")
    log(f"synthesising {todo:,} of {mine:,} face ONVs ({cfg.identities} identities x {cfg.poses} poses; "
        f"P={cfg.photoreceptors:,}, S={cfg.samples_per_receptor}) into {out_dir}")
    eye, scene = make_eye(cfg), make_scene(ids)
    render_missing(store, lambda r: render_samples(cfg, r, ids, scene, retina, eye, device), batch, progress, log,
                   "face ONVs")
    return store
