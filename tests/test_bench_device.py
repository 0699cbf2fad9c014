"""``--device`` of ``python -m warp_vision.bench linet`` and ``raytrace``: refused in one line before any
work where there is no such GPU, and the CPU results unchanged. The GPU tests skip without a GPU."""

from __future__ import annotations

import json

import pytest
import torch

from warp_vision.bench import cli
from warp_vision.bench import linet as bl
from warp_vision.bench import raytrace as br

#: The keys of a CPU linet configuration and its implementations (as before --device existed).
CPU_CONFIG_KEYS = {"B", "N_in", "N", "R", "P", "dtype", "min_bytes", "layouts", "half_onv", "warp_kernels_only_ms"}
CPU_IMPLS = {"warp_1thread", "warp", "torch_gather", "torch_index_add", "torch_csr"}


@pytest.fixture
def no_work(monkeypatch):
    """Every benchmark's work (and the machine probe before it) fails the test if it starts."""
    def started(*_a, **_k):
        raise AssertionError("work started before the device was checked")

    monkeypatch.setattr(cli, "machine_info", started)
    monkeypatch.setattr(bl, "run", started)
    monkeypatch.setattr(br, "run", started)


def _refused(capsys, argv: list[str], tmp_path) -> str:
    out = tmp_path / "r.json"
    rc = cli.main([*argv, "--out", str(out)])
    captured = capsys.readouterr()
    assert rc == 2
    assert not out.exists()
    assert captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("error: --device: ")
    return lines[0]


@pytest.mark.parametrize("bench", ["linet", "raytrace"])
def test_cuda_without_a_gpu_is_refused_in_one_line_before_any_work(bench, no_work, capsys, tmp_path):
    if torch.cuda.device_count():
        pytest.skip("this machine has a GPU")
    line = _refused(capsys, [bench, "--device", "cuda"], tmp_path)
    assert "cuda requested" in line and "0 CUDA device(s)" in line and "--device cpu" in line


@pytest.mark.parametrize("bench", ["linet", "raytrace"])
def test_a_gpu_this_machine_lacks_is_refused(bench, no_work, capsys, tmp_path):
    line = _refused(capsys, [bench, "--device", "cuda:99"], tmp_path)
    assert "cuda:99 requested" in line


@pytest.mark.parametrize("name", ["bogus", "gpu", "cuda:x", "cuda:-1", "cpu:0"])
@pytest.mark.parametrize("bench", ["linet", "raytrace"])
def test_bogus_device_is_rejected(bench, name, no_work, capsys, tmp_path):
    line = _refused(capsys, [bench, "--device", name], tmp_path)
    assert "expected cpu, cuda or cuda:N" in line and repr(name) in line


def test_debug_shows_the_error_itself(no_work, tmp_path):
    with pytest.raises(ValueError, match="--device: expected cpu, cuda or cuda:N"):
        cli.main(["linet", "--device", "bogus", "--debug", "--out", str(tmp_path / "r.json")])


def test_device_defaults_to_cpu():
    p = cli._parser()
    assert p.parse_args(["linet"]).device == "cpu"
    assert p.parse_args(["raytrace"]).device == "cpu"


def test_linet_on_cpu_reports_what_it_did_before():
    import warp as wp

    from warp_vision.kernels.launch import init

    init()
    if not wp.is_cpu_available():
        pytest.skip("this Warp cannot compile CPU kernels (no warp-clang)")
    res = bl.run([200], batch=64, reduction=5, receptive_field=5, repeats=1, log=lambda *_: None, device="cpu")
    assert set(res) == {"configs"}
    (cfg,) = res["configs"]
    assert set(cfg) == CPU_CONFIG_KEYS
    for layout in cfg["layouts"].values():
        assert set(layout["impls"]) == CPU_IMPLS
        assert all(impl["max_rel_err_vs_warp"] < 1e-5 for impl in layout["impls"].values())
    assert cfg["warp_kernels_only_ms"]["forward_backward"] > 0


# ---------------------------------------------------------------------------------------------
# On a GPU (skipped without one)
# ---------------------------------------------------------------------------------------------


def test_linet_inputs_on_the_gpu_hold_the_cpu_values(cuda_device):
    cpu = bl.layer_inputs(64, 200, 5, 5, seed=3)
    gpu = bl.layer_inputs(64, 200, 5, 5, seed=3, device=cuda_device)
    for k in ("index", "x_bm", "weight", "bias", "grad_y_bm"):
        assert gpu[k].device.type == "cuda"
        assert torch.equal(gpu[k].detach().cpu(), cpu[k].detach()), k
    assert gpu["weight"].requires_grad and gpu["bias"].requires_grad


def test_linet_on_the_gpu_times_the_gpu_paths_and_names_the_skipped(cuda_device):
    cfg = bl.run_config(B=64, P=200, reduction=5, R=5, repeats=1, log=lambda *_: None, device=cuda_device)
    assert cfg["device"] == cuda_device and set(cfg["skipped"]) == set(bl.CUDA_SKIPPED)
    assert "warp_kernels_only_ms" not in cfg
    for layout in cfg["layouts"].values():
        assert set(layout["impls"]) == CPU_IMPLS - {"warp_1thread"}
        for name, impl in layout["impls"].items():
            assert impl["max_rel_err_vs_warp"] < 1e-5, name
            assert impl["times"]["forward"]["median_ms"] > 0
    assert cfg["half_onv"]["median_ms"]["float16"]["forward"] > 0


def test_raytrace_on_the_gpu_agrees_with_wp_mesh(cuda_device):
    out = br.closest_hit_rates(repeats=1, P=60, S=2, detail=2, log=lambda *_: None, device=cuda_device)
    assert out["device"] == cuda_device
    for res in out["rays"].values():
        assert res["agree_with_warp_mesh"] > 0.99
        assert res["warp_packet"]["mrays_per_s"] > 0 and res["warp_mesh"]["mrays_per_s"] > 0
        assert "warp_packet_1thread" not in res and "packet_2threads_over_1" not in res
    onv = br.onv_rate(P=50, S=2, batch=1, repeats=1, log=lambda *_: None, device=cuda_device)
    assert onv["onv_per_s"] > 0


def test_cli_linet_on_the_gpu_writes_the_device(cuda_device, tmp_path):
    out = tmp_path / "linet.json"
    rc = cli.main(["linet", "--device", "cuda", "--photoreceptors", "200", "--batch", "64", "--reduction", "5",
                   "--receptive-field", "5", "--repeats", "1", "--out", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    assert res["device"] == cuda_device and res["device_name"] and set(res["skipped"]) == set(bl.CUDA_SKIPPED)
