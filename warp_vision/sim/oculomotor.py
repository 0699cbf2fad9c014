"""Muscle control the body learns from itself: the activations that hold a pose, and the oculomotor nets.

:func:`holding_activations` finds the least-effort muscle activations that hold a set of joints still in
a given pose: with the velocities zero, each muscle's force is affine in its activation (MuJoCo's
``force = gain(length) * act + bias(length)``), so the joint torques are ``A a + tau0``, where column i of
A is muscle i's torque at full activation through its moment arms; the activations solve
``min |A a + tau0 + tau_passive - tau_gravity|^2 + effort |a|^2`` with ``0 <= a <= 1`` (scipy's bounded
least squares). For an eye the pose is a gaze (yaw, pitch) with no torsion (the Fick rotation).

The oculomotor net of each eye (:class:`warp_vision.nn.heads.OculomotorNet`, trained by
``python -m warp_vision.train oculomotor``, :mod:`warp_vision.train.oculomotor`) maps (desired change of
gaze, current six activations) to the next six activations. Its data (:func:`synthesize_holding`): gazes
sampled in a disc, their holding activations, and transitions between them (:func:`transition_pairs`) (the current
activations hold gaze g, the next ones hold g + change): a tenth stay put, 36% go to a gaze within 3 deg (the small
corrections the loop asks for every period) and the rest, 54%, to a random gaze (saccades); the fit weighs each error by
the inverse square of (1 deg + the change). Its held-out accuracy is evaluated where it matters, on the body:
the gaze the eye settles at under the net's activations against the gaze asked for, after one saccade
and after 30 small steps with the net fed its own output (:func:`evaluate_on_body`).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass

import mujoco
import numpy as np
import torch
from scipy.optimize import lsq_linear

from warp_vision.body import EYE_MUSCLE_NAMES, SIDES, Body, BodyConfig, quat_from_matrix
from warp_vision.frames import fick_rotation
from warp_vision.nn.heads import OculomotorNet

#: Effort weight: small next to the torque residual (N m), so the pose is held exactly where it can be.
EFFORT = 1e-8
#: For an eye the torque about the line of sight counts 0.3 of the others': where the
#: muscles can hold a gaze with no torsion they do (the effort is tiny next to any residual), and where they
#: cannot (a low temporal part of the 35 deg disc) the gaze is held and torsion gives. One objective
#: everywhere: switching to a second solve where an exact one fails makes the activations jump between
#: neighbouring gazes, which the oculomotor nets cannot learn; with one objective the only jumps are the
#: optimum's own switches between muscle combinations.
EYE_TORQUE_WEIGHTS = np.array([1.0, 1.0, 0.3])


def muscle_torques(body: Body, actuators, dofs, qpos, data: mujoco.MjData | None = None):
    """(A [len(dofs), len(actuators)], tau0 [len(dofs)], tau_passive_minus_bias [len(dofs)]) at ``qpos``
    with zero velocities: the torque of each muscle at full activation beyond its activation-free force,
    the muscles' activation-free (passive) torque, and the passive joint torque minus gravity."""
    m = body.model
    d = data if data is not None else mujoco.MjData(m)
    d.qpos[:] = qpos
    d.qvel[:] = 0
    d.act[:] = 0
    # what the torques need of mj_forward (positions, tendons and moment arms; passive and bias forces;
    # the actuators'), without its constraint solve and accelerations
    mujoco.mj_fwdPosition(m, d)
    mujoco.mj_fwdVelocity(m, d)
    mujoco.mj_fwdActuation(m, d)
    adr = m.actuator_actadr[np.asarray(actuators)]
    tau0 = d.qfrc_actuator[dofs].copy()
    rest = d.qfrc_passive[dofs] - d.qfrc_bias[dofs]
    A = np.empty((len(dofs), len(actuators)))
    for i, a in enumerate(adr):
        d.act[a] = 1.0
        mujoco.mj_fwdActuation(m, d)
        A[:, i] = d.qfrc_actuator[dofs] - tau0
        d.act[a] = 0.0
    return A, tau0, rest


def holding_activations(body: Body, actuators, dofs, qpos, effort=EFFORT, weights=None,
                        data=None) -> tuple[np.ndarray, float]:
    """Least-effort activations in [0, 1] that hold joints ``dofs`` still at ``qpos``; returns
    (activations [len(actuators)], residual torque norm N m). ``effort``: a weight, or one per muscle;
    ``weights``: one per dof on the torque residual."""
    A, tau0, rest = muscle_torques(body, actuators, dofs, qpos, data)
    W = np.diag(np.ones(len(dofs)) if weights is None else np.asarray(weights, float))
    a, _ = least_effort(W @ A, -W @ (tau0 + rest), effort)
    return a, float(np.linalg.norm(A @ a + tau0 + rest))


def least_effort(A: np.ndarray, b: np.ndarray, effort=EFFORT, tone: float = 0.0) -> tuple[np.ndarray, float]:
    """The activations in [0, 1] that best solve ``A a = b`` (torques, N m) with the least
    ``effort``-weighted ``|a - tone|^2`` (``effort``: a weight, or one per muscle; scipy's bounded least
    squares), and the residual norm ``|A a - b|``."""
    n = A.shape[1]
    w = np.sqrt(np.broadcast_to(np.asarray(effort, float), (n,)))
    sol = lsq_linear(np.vstack([A, np.diag(w)]), np.concatenate([b, w * tone]), bounds=(0.0, 1.0), method="bvls")
    a = np.clip(sol.x, 0.0, 1.0)
    return a, float(np.linalg.norm(A @ a - b))


def eye_qpos(body: Body, side: str, yaw: float, pitch: float) -> np.ndarray:
    """The body's rest qpos with eye ``side`` turned to (yaw, pitch) rad (no torsion)."""
    q = body.model.qpos0.copy()
    a = body.model.jnt_qposadr[body.eye_joint[side]]
    q[a:a + 4] = quat_from_matrix(fick_rotation(yaw, pitch))
    return q


def eye_dofs(body: Body, side: str) -> np.ndarray:
    v = body.model.jnt_dofadr[body.eye_joint[side]]
    return np.arange(v, v + 3)


def eye_holding_activations(body: Body, side: str, gazes, progress: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Holding activations [N, 6] of eye ``side`` for gazes [N, 2] (yaw, pitch rad), and residuals [N]."""
    from tqdm import tqdm

    gazes = np.atleast_2d(np.asarray(gazes, float))
    d = mujoco.MjData(body.model)
    out = np.empty((len(gazes), len(EYE_MUSCLE_NAMES)))
    res = np.empty(len(gazes))
    for k, (yaw, pitch) in enumerate(tqdm(gazes, desc=f"holding activations ({side} eye)", disable=not progress,
                                          leave=False)):
        out[k], res[k] = holding_activations(body, body.eye_muscles[side], eye_dofs(body, side),
                                             eye_qpos(body, side, yaw, pitch), weights=EYE_TORQUE_WEIGHTS, data=d)
    return out, res


def sample_gazes(n: int, max_deg: float, rng: np.random.Generator) -> np.ndarray:
    """[n, 2] gazes (yaw, pitch rad) uniform in a disc of ``max_deg``."""
    r = np.radians(max_deg) * np.sqrt(rng.uniform(size=n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], 1)


#: The dataset generator's version: bump it when the gazes or their solves change.
#: 2: the obliques wrap the globe on the temporal side (their paths jumped to the far side over parts of the disc).
HOLDING_VERSION = 2


@dataclass
class HoldingDataConfig:
    """The holding-activation dataset of one eye: gazes drawn in a disc and the activations that hold them."""

    eye: str = "left"
    gazes: int = 5000  # gazes whose holding activations are solved
    max_gaze_deg: float = 35.0  # the disc they are drawn from
    seed: int = 0
    chunk_size: int = 500

    def validate(self) -> None:
        if self.eye not in SIDES:
            raise ValueError(f"eye: expected one of {SIDES}, got {self.eye!r}")
        if self.gazes < 4 or self.chunk_size < 1:
            raise ValueError(f"gazes: expected at least 4, got {self.gazes}")
        if not 0 < self.max_gaze_deg <= 45:
            raise ValueError(f"max_gaze_deg: expected degrees in (0, 45], got {self.max_gaze_deg}")

    def manifest(self) -> dict:
        return {"generator": "holding_activations", "generator_version": HOLDING_VERSION, **asdict(self)}

    def key(self) -> str:
        """A short hash of the config (dataset cache directory names)."""
        return hashlib.sha256(json.dumps(self.manifest(), sort_keys=True).encode()).hexdigest()[:12]

    def sample_gazes(self) -> np.ndarray:
        """[gazes, 2] (yaw, pitch rad): the dataset's gazes (seeded by the seed and the eye)."""
        return sample_gazes(self.gazes, self.max_gaze_deg, np.random.default_rng([self.seed, SIDES.index(self.eye)]))


def synthesize_holding(out_dir, cfg: HoldingDataConfig, shard=(0, 1), progress: bool = True, log=print):
    """Solve the holding activations of ``cfg``'s gazes into a chunked store in ``out_dir`` (resuming what
    is there); fields ``gaze`` [2], ``act`` [6], ``residual`` (N m). Returns the store."""
    from warp_vision.data.store import ChunkedStore
    from warp_vision.data.synth import pending, render_missing

    cfg.validate()
    fields = {"gaze": ((2,), "float64"), "act": ((len(EYE_MUSCLE_NAMES),), "float64"), "residual": ((), "float64")}
    store = ChunkedStore.create_or_resume(out_dir, cfg.manifest(), cfg.gazes, cfg.chunk_size, fields,
                                          shard=tuple(shard))
    todo, mine = pending(store)
    if todo:
        log(f"solving the holding activations of {todo:,} of {mine:,} gazes ({cfg.eye} eye) into {out_dir}")
        body = Body(BodyConfig(arms=False))  # the eyes are the same in every body; the bare one is faster
        gazes = cfg.sample_gazes()

        def solve(r: range) -> dict:
            g = gazes[r.start:r.stop]
            acts, res = eye_holding_activations(body, cfg.eye, g)
            return {"gaze": g, "act": acts, "residual": res}

        render_missing(store, solve, batch=50, progress=progress, log=log, what="gazes")
    return store


def transition_pairs(idx: np.ndarray, n: int, rng, gaze: np.ndarray | None = None,
                     near_deg: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` (current, next) index pairs among ``idx``: random pairs (saccades); with ``gaze`` given, four
    tenths of them then go to a gaze within ``near_deg`` instead (the small corrections of fixation and
    pursuit, which the loop asks for every period and random pairs almost never hold) and a tenth of all,
    drawn independently, stay put (so 54% random, 36% near, 10% still)."""
    i, j = rng.choice(idx, n), rng.choice(idx, n)
    if gaze is None:
        return i, j
    from scipy.spatial import cKDTree

    tree = cKDTree(gaze[idx])
    near = np.nonzero(rng.uniform(size=n) < 0.4)[0]
    for k, nb in zip(near, tree.query_ball_point(gaze[i[near]], np.radians(near_deg))):
        j[k] = idx[rng.choice(nb)]
    same = np.nonzero(rng.uniform(size=n) < 0.1)[0]
    j[same] = i[same]
    return i, j


def settle_gaze(body: Body, side: str, activations, seconds: float = 0.3) -> np.ndarray:
    """Hold ``activations`` on eye ``side`` of a freshly reset body for ``seconds``; the gaze (rad) it settles at."""
    body.reset()
    body.set_eye_activations(side, np.clip(activations, 0, 1))
    body.step(int(round(seconds / body.model.opt.timestep)))
    return body.gaze_in_head(side)


def evaluate_on_body(net: OculomotorNet, body: Body, side: str, gaze: np.ndarray, act: np.ndarray, held_out: np.ndarray,
                     n: int = 100, seed: int = 7) -> dict:
    """Held-out accuracy on the body, in degrees of gaze:

    - saccades: from the holding activations of a held-out gaze g_i, ask the net for g_j - g_i (another
      held-out gaze), let the eye settle under its activations and compare with g_j;
    - pursuit: from a held-out gaze, apply the net recursively (its output is its next input) for 30
      steps of 0.5 deg in a fixed direction, as the loop does every period, then settle and compare
      with where the 15 deg path ends (errors that compound show here).

    Also the error of the exact holding activations of g_j (what the net learns from)."""
    rng = np.random.default_rng(seed)
    te = np.asarray(held_out)
    i, j = transition_pairs(te, n, rng)
    g, acts = gaze, act
    with torch.no_grad():
        pred = net(torch.as_tensor(g[j] - g[i], dtype=torch.float32),
                   torch.as_tensor(acts[i], dtype=torch.float32)).numpy()
    err = np.array([np.degrees(np.linalg.norm(settle_gaze(body, side, pred[k]) - g[j[k]])) for k in range(n)])
    exact = np.array([np.degrees(np.linalg.norm(settle_gaze(body, side, acts[j[k]]) - g[j[k]])) for k in range(n)])
    chain = []
    lim = np.radians(30.0)
    for _ in range(n // 4):
        start = g[te[rng.integers(len(te))]]
        phi = rng.uniform(0, 2 * np.pi)
        step = np.radians(0.5) * np.array([np.cos(phi), np.sin(phi)])
        if np.linalg.norm(start + 30 * step) > lim:
            step = -step
        a = eye_holding_activations(body, side, start)[0][0]
        with torch.no_grad():
            for _ in range(30):
                a = net(torch.as_tensor(step, dtype=torch.float32)[None],
                        torch.as_tensor(a, dtype=torch.float32)[None])[0].numpy()
        chain.append(np.degrees(np.linalg.norm(settle_gaze(body, side, a) - (start + 30 * step))))
    return {
        "gaze_error_deg_median": float(np.median(err)),
        "gaze_error_deg_p90": float(np.percentile(err, 90)),
        "pursuit_chain_error_deg_median": float(np.median(chain)),
        "pursuit_chain_error_deg_p90": float(np.percentile(chain, 90)),
        "holding_activation_error_deg_median": float(np.median(exact)),
        "transitions": n,
    }


def load_oculomotor(run_root) -> dict:
    """{side: OculomotorNet} from ``run_root/<side>``, the runs of ``python -m warp_vision.train oculomotor``."""
    from warp_vision.nn.trained import load_net

    nets = {}
    for side in SIDES:
        run = os.path.join(run_root, side)
        nets[side], ck = load_net(run, expect={"task": "oculomotor", "eye": side})
        # checkpoints saved before the version travelled with them learnt from v1
        version = int(ck["data"].get("generator_version", 1))
        if version != HOLDING_VERSION:
            raise ValueError(f"{run}: an oculomotor net of holding data v{version}, solved on an eye plant since "
                             f"corrected (now v{HOLDING_VERSION}: see HOLDING_VERSION); retrain it: python -m "
                             f"warp_vision.train oculomotor --eye {side} --out {run} --overwrite")
    return nets
