"""Fault drills: every size is bounded before it is allocated (warp_vision.limits): image and video sizes, mesh
subdivisions, frame rates and slow-motion factors, seeds and counts are refused at parse time or before any net is
trained, in one line; a size within its range that would not fit in memory is refused with the estimate beside
the memory available."""

from __future__ import annotations

import argparse

import pytest

from warp_vision import limits
from warp_vision.scene import Scene
from warp_vision.sim.cli import main as sim_main
from warp_vision.train.cli import main as train_main


def _error(err: str) -> str:
    lines = [x for x in err.strip().splitlines() if x.strip()]
    assert lines and "error:" in lines[-1] and "Traceback" not in err, err
    return lines[-1]


@pytest.mark.parametrize("argv, says", [
    (["demo", "--width", "100000", "--height", "100000"], "--width: expected an integer 1..8,192 pixels, got 100,000"),
    (["demo", "--height", "0"], "--height: expected an integer 1..8,192 pixels, got 0"),
    (["demo", "--slow-motion", "1e-300"], "--slow-motion: expected a finite number 0.001..1000, got 1e-300"),
    (["demo", "--slow-motion", "0.01"], "makes a video of 1e+04 frames a second; expected 0.01..1000 frames a second"),
    (["demo", "--slow-motion", "nan"], "--slow-motion: expected a finite number"),
    (["demo", "--seed", "1180591620717411303424"], "--seed: expected an integer 0..2,147,483,647"),
    (["demo", "--duration", "1e9"], "--duration: expected a finite number 0.01..60 simulated seconds"),
    (["demo", "--video-every", "-1"], "--video-every: expected an integer 1..1,000 control periods"),
    (["intercept", "--shots", "100000000000"], "--shots: expected an integer 1..10,000,000, got 100,000,000,000"),
    (["intercept", "--shots", "1000001"], "--shots: expected 1..1,000,000 (the held-out shots), got 1,000,001"),
    (["intercept", "--shot-seed", "99999999999999999999"], "--shot-seed: expected an integer 0..2,147,483,647"),
    (["intraocular", "--cards", "100000"], "--cards: expected an integer 1..100 cards"),
])
def test_a_simulation_size_out_of_range_is_one_line_before_any_work(argv, says, tmp_path, capsys):
    try:
        code = sim_main([*argv, "--out", str(tmp_path / "out")])
    except SystemExit as e:  # (a value out of its range is the parser's error: it exits)
        code = e.code
    assert code == 2
    line = _error(capsys.readouterr().err)
    assert says in line, line
    assert not (tmp_path / "out").exists()


def test_a_video_that_would_not_fit_in_memory_is_refused_with_its_estimate(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("WARP_VISION_MEMORY_LIMIT", str(2 * 2**30))
    code = sim_main(["demo", "--width", "4096", "--height", "4096", "--gif", "--out", str(tmp_path / "out")])
    assert code == 2
    line = _error(capsys.readouterr().err)
    assert "the video (81 frames of a 4096 x 4096 view, kept for the GIF) needs about" in line
    assert "more than the 2.0 GiB of memory available; lower --width, --height, --duration or --video-every" in line


def test_a_train_seed_past_64_bits_is_named_before_anything_is_written(tmp_path, capsys):
    code = train_main(["--preset", "smoke", "--seed", "1180591620717411303424", "--out", str(tmp_path / "out"),
                       "--no-progress"])
    assert code == 2
    assert "--seed: expected a seed 0..2,147,483,647, got 1180591620717411303424" in _error(capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_an_icosphere_is_bounded_before_its_mesh_is_built(monkeypatch):
    with pytest.raises(ValueError, match=r"subdivisions: expected 0\.\.10, got 12"):
        Scene().add_sphere("b", 0.1, subdivisions=12)
    with pytest.raises(ValueError, match="subdivisions: expected an integer"):
        Scene().add_sphere("b", 0.1, subdivisions=2.5)
    monkeypatch.setenv("WARP_VISION_MEMORY_LIMIT", str(2**30))
    with pytest.raises(ValueError,
                       match=r"an icosphere of 9 subdivisions \(5,242,880 triangles\) needs about 2.0 GiB, more than "
                             r"the 1.0 GiB"):
        Scene().add_sphere("b", 0.1, subdivisions=9)
    Scene().add_sphere("b", 0.1, subdivisions=3)


def test_the_argparse_types_read_their_range_and_nothing_else():
    read = limits.integer(limits.Range(1, 10))
    assert read("10") == 10
    for bad in ("0", "11", "1.5", "abc", "", "1e3"):
        with pytest.raises(argparse.ArgumentTypeError):
            read(bad)
    read = limits.number(limits.Range(0.5, 2.0))
    assert read("1e0") == 1.0
    for bad in ("nan", "inf", "-inf", "0.49", "3", "x"):
        with pytest.raises(argparse.ArgumentTypeError):
            read(bad)
    assert limits.video_frame_shape(640, 480) == (480, 880)


def test_the_memory_benchmark_refuses_a_net_it_cannot_build_and_an_out_that_is_its_figure(tmp_path, capsys):
    from warp_vision.bench.cli import main as bench_main

    assert bench_main(["memory", "--sizes", "100", "--out", str(tmp_path / "m.json")]) == 2
    assert "--sizes: expected 375..300,000,000 inputs, got 100" in _error(capsys.readouterr().err)
    assert bench_main(["memory", "--out", str(tmp_path / "m.png")]) == 2
    assert "names the figure's path" in _error(capsys.readouterr().err)
    assert not list(tmp_path.iterdir())
