"""``spikenerf-paper``: the published SpikeNeRF pixel (fixed-pattern formula, 256-step
integrate-and-fire loop, gamma 1/2.2) against plain re-computations, its targets, and
``--frames w`` (train from the first w frames of each stream)."""
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from click.testing import CliRunner  # noqa: E402

from spikenerf import neuron  # noqa: E402
from spikenerf.cli import main  # noqa: E402
from spikenerf.data import load_dataset  # noqa: E402
from spikenerf.methods import METHODS  # noqa: E402
from spikenerf.targets import build_targets, paper_target  # noqa: E402
from spikenerf.train import train  # noqa: E402
from test_trainer_cli import SIZE, _cfg, dataset  # noqa: E402,F401  (the sphere dataset fixture)

# inputs where float32 sums decide the period (0.1 summed 10 times exceeds 1; 0.5 twice does not),
# never-firing, always-firing and in-between values
CHARGES = [0.0, 1e-3, 0.0039, 0.1, 0.2, 1 / 3, 0.25, 0.3, 0.4, 0.5, 0.7, 0.999, 1.0, 1.0001, 1.5]


def _loop(c: float, steps: int = 256) -> tuple[float, int]:
    """The published loop, written out: (count / steps, step of the last spike)."""
    c, one = np.float32(c), np.float32(1.0)
    m, count, last = np.float32(0.0), 0, 0
    for t in range(1, steps + 1):
        m = np.float32(m + c)
        if m > one:
            count, last, m = count + 1, t, np.float32(0.0)
    return count / steps, last


def test_if_loop_forward_equals_a_plain_loop():
    c = torch.tensor(CHARGES, dtype=torch.float32)
    got = neuron.PaperIF.apply(c, 256)
    want = torch.tensor([_loop(v)[0] for v in CHARGES], dtype=torch.float32)
    assert torch.equal(got, want)
    assert got[CHARGES.index(0.1)] == 25 / 256  # period 10 in float32 (not 11 as in exact arithmetic)
    assert got[CHARGES.index(0.5)] == 85 / 256  # 0.5 + 0.5 is not > 1: period 3
    assert got[CHARGES.index(1.0)] == 128 / 256 and got[CHARGES.index(1.5)] == 1.0


def test_if_loop_gradient_is_the_last_spike_over_256():
    c = torch.tensor(CHARGES, dtype=torch.float32, requires_grad=True)
    neuron.PaperIF.apply(c, 256).sum().backward()
    want = torch.tensor([_loop(v)[1] / 256 for v in CHARGES], dtype=torch.float32)
    assert torch.equal(c.grad, want)
    assert c.grad[0] == 0 and c.grad[CHARGES.index(0.3)] == 1.0  # period 4: the last spike is at step 256
    assert c.grad[CHARGES.index(0.25)] == 255 / 256  # 4 x 0.25 is not > 1: period 5, last spike at 255
    assert c.grad[CHARGES.index(0.4)] == 255 / 256  # period 3: the last spike is at step 255


def test_fixed_pattern_formula_by_hand():
    x, nl, nd, dl = 0.25, 0.64, 7.66, 4.95  # the published camera's median Nl, Nd (lux), D_light
    D = 1 / (x + 1e-5) - 1
    want = 1 / (D / (nl + D * nd / (dl * (335 + nd))) + 1)
    got = neuron.paper_fpn(*(torch.tensor([v], dtype=torch.float64) for v in (x, nl, nd, dl)))
    assert float(got) == pytest.approx(want, rel=1e-12)


def test_fixed_pattern_maps_give_the_datasets_rate_at_low_light():
    resp = torch.tensor([0.8, 1.0, 1.25], dtype=torch.float64)
    dark = torch.tensor([0.0, 0.004, 0.02], dtype=torch.float64)
    maps = neuron.paper_fpn_maps(resp, dark, 4.9e-4)
    for x in (1e-4, 1e-3):
        rate = neuron.paper_fpn(torch.full_like(resp, x), *maps)
        assert torch.allclose(rate, resp * (x + dark), rtol=0.03, atol=2e-5)  # R (x + d), the dataset's law
    other = neuron.paper_fpn(torch.full_like(resp, 0.25), *neuron.paper_fpn_maps(resp, dark, 1e-3))
    assert torch.allclose(other, neuron.paper_fpn(torch.full_like(resp, 0.25), *maps))  # L cancels


def test_paper_pixel_equals_formula_then_plain_loop_then_gamma():
    x = torch.linspace(0, 1, 41, dtype=torch.float32)
    resp, dark = torch.full_like(x, 1.1), torch.full_like(x, 0.003)
    maps = neuron.paper_fpn_maps(resp, dark, 4.9e-4)
    got = neuron.paper_pixel(x, 64, *maps)
    charge = neuron.paper_fpn(x * 0.25, *maps)  # I = 64: the published x / 4
    want = torch.tensor([_loop(float(c))[0] ** (1 / 2.2) for c in charge], dtype=torch.float32)
    assert torch.allclose(got, want, rtol=1e-6, atol=0)


def test_paper_pixel_has_finite_gradients_where_nothing_fires():
    x = torch.tensor([0.0, 0.5], requires_grad=True)
    ones = torch.ones(2)
    neuron.paper_pixel(x, 16, ones, 0 * ones, ones).sum().backward()  # I = 16, x = 0: no spike
    assert torch.isfinite(x.grad).all() and x.grad[0] == 0 and x.grad[1] > 0


def test_paper_target_is_gamma_encoded_8_bit():
    spikes = np.zeros((256, 2, 2), np.uint8)
    spikes[::4, 0, 0] = 1  # 64 of 256 frames
    spikes[:, 1, 1] = 1
    img = paper_target(spikes, 2, 2)
    assert img[0, 0] == np.float32(round(255 * 0.25 ** (1 / 2.2)) / 255)
    assert img[1, 1] == 1.0 and img[0, 1] == 0.0
    assert img.dtype == np.float32


def test_frames_w_uses_the_first_w_frames(dataset):
    ds = load_dataset(dataset)
    whole = build_targets(ds, METHODS["spikenerf"], SIZE, SIZE, progress=False)
    first = build_targets(ds, METHODS["spikenerf"], SIZE, SIZE, progress=False, frames=32)
    assert set(first.frames) == {32.0} and set(whole.frames) == {float(ds.frames)}
    assert 0 < first.values.sum() < whole.values.sum()
    from spikenerf.data import read_view_spikes

    spikes = read_view_spikes(ds, ds.splits["train"][0])
    assert np.array_equal(first.values[0], spikes[:32].sum(axis=0).reshape(-1).astype(np.float32))


def _train_cli(dataset, run, *extra):
    return CliRunner().invoke(main, ["train", str(dataset), "--out", str(run), "--iters", "3", "--batch-rays", "256",
                                     "--device", "cpu", "--quiet", *extra])


@pytest.mark.parametrize("w", ["0", "-3", "1000"])
def test_frames_out_of_range_is_one_line(dataset, tmp_path, w):
    res = _train_cli(dataset, tmp_path / "run", "--frames", w)
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and f"--frames {w}" in lines[0] and "256" in lines[0], lines
    assert not (tmp_path / "run").exists()  # nothing written


def test_frames_recorded_and_checked_on_resume(dataset, tmp_path):
    run = tmp_path / "run"
    res = _train_cli(dataset, run, "--frames", "64", "--method", "spikenerf-paper")
    assert res.exit_code == 0, res.output
    assert json.loads((run / "config.json").read_text())["frames"] == 64
    res = _train_cli(dataset, run, "--frames", "128", "--method", "spikenerf-paper")
    assert res.exit_code == 2 and "frames=64" in res.output and "Traceback" not in res.output
    res = _train_cli(dataset, tmp_path / "all")
    assert res.exit_code == 0 and json.loads((tmp_path / "all" / "config.json").read_text())["frames"] == 256


def test_spikenerf_paper_learns_the_sphere(dataset, tmp_path):
    from spikenerf.eval import evaluate

    run = tmp_path / "paper"
    train(_cfg(dataset, method="spikenerf-paper", iters=150), run, progress=False, log=lambda m: None)
    m = evaluate(run, device="cpu", progress=False)
    assert m["method"] == "spikenerf-paper"
    assert m["psnr"] > 20, m  # a blank white image scores about 9 dB here
