"""``--device cuda`` end to end (train, eval, resume) against the CPU for the same seed.

Skipped without CUDA. CUDA's ``grid_sample`` backward adds with atomics, so GPU runs are seeded
but not bit-reproducible: results are compared within float noise, not bit for bit.
"""
import json
import math

import pytest

torch = pytest.importorskip("torch")
pytestmark = [pytest.mark.torch, pytest.mark.gpu,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]

from spikenerf import neuron  # noqa: E402
from spikenerf.eval import evaluate  # noqa: E402
from spikenerf.train import train  # noqa: E402
from test_trainer_cli import _cfg, dataset  # noqa: E402,F401  (the sphere dataset fixture)


def _quiet(*args):
    return None


def _run(dataset, out, device, stop_at=None, **kw):
    train(_cfg(dataset, device=device, **kw), out, progress=False, log=_quiet, stop_at=stop_at)
    return torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=False)


@pytest.mark.parametrize("method", ["spikelik", "spikenerf-paper", "tfi"])
def test_cuda_trains_like_the_cpu(dataset, tmp_path, method):
    cpu = _run(dataset, tmp_path / "cpu", "cpu", method=method, iters=60)
    gpu = _run(dataset, tmp_path / "gpu", "cuda", method=method, iters=60)
    assert json.loads((tmp_path / "gpu" / "config.json").read_text())["device_used"].startswith("cuda")
    assert gpu["iteration"] == cpu["iteration"] == 60
    for key in ("grid", "sh"):
        a, b = cpu["state"][key], gpu["state"][key]
        assert a.shape == b.shape and torch.isfinite(b).all()
        assert (a - b).abs().max() < 0.05 * (a.abs().max() + 1), key  # float noise only, not another field
    m_cpu = evaluate(tmp_path / "cpu", device="cpu", progress=False)
    m_gpu = evaluate(tmp_path / "gpu", device="cuda", progress=False)
    assert abs(m_cpu["psnr"] - m_gpu["psnr"]) < 0.3, (m_cpu, m_gpu)


def test_cuda_resume_continues_the_run(dataset, tmp_path):
    whole = _run(dataset, tmp_path / "whole", "cuda", iters=60)
    _run(dataset, tmp_path / "cut", "cuda", iters=60, stop_at=30)
    cut = _run(dataset, tmp_path / "cut", "cuda", iters=60)  # resumed at 30
    assert cut["iteration"] == 60
    diff = (cut["state"]["grid"] - whole["state"]["grid"]).abs().max()
    assert diff < 0.05 * (whole["state"]["grid"].abs().max() + 1)


def test_a_cuda_run_evaluates_on_the_cpu_and_back(dataset, tmp_path):
    _run(dataset, tmp_path / "gpu", "cuda", iters=40)
    a = evaluate(tmp_path / "gpu", device="cpu", progress=False)
    b = evaluate(tmp_path / "gpu", device="cuda", progress=False)
    assert math.isfinite(a["psnr"]) and abs(a["psnr"] - b["psnr"]) < 0.05
    _run(dataset, tmp_path / "gpu", "cpu", iters=60)  # a CUDA checkpoint resumed on the CPU


def test_error_rays_on_cuda(dataset, tmp_path):
    """``--error-rays`` on the GPU: its errors are summed there, the map and the draws made on the CPU; the
    run trains like the CPU's (float noise can move a draw, not the field), and resumes on the CPU."""
    cpu = _run(dataset, tmp_path / "cpu", "cpu", iters=90, error_rays=0.5)
    gpu = _run(dataset, tmp_path / "gpu", "cuda", iters=90, error_rays=0.5)
    for key in ("grid", "sh"):
        a, b = cpu["state"][key], gpu["state"][key]
        assert torch.isfinite(b).all() and (a - b).abs().max() < 0.05 * (a.abs().max() + 1), key
    ea, eb = cpu["error_rays"]["error"], gpu["error_rays"]["error"]
    assert ea.shape == eb.shape and (eb >= 0).any() and torch.isfinite(eb).all()
    resumed = _run(dataset, tmp_path / "gpu", "cpu", iters=120, error_rays=0.5)  # the CUDA run, on the CPU
    assert resumed["iteration"] == 120


def test_sensor_models_agree_on_cuda():
    g = torch.Generator().manual_seed(3)
    x = torch.rand(4096, generator=g)
    resp, dark = 0.8 + 0.4 * torch.rand(4096, generator=g), 0.02 * torch.rand(4096, generator=g)
    for dev in ("cpu", "cuda"):
        xs = x.detach().clone().to(dev).requires_grad_(True)  # a leaf on each device (x itself stays grad-free)
        maps = neuron.paper_fpn_maps(resp.to(dev), dark.to(dev), 4.9e-4)
        out = (neuron.paper_pixel(xs, 64, *maps).sum()
               + neuron.rsir_rate(xs, 32, resp.to(dev), dark.to(dev)).sum()
               + neuron.expected_count(neuron.spike_rate(xs, 64, resp.to(dev), dark.to(dev)), 256, "zero").sum())
        out.backward()
        if dev == "cpu":
            ref, ref_grad = out.detach(), xs.grad
        else:
            assert torch.allclose(out.detach().cpu(), ref, rtol=1e-4)
            assert (xs.grad.cpu() - ref_grad).abs().mean() < 1e-4  # a loop period may flip at a float tie
