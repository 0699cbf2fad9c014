"""The limb vision nets' data: what an eye sees of the body's arms and the cannon's ball, and where the
ball is relative to each hand.

Each sample is one eye's ONV of the closed loop's own world (:func:`warp_vision.sim.loop.body_scene`: a
room, the body's visible parts, the cannon's ball the loop's foveation nets track: by default the ordinary
ball, lit by the room's lamps, ``ball="glowing"`` v7's glowing ball in the dimmed room) with the body in a
state of its own repertoire, and the target the paper's limb vision nets estimate: the hand-to-ball
discrepancy ``ball - hand`` for each arm (left first), in the eye frame (m).

- **Arms**: both arms' seven main joints drawn uniformly within the arm nets' ranges
  (:data:`warp_vision.sim.arm.SAMPLE_RANGES`, myo-sim's couplings applied, fingers at the relaxed pose);
  in :data:`FRONT_SHARE` of the draws an arm's hand must lie 0.2-0.6 m in front of its shoulder (the
  postures the interception uses), and no arm touches the torso or the other arm.
- **The ball**: in :data:`PATH_SHARE` of the samples somewhere on a cannon shot's path, from the muzzle
  to just past the body (the shots of the config's ``shots`` split: training and held-out shots are
  disjoint seed ranges, :data:`warp_vision.sim.cannon.SPLITS`); otherwise within :data:`NEAR_M` of a hand
  (distance uniform, direction uniform) and in front of the body.
- **Gaze**: the eye looks at the ball as the loop's tracking does, off by a tracking error: within 2 deg
  for half the samples, 2-10 deg for a third, 10-25 deg for the rest (the ball fast or lost), with a
  torsion of up to 3 deg. The head is turned toward the ball by a random share (0-1) of its direction, as
  the neck's synergy does. The eye's position is the body's at that head pose.
- **Optics and light**: accommodation and pupil from a small grid (the renderer's eye rays are cached
  per optical state), per batch of 16; the light level is scaled per sample by 10^U(-0.5, 0.5) (the
  renderer is linear in it).
- **Rooms**: each chunk of :data:`ROOM_CHUNK` samples shares a room of seed (family, dataset seed,
  chunk); ``rooms="heldout"`` draws from a disjoint family, so held-out ONVs show rooms never trained on.

Every sample's parameters come from a generator seeded with (dataset seed, index), so a sample never
depends on batching or sharding. Frames: the world frame of :mod:`warp_vision.body` (the torso's), the
eye frame of docs/ARCHITECTURE.md (+z along the line of sight). Units: m, rad.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from warp_vision.data.store import ChunkedStore
from warp_vision.errors import require_positive, require_seeds
from warp_vision.frames import gaze_direction, line_crossing, look_rotation

#: The generator's version: bump it when the samples change.
LIMB_DATA_VERSION = 1
SIDES = ("left", "right")
#: Samples whose ball lies on a cannon shot's path (the rest: near a hand).
PATH_SHARE = 0.45
#: m: the near-hand balls lie this far from the hand's grasp site at most; the errors' near range (the issue's).
NEAR_M = 0.6
#: Share of arm draws whose hand must lie in front of the shoulder (the interception's postures).
FRONT_SHARE = 0.7
#: Samples sharing one room (one scene build: about 3 s for the body's 290,000 triangles).
ROOM_CHUNK = 256
#: Room seed families: training rooms and held-out rooms never coincide.
ROOM_FAMILIES = {"train": 0, "heldout": 1}
SHOT_SPLITS = ("train", "heldout")
#: Optical states drawn per batch (accommodation D, pupil mm).
ACCOMMODATIONS_D = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
PUPILS_MM = (3.0, 4.0, 5.0)
#: The meta fields (one float each), in order.
META = ("ball_eye_m", "ball_hand_left_m", "ball_hand_right_m", "gaze_error_deg", "on_path", "light_scale",
        "accommodation_D", "pupil_mm")


@dataclass
class LimbDataConfig:
    """What a limb vision dataset is; two datasets with equal configs are identical."""

    eye: str = "left"
    samples: int = 10_000
    photoreceptors: int = 14_400  # the foveation nets' retina (the loop renders one ONV per eye for both)
    samples_per_receptor: int = 4
    seed: int = 0
    rooms: str = "train"  # "train" or "heldout" room family
    shots: str = "train"  # the cannon's seed split the on-path balls come from
    chunk_size: int = ROOM_CHUNK
    ball: str = "ordinary"  # the loop's ball (warp_vision.sim.loop.BALLS):
                            # ordinary, or glowing (the datasets before it)

    def validate(self) -> None:
        require_seeds(self)
        if self.eye not in SIDES:
            raise ValueError(f"eye: expected one of {SIDES}, got {self.eye!r}")
        require_positive(self, ("samples", "photoreceptors", "samples_per_receptor", "chunk_size"), flags=False)
        if self.rooms not in ROOM_FAMILIES:
            raise ValueError(f"rooms: expected one of {sorted(ROOM_FAMILIES)}, got {self.rooms!r}")
        if self.shots not in SHOT_SPLITS:
            raise ValueError(f"shots: expected one of {SHOT_SPLITS}, got {self.shots!r}")
        from warp_vision.sim.loop import BALLS

        if self.ball not in BALLS:
            raise ValueError(f"ball: expected one of {BALLS}, got {self.ball!r}")

    @classmethod
    def from_manifest(cls, m: dict) -> LimbDataConfig:
        """The config a dataset store recorded (:meth:`manifest`)."""
        return cls(**{"ball": "glowing", **{k: v for k, v in m.items() if k != "generator_version"}})

    def manifest(self) -> dict:
        """The config as the dataset store records it; a glowing-ball config's is what it was before the
        ``ball`` field (so its cached datasets are found again)."""
        d = dataclasses.asdict(self)
        if d["ball"] == "glowing":
            del d["ball"]
        return {"generator_version": LIMB_DATA_VERSION, **d}

    def key(self) -> str:
        return hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode()).hexdigest()[:12]

    def foveation_config(self):
        """The foveation dataset config whose retina (and eye) these ONVs share."""
        from warp_vision.data.foveation import FoveationDataConfig

        return FoveationDataConfig(eye=self.eye, photoreceptors=self.photoreceptors,
                                   samples_per_receptor=self.samples_per_receptor)


def dataset_fields(cfg: LimbDataConfig) -> dict:
    return {"onv": ((3 * cfg.photoreceptors,), "float16"), "target": ((6,), "float32"),
            "eye_in_head": ((9,), "float32"), "meta": ((len(META),), "float32")}


class Poser:
    """Poses the body (kinematics only) for samples: arms, head, eye; reads hands and eye poses."""

    def __init__(self, body=None):
        from warp_vision.body import Body
        from warp_vision.sim.arm import Arm

        self.body = body or Body()
        self.model = self.body.model
        self.data = mujoco.MjData(self.model)
        self.arms = {s: Arm(self.body, s) for s in SIDES}
        m = self.model
        self.neck_adr = m.jnt_qposadr[self.body.neck_joints]
        self.neck_range = m.jnt_range[self.body.neck_joints]

    def arm_angles(self, rng, side: str, front: bool, tries: int = 400) -> np.ndarray:
        from warp_vision.sim.arm import FRONT_M, MAIN_JOINTS, SAMPLE_RANGES

        lo, hi = np.array([SAMPLE_RANGES[n] for n in MAIN_JOINTS]).T
        arm, d = self.arms[side], self.data
        q = rng.uniform(lo, hi)
        for _ in range(tries):
            q = rng.uniform(lo, hi)
            d.qpos[:] = arm.qpos(q)
            mujoco.mj_kinematics(self.model, d)
            ahead = arm.shoulder(d)[1] - arm.hand(d)[1]
            if front and not FRONT_M[0] <= ahead <= FRONT_M[1]:
                continue
            mujoco.mj_comPos(self.model, d)
            mujoco.mj_collision(self.model, d)
            if not arm.touching(d):
                return q
        return q

    def pose(self, angles: dict, neck) -> None:
        """Both arms at their main ``angles`` and the neck at (yaw, pitch, 0): kinematics into ``self.data``."""
        d = self.data
        q = self.model.qpos0.copy()
        for s in SIDES:
            q = self.arms[s].qpos(angles[s], q)
        q[self.neck_adr[:2]] = np.clip(neck, self.neck_range[:2, 0], self.neck_range[:2, 1])
        d.qpos[:] = q
        mujoco.mj_kinematics(self.model, d)

    def hands(self) -> dict:
        return {s: self.arms[s].hand(self.data).copy() for s in SIDES}

    def body_poses(self, bodies) -> list:
        d = self.data
        out = []
        for b in bodies:
            T = np.eye(4)
            T[:3, :3] = d.xmat[b].reshape(3, 3)
            T[:3, 3] = d.xpos[b]
            out.append(T)
        return out

    def head_rotation(self) -> np.ndarray:
        from warp_vision.body import EYE_REST_ROTATION, SCAFFOLD_HEAD_ROTATION

        return self.data.xmat[self.body.head_body].reshape(3, 3) @ SCAFFOLD_HEAD_ROTATION.T @ EYE_REST_ROTATION

    def eye_centre(self, side: str) -> np.ndarray:
        return self.data.xpos[self.body.eye_body[side]].copy()


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _shot_ball(rng, split: str, side: str) -> np.ndarray:
    from warp_vision.sim.cannon import SPLITS, shot_from_seed
    from warp_vision.sim.intercept import ballistic_path

    seeds = SPLITS[split]
    shot = shot_from_seed(int(seeds[0] + rng.integers(len(seeds))), side)
    t = rng.uniform(0.0, shot.flight_time + 0.05)
    return ballistic_path(shot.muzzle, shot.launch_velocity, [t])[0]


def sample_params(cfg: LimbDataConfig, index: int, poser: Poser) -> dict:
    """Sample ``index``'s body state, ball, gaze and light (a generator seeded with (seed, index))."""
    from warp_vision.sim.cannon import SHOULDER_LEFT

    rng = np.random.default_rng([11, cfg.seed, index])
    angles = {s: poser.arm_angles(rng, s, rng.uniform() < FRONT_SHARE) for s in SIDES}
    poser.pose(angles, (0.0, 0.0))
    hands = poser.hands()
    on_path = rng.uniform() < PATH_SHARE
    near = SIDES[int(rng.integers(2))]
    for _ in range(200):
        if on_path:
            ball = _shot_ball(rng, cfg.shots, near)
        else:
            ball = hands[near] + rng.uniform(0.06, NEAR_M) * _unit(rng)
        # in front of the body, above the stool, clear of both hands
        if (
            ball[1] < SHOULDER_LEFT[1] - 0.12
            and ball[2] > 0.55
            and min(np.linalg.norm(ball - h) for h in hands.values()) > 0.05
        ):
            break
    # the head turned toward the ball by a random share of its direction (the neck's synergy)
    mid = 0.5 * (poser.eye_centre("left") + poser.eye_centre("right"))
    R_head = poser.head_rotation()
    g = _gaze_angles(R_head.T @ (ball - mid))
    share = rng.uniform(0.0, 1.0)
    poser.pose(angles, share * g)
    centre = poser.eye_centre(cfg.eye)
    u = rng.uniform()
    err_deg = rng.uniform(0, 2) if u < 0.5 else (rng.uniform(2, 10) if u < 0.83 else rng.uniform(10, 25))
    los = ball - centre
    look = look_rotation(los, up=poser.head_rotation()[:, 1])
    off = gaze_direction(*(np.radians(err_deg) * _unit2(rng)))
    R = look @ look_rotation(off, up=(0.0, 1.0, 0.0))  # the gaze off the ball by err_deg, toward a random side
    roll = np.radians(rng.uniform(-3, 3))
    c, s = np.cos(roll), np.sin(roll)
    R = R @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    eye_pose = np.eye(4)
    eye_pose[:3, :3], eye_pose[:3, 3] = R, centre
    hands = poser.hands()
    target = np.concatenate([R.T @ (ball - hands[s]) for s in SIDES])
    return {"angles": angles, "neck": share * g, "ball": ball, "eye_pose": eye_pose, "target": target,
            "eye_in_head": (poser.head_rotation().T @ R).ravel(),
            "hands": hands, "on_path": on_path, "err_deg": err_deg,
            "light": 10 ** rng.uniform(-0.5, 0.5), "ball_eye": float(np.linalg.norm(los))}


def _gaze_angles(v) -> np.ndarray:
    return np.array([np.arctan2(v[0], v[2]), np.arctan2(v[1], np.hypot(v[0], v[2]))])


def _unit2(rng) -> np.ndarray:
    a = rng.uniform(0, 2 * np.pi)
    return np.array([np.cos(a), np.sin(a)])


_SCENE: dict = {}


def _scene(cfg: LimbDataConfig, chunk: int, poser: Poser):
    from warp_vision.sim.loop import body_scene, set_eye_view

    key = (ROOM_FAMILIES[cfg.rooms], cfg.seed, chunk)
    if _SCENE.get("key") != (key, cfg.ball):
        seed = int(np.random.default_rng([12, *key]).integers(2**31))
        sc = body_scene(poser.body, seed, cfg.ball)
        set_eye_view(sc, True)
        _SCENE.update(key=(key, cfg.ball), scene=sc)
    return _SCENE["scene"]


def render_samples(cfg: LimbDataConfig, indices, poser: Poser, retina, device: str = "cpu") -> dict:
    """The samples ``indices`` (all in one chunk): ONVs and targets."""
    from warp_vision.eye.optics import NavarroEye
    from warp_vision.kernels.render import render_onv

    indices = [int(i) for i in indices]
    chunk = indices[0] // cfg.chunk_size
    if any(i // cfg.chunk_size != chunk for i in indices):
        raise ValueError("render_samples: indices must lie in one chunk (one room)")
    sc = _scene(cfg, chunk, poser)
    ps, poses = [], {name: [] for name, _ in sc._mj_bodies}
    for i in indices:
        p = sample_params(cfg, i, poser)
        for (name, _b), T in zip(sc._mj_bodies, poser.body_poses([b for _, b in sc._mj_bodies])):
            poses[name].append(T)
        ps.append(p)
    for name, Ts in poses.items():
        sc.set_transform(name, np.stack(Ts))
    ball = np.repeat(np.eye(4)[None], len(ps), 0)
    ball[:, :3, 3] = [p["ball"] for p in ps]
    sc.set_transform("mj_ball", ball)
    rng = np.random.default_rng([13, cfg.seed, indices[0]])
    acc, pupil = float(rng.choice(ACCOMMODATIONS_D)), float(rng.choice(PUPILS_MM))
    onv = render_onv(sc, retina, NavarroEye(acc, pupil), np.stack([p["eye_pose"] for p in ps]),
                     cfg.samples_per_receptor, seed=cfg.seed, device=device).cpu().numpy()
    light = np.array([p["light"] for p in ps])
    onv = onv * light[:, None]
    meta = np.array([[p["ball_eye"], *(np.linalg.norm(p["ball"] - p["hands"][s]) for s in SIDES), p["err_deg"],
                      float(p["on_path"]), p["light"], acc, pupil] for p in ps], np.float32)
    return {"onv": onv.astype(np.float16), "target": np.stack([p["target"] for p in ps]).astype(np.float32),
            "eye_in_head": np.stack([p["eye_in_head"] for p in ps]).astype(np.float32), "meta": meta}


def synthesize(out_dir, cfg: LimbDataConfig, shard=(0, 1), batch: int = 16, device: str = "cpu", progress: bool = True,
               log=print) -> ChunkedStore:
    """Render the dataset ``cfg`` into ``out_dir`` (this shard's part), resuming what is there."""
    from warp_vision.data.foveation import make_retina
    from warp_vision.data.synth import open_store, pending, render_missing

    cfg.validate()
    retina = make_retina(cfg.foveation_config())
    store = open_store(out_dir, cfg.manifest(), cfg.samples, cfg.chunk_size, dataset_fields(cfg), shard, retina, batch)
    todo, mine = pending(store)
    if not todo:
        return store
    log(f"synthesising {todo:,} of {mine:,} limb vision ONVs ({cfg.eye} eye, rooms {cfg.rooms}, shots {cfg.shots}) "
        f"into {out_dir}")
    poser = Poser()
    render_missing(store, lambda r: render_samples(cfg, r, poser, retina, device), batch, progress, log)
    return store


# --------------------------------------------------------------------------------------------------
# at run time: the ball's position and velocity from what the eyes see

#: s: the ballistic fit uses the observations of the last FIT_WINDOW_S
FIT_WINDOW_S = 0.25
#: m: an observation's weight in the fit is 1 / (FIT_NEAR_M + its estimated hand-ball distance)^2: the
#: estimates' errors grow with the distance
FIT_NEAR_M = 0.15
#: m: a fixation estimate's depth is capped here (gaze lines that barely converge)
MAX_DEPTH_M = 8.0
#: The validation gate: once the path is fitted to GATE_MIN_OBS observations spanning GATE_MIN_SPAN_S, an
#: observation farther than GATE_M from where that path puts the ball is not the ball (the eyes caught by
#: something else: the cannon's muzzle, a hand) and is left out of the fit. GATE_RELOCK consecutive
#: rejected observations that lie on a path of their own, moving faster than GATE_MIN_SPEED (the cannon's
#: ball flies at 6-12 m/s; a decoy stands still), replace the track: the first one was wrong.
GATE_M = 0.3
GATE_MIN_OBS = 4
GATE_MIN_SPAN_S = 0.05
GATE_RELOCK = 4
GATE_MIN_SPEED = 3.0


class BallisticPerception:
    """What a visual perception of the ball shares: its observations (one per visual frame, world frame),
    and, when called as the interceptor's ``perception`` ``(body, t) -> (position, velocity)``, a ballistic
    path (gravity known) fitted by :func:`fit_ballistic` to the accepted observations of the
    :data:`FIT_WINDOW_S` before the latest one (so the path is extrapolated when the eyes lose the ball),
    each weighted by 1 / (:data:`FIT_NEAR_M` + its estimated distance to the hand)^2, evaluated at ``t``
    (one observation: at rest; none yet: None, and the interceptor holds). Observations the validation
    gate (:data:`GATE_M`) rejects stay out of the fit. :meth:`reset` forgets the observations (at the
    launch); ``log`` keeps them all, with each eye's part and the hand at the render: (t, estimate [3],
    {eye: [3]}, hand [3]); ``rejected`` the times of the rejected ones."""

    def __init__(self, arm: str):
        if arm not in SIDES:
            raise ValueError(f"arm: expected one of {SIDES}, got {arm!r}")
        self.arm = arm
        self.log: list = []
        self.rejected: list = []
        self._obs: list = []
        self._out: list = []  # the rejected observations since the last accepted one

    def reset(self) -> None:
        self._obs, self._out = [], []

    def _add(self, t: float, p: np.ndarray, hand, per_eye: dict) -> np.ndarray:
        hand = np.asarray(hand, float).copy()
        ob = (float(t), p, float(np.linalg.norm(p - hand)))
        self.log.append((float(t), p, per_eye, hand))
        if self._gated(ob):
            self.rejected.append(float(t))
        else:
            self._obs.append(ob)
        return p

    def _gated(self, ob) -> bool:
        """Whether the validation gate rejects observation ``ob`` (updating the track on a relock)."""
        window = self._window()
        if len(window) < GATE_MIN_OBS or window[-1][0] - window[0][0] < GATE_MIN_SPAN_S:
            return False
        pred, _ = self._fit(window, ob[0])
        if np.linalg.norm(ob[1] - pred) <= GATE_M:
            self._out = []
            return False
        self._out.append(ob)
        if len(self._out) >= GATE_RELOCK:
            _, v = self._fit(self._out, ob[0])
            fits = all(np.linalg.norm(o[1] - self._fit(self._out, o[0])[0]) <= GATE_M / 2 for o in self._out)
            if fits and np.linalg.norm(v) >= GATE_MIN_SPEED:  # a moving path of its own: the track was wrong
                self._obs, self._out = list(self._out), []
                return False
        return True

    def _window(self) -> list:
        if not self._obs:
            return []
        last = self._obs[-1][0]
        return [o for o in self._obs if o[0] >= last - FIT_WINDOW_S]

    @staticmethod
    def _fit(obs, t: float):
        w = 1.0 / (FIT_NEAR_M + np.array([o[2] for o in obs])) ** 2
        return fit_ballistic([o[0] for o in obs], [o[1] for o in obs], w, t)

    def __call__(self, body, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        obs = self._window()
        if not obs:
            return None
        return self._fit(obs, t)


class LimbVision(BallisticPerception):
    """Both eyes' limb vision nets (trained by ``python -m warp_vision.train limb --eye left|right``) as the
    interception's perception of the ball (:class:`warp_vision.sim.intercept.ArmInterceptor`'s
    ``perception``; the fit: :class:`BallisticPerception`). The two eyes' estimates are averaged, as in
    the paper; the hand's position (m, world) comes from proprioception.

    - Ranging nets (``--model range``, the default preset's): on each visual frame each eye whose
      foveation net sees the ball within :data:`~warp_vision.nn.retina_cnn.RANGE_GATE_DEG` of its line of
      sight (``loop.estimate``, the loop's own tracking input) gives the ball at the distance its ranging
      net reads from its ONV along that direction, turned into the world frame with the eye's pose at the
      render (the oculomotor system's knowledge of where its eye points); the discrepancy is that ball
      minus the hand. No eye within its gate: no observation that frame.
    - ONV-only nets (linet, fc, cnn): each eye's net gives the discrepancy of ``arm``'s hand (eye frame)
      from its ONV; turned into the world frame and added to the hand's position, one estimate of the
      ball per eye."""

    def __init__(self, run_dirs: dict, arm: str, device: str = "cpu"):
        from warp_vision.nn.trained import load_net, onv_dtype

        super().__init__(arm)
        if set(run_dirs) != set(SIDES):
            raise ValueError(f"run_dirs: expected one run per eye {SIDES}, got {sorted(run_dirs)}")
        self.nets, self.norms, self.dtypes, self.data, models = {}, {}, {}, {}, {}
        for s, rd in run_dirs.items():
            model, ck = load_net(rd, device, expect={"eye": s})
            if ck.get("net", {}).get("kind") != "limb":
                raise ValueError(f"{rd}: expected a limb vision run (python -m warp_vision.train limb), got a "
                                 f"{ck.get('net', {}).get('kind')!r} net")
            if ck["data"]["eye"] != s:
                raise ValueError(f"{rd}: a net of the {ck['data']['eye']} eye, given for the {s} eye")
            self.nets[s], self.norms[s] = model, ck["norm"]
            self.dtypes[s], self.data[s] = onv_dtype(ck["net"]), ck["data"]
            models[s] = ck["net"]["model"]
        ranging = {s: m == "range" for s, m in models.items()}
        if len(set(ranging.values())) > 1:
            raise ValueError(f"limb vision runs: both eyes' nets must be ranging nets or neither, got {models}")
        self.ranging = ranging["left"]
        self.run_dirs = dict(run_dirs)
        self.device = device
        self._k = 0 if arm == "left" else 3

    def check_ball(self, ball: str) -> None:
        """ValueError unless both eyes' nets learnt the ball the loop shows (``ball``: ordinary or glowing;
        a net saved before the choice existed learnt the glowing one)."""
        for s in SIDES:
            learnt = self.data[s].get("ball", "glowing")
            if learnt != ball:
                raise ValueError(f"{self.run_dirs[s]}: the {s} eye's limb vision net learnt the {learnt} ball, the "
                                 f"loop shows the {ball} one (--ball {learnt}, or train it again: python -m "
                                 f"warp_vision.train limb --eye {s} --ball {ball} --out {self.run_dirs[s]})")

    def check_retinas(self, retinas: dict) -> None:
        """ValueError unless each eye's net reads the photoreceptors of ``retinas[eye]`` (the loop's)."""
        for s in SIDES:
            P = int(self.data[s]["photoreceptors"])
            if retinas[s].P != P:
                raise ValueError(f"limb vision net of the {s} eye: trained on P={P} photoreceptors, the loop renders "
                                 f"{retinas[s].P}")

    def _predict(self, s: str, onv) -> np.ndarray:
        from warp_vision.nn.trained import predict_targets

        x = torch.as_tensor(onv).reshape(1, -1)
        return predict_targets(self.nets[s], x, self.norms[s], self.device, self.dtypes[s])[0].double().numpy()

    def discrepancy(self, onv: dict) -> dict:
        """ONV-only nets: {eye: [6]} each eye's net on its ONV [1, 3P] (or [3P]): ball - hand of the left and
        right arm, eye frame (m)."""
        if self.ranging:
            raise ValueError("discrepancy: ranging nets read the ball's distance (distance()); the loop adds the "
                             "direction and the hand (observe())")
        return {s: self._predict(s, onv[s]) for s in SIDES}

    def distance(self, onv, eye: str) -> float:
        """Ranging nets: the ball's distance (m) from ``eye``'s centre, read from its ONV [1, 3P] (or [3P])."""
        if not self.ranging:
            raise ValueError("distance: these limb vision nets give discrepancies (discrepancy())")
        return float(np.exp(self._predict(eye, onv)[0]))

    def ball_in_eyes(self, loop, eye_poses: dict) -> dict:
        """Ranging nets: {eye: the ball's world position (m)} for each eye whose foveation estimate
        (``loop.estimate``) lies within the ranging gate."""
        from warp_vision.nn.retina_cnn import RANGE_GATE_DEG

        out = {}
        for s, est in (getattr(loop, "estimate", None) or {}).items():
            u = gaze_direction(*np.asarray(est, float))
            if np.degrees(np.arccos(np.clip(u[2], -1.0, 1.0))) <= RANGE_GATE_DEG:
                out[s] = eye_poses[s][:3, 3] + eye_poses[s][:3, :3] @ (self.distance(loop.onv[s], s) * u)
        return out

    def observe(self, loop, eye_poses: dict, hand, t: float) -> np.ndarray | None:
        """One frame: the ball's estimated world position (m) from the ONVs ``loop`` just rendered
        (``loop.onv``, and with ranging nets ``loop.estimate``), with the eyes at ``eye_poses`` ({eye: [4, 4]
        world-from-eye}) and ``arm``'s hand at ``hand`` (m, world) at the render, at t (s); None when no eye
        sees the ball within its gate (ranging nets)."""
        if self.ranging:
            per_eye = self.ball_in_eyes(loop, eye_poses)
            if not per_eye:
                return None
            return self._add(t, np.mean(list(per_eye.values()), axis=0), hand, per_eye)
        d = self.discrepancy(loop.onv)
        per_eye = {s: np.asarray(hand, float) + eye_poses[s][:3, :3] @ d[s][self._k:self._k + 3] for s in SIDES}
        return self._add(t, 0.5 * (per_eye["left"] + per_eye["right"]), hand, per_eye)


class FixationVision(BallisticPerception):
    """The ball where the two eyes see it, without limb vision nets: each eye's foveation net gives the
    ball's direction in its eye frame (``loop.estimate``, the loop's own tracking input), the eye's
    orientation at the render turns it into a world ray from the eye's centre, and the ball is the
    point nearest both rays (the gaze lines' crossing, corrected by the foveation nets' residual
    errors; depth capped at :data:`MAX_DEPTH_M`). A comparison for the limb vision nets: the eyes'
    binocular geometry with the hand known by proprioception."""

    def observe(self, loop, eye_poses: dict, hand, t: float) -> np.ndarray | None:
        from warp_vision.frames import gaze_direction

        est = getattr(loop, "estimate", None)
        if not est:
            return None
        origins = {s: eye_poses[s][:3, 3] for s in SIDES}
        rays = {s: eye_poses[s][:3, :3] @ gaze_direction(*np.asarray(est[s], float)) for s in SIDES}
        p = nearest_to_rays(origins["left"], rays["left"], origins["right"], rays["right"])
        return self._add(t, p, hand, {s: rays[s] for s in SIDES})


def nearest_to_rays(o1, u1, o2, u2, max_depth: float = MAX_DEPTH_M) -> np.ndarray:
    """The point midway between the closest points of rays ``o + s u`` (s >= 0, unit ``u``; depth capped at
    ``max_depth`` m): where two gaze lines cross, or nearly."""
    o1, u1, o2, u2 = (np.asarray(x, float) for x in (o1, u1, o2, u2))
    st = line_crossing(o1, u1, o2, u2)
    s1, s2 = (max_depth, max_depth) if st is None else st  # parallel: as far as allowed
    s1, s2 = float(np.clip(s1, 0, max_depth)), float(np.clip(s2, 0, max_depth))
    return 0.5 * (o1 + s1 * u1 + o2 + s2 * u2)


def fit_ballistic(times, positions, weights, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(position [3], velocity [3]) at ``t`` s of the ballistic path (gravity known:
    :data:`warp_vision.sim.cannon.GRAVITY`) that fits the observed ``positions`` [n, 3] (m) at ``times``
    [n] (s) best by least squares weighted by ``weights`` [n]. One observation: it, at rest."""
    from warp_vision.sim.cannon import GRAVITY

    P0 = np.asarray(positions, float).reshape(-1, 3)
    if len(P0) == 1:
        return P0[0].copy(), np.zeros(3)
    ts = np.asarray(times, float) - t
    P = P0 - 0.5 * np.asarray(GRAVITY) * ts[:, None] ** 2
    sw = np.sqrt(np.asarray(weights, float))[:, None]
    A = np.stack([np.ones_like(ts), ts], 1) * sw
    coef, *_ = np.linalg.lstsq(A, P * sw, rcond=None)
    return coef[0], coef[1]


def ball_in_eye(cfg: LimbDataConfig, index: int, poser: Poser) -> np.ndarray:
    """Sample ``index``'s ball in its eye frame (m; :func:`sample_params` again: samples are reproducible)."""
    p = sample_params(cfg, index, poser)
    R, centre = p["eye_pose"][:3, :3], p["eye_pose"][:3, 3]
    return R.T @ (p["ball"] - centre)
