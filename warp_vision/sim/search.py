"""Active search: peripheral candidates, both eyes agreeing, a saccade, foveal verification, inhibition of
return, tracking with a motion prior.

On every visual frame :meth:`ActiveSearch.frame` turns both eyes' ONVs into each eye's retinal error of
the one thing the eyes should look at (or None: hold the gaze), which the gaze controller
(:class:`warp_vision.sim.gaze.GazeController`) follows between frames as it follows the foveation nets'
single answer.

- **Candidates.** Each eye's foveation net proposes its few strongest answers
  (:meth:`warp_vision.sim.loop.Foveator.candidates`): a direction in the eye frame and a score each.
- **Both eyes agree.** A candidate of the left eye and one of the right eye make a pair when their rays
  (from each eye's centre, the eye's pose read from the body as the vestibulo-ocular reflex reads the
  neck) pass within ``AGREE_M`` + ``AGREE_DEG`` of the distance of each other, at a distance in
  ``DISTANCE_M``. The pair's point is the rays' closest approach. An object that only one eye proposes
  makes no pair and is never looked at; with no pair the gaze holds.
- **Inhibition of return.** A rejected pair's point is remembered in the world for ``IOR_S`` seconds:
  a pair whose rays pass within ``IOR_DEG`` of a remembered point (seen from either eye) is dropped.
  Being a point in the world, the memory moves with nothing: the eyes and the head turn under it.
- **Motion.** A pair whose direction from the eyes' midpoint moved by ``MOTION_DEG`` since the last
  frame's nearest pair (in the world: the eyes' own rotation cancels) scores ``MOTION_BONUS`` more; while
  tracking, the tracked point's predicted position is the prior: only pairs within ``GATE_DEG`` of it
  (in both eyes) continue the track.
- **The cycle.** *search*: the best remaining pair is the target; the eyes saccade to it. *verify*: once
  both eyes' axes are within ``LANDED_DEG`` of the target (or ``VERIFY_TIMEOUT_S`` after the saccade),
  each eye's verification net (:class:`warp_vision.nn.verify.FovealVerifier`) reads its central field:
  both accept, and the target's point moves to where the two nets' offsets put the ball (the corrective
  saccade), and tracking begins; either rejects, and the point joins the inhibited ones and the search
  goes on at once. *track*: the point follows the gated pairs (or the verifiers' offsets), its velocity
  a running estimate; every ``REVERIFY_S`` both nets check again, and a rejection by both (or
  ``LOST_FRAMES`` frames without a pair or an accept) ends the track: back to search.

``log`` keeps the events (time, kind, point) for the scanpath figure.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from warp_vision.body import SIDES
from warp_vision.frames import gaze_direction, line_crossing
from warp_vision.sim.gaze import CONTROL_DT

CANDIDATES = 4
MIN_SEP_DEG = 4.0
AGREE_M, AGREE_DEG = 0.03, 1.5
DISTANCE_M = (0.25, 8.0)
IOR_S, IOR_DEG = 2.0, 3.0
MOTION_DEG = (1.0, 20.0)
MOTION_BONUS = 0.5
GATE_DEG = 4.0
LANDED_DEG = 1.5
VERIFY_TIMEOUT_S = 0.3
REVERIFY_S = 0.2
LOST_FRAMES = 4
VELOCITY_SMOOTHING = 0.5


@dataclass
class Pair:
    """A candidate both eyes see: its world point (m), score, and each eye's candidate index."""

    point: np.ndarray
    score: float
    index: tuple
    moving: bool = False


@dataclass
class SearchState:
    state: str = "search"
    target: np.ndarray | None = None  # the world point the eyes look at
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m/s, while tracking
    since: float = 0.0  # when the state began
    last_verified: float = 0.0
    misses: int = 0
    inhibited: list = field(default_factory=list)  # [(world point, until time)]
    last_pairs: list = field(default_factory=list)  # the previous frame's pair directions (world, from the eyes'
                                                    # midpoint)


class Verifier:
    """An eye's trained verification net (:class:`warp_vision.nn.verify.FovealVerifier`) and its input norm:
    ``(accepted, probability, offset (yaw, pitch) rad)`` of one full ONV [1, 3P]. ``eye``: the eye it serves;
    another eye's net is refused."""

    def __init__(self, run_dir: str, device: str = "cpu", eye: str | None = None):
        from warp_vision.sim.loop import _load_kind

        self.run_dir = run_dir
        self.model, ck = _load_kind(run_dir, "verify", device, eye)
        self.norm, self.device = ck["norm"], device

    def __call__(self, onv: torch.Tensor) -> tuple[bool, float, np.ndarray]:
        from warp_vision.nn.trained import net_input

        if onv.ndim != 2 or onv.shape[0] != 1:
            raise ValueError(f"onv: expected one ONV [1, 3P], got {tuple(onv.shape)}")
        with torch.no_grad():
            ok, p, off = self.model.verdict(net_input(self.model.field(onv), self.norm, self.device))
        return bool(ok[0]), float(p[0]), off[0].cpu().numpy().astype(np.float64)


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)), -1.0, 1.0))))


def eye_ray(body, side: str, yaw_pitch) -> tuple[np.ndarray, np.ndarray]:
    """(origin, unit direction) in the world of the direction ``yaw_pitch`` (rad) in eye ``side``'s frame."""
    T = body.eye_pose(side)
    return T[:3, 3], T[:3, :3] @ gaze_direction(*np.asarray(yaw_pitch, float))


def pair_point(o1, d1, o2, d2) -> np.ndarray | None:
    """Where two rays agree: the midpoint of their closest approach, or None when they do not meet within
    the tolerance (``AGREE_M`` + ``AGREE_DEG`` of the distance) at a distance in ``DISTANCE_M``."""
    st = line_crossing(o1, d1, o2, d2, parallel=1e-9)
    if st is None:
        return None
    t1, t2 = st
    if not (DISTANCE_M[0] <= t1 <= DISTANCE_M[1] and DISTANCE_M[0] <= t2 <= DISTANCE_M[1]):
        return None
    p1, p2 = o1 + t1 * d1, o2 + t2 * d2
    if np.linalg.norm(p1 - p2) > AGREE_M + np.tan(np.radians(AGREE_DEG)) * 0.5 * (t1 + t2):
        return None
    return 0.5 * (p1 + p2)


def pairs(body, cands: dict) -> list[Pair]:
    """Every left-right pair of candidates whose rays agree (:func:`pair_point`), best score first; the score
    is the geometric mean of the two candidates'."""
    out = []
    (dl, sl), (dr, sr) = cands["left"], cands["right"]
    for i in range(len(dl)):
        if not np.isfinite(dl[i]).all():
            continue
        ol, ul = eye_ray(body, "left", dl[i])
        for j in range(len(dr)):
            if not np.isfinite(dr[j]).all():
                continue
            orr, ur = eye_ray(body, "right", dr[j])
            p = pair_point(ol, ul, orr, ur)
            if p is not None:
                out.append(Pair(p, float(np.sqrt(max(sl[i], 0.0) * max(sr[j], 0.0))), (i, j)))
    return sorted(out, key=lambda q: -q.score)


class ActiveSearch:
    """The search cycle of the module docstring, for both eyes. ``verifiers``: each eye's :class:`Verifier`
    (None: every target is accepted on arrival, the search without foveal verification)."""

    def __init__(self, verifiers: dict | None = None, candidates: int = CANDIDATES):
        if verifiers is not None and set(verifiers) != set(SIDES):
            raise ValueError(f"verifiers: expected one per eye {SIDES}, got {sorted(verifiers)}")
        self.verifiers, self.k = verifiers, int(candidates)
        self.reset()

    def reset(self) -> None:
        self.s = SearchState()
        #: (time s, event, world point) per event: "target", "reject", "accept", "lost"
        self.log: list = []
        #: the last frame's pairs (for figures and tests)
        self.pairs: list = []
        #: wall seconds of what the search adds to a frame: the candidates beyond the net's single answer, pairing
        #: and memory, the verification nets; the single answer's own (which the loop computes without a search
        #: too), for reference; and the frames
        self.timing = {"candidates": 0.0, "single_answer": 0.0, "pairs": 0.0, "verify": 0.0, "frames": 0}

    # ----------------------------------------------------------------------------------------------
    def inhibited(self, body, point: np.ndarray, now: float) -> bool:
        """Whether ``point`` lies within IOR_DEG of a remembered rejected point, seen from either eye."""
        self.s.inhibited = [(q, until) for q, until in self.s.inhibited if until > now]
        for q, _ in self.s.inhibited:
            for side in SIDES:
                o = body.eye_pose(side)[:3, 3]
                if _angle_deg(point - o, q - o) < IOR_DEG:
                    return True
        return False

    def inhibit(self, point: np.ndarray, now: float) -> None:
        self.s.inhibited.append((np.asarray(point, float).copy(), now + IOR_S))

    def _mark_motion(self, body, found: list[Pair]) -> None:
        mid = 0.5 * (body.eye_pose("left")[:3, 3] + body.eye_pose("right")[:3, 3])
        dirs = [(q.point - mid) / np.linalg.norm(q.point - mid) for q in found]
        for q, u in zip(found, dirs):
            if self.s.last_pairs:
                nearest = min(_angle_deg(u, v) for v in self.s.last_pairs)
                q.moving = MOTION_DEG[0] <= nearest <= MOTION_DEG[1]
                if q.moving:
                    q.score += MOTION_BONUS
        self.s.last_pairs = dirs
        found.sort(key=lambda q: -q.score)

    def _event(self, now: float, kind: str, point) -> None:
        self.log.append((float(now), kind, np.asarray(point, float).copy()))

    # ----------------------------------------------------------------------------------------------
    def frame(self, loop, onv: dict) -> dict | None:
        """One visual frame: each eye's retinal error (yaw, pitch) rad of the target, or None (hold)."""
        body, now = loop.body, loop.body.time
        extra0 = sum(getattr(loop.fov[s], "extra_seconds", 0.0) for s in SIDES)  # (a stand-in net may keep none)
        t0 = time.perf_counter()
        cands = {s: loop.fov[s].candidates(onv[s], self.k, MIN_SEP_DEG) for s in SIDES}
        t1 = time.perf_counter()
        extra = sum(getattr(loop.fov[s], "extra_seconds", 0.0) for s in SIDES) - extra0
        self.timing["candidates"] += extra
        self.timing["single_answer"] += t1 - t0 - extra
        found = [q for q in pairs(body, cands) if not self.inhibited(body, q.point, now)]
        self._mark_motion(body, found)
        self.pairs = found
        self.timing["pairs"] += time.perf_counter() - t1
        self.timing["frames"] += 1
        st = self.s
        if st.state == "verify":
            self._verify(loop, onv, now)
        elif st.state == "track":
            self._track(loop, onv, found, now)
        if st.state == "search":
            found = [q for q in found if not self.inhibited(body, q.point, now)]
            if found:
                st.state, st.target, st.since, st.velocity = "verify", found[0].point.copy(), now, np.zeros(3)
                self._event(now, "target", st.target)
        if st.target is None:
            return None
        from warp_vision.sim.loop import true_direction

        return {s: true_direction(body, s, st.target) for s in SIDES}

    def _landed(self, body) -> bool:
        return all(_angle_deg(body.eye_pose(s)[:3, 2],
                              self.s.target - body.eye_pose(s)[:3, 3]) < LANDED_DEG for s in SIDES)

    def _verdicts(self, loop, onv: dict) -> dict:
        """Each eye's (accepted, probability, offset) of its central field; all accepted without verifiers."""
        if self.verifiers is None:
            return {s: (True, 1.0, np.zeros(2)) for s in SIDES}
        t0 = time.perf_counter()
        out = {s: self.verifiers[s](onv[s]) for s in SIDES}
        self.timing["verify"] += time.perf_counter() - t0
        return out

    def _fixated_point(self, body, verdicts: dict) -> np.ndarray | None:
        """Where the two verifiers' offsets put the ball (their rays' agreement), or None."""
        (ol, ul), (orr, ur) = (eye_ray(body, s, verdicts[s][2]) for s in SIDES)
        return pair_point(ol, ul, orr, ur)

    def _verify(self, loop, onv: dict, now: float) -> None:
        st, body = self.s, loop.body
        if not self._landed(body) and now - st.since < VERIFY_TIMEOUT_S:
            return
        v = self._verdicts(loop, onv)
        if all(v[s][0] for s in SIDES):
            p = self._fixated_point(body, v)
            if p is not None:
                st.target = p
            st.state, st.since, st.last_verified, st.misses = "track", now, now, 0
            self._event(now, "accept", st.target)
        else:
            self.inhibit(st.target, now)
            self._event(now, "reject", st.target)
            st.state, st.target = "search", None

    def _track(self, loop, onv: dict, found: list[Pair], now: float) -> None:
        st, body = self.s, loop.body
        dt = loop.frame_every * CONTROL_DT
        predicted = st.target + st.velocity * dt
        gated = [q for q in found if all(_angle_deg(q.point - body.eye_pose(s)[:3, 3],
                                                    predicted - body.eye_pose(s)[:3, 3])
                                         < GATE_DEG for s in SIDES)]
        new = gated[0].point if gated else None
        if now - st.last_verified >= REVERIFY_S:
            st.last_verified = now
            v = self._verdicts(loop, onv)
            if not any(v[s][0] for s in SIDES):
                self.inhibit(st.target, now)
                self._event(now, "lost", st.target)
                st.state, st.target = "search", None
                return
            if all(v[s][0] for s in SIDES) and new is None:
                new = self._fixated_point(body, v)
        if new is None:
            st.misses += 1
            st.target = predicted
            if st.misses >= LOST_FRAMES:
                self._event(now, "lost", st.target)
                st.state, st.target = "search", None
            return
        st.misses = 0
        st.velocity = (1 - VELOCITY_SMOOTHING) * st.velocity + VELOCITY_SMOOTHING * (new - st.target) / dt
        st.target = new
