"""What a training step asks of the host, counted on the CPU (bench/bench_trainer_profile.py's
HostCounter): on a GPU each read of a tensor's values waits for the device and each tensor made
from host data is a transfer, so a step must make few of the first and none of the second."""
import shutil
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
profile = pytest.importorskip("bench_trainer_profile")

from spikenerf.train import train  # noqa: E402
from test_trainer_cli import _cfg, dataset  # noqa: E402,F401  (the sphere dataset fixture)


def _counted(run, cfg, until):
    counter = profile.HostCounter()
    with counter:
        profile.continue_run(run, cfg, until)
    return counter


@pytest.mark.parametrize("stop", [1e-4, 0.0])
def test_a_training_step_reads_few_values_and_uploads_nothing(dataset, tmp_path, stop):
    cfg = _cfg(dataset, iters=60, stop_transmittance=stop, checkpoint_every=10 ** 6, checkpoint_every_s=1e9)
    base = tmp_path / "base"
    train(cfg, base, progress=False, log=lambda m: None)  # past the grid's growth (it ends at 30 % of 60)
    counts = []
    for steps in (10, 30):  # two continuations from the same checkpoint: their difference is 20 steps' work
        run = tmp_path / f"run{steps}"
        shutil.copytree(base, run)
        counts.append(_counted(run, cfg, 60 + steps))
    reads = (sum(counts[1].reads.values()) - sum(counts[0].reads.values())) / 20
    uploads = (sum(counts[1].uploads.values()) - sum(counts[0].uploads.values())) / 20
    assert uploads == 0, counts[1].uploads
    # sampling: one read of the rays' extent, one or three for the packed samples, one for early
    # termination; the loss check (one on the CPU); the occupancy's update every 10 steps here
    assert 2 <= reads <= 7, counts[1].reads


def test_the_profiler_refuses_what_it_cannot_profile(tmp_path):
    """bench_trainer_profile.py: a folder that is not a trained run, a GPU where there is none, too few
    steps: one line, exit 2, no traceback."""
    import subprocess

    script = Path(__file__).resolve().parents[1] / "bench" / "bench_trainer_profile.py"
    (tmp_path / "half").mkdir()
    (tmp_path / "half" / "config.json").write_text("{}")
    shutil.copytree(tmp_path / "half", tmp_path / "whole")
    (tmp_path / "whole" / "checkpoint.pt").write_bytes(b"")  # (the checks below come before it is read)
    cases = [([str(tmp_path / "nothing")], "is not a trained run"), ([str(tmp_path / "half")], "no checkpoint.pt"),
             ([str(tmp_path / "whole"), "--steps", "1"], "--steps must be at least 2")]
    if not torch.cuda.is_available():
        cases.append(([str(tmp_path / "whole"), "--device", "cuda"], "has no CUDA GPU"))
    for args, want in cases:
        r = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True)
        assert r.returncode == 2 and want in r.stderr and "Traceback" not in r.stderr, r.stderr
