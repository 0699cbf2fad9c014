"""Benchmark plumbing: parameter counts (the paper's Fig. 4 set-up), floors, baselines, JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from warp_vision.bench import memory
from warp_vision.bench import torch_baselines as tb
from warp_vision.bench.linet import run_config
from warp_vision.eye.retina import Retina
from warp_vision.fileio import write_json
from warp_vision.kernels.linet.reference import locally_connected_ref
from warp_vision.nn import LiNet, onv_positions


def test_fig4_parameter_counts_match_hand_count():
    # 3P = 43,200 (P = 14,400), H = 4, f = 5, R = 5, plus the 2-output head:
    # sizes 43200 -> 8640 -> 1728 -> 345 -> 69
    sizes = memory.layer_sizes(43_200)
    assert sizes == [43_200, 8_640, 1_728, 345, 69]
    # liNet: (8640 + 1728 + 345 + 69) units x (5 weights + 1 bias) = 64,692; head 69*2 + 2 = 140
    assert memory.param_count("linet", sizes) == 64_832
    # FC: 43200*8640+8640 + 8640*1728+1728 + 1728*345+345 + 345*69+69 + 140
    assert memory.param_count("fc", sizes) == 388_808_807


def test_built_linet_has_the_counted_parameters():
    pos = onv_positions(Retina.log_polar(1_000, seed=2).domain_xy)
    net = LiNet(pos, layers=4, receptive_field=5, reduction=5)
    head = torch.nn.Linear(net.out_features, memory.OUTPUTS)
    built = net.num_parameters() + sum(p.numel() for p in head.parameters())
    assert built == memory.param_count("linet", net.layer_sizes)


def test_floor_at_paper_scale():
    # The floor for 3P = 1.28e7: input 3.28 GB, ~5.1 GB in all.
    f = memory.floor_bytes("linet", memory.layer_sizes(12_800_000), batch=64)
    assert f["input_batch"] == 64 * 12_800_000 * 4
    assert 5.0e9 < f["total"] < 5.2e9


def test_torch_baselines_agree_with_reference():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(5, 60, generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.randn(12, 4, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.randn(12, generator=g, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(0, 60, (12, 4), generator=g)
    gy = torch.randn(5, 12, generator=g, dtype=torch.float64)
    y_ref = locally_connected_ref(x, w, b, idx)
    g_ref = torch.autograd.grad(y_ref, (x, w, b), gy)
    for y in (
        tb.gather_sum(x, w, b, idx),
        tb.index_add(x, w, b, idx.reshape(-1)),
        tb.csr_matmul(x, w, b, tb.CsrPlan(idx, 60)),
    ):
        assert torch.allclose(y, y_ref, atol=1e-12)
        for a, c in zip(torch.autograd.grad(y, (x, w, b), gy), g_ref):
            assert torch.allclose(a, c, atol=1e-12)


def test_linet_bench_small_config_reports_agreement(tmp_path):
    res = run_config(B=8, P=300, reduction=5, R=6, repeats=1, log=lambda *_: None)
    assert res["N_in"] == 900 and res["N"] == 180
    assert set(res["layouts"]) == {"batch_major", "feature_major"}
    for layout in res["layouts"].values():
        for name, impl in layout["impls"].items():
            assert impl["max_rel_err_vs_warp"] < 1e-5, name
            assert impl["times"]["forward"]["median_ms"] > 0
        assert set(layout["speedup_of_warp"]) == {
            "forward", "backward", "forward_backward", "forward_backward_no_grad_x"
        }
    path = tmp_path / "out.json"
    assert write_json(path, res)
    assert json.loads(path.read_text())["N"] == 180


def test_linet_bench_times_the_kernels_alone_at_a_feature_major_batch():
    res = run_config(B=64, P=200, reduction=5, R=5, repeats=1, log=lambda *_: None)
    k = res["warp_kernels_only_ms"]
    assert {"forward", "grad_x", "grad_weight_bias"} <= set(k)
    assert all(k[p] > 0 for p in ("forward", "grad_x", "grad_weight_bias"))
    assert k["forward_backward"] == pytest.approx(k["forward"] + k["grad_x"] + k["grad_weight_bias"])
    assert k["op_overhead_ms"] == pytest.approx(k["op_forward_backward_ms"] - k["forward_backward"])


def test_raytrace_bench_runs_small_and_agrees():
    from warp_vision.bench import raytrace as br

    out = br.closest_hit_rates(repeats=1, P=60, S=2, detail=2, log=lambda *a: None)
    for name in ("eye", "random"):
        res = out["rays"][name]
        assert res["rays"] == 60 * 3 * 2 if name == "eye" else res["rays"] > 0
        assert res["agree_with_warp_mesh"] > 0.99
        assert res["warp_packet_1thread"]["mrays_per_s"] > 0
    onv = br.onv_rate(P=50, S=2, batch=1, repeats=1, log=lambda *a: None)
    assert onv["onv_per_s"] > 0 and onv["P"] == 50


def test_agreement_metric():
    from warp_vision.bench.raytrace import _agree

    inf = np.inf
    assert _agree(np.array([1.0, inf, 2.0]), np.array([1.00001, inf, 2.0])) == 1.0
    assert _agree(np.array([1.0, inf]), np.array([1.1, 3.0])) == 0.0


def test_memory_bench_runs_small_sizes_and_plots_into_a_new_directory(tmp_path):
    # one tiny size measured (each in a fresh subprocess), a huge FC one estimated, figure in a new dir
    result = memory.run([999, 12_800_000], batch=4, budget_gib=0.05, log=lambda *_: None)
    rows = {(r["model"], r["onv"]): r for r in result["rows"]}
    assert not rows[("linet", 999)]["estimated"] and rows[("linet", 999)]["peak_bytes"] > 0
    assert rows[("fc", 12_799_998)]["estimated"]  # sizes round down to whole photoreceptors
    png = tmp_path / "new" / "memory.png"
    memory.plot(result, str(png))
    assert png.stat().st_size > 10_000


def test_readout_bench_writes_a_row_per_setting_with_its_ratio(tmp_path):
    from warp_vision.bench.cli import main

    out = tmp_path / "readout.json"
    assert main(["readout", "--views", "1", "2", "--batch", "2", "--repeats", "1", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["software"]["warp_vision"] and res["software"]["warp-lang"]
    # each fact once: the libraries' versions are the software's, the machine is the hardware's
    assert res["machine"]["cores"] >= 1 and not {"python", "torch", "warp", "numpy"} & set(res["machine"])
    assert [(r["batch"], r["views"], r["precision"]) for r in res["results"]] == [
        (2, 1, "float32"), (2, 1, "bfloat16"), (2, 2, "float32"), (2, 2, "bfloat16")]
    assert res["results"][0]["ratio_to_1_views"] == 1.0 and res["results"][0]["speedup_over_float32"] == 1.0
    assert all(r["median_ms"] > 0 for r in res["results"]) and isinstance(res["native_bfloat16"], bool)
    [bin_row] = res["binning"]
    assert bin_row["views"] == 2 and bin_row["speedup"] == bin_row["index_add_ms"] / bin_row["csr_ms"]
    assert main(["readout", "--views", "0", "--out", str(out)]) == 2  # refused before any work


def test_cnn_bench_times_both_precisions_per_width_with_the_speedup(tmp_path):
    from warp_vision.bench.cli import main

    out = tmp_path / "cnn.json"
    assert main(["cnn", "--channels", "2", "--batch", "4", "--repeats", "1", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert [(r["channels"], r["precision"]) for r in res["results"]] == [(2, "float32"), (2, "bfloat16")]
    assert res["results"][0]["speedup_over_float32"] == 1.0 and res["results"][1]["median_ms"] > 0
    assert isinstance(res["native_bfloat16"], bool) and res["photoreceptors"] == 14_400
    assert main(["cnn", "--batch", "2", "--out", str(out)]) == 2  # refused before any work


@pytest.mark.parametrize("argv, said", [  # small sizes: without the checks each fails in seconds
    # was torch's RuntimeError
    (["linet", "--photoreceptors", "100", "--batch", "0"], "--batch: expected a positive integer"),
    (["linet", "--photoreceptors", "100", "--receptive-field", "0"], "--receptive-field"),
    (["linet", "--photoreceptors", "100", "--repeats", "0"], "--repeats"),
    (["raytrace", "--photoreceptors", "100", "--samples", "0"], "--samples"),
    (["memory", "--sizes", "0"], "--sizes"),
    (["memory", "--sizes", "300", "--batch", "0"], "--batch"),
    (["memory", "--sizes", "375", "--budget-gib", "nan"], "--budget-gib"),
    # these named two options for one ("--batch and --repeats: expected positive integers")
    (["readout", "--batch", "4", "0"], "--batch: expected positive integers, got [4, 0]"),
    (["cnn", "--channels", "0"], "--channels: expected positive integers, got [0]"),
    (["cnn", "--batch", "2"], "--batch: expected at least 4 (four augmentation groups), got 2"),
    (["loop", "--frame-every", "4", "0"], "--frame-every: expected positive integers, got [4, 0]"),  # was frame_every
])
def test_bad_bench_settings_are_one_line_before_any_work(argv, said, tmp_path, capsys):
    from warp_vision.bench.cli import main

    out = tmp_path / "b.json"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert said in err and "Traceback" not in err and not out.exists(), err


def test_bench_with_no_command_runs_the_kernel_benchmarks_on_their_defaults(tmp_path, monkeypatch, capsys):
    from warp_vision.bench import cli, linet, raytrace

    calls = []
    monkeypatch.setattr(linet, "run", lambda *a, **k: calls.append(("linet", a)) or {"rows": 1})
    monkeypatch.setattr(raytrace, "run", lambda *a, **k: calls.append(("raytrace", a)) or {"rows": 2})
    monkeypatch.chdir(tmp_path)
    assert cli.main([]) == 0
    assert [name for name, _ in calls] == ["linet", "raytrace"]
    assert calls[0][1][0] == [14_400, 144_000] and calls[1][1][1:3] == (14_400, 16)  # each its own defaults
    for name, rows in (("linet", 1), ("raytrace", 2)):
        got = json.loads((tmp_path / "bench_results" / f"{name}.json").read_text())
        assert got["benchmark"] == name and got["rows"] == rows
    assert "-- python -m warp_vision.bench raytrace" in capsys.readouterr().out


def test_bench_with_no_command_checks_every_output_before_the_first_timing(tmp_path, monkeypatch, capsys):
    from warp_vision.bench import cli, linet

    calls = []
    monkeypatch.setattr(linet, "run", lambda *a, **k: calls.append(a) or {})
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bench_results" / "raytrace.json").mkdir(parents=True)  # the second's output is in the way
    assert cli.main([]) == 2
    err = capsys.readouterr().err
    assert "raytrace.json" in err and "Traceback" not in err and calls == [], err
