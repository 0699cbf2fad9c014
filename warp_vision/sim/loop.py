"""The closed loop: MuJoCo body -> scene -> both eyes' ONVs -> foveation nets -> gaze and neck control
-> oculomotor nets -> muscles -> MuJoCo.

On each visual frame (every ``FRAME_EVERY`` control periods of ``CONTROL_DT``) the scene follows the MuJoCo
state, each eye renders its ONV from its eye body's pose with its own retina and current optical state
(pupil, accommodation), and its foveation net (trained by ``python -m warp_vision.train --eye
left|right``) estimates the ball's direction in the eye frame. Every control period the gaze controller
(:class:`warp_vision.sim.gaze.GazeController`: an internal model of the eye, saccades, pursuit, bias
learning, the vestibulo-ocular reflex) turns the latest estimate into a change of the commanded gaze.

The oculomotor net maps (change of commanded gaze, current activations) to the next activations. The
neck controller moves the head's target a fraction ``NECK_GAIN`` per period toward the eyes' mean gaze
(the eye-head synergy: the eyes return toward centre as the head takes over), held by least-effort neck
activations (:func:`warp_vision.sim.oculomotor.holding_activations`). Accommodation is commanded by
the lens nets from each eye's central field, both lenses taking the mean of the two eyes' readings
(yoked, as human accommodation is), or with no nets to the distance where the two gaze lines converge;
the pupil by each eye's pupil net from its ONV (or, with no nets, by their teacher: Watson & Yellott's
diameter for the adapting luminance); the iris and lens plants (:mod:`warp_vision.eye.plants`) answer
after their latencies.
"""

from __future__ import annotations

import time

import mujoco
import numpy as np
import torch

from warp_vision.body import ARM_PARTS, HIDDEN_FROM_EYES, SIDES, Body, visible_parts
from warp_vision.frames import gaze_angles, gaze_direction, line_crossing
from warp_vision.sim.gaze import CONTROL_DT, GazeController
from warp_vision.sim.oculomotor import holding_activations

#: The eyes render (and the foveation nets run) every FRAME_EVERY control periods: 25 frames a second.
#: Human visual latency is 50-100 ms and flicker fusion in the periphery 20-60 Hz. At 40 ms a frame the
#: loop renders a quarter as often; its saccades are as fast as with a frame every period, its tracking
#: errors somewhat larger (``python -m warp_vision.bench loop`` measures both; docs/RESULTS.md has the numbers).
FRAME_EVERY = 4
NECK_GAIN = 0.02
#: The most a muscle's holding activation changes per degree of gaze between neighbouring gazes (above the
#: 99th percentile over the 35 deg disc): an oculomotor net's output that moves a muscle faster is off the
#: activations it was trained on, and fed back period after period it can run away with the obliques and
#: lose the ball. The loop clips each period's change to this rate.
ACTIVATION_PER_DEG = 0.12
ACTIVATION_SLACK = 0.005
OPTICS_STEP_D = 0.5
LENS_OPTICS_STEP_D = 0.1  # with lens nets in the loop (their goal: within 0.25 D)
PUPIL_STEP_MM = 0.5
OPTICS_HYSTERESIS = 0.75  # of a step: how far from its rendered state the eye must be to change it


#: Who commands the iris and the lens: "nets" (each eye's pupil and lens nets) or "analytic" (their
#: teachers: Watson & Yellott's pupil, and accommodation to where the gaze lines converge).
INTRAOCULAR = ("nets", "analytic")
#: Who tells the gaze controller where the ball is: "nets" (each eye's foveation net's single answer, from its
#: ONV), "search" (active search over both eyes' candidates with foveal verification: :mod:`warp_vision.sim.search`)
#: or "oracle" (the ball's true direction in the eye frame: separates perception's errors from control's).
PERCEPTION = ("nets", "search", "oracle")


def _load_kind(run_dir: str, kind: str, device: str, eye: str | None = None):
    """(model, checkpoint) of the run in ``run_dir``, or a ValueError when it holds another kind of net, or
    (``eye`` given) the other eye's, or a checkpoint of another run than its config.json's."""
    from warp_vision.nn.trained import load_net, task_command

    model, ck = load_net(run_dir, device, expect={"eye": eye})  # (the kind is checked below, naming its command)
    if ck.get("net", {}).get("kind") != kind:
        raise ValueError(f"{run_dir}: expected a {kind} run ({task_command(kind)}); it holds a "
                         f"net of kind {ck.get('net', {}).get('kind')!r}")
    return model, ck


def load_pupil(run_dir: str, device: str = "cpu", eye: str | None = None):
    """An eye's trained pupil net (:class:`warp_vision.nn.intraocular.PupilNet`), in eval mode; with ``eye``, refused
    unless it is that eye's."""
    return _load_kind(run_dir, "pupil", device, eye)[0]


def load_lens(run_dir: str, device: str = "cpu", eye: str | None = None):
    """An eye's trained lens net (:class:`warp_vision.nn.intraocular.LensNet`), in eval mode; with ``eye``, refused
    unless it is that eye's."""
    return _load_kind(run_dir, "lens", device, eye)[0]


class Foveator:
    """An eye's trained foveation net (a liNet or the retina CNN): ONV [B, 3P] -> the ball's (yaw, pitch) in
    the eye frame, rad ([B, 2] numpy). What rendering an ONV for it takes comes with it, from the run's
    dataset config: ``retina`` (its photoreceptors), ``trained_eye`` (the optics its training ONVs were
    rendered through), ``samples_per_receptor``; and ``generator``, the dataset's version. ``eye``: the eye it
    serves; another eye's net is refused."""

    def __init__(self, run_dir: str, device: str = "cpu", eye: str | None = None):
        from warp_vision.data.foveation import FoveationDataConfig, make_eye, make_retina
        from warp_vision.nn.trained import onv_dtype

        self.run_dir = run_dir
        self.model, ck = _load_kind(run_dir, "foveation", device, eye)
        data = FoveationDataConfig.saved(ck["data"])
        self.generator = data.generator
        self.retina = make_retina(data)
        self.trained_eye = make_eye(data)  # the optical state its training ONVs were rendered with
        self.samples_per_receptor = data.samples_per_receptor
        self.norm = ck["norm"]
        self.device = device
        self.onv_dtype = onv_dtype(ck["net"])
        #: wall seconds spent in :meth:`candidates` beyond the single answer (the heat map's further peaks)
        self.extra_seconds = 0.0

    def __call__(self, onv: torch.Tensor) -> np.ndarray:
        from warp_vision.nn.trained import predict_targets

        return predict_targets(self.model, onv, self.norm, self.device, self.onv_dtype).numpy()

    def candidates(self, onv: torch.Tensor, k: int = 4, min_sep_deg: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
        """The net's few strongest answers for one ONV [1, 3P]: (directions [k, 2] (yaw, pitch) rad in the eye
        frame, scores [k]), the first of them the net's single answer (:meth:`__call__`). A retina CNN adds
        the further peaks of its heat map (:meth:`~warp_vision.nn.retina_cnn.RetinaCNNFoveationNet.candidates`)
        farther than ``min_sep_deg`` from it and from each other; a net without a heat map gives its one answer.
        Missing candidates have NaN directions and score 0."""
        from warp_vision.nn.trained import net_input

        best = self(onv)[0]
        dirs, scores = np.full((k, 2), np.nan), np.zeros(k)
        dirs[0], scores[0] = best, 1.0
        if not hasattr(self.model, "candidates"):
            return dirs, scores
        t0 = time.perf_counter()
        with torch.no_grad():
            d, sc = self.model.candidates(net_input(onv[:1], self.norm, self.device, self.onv_dtype), k + 1,
                                          min_sep_deg)
        self.extra_seconds += time.perf_counter() - t0
        d, sc = d[0].cpu().numpy().astype(np.float64), sc[0].cpu().numpy().astype(np.float64)
        cos_sep = np.cos(np.radians(min_sep_deg))
        best_dir = gaze_direction(*best)
        near_best = [j for j in range(len(d))
                     if np.isfinite(d[j]).all() and gaze_direction(*d[j]) @ best_dir >= cos_sep]
        scores[0] = float(sc[near_best[0]]) if near_best else 0.0
        rest = [j for j in range(len(d)) if j not in near_best and np.isfinite(d[j]).all()][: k - 1]
        for n, j in enumerate(rest, start=1):
            dirs[n], scores[n] = d[j], sc[j]
        return dirs, scores


#: Bodies whose parts move together in the scene: each arm's humerus, ulna, radius and hand (the carpals
#: with the fingers), and the head, neck and eyes; everything else (the fixed torso scaffold, clavicles,
#: scapulae, stool, cannon) is baked into the static BVH at the pose it has when the scene is built. The
#: passive arms' small joints barely move, and one BVH per MuJoCo body (about 100 objects) makes each
#: eye's render an order of magnitude slower.
SCENE_ANCHORS = ARM_PARTS["right"] + ARM_PARTS["left"] + HIDDEN_FROM_EYES


#: The balls the loop can show: "ordinary" (a grey-white glossy ball, lit by the room's lamps, in a room
#: at its everyday albedos: what the v8 and v9 nets are trained for) or "glowing" (v7's set-up: a white ball that
#: glows, in the room dimmed to ROOM_ALBEDO, the body dimmed alike).
BALLS = ("ordinary", "glowing")
#: The ordinary ball's material and the second lamp of its room (the first is the room's hanging lamp).
ORDINARY_BALL = dict(diffuse=(0.7, 0.7, 0.7), specular=0.3, shininess=32)
SECOND_LAMP = ((2.5, -2.0, 3.4), (1.0, 0.95, 0.85), 5.0)


def body_scene(body: Body, seed: int = 0, ball: str = "glowing"):
    """The room with the body's visible parts (group-0 geoms, grouped as in :data:`SCENE_ANCHORS`) and
    the ball (:data:`BALLS`), at the body's current pose."""
    import trimesh

    from warp_vision.data.foveation import BALL_EMISSION, ROOM_ALBEDO, ROOM_SIZE, make_scene
    from warp_vision.scene import Material
    from warp_vision.scene.room import make_room

    if ball not in BALLS:
        raise ValueError(f"ball: expected one of {BALLS}, got {ball!r}")
    glowing = ball == "glowing"
    if glowing:
        sc = make_scene(seed)
        for o in sc.objects:  # the dataset's balls and panel
            if o.name.startswith("ball") or o.name == "occluder":
                sc.set_visible(o.name, False)
    else:
        sc = make_room(size=ROOM_SIZE, n_objects=6, seed=seed, ball_centre=(0.0, 0.0, -10.0))
        sc.set_visible("ball", False)
        sc.lights[0].position = np.array([0.0, 0.0, ROOM_SIZE[2] - 0.6])
        sc.add_light(*SECOND_LAMP)
    m = body.model
    parts = visible_parts(body, SCENE_ANCHORS, exclude=("ball",))
    if glowing:
        for meshes in parts.values():
            # dimmed like the room (x ROOM_ALBEDO / 0.4), so the glowing ball stays the brightest thing in view
            for mesh in meshes:
                c = np.array(mesh.visual.vertex_colors)
                c[:, :3] = (c[:, :3] * min(1.0, ROOM_ALBEDO / 0.4)).astype(np.uint8)
                mesh.visual.vertex_colors = c
    sc._mj_bodies = []
    for b, meshes in parts.items():
        name = f"mj_{m.body(b).name}" if b else "mj_fixed"
        sc.add(name, trimesh.util.concatenate(meshes), Material(vertex_colors=True), body.pose(b), static=(b == 0))
        if b:
            sc._mj_bodies.append((name, b))
    mat = (Material((1.0, 1.0, 1.0), specular=0.4, shininess=32, smooth=True, emission=(BALL_EMISSION,) * 3) if glowing
           else Material(**ORDINARY_BALL, smooth=True))
    sc.add_sphere("mj_ball", m.geom_size[m.geom("ball").id, 0], material=mat)
    return sc


def sync_scene(scene, body: Body) -> None:
    """Move the scene's body parts and ball to the MuJoCo state."""
    for name, b in scene._mj_bodies:
        scene.set_transform(name, body.pose(b))
    T = np.eye(4)
    T[:3, 3] = body.ball_position()
    scene.set_transform("mj_ball", T)


def set_eye_view(scene, eyes: bool) -> None:
    """Hide (eyes=True) or show the parts the eyes do not see."""
    for name, _b in scene._mj_bodies:
        if name[3:] in HIDDEN_FROM_EYES:
            scene.set_visible(name, not eyes)


def _quantise(x: float, step: float, last: float | None) -> float:
    """``x`` to the nearest multiple of ``step``, but ``last`` while ``x`` is within OPTICS_HYSTERESIS steps of it."""
    if last is not None and abs(x - last) <= OPTICS_HYSTERESIS * step:
        return last
    return round(x / step) * step


class VisuomotorLoop:
    """Both eyes, their foveation and oculomotor nets, the neck controller; :meth:`step` advances one
    control period. ``timing`` accumulates wall seconds per stage (render, nets, mujoco, control)."""

    def __init__(self, body: Body, foveators: dict, oculomotor: dict, seed: int = 0, frame_every: int = FRAME_EVERY,
                 ball: str = "glowing", pupil_nets: dict | None = None, lens_nets: dict | None = None,
                 perception: str = "nets", search=None):
        if perception not in PERCEPTION:
            raise ValueError(f"perception: expected one of {PERCEPTION}, got {perception!r}")
        if (perception == "search") != (search is not None):
            raise ValueError("search: an ActiveSearch (warp_vision.sim.search) goes with perception='search', and only "
                             "with it")
        #: the active search (:class:`warp_vision.sim.search.ActiveSearch`) with perception "search", else None
        self.search = search
        #: "nets" (the foveation nets' estimates) or "oracle" (the true directions; the eyes still render)
        self.perception = perception
        if not isinstance(frame_every, (int, np.integer)) or frame_every < 1:
            raise ValueError(f"frame_every: expected a whole number of control periods >= 1, got {frame_every!r}")
        for name, nets in (("pupil_nets", pupil_nets), ("lens_nets", lens_nets)):
            if nets is not None and set(nets) != set(SIDES):
                raise ValueError(f"{name}: expected one net per eye {SIDES}, got {sorted(nets)}")
        #: each eye's pupil net (:class:`warp_vision.nn.intraocular.PupilNet`), or None: the analytic law
        self.pupil_nets = pupil_nets
        #: each eye's lens net (:class:`warp_vision.nn.intraocular.LensNet`), or None: the vergence law
        self.lens_nets = lens_nets
        #: the accommodation steps the eyes render at: a lens net needs finer ones than its 0.25 D goal
        self.optics_step_d = LENS_OPTICS_STEP_D if lens_nets is not None else OPTICS_STEP_D
        #: with lens nets: both lenses take the mean of the two eyes' readings (False: each eye its own)
        self.yoked_lens = True
        #: per eye, the vergence law's accommodation command (D) and, with lens nets, the defocus they read
        self.lens_teacher: dict = {}
        self.defocus_estimate: dict = {}
        #: the room's light level: every lamp, the ambient light and every emission times this (the renderer
        #: is linear in them, so the ONVs are the rendered ones times it); the light-step scenario changes it
        self.light_scale = 1.0
        #: per eye, the analytic law's pupil command (Watson & Yellott) of the last frame: the nets' teacher
        self.pupil_teacher: dict = {}
        self.body, self.fov, self.ocu = body, foveators, oculomotor
        self.frame_every = int(frame_every)
        self.period = 0
        self.ball = ball
        self.scene = body_scene(body, seed, ball)
        #: per eye, the central field rendered for its lens net on the last frame
        self.lens_onv: dict = {}
        self._lens_positions: dict = {}
        #: the gaze controller: each eye's commanded and believed gaze, its estimates and the saccade logic
        self.gaze = GazeController(self.frame_every)
        self.neck_target = np.zeros(3)
        self.last_neck = body.neck_angles()
        self.timing = {"render": 0.0, "nets": 0.0, "mujoco": 0.0, "control": 0.0}
        #: called after every MuJoCo step of :meth:`step` when set (a callable of no arguments)
        self.substep = None
        self.scratch = mujoco.MjData(body.model)
        self.neck_dofs = body.model.jnt_dofadr[body.neck_joints]
        self.onv: dict = {}
        self.estimate: dict = {}
        self._pupil_command: dict = {}
        self._lens_command: dict = {}
        self._optics: dict = {}  # per eye, the quantised (accommodation, pupil) it renders with
        self._neck_hold()

    @property
    def eyes(self) -> dict:
        """Each eye's :class:`~warp_vision.sim.gaze.EyeState` (the gaze controller's)."""
        return self.gaze.eyes

    def reset(self, settle_s: float = 0.0) -> None:
        """Reset the body (then let it settle ``settle_s`` s with the eyes and neck held centred) and the
        controllers' state; the timing totals are kept."""
        self.body.reset()
        self.period = 0
        self._pupil_command = {}
        self._lens_command = {}
        # and what the last run saw: a run's result must not depend on the runs before it (the optics'
        # quantisation keeps a hysteresis, so a state left over changes which ray set the next run renders with)
        self._optics = {}
        self.onv, self.lens_onv, self.estimate = {}, {}, {}
        self.lens_teacher, self.pupil_teacher, self.defocus_estimate = {}, {}, {}
        self.gaze.reset()
        if self.search is not None:
            self.search.reset()
        self.neck_target = np.zeros(3)
        self._neck_hold()
        self.body.step(int(round(settle_s / self.body.model.opt.timestep)))
        self.last_neck = self.body.neck_angles()

    def _neck_hold(self) -> None:
        q = self.body.data.qpos.copy()
        q[self.body.model.jnt_qposadr[self.body.neck_joints]] = self.neck_target
        a, _ = holding_activations(self.body, self.body.neck_muscles, self.neck_dofs, q, data=self.scratch)
        self.body.set_neck_activations(a)

    def render(self) -> dict:
        from warp_vision.eye.optics import NavarroEye
        from warp_vision.kernels.render import render_onv, scene_data

        t0 = time.perf_counter()
        sync_scene(self.scene, self.body)
        set_eye_view(self.scene, True)
        packed = scene_data(self.scene)  # once for every view of this state
        out = {}
        for s in SIDES:
            pupil, acc = self.body.intraocular(s)
            # quantised so the eye-ray cache (keyed by the optical state) is reused between frames: a new
            # state costs a new aiming of every ray through the optics, several frames' rendering. Steps
            # of OPTICS_STEP_D stay within the eye's depth of focus (about +-0.3 D); a state is left only
            # when the eye is OPTICS_HYSTERESIS steps beyond it, so a state near a boundary does not
            # flicker between two ray sets.
            last = self._optics.get(s)
            q = (_quantise(acc, self.optics_step_d, None if last is None else last[0]),
                 _quantise(pupil, PUPIL_STEP_MM, None if last is None else last[1]))
            self._optics[s] = q
            eye = NavarroEye(*q)
            out[s] = render_onv(self.scene, self.fov[s].retina, eye, self.body.eye_pose(s)[None],
                                self.fov[s].samples_per_receptor, seed=0, packed=packed) * self.light_scale
            if self.lens_nets is not None:  # the lens net's central field, at the S it was trained with
                self.lens_onv[s] = render_onv(self.scene, self._lens_field(s), eye, self.body.eye_pose(s)[None],
                                              self.lens_nets[s].samples_per_receptor, seed=0,
                                              packed=packed) * self.light_scale
        self.timing["render"] += time.perf_counter() - t0
        self.onv = out
        return out

    def step(self) -> None:
        """One control period. On a visual frame (every ``frame_every``-th period, the first included) both
        eyes render and their foveation nets estimate the ball's direction; in between, the gaze
        controller (:class:`~warp_vision.sim.gaze.GazeController`) carries its last estimate forward."""
        seen = self.period % self.frame_every == 0
        self.period += 1
        err = self._see() if seen else None
        t0 = time.perf_counter()
        neck = self.body.neck_angles()
        head_turn = (neck - self.last_neck)[:2]  # (yaw, pitch): same signs as the eyes' in the head
        self.last_neck = neck
        changes = self.gaze.update(err, head_turn, self.body.time)
        self.timing["control"] += time.perf_counter() - t0
        self._drive_eyes(changes)
        t0 = time.perf_counter()
        self._drive_neck()
        self._intraocular(seen)
        self.timing["control"] += time.perf_counter() - t0
        self._advance()

    def _see(self) -> dict | None:
        """A visual frame: both eyes render, and each eye's retinal error of the target is returned (and kept
        in ``estimate``): the foveation net's estimate of the ball, with ``perception="search"`` the active
        search's target (None while it holds the gaze), or with ``perception="oracle"`` the ball's true
        direction in the eye frame."""
        onv = self.render()
        t0 = time.perf_counter()
        if self.perception == "oracle":
            err = {s: true_direction(self.body, s, self.body.ball_position()) for s in SIDES}
        elif self.perception == "search":
            err = self.search.frame(self, onv)
        else:
            err = {s: self.fov[s](onv[s])[0] for s in SIDES}  # the ball's (yaw, pitch) in each eye frame
        self.estimate = err if err is not None else {}
        self.timing["nets"] += time.perf_counter() - t0
        return err

    def _drive_eyes(self, changes: dict) -> None:
        """Each eye's oculomotor net turns its change of commanded gaze into the next activations of its six
        muscles, under a rate guard: no muscle's activation moves more than ACTIVATION_PER_DEG per degree
        of gaze change asked for (plus ACTIVATION_SLACK); see the constants."""
        t0 = time.perf_counter()
        with torch.no_grad():
            for s in SIDES:
                e = self.eyes[s]
                a = self.ocu[s](torch.as_tensor(changes[s], dtype=torch.float32)[None],
                                torch.as_tensor(e.activations, dtype=torch.float32)[None])[0].numpy().astype(np.float64)
                lim = ACTIVATION_PER_DEG * np.degrees(np.linalg.norm(changes[s])) + ACTIVATION_SLACK
                e.activations = np.clip(e.activations + np.clip(a - e.activations, -lim, lim), 0, 1)
                self.body.set_eye_activations(s, e.activations)
        self.timing["nets"] += time.perf_counter() - t0

    def _drive_neck(self) -> None:
        """The eye-head synergy: the head's target moves NECK_GAIN of the eyes' mean gaze a period, held by
        least-effort neck activations."""
        mean_gaze = 0.5 * (self.eyes["left"].command + self.eyes["right"].command)
        self.neck_target[:2] += NECK_GAIN * mean_gaze
        self.neck_target[2] = 0.0
        self._neck_hold()

    def _advance(self) -> None:
        """MuJoCo through one control period (calling ``substep`` after every step when it is set)."""
        t0 = time.perf_counter()
        n = int(round(CONTROL_DT / self.body.model.opt.timestep))
        if self.substep is None:
            self.body.step(n)
        else:  # e.g. the cannon's deflection detector, which reads every MuJoCo step's contacts
            for _ in range(n):
                self.body.step()
                self.substep()
        self.timing["mujoco"] += time.perf_counter() - t0

    def _lens_field(self, s: str) -> np.ndarray:
        """[N, 3] optical-frame positions (mm) of the photoreceptors eye ``s``'s lens net reads (its central
        field), taken from the eye's retina once per net."""
        net = self.lens_nets[s]
        cached = self._lens_positions.get(s)
        if cached is None or cached[0] is not net:
            pos = np.asarray(self.fov[s].retina.positions_optical_mm)
            if net.P != len(pos):
                raise ValueError(f"lens_nets[{s!r}]: reads a retina of {net.P:,} photoreceptors, the {s} eye has "
                                 f"{len(pos):,}")
            cached = self._lens_positions[s] = (net, np.ascontiguousarray(pos[net.central.cpu().numpy()]))
        return cached[1]

    def _intraocular(self, seen: bool) -> None:
        """Accommodate to where the gaze lines converge; on a new frame (``seen``) the pupil is commanded
        from its ONV: by the eye's pupil net, or by the analytic law (Watson & Yellott's pupil for the
        adapting luminance, :func:`warp_vision.eye.pupil.adapting_luminance`), which is always computed as
        the nets' teacher. Both read the ONV with the pupil it was rendered through."""
        from warp_vision.eye.pupil import adapting_luminance, pupil_diameter_mm

        dist = vergence_distance(self.body)
        for s in SIDES:
            self.lens_teacher[s] = 1.0 / max(dist, 0.1)
            if seen or s not in self._pupil_command:
                acc_looked, looked = self._optics[s]  # the (quantised) lens and pupil the frame was rendered through
                luminance = adapting_luminance(max(float(self.onv[s].mean()), 1e-12), looked)
                self.pupil_teacher[s] = float(pupil_diameter_mm(luminance))
                with torch.no_grad():
                    if self.pupil_nets is None:
                        self._pupil_command[s] = self.pupil_teacher[s]
                    else:
                        self._pupil_command[s] = float(self.pupil_nets[s](self.onv[s].float(),
                                                                          torch.tensor([looked]))[0])
                    if self.lens_nets is not None:
                        self._lens_command[s], self.defocus_estimate[s] = _lens_command(
                            self.lens_nets[s], self.lens_onv[s], acc_looked, looked,
                            self._lens_command.get(s, acc_looked))
        if self.lens_nets is not None and self.yoked_lens and seen:
            # accommodation is yoked: one command drives both lenses (the consensual response; Campbell
            # 1960, Ball 1952), the mean of the vergences the two eyes' nets read. Their errors are in part
            # the eye's own (each retina samples the object differently), so the mean is steadier.
            read = [self._lens_command[s] for s in SIDES if self.defocus_estimate.get(s) is not None]
            if read:
                for s in SIDES:
                    self._lens_command[s] = float(np.mean(read))
        for s in SIDES:
            acc = self._lens_command[s] if self.lens_nets is not None else self.lens_teacher[s]
            self.body.set_intraocular(s, pupil_mm=self._pupil_command[s], accommodation_D=acc)


def _lens_command(net, onv: torch.Tensor, acc_looked: float, pupil: float, hold: float) -> tuple[float, float | None]:
    """(accommodation command, defocus estimate or None) of a lens net for its central field ``onv`` (the
    photoreceptors ``net.central`` only) rendered at ``acc_looked`` through ``pupil``. The defocus is the accommodation
    minus the object's vergence, so the command is the vergence the net sees: an absolute target (the plant's latency
    winds nothing up). An image without fine contrast (``net.contrast`` under its floor: a uniform glowing ball filling
    the fovea) carries no defocus cue: the lens holds ``hold``, its last command. The estimate is calibrated by
    the accommodation it was seen with (:meth:`~warp_vision.nn.intraocular.LensNet.calibrated`)."""
    with torch.no_grad():
        raw = net.raw_features(onv.float(), torch.tensor([pupil]), central_only=True)
        if float(net.contrast(raw)[0]) < float(net.contrast_floor):
            return hold, None
        d = float(net.calibrated(net.head(raw), acc_looked)[0])
    return acc_looked - d, d


def gaze_line(body: Body, side: str) -> tuple[np.ndarray, np.ndarray]:
    """(eye centre, unit optical axis) in the world."""
    T = body.eye_pose(side)
    return T[:3, 3], T[:3, 2]


def vergence_distance(body: Body) -> float:
    """Distance (m) from the eyes' midpoint to where the two gaze lines pass closest (inf if parallel or
    diverging)."""
    (p1, d1), (p2, d2) = gaze_line(body, "left"), gaze_line(body, "right")
    st = line_crossing(p1, d1, p2, d2, parallel=1e-9)
    if st is None or st[0] <= 0 or st[1] <= 0:
        return np.inf
    t1, t2 = st
    return float(np.linalg.norm(0.5 * (p1 + t1 * d1 + p2 + t2 * d2) - 0.5 * (p1 + p2)))


def true_direction(body: Body, side: str, point) -> np.ndarray:
    """(yaw, pitch) rad of ``point`` in eye ``side``'s frame: what its foveation net estimates."""
    T = body.eye_pose(side)
    return gaze_angles(T[:3, :3].T @ (np.asarray(point, float) - T[:3, 3]))


def gaze_error_deg(body: Body, side: str, point) -> float:
    """Angle (deg) between eye ``side``'s optical axis and the direction to ``point``."""
    p, d = gaze_line(body, side)
    v = np.asarray(point, float) - p
    return float(np.degrees(np.arccos(np.clip(d @ v / np.linalg.norm(v), -1, 1))))


def line_distance(body: Body, side: str, point) -> float:
    """Distance (m) from ``point`` to eye ``side``'s gaze line."""
    p, d = gaze_line(body, side)
    v = np.asarray(point, float) - p
    return float(np.linalg.norm(v - (v @ d) * d))


def point_at(body: Body, yaw_deg: float, pitch_deg: float, distance: float) -> np.ndarray:
    """The world point at (yaw, pitch) deg from the eyes' midpoint in the head's rest frame, ``distance`` m away."""
    mid = 0.5 * (body.eye_pose("left")[:3, 3] + body.eye_pose("right")[:3, 3])
    return mid + body.head_pose()[:3, :3] @ gaze_direction(np.radians(yaw_deg), np.radians(pitch_deg)) * distance

