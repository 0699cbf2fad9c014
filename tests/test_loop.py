"""The closed loop at a visual frame rate below its control rate, and the provisioning of its nets."""

import hashlib
import json
import os

import numpy as np
import pytest
import torch

from warp_vision.body import SIDES, Body, BodyConfig

# --- provisioning ------------------------------------------------------------------------------------


def _fake_trainer(calls, fail_on=None):
    """A runner that 'trains' by writing the run's best.pt and config.json (as the training command would:
    a task's config names its task, the foveation config, the command's default task, none)."""

    def run(cmd):
        calls.append(cmd)
        if fail_on and fail_on in cmd:
            return 1
        out = cmd[cmd.index("--out") + 1]
        os.makedirs(out, exist_ok=True)
        with open(os.path.join(out, "best.pt"), "wb") as f:
            f.write(out.encode())
        task = {} if cmd[3].startswith("--") else {"task": cmd[3]}
        with open(os.path.join(out, "config.json"), "w") as f:
            json.dump({"out": out, **task}, f)
        return 0

    return run


def test_provide_trains_only_what_is_missing_and_the_manifest_names_it(tmp_path):
    from warp_vision.sim.provision import manifest, plan, provide

    specs = plan(str(tmp_path / "fl"), str(tmp_path / "fr"), str(tmp_path / "ocu"), quick=True)
    assert [(s.kind, s.eye) for s in specs] == [("foveation", "left"), ("foveation", "right"),
                                                ("oculomotor", "left"), ("oculomotor", "right")]
    os.makedirs(tmp_path / "fr")
    (tmp_path / "fr" / "best.pt").write_bytes(b"already here")
    lines, calls = [], []
    trained = provide(specs, progress=False, log=lines.append, runner=_fake_trainer(calls))
    assert [s.run for s in trained] == [str(tmp_path / "fl"), str(tmp_path / "ocu" / "left"),
                                        str(tmp_path / "ocu" / "right")]
    assert len(calls) == 3 and all("--no-progress" in c and c[c.index("--preset") + 1] == "quick" for c in calls)
    assert calls[1][3] == "oculomotor" and calls[0][3] == "--preset"  # foveation is the training command's default task
    assert "about 3 min" in lines[0] and len([ln for ln in lines if ln.startswith("  ")]) == 3  # the plan first
    assert "(about 2 min)" in lines[1] and "(under a minute)" in lines[2]  # the quick oculomotor net: 0.5 min
    assert provide(specs, progress=False, log=lines.append, runner=_fake_trainer(calls)) == []  # cached: nothing to do
    assert len(calls) == 3
    m = manifest(specs)
    assert m["foveation_right"]["sha256"] == hashlib.sha256(b"already here").hexdigest()
    assert m["oculomotor_left"]["config"] == {"out": str(tmp_path / "ocu" / "left"), "task": "oculomotor"}


def test_provide_resumes_a_stopped_run_and_stops_on_a_failed_one(tmp_path):
    from warp_vision.sim.provision import plan, provide

    specs = plan(str(tmp_path / "fl"), str(tmp_path / "fr"), str(tmp_path / "ocu"))
    os.makedirs(tmp_path / "fl")
    # stopped part way (Ctrl-C, a crash): best.pt and latest.pt, but not the summary.json a run writes
    # once its net is final; the loop used that half-trained net as it stood
    (tmp_path / "fl" / "latest.pt").write_bytes(b"x")
    (tmp_path / "fl" / "best.pt").write_bytes(b"x")
    assert not specs[0].ready() and specs[0].command() == ["--resume", str(tmp_path / "fl")]
    calls = []

    def finish(cmd):  # the resumed training ends the run
        calls.append(cmd)
        (tmp_path / "fl" / "summary.json").write_text("{}")
        return 0

    provide(specs[:1], progress=False, log=lambda _m: None, runner=finish)
    assert [c[3:5] for c in calls] == [["--resume", str(tmp_path / "fl")]] and specs[0].ready()
    assert specs[2].command()[:3] == ["oculomotor", "--preset", "default"]
    with pytest.raises(SystemExit, match="right eye's foveation net failed"):
        provide(specs[1:], progress=False, log=lambda _m: None, runner=_fake_trainer([], fail_on=str(tmp_path / "fr")))


def _wait_for(lines, text, timeout=30.0):
    import time

    t0 = time.monotonic()
    while not any(text in ln for ln in lines):
        assert time.monotonic() - t0 < timeout, f"no line with {text!r}: {lines}"
        time.sleep(0.02)


def test_two_simulations_needing_one_net_train_it_once(tmp_path):
    """A second simulation that needs a net the first is having trained waits for it and uses it; it
    used to start the same training, which the run lock refused, and stopped with 'training ... failed'.
    (flock treats two opens of one file as two owners, so two threads stand for two processes.)"""
    import threading

    from warp_vision.sim.provision import plan, provide

    spec = plan(str(tmp_path / "fl"), str(tmp_path / "fr"), str(tmp_path / "ocu"))[0]
    started, go = threading.Event(), threading.Event()
    first_calls, second_calls, lines, results = [], [], [], {}

    def slow(cmd):  # the first simulation's training, held until the second is seen waiting
        started.set()
        assert go.wait(30)
        return _fake_trainer(first_calls)(cmd)

    a = threading.Thread(target=lambda: results.setdefault("a", provide([spec], False, lambda _m: None, slow)))
    a.start()
    assert started.wait(30)
    b = threading.Thread(target=lambda: results.setdefault(
        "b", provide([spec], False, lines.append, _fake_trainer(second_calls))))
    b.start()
    _wait_for(lines, f"waiting for process {os.getpid()}, which is having the left eye's foveation net trained into")
    go.set()
    a.join(30)
    b.join(30)
    assert len(first_calls) == 1 and second_calls == []
    assert results == {"a": [spec], "b": []}
    assert any("the left eye's foveation net is ready: another process trained it" in ln for ln in lines)


def test_a_simulation_waits_for_a_training_started_by_hand(tmp_path):
    """``python -m warp_vision.train --out RUN`` running (it holds RUN's run lock): a simulation needing
    that net waits for it, then uses the finished net, rather than failing on the lock."""
    import threading

    from warp_vision.fileio import FileLock
    from warp_vision.nn.trained import TRAINING_LOCK
    from warp_vision.sim.provision import plan, provide

    spec = plan(str(tmp_path / "fl"), str(tmp_path / "fr"), str(tmp_path / "ocu"))[0]
    os.makedirs(spec.run)
    by_hand = FileLock(os.path.join(spec.run, TRAINING_LOCK))
    assert by_hand.acquire()
    lines, calls, results = [], [], {}
    b = threading.Thread(target=lambda: results.setdefault("b",
                                                           provide([spec], False, lines.append, _fake_trainer(calls))))
    b.start()
    _wait_for(lines,
              f"waiting for process {os.getpid()}, which is training the left eye's foveation net into {spec.run}")
    for name in ("best.pt", "latest.pt", "summary.json"):  # the hand-started run ends
        open(os.path.join(spec.run, name), "wb").close()
    by_hand.release()
    b.join(30)
    assert calls == [] and results == {"b": []}
    # a run of another net trained there meanwhile (the other eye's) is refused, not used
    spec = plan(str(tmp_path / "fl2"), str(tmp_path / "fr"), str(tmp_path / "ocu"))[0]
    os.makedirs(spec.run)
    by_hand = FileLock(os.path.join(spec.run, TRAINING_LOCK))
    assert by_hand.acquire()
    errors = []

    def provide_catching():
        try:
            provide([spec], False, lines.append, _fake_trainer(calls))
        except ValueError as e:
            errors.append(str(e))

    b = threading.Thread(target=provide_catching)
    b.start()
    _wait_for(lines, f"which is training the left eye's foveation net into {spec.run}")
    with open(os.path.join(spec.run, "config.json"), "w") as f:
        json.dump({"eye": "right"}, f)
    open(os.path.join(spec.run, "best.pt"), "wb").close()
    by_hand.release()
    b.join(30)
    assert calls == [] and len(errors) == 1
    assert "fl2 holds the right eye's foveation net, not the left eye's foveation net" in errors[0], errors


def test_provide_refuses_a_run_directory_that_holds_another_net_before_training_any(tmp_path):
    import json

    from warp_vision.sim.provision import plan, provide, strike_plan

    def run(name, **config):
        os.makedirs(tmp_path / name)
        (tmp_path / name / "config.json").write_text(json.dumps(config))
        (tmp_path / name / "best.pt").write_bytes(b"net")
        return str(tmp_path / name)

    arm = run("arm/left", task="arm", side="left")
    right = run("fr", eye="right")  # a foveation run: its config names no task
    calls = []
    specs = plan(arm, right, str(tmp_path / "ocu"))
    with pytest.raises(ValueError,
                       match="arm/left holds the left arm's motor nets, not the left eye's foveation net \\(check"):
        provide(specs, progress=False, log=lambda _m: None, runner=_fake_trainer(calls))
    assert calls == []  # nothing trained: the oculomotor nets are missing too
    specs = plan(right, right, str(tmp_path / "ocu"))  # the right eye's net for the left eye
    with pytest.raises(ValueError, match="fr holds the right eye's foveation net, not the left eye's foveation net"):
        provide(specs, progress=False, log=lambda _m: None, runner=_fake_trainer(calls))
    run("limb/left", task="limb", eye="left")
    run("limb/right", task="pupil", eye="right")
    with pytest.raises(ValueError,
                       match="right holds the right eye's pupil net, not the right eye's limb vision net") as e:
        provide(strike_plan("left", str(tmp_path / "arm"), str(tmp_path / "limb")), progress=False, log=lambda _m: None,
                runner=_fake_trainer(calls))
    assert "limb/left" not in str(e.value) and calls == []
    # the right runs pass: nothing to train
    assert provide(strike_plan("left", str(tmp_path / "arm"), None), progress=False, log=lambda _m: None,
                   runner=_fake_trainer(calls)) == []


# --- the loop between frames ---------------------------------------------------------------------------


class _OracleFoveator:
    """Stands in for a trained foveation net: the true direction of the ball in the eye frame, read from
    the body whenever the loop renders (it counts the frames)."""

    def __init__(self, body, side):
        from warp_vision.data.foveation import FoveationDataConfig, make_eye, make_retina

        cfg = FoveationDataConfig(photoreceptors=300, samples_per_receptor=1, eye=side)
        self.retina, self.trained_eye, self.samples_per_receptor = make_retina(cfg), make_eye(cfg), 1
        self.norm = {"input_scale": 1.0}
        self.body, self.side, self.frames = body, side, 0

    def __call__(self, onv):
        from warp_vision.sim.loop import true_direction

        self.frames += 1
        return true_direction(self.body, self.side, self.body.ball_position())[None]


class _UnaskedFoveator(_OracleFoveator):
    """A foveation net that must not be asked (the loop's perception is the oracle)."""

    def __call__(self, onv):
        pytest.fail("a foveation net was asked")


class _HoldingOculomotor:
    """Stands in for a trained oculomotor net: integrates the commanded changes into a gaze and returns
    the least-effort activations that hold it (what the nets are trained to reproduce)."""

    def __init__(self, body, side):
        self.body, self.side, self.gaze = body, side, np.zeros(2)

    def __call__(self, change, activations):
        from warp_vision.sim.oculomotor import eye_holding_activations

        self.gaze = self.gaze + change[0].numpy()
        a, _ = eye_holding_activations(self.body, self.side, self.gaze[None])
        return torch.as_tensor(a, dtype=torch.float32)


@pytest.fixture(scope="module")
def bare_body():
    return Body(BodyConfig(arms=False))


@pytest.mark.parametrize("frame_every", [1, 4])
def test_the_loop_renders_every_nth_period_and_still_saccades(bare_body, frame_every):
    from warp_vision.sim.loop import VisuomotorLoop, point_at
    from warp_vision.sim.scenarios import run_scenario

    body = bare_body
    body.reset()
    body.model.opt.gravity[:] = 0
    fov = {s: _OracleFoveator(body, s) for s in SIDES}
    ocu = {s: _HoldingOculomotor(body, s) for s in SIDES}
    loop = VisuomotorLoop(body, fov, ocu, frame_every=frame_every)
    p = point_at(body, 15.0, 5.0, 1.0)
    tr = run_scenario(loop, 0.4, ball=lambda _t: p, progress=False)
    periods = len(tr["t"])
    assert periods == 40
    assert fov["left"].frames == -(-periods // frame_every)  # frames on periods 0, n, 2n, ...
    err = np.maximum(tr["error_left"], tr["error_right"])
    assert err[0] > 10  # the ball starts in the periphery
    assert err[-5:].max() < 1.0, err  # and ends on both foveas
    assert loop._optics and loop.estimate and loop.onv
    loop.reset()  # forgets what the run saw, so the next run does not depend on this one
    assert loop.period == 0 and not loop._optics and not loop.estimate and not loop.onv


def test_oracle_perception_takes_the_true_direction_and_asks_no_net(bare_body):
    """With perception="oracle" the controller gets the ball's true direction in each eye frame (the eyes
    still render, for the pupils) and the foveation nets are never asked; unknown modes are refused."""
    from warp_vision.sim.loop import VisuomotorLoop, point_at, true_direction
    from warp_vision.sim.scenarios import run_scenario

    body = bare_body
    body.reset()
    body.model.opt.gravity[:] = 0
    fov = {s: _UnaskedFoveator(body, s) for s in SIDES}
    loop = VisuomotorLoop(body, fov, {s: _HoldingOculomotor(body, s) for s in SIDES}, perception="oracle")
    p = point_at(body, -12.0, -6.0, 1.0)
    tr = run_scenario(loop, 0.4, ball=lambda _t: p, progress=False)
    assert tr["error_left"][0] > 8 and max(tr["error_left"][-1], tr["error_right"][-1]) < 1.0
    assert np.allclose(loop.estimate["left"], true_direction(body, "left", p), atol=np.radians(2.0)) and loop.onv
    # the true direction: a point on the eye's optical axis is straight ahead, one to its +x side has yaw > 0
    c, z, x = body.eye_pose("left")[:3, 3], body.eye_pose("left")[:3, 2], body.eye_pose("left")[:3, 0]
    assert np.allclose(true_direction(body, "left", c + z), 0.0, atol=1e-12)
    assert true_direction(body, "left", c + z + 0.1 * x)[0] == pytest.approx(np.arctan(0.1))
    with pytest.raises(ValueError, match="perception"):
        VisuomotorLoop(body, fov, {}, perception="vision")


def test_the_loop_rejects_a_bad_frame_rate(bare_body):
    from warp_vision.sim.loop import VisuomotorLoop

    for bad in (0, -1, 2.5):
        with pytest.raises(ValueError, match="frame_every"):
            VisuomotorLoop(bare_body, {}, {}, frame_every=bad)


def test_bad_settings_are_refused_before_any_training(tmp_path, monkeypatch, capsys):
    """A typo must not cost the user a quarter of an hour of training first."""
    from warp_vision.bench.cli import main as bench_main
    from warp_vision.sim.cli import main as sim_main

    monkeypatch.chdir(tmp_path)
    assert bench_main(["loop", "--frame-every", "0", "--out", str(tmp_path / "loop.json")]) == 2
    assert "--frame-every: expected positive integers, got [0]" in capsys.readouterr().err
    def code(argv) -> int:  # (a value out of its range is the parser's error: it exits)
        try:
            return sim_main(argv)
        except SystemExit as e:
            return e.code

    for bad in (["--width", "0"], ["--slow-motion", "0"], ["--frame-every", "0"], ["--seed", "-1"],
                ["--slow-motion", "inf"], ["--duration", "nan"], ["--duration", "-1"], ["--flight", "0"],
                ["--stop", "inf"]):
        assert code(["demo", *bad, "--out", str(tmp_path / "demo")]) == 2
        assert bad[0] in capsys.readouterr().err
    assert code(["experiments", "--seed", "-2", "--quick"]) == 2
    assert not (tmp_path / "runs").exists()  # nothing was trained


@pytest.mark.parametrize("command", ["demo", "experiments", "intraocular", "oculomotor", "intercept", "search"])
def test_the_simulations_help_reads_by_section_and_states_each_default(command, capsys):
    """``sim demo --help`` listed its 24 flags in the order they were written (--no-progress between two
    nets' directories, --seed among the video's), and --seed, --duration, --flight, --stop, --width, --height
    and --video-every did not say their defaults."""
    from warp_vision.sim.cli import parser

    with pytest.raises(SystemExit):
        parser().parse_args([command, "--help"])
    shown = capsys.readouterr().out
    shown = shown[shown.index("\noptions:"):]  # (past the usage lines, which name every flag)
    sections = {"the nets": ["--quick", "--oculomotor"], "the output": ["--no-progress"]}
    if command != "oculomotor":
        sections["the nets"] += ["--left", "--right", "--pupil", "--lens"]
        sections["the scene"] = ["--seed", "--ball", "--frame-every"]
        sections["the output"].append("--out")
    if command == "demo":
        sections["the scene"] += ["--no-arms", "--duration", "--flight", "--stop"]
        sections["the output"] += ["--width", "--height", "--video-every", "--slow-motion", "--gif", "--viewer"]
    if command == "search":  # a fixed ball and frame rate: the trials set them
        sections["the nets"].append("--verify")
        sections["the scene"] = ["--seed", "--trials", "--split", "--scanpaths", "--no-baseline", "--cannon"]
    if command == "intercept":
        sections["the nets"] += ["--perception", "--arm", "--limb"]
        sections["the scene"] += ["--side", "--shots", "--shot-seed", "--perception-error-cm"]
        sections["the output"] += ["--width", "--height", "--slow-motion", "--video-format"]
    heads = {title: shown.index(f"\n{title}:\n") for title in ("the nets", "the scene",
                                                               "the output") if title in sections}
    assert list(heads) == sorted(heads, key=heads.get)  # the nets, the scene, the output
    ends = dict(zip(heads, [*sorted(heads.values())[1:], len(shown)]))
    for title, flags in sections.items():
        part = shown[heads[title]:ends[title]]
        for flag in flags:
            assert f"  {flag} " in part or f"  {flag}\n" in part, (title, flag)
    for flag in ("--seed", "--duration", "--flight", "--stop", "--width", "--height", "--video-every"):
        if f"  {flag} " in shown:
            said = shown[shown.index(f"  {flag} "):].split("\n  --", 1)[0]
            assert "default" in said, flag


def test_a_run_directory_given_that_holds_no_run_is_refused_before_any_training(tmp_path, monkeypatch, capsys):
    """Only the default directories are trained into when missing: a mistyped --left must not start a
    quarter of an hour of training into the typo."""
    import warp_vision.sim.provision as provision
    from warp_vision.sim.cli import main as sim_main

    monkeypatch.chdir(tmp_path)
    trained = []
    monkeypatch.setattr(provision, "provide", lambda specs, **_kw: trained.append(specs) or [])
    for argv, flag in ((["experiments", "--left", "runs/foveaton"],
                        "--left runs/foveaton: no left eye's foveation net"),
                       (["oculomotor", "--oculomotor", "ocu"], "--oculomotor ocu: no right eye's oculomotor net"),
                       (["intercept", "--shots", "2", "--limb", "limbs"],
                        "--limb limbs: no left eye's limb vision net")):
        assert sim_main(argv) == 2
        err = capsys.readouterr().err
        assert flag in err and "python -m warp_vision.train" in err, err
    assert trained == [] and not list(tmp_path.iterdir())
    # a stopped run given by name carries on, and the default directories are provided: the loop is built
    import warp_vision.sim.build as build

    def stop(*_a, **_k):
        raise RuntimeError("the body is built")

    monkeypatch.setattr(build, "Body", stop)
    (tmp_path / "fl").mkdir()
    (tmp_path / "fl" / "latest.pt").write_bytes(b"x")
    with pytest.raises(RuntimeError, match="the body is built"):
        sim_main(["experiments", "--left", "fl"])
    assert [s.run for s in trained[0][:2]] == ["fl", os.path.join("runs", "foveation_right")]


def test_the_viewer_is_skipped_with_one_line_where_there_is_no_display(monkeypatch, capsys):
    from warp_vision.sim.demo import _Viewer

    for var in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(var, raising=False)
    v = _Viewer(None, True)
    assert v.handle is None
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "no display" in out[0]
    v.sync()
    v.close()  # no-ops
    assert _Viewer(None, False).handle is None and capsys.readouterr().out == ""


def test_experiments_measure_and_draw_every_scenario(bare_body, tmp_path):
    """``experiments`` runs every scenario of ``_scenarios`` and, with ``return_traces``, hands back their
    traces; ``plot_experiments`` draws them and refuses traces that lack a scenario. With the true
    direction as perception and eyes that hold any commanded gaze, the saccades, vergence and tracking meet
    the goals the summary reports (a loop that cannot meet them here would not in the real run either)."""
    from PIL import Image

    from warp_vision.sim.loop import VisuomotorLoop
    from warp_vision.sim.scenarios import _scenarios, experiments, goal_lines, plot_experiments

    body = bare_body
    body.reset()
    loop = VisuomotorLoop(body, {s: _OracleFoveator(body, s) for s in SIDES},
                          {s: _HoldingOculomotor(body, s) for s in SIDES}, perception="oracle")
    result, traces = experiments(loop, progress=False, return_traces=True)
    assert set(traces) == {name for name, _, _ in _scenarios()}
    sac = result["saccade_20deg"]
    assert [tt["direction_deg"] for tt in sac["trials"]] == [45.0 * k for k in range(8)]
    assert sac["all_within_1deg_by_0.3s"], sac
    assert result["vergence_1m"]["gaze_line_distance_cm_max"] < 2.0, result["vergence_1m"]
    for omega in (15, 30):
        tracking = result[f"tracking_{omega}deg_s"]
        assert max(tracking["median_error_deg"].values()) < 1.0, tracking
    # each trace starts with the ball away from the gaze: a saccade is measured, not a ball already fixated
    assert min(max(tr["error_left"][0], tr["error_right"][0]) for tr in traces.values()) > 10
    path = plot_experiments(traces, str(tmp_path / "experiments.png"), title="oracle")
    with Image.open(path) as im:
        # 16 x 4.6 in at 110 dpi; 4.6 * 110 is 505.99... in floating point, which matplotlib < 3.11 truncates
        assert im.size in ((1760, 506), (1760, 505))
    with pytest.raises(ValueError, match="saccade_90"):
        plot_experiments({k: v for k, v in traces.items() if k != "saccade_90"}, str(tmp_path / "x.png"))
    # what the command prints: a line per experiment against its goal (it printed the JSON)
    lines = goal_lines(result)
    assert len(lines) == 5 and all(line.endswith(": met") for line in lines[:4]), lines
    assert lines[0].startswith("saccades to 20 deg, 8 directions: both eyes within 1 deg after ")
    assert lines[3].startswith("tracking at 30 deg/s: median error ") and lines[4].startswith("the loop: ")
    worse = json.loads(json.dumps(result))
    worse["vergence_1m"]["gaze_line_distance_cm_max"] = 2.5
    worse["tracking_30deg_s"]["median_error_deg"]["right"] = 1.2
    worse["saccade_20deg"].update({"all_within_1deg_by_0.3s": False, "time_both_within_1deg_s_max": float("inf")})
    lines = goal_lines(worse)
    assert lines[0].endswith("not in every direction within the run (goal: by 0.3 s): MISSED"), lines[0]
    assert "2.50 cm apart at the most (goal: < 2 cm): MISSED" in lines[1] and lines[2].endswith(": met")
    assert " / 1.20 deg (left / right; " in lines[3] and lines[3].endswith("MISSED")


def test_the_demo_prints_the_gaze_error_and_what_it_wrote():
    from warp_vision.sim.demo import demo_lines

    eye = {"median": 2.5, "share_over_5deg": 0.25, "at_0.1_s": 7.0, "at_0.5_s": 1.25}
    result = {"gaze_error_deg": {"left": eye, "right": {**eye, "median": 3.0}},
              "final_error_deg": {"left": 0.5, "right": 0.75},
              "video": {"paths": ["out/demo.mp4", "out/demo.gif"], "frames": 80, "fps": 25.0, "size": [880, 480]}}
    assert demo_lines(result, "out") == [
        "gaze error over the flight (left / right eye): median 2.50 / 3.00 deg, over 5 deg 25 / 25% of the time; "
        "at 0.1 s 7.00 / 7.00, at 0.5 s 1.25 / 1.25; at the end 0.50 / 0.75 deg",
        f"wrote out/demo.mp4, out/demo.gif (80 frames, 25 fps, 880x480), {os.path.join('out', 'left_retina.png')}, "
        f"{os.path.join('out', 'gaze_error.png')} and {os.path.join('out', 'demo.json')}"]


def test_ctrl_c_lets_a_net_s_training_stop_its_helpers_and_say_where_it_stands(tmp_path):
    """subprocess.run killed the training a quarter second after Ctrl-C: its message was lost, and its
    synthesis helpers could be left behind."""
    import signal
    import sys
    import threading

    from warp_vision.sim.provision import _run_training

    done = tmp_path / "stopped"
    child = [sys.executable, "-c", f"import time, pathlib; time.sleep(3.0); pathlib.Path({str(done)!r}).write_text('')"]
    # Python's Ctrl-C handler, as a terminal's process has it: a job a shell starts in the background (`pytest &`)
    # begins with SIGINT ignored, and the signal below would then pass unseen
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGINT)).start()  # Ctrl-C, once the child runs
        with pytest.raises(KeyboardInterrupt):
            _run_training(child)
    finally:
        signal.signal(signal.SIGINT, old)
    assert done.exists()  # the child was waited for, not killed


def test_sigterm_stops_the_command_as_ctrl_c_does_and_reaches_a_net_s_training(tmp_path):
    """SIGTERM (kill, a scheduler) ended the process at once: no line on where the run stood, and a sim's
    training child, which a SIGTERM to the sim does not reach, trained on."""
    import signal
    import sys
    import threading
    import time

    from warp_vision.errors import Terminated, guarded, sigterm_as_interrupt
    from warp_vision.sim.provision import _run_training

    said = tmp_path / "said"
    child = [sys.executable, "-c", "import signal, sys, time, pathlib\n"
             f"signal.signal(signal.SIGTERM, lambda *a: (pathlib.Path({str(said)!r}).write_text('stopped'), "
             "sys.exit(143)))\ntime.sleep(30)"]
    threading.Timer(1.5, os.kill, (os.getpid(), signal.SIGTERM)).start()
    with pytest.raises(Terminated):
        with sigterm_as_interrupt():
            _run_training(child)
    assert said.read_text() == "stopped"  # the training got the SIGTERM, and was waited for
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler is the command's alone
    threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGTERM)).start()
    assert guarded(lambda: time.sleep(10)) == 143


def test_sim_oculomotor_prints_each_eye_s_check_on_the_body():
    from warp_vision.sim.cli import oculomotor_line

    summary = {"transitions": 100, "gaze_error_deg_median": 0.318, "gaze_error_deg_p90": 0.975,
               "pursuit_chain_error_deg_median": 0.232, "pursuit_chain_error_deg_p90": 0.702}
    assert oculomotor_line("left", "runs/oculomotor/left", summary) == (
        "left eye, runs/oculomotor/left: on the body, 100 held-out saccades land 0.32 deg from their gazes (median; "
        "p90 0.97), pursuits of 30 of its steps end 0.23 deg off (p90 0.70); the rest in "
        f"{os.path.join('runs/oculomotor/left', 'summary.json')}")
