"""Where Cycles renders: --device auto|cpu|gpu (needs bpy; the GPU cases need a GPU backend)."""
import json

import pytest

pytest.importorskip("bpy")

from _scale_helpers import run_spikegen  # noqa: E402
from spikegen.errors import InputError  # noqa: E402
from spikegen.formats import GPU_BACKENDS  # noqa: E402
from spikegen.render_blender import gpu_devices, resolve_device  # noqa: E402

pytestmark = pytest.mark.blender
HAS_GPU = any(gpu_devices(b) for b in GPU_BACKENDS)
SMALL = ["--scene", "mic", "--intensity", "16", "--resolution", "16", "--views", "1,0,0", "--subframes", "2",
         "--frames", "8", "--samples", "1", "--png-samples", "1", "--sensor", "ideal"]


def test_cpu_is_cpu_and_auto_names_a_backend_or_falls_back():
    assert resolve_device("cpu") == "cpu"
    said = []
    got = resolve_device("auto", log=said.append)
    if HAS_GPU:
        assert got.split(":")[1] in GPU_BACKENDS and said == []
    else:
        assert got == "cpu" and len(said) == 1 and "rendering on the CPU" in said[0]


@pytest.mark.skipif(HAS_GPU, reason="this machine has a GPU backend")
def test_gpu_where_there_is_none_is_one_line_exit_2_and_nothing_rendered(tmp_path):
    with pytest.raises(InputError, match="no GPU backend"):
        resolve_device("gpu")
    res = run_spikegen("render", *SMALL, "--device", "gpu", "--out", tmp_path)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "--device gpu" in res.stderr
    assert not any(tmp_path.iterdir())


def test_the_resolved_device_is_recorded_in_render_json(tmp_path):
    res = run_spikegen("render", *SMALL, "--device", "cpu", "--out", tmp_path)
    assert res.returncode == 0, res.stderr
    doc = json.loads((tmp_path / "mic_render" / "render.json").read_text())
    assert doc["device"] == "cpu"
    assert json.loads((tmp_path / "mic_i16" / "manifest.json").read_text())["parameters"]["render"]["device"] == "cpu"


@pytest.mark.gpu
@pytest.mark.skipif(not HAS_GPU, reason="no GPU backend (OptiX, CUDA, HIP, Metal, oneAPI) found by Cycles")
def test_a_gpu_render_is_recorded_and_reproducible(tmp_path):
    for out in ("a", "b"):
        res = run_spikegen("render", *SMALL, "--device", "gpu", "--out", tmp_path / out)
        assert res.returncode == 0, res.stderr
    doc = json.loads((tmp_path / "a" / "mic_render" / "render.json").read_text())
    assert doc["device"].startswith("gpu:")
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert all((tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes() for f in files)
