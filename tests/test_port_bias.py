"""bench/bench_port_bias.py: the published neuron's rate loss against the pixels that make the data,
and the tool that finds a port's brightness bias in a run's saved predictions."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

BENCH = Path(__file__).resolve().parents[1] / "bench"
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_port_bias as pb  # noqa: E402

from spikegen.spikeio import linear_to_srgb, write_json_atomic, write_png  # noqa: E402
from test_trainer_cli import dataset, sphere_dataset  # noqa: E402,F401  (dataset: the sphere, paper sensor, i64)


def test_rsir_rate_is_the_generators_mean_charge():
    """The closed form against the generator itself (spikegen.sensor.rsir_charge, R = 1, d = 0)."""
    from spikegen.sensor import rsir_charge

    rng = np.random.default_rng(20261127)
    for x, intensity in ((0.1, 16), (0.6, 32), (1.0, 64)):
        q = rsir_charge(np.full((200_000, 1), x), intensity, np.ones(1), np.zeros(1), rng)
        se = q.std() / np.sqrt(q.size)
        assert abs(q.mean() - pb.rsir_rate(x, intensity)) < 4 * se, (x, intensity)


def test_the_published_loop_loses_about_half_a_frame_a_spike_and_rsir_alike():
    """At many spikes (c = 0.25, i64 x = 1) the loop reads about c / (1 + c / 2): each interval is half
    a frame longer than the subtractive pixel's 1 / c, as rsir's uniform interval noise makes it; at a
    few spikes (i16 x = 0.1, about 1.6 in 256 frames) the whole intervals counted from an empty
    membrane lose far more, while rsir stays near c."""
    c = 0.25
    loop = pb.hard_reset_rate(np.array([c]), 0.1)[0]
    assert loop == pytest.approx(c / (1 + c / 2), rel=0.02)
    assert pb.rsir_rate(1.0, 64) == pytest.approx(c / (1 + c / 2), rel=0.01)
    assert loop / c < 0.92                                       # 8 % and more below the subtractive pixel
    few = 0.1 * 16 / 256
    assert pb.hard_reset_rate(np.array([few]), 0.1)[0] / few < 0.7
    assert pb.rsir_rate(0.1, 16) / few > 0.99
    xs, hx = pb.rate_loss_inverse(64, 0.1)
    assert np.all(np.diff(hx) >= 0) and np.all(hx[1:] < xs[1:])   # monotone, always below the luminance


@pytest.fixture(scope="module")
def rsir_dataset(tmp_path_factory):
    """The sphere of test_trainer_cli's fixture, converted with the `rsir` generator (i64)."""
    return sphere_dataset(tmp_path_factory, "rsir")


def test_the_loss_is_undone_against_the_datas_own_pixel():
    """The inverse reads, for the luminance the loop is fed, the luminance at which the data's pixel reads
    the same mean charge. Against a subtractive pixel at i64 (x 0.3 to 1) that is 6 to 12 % lower; against `rsir`,
    which loses about as much as the loop at many spikes, it stays within 4 % (3.1 at most); at a few spikes
    (i16 x = 0.1) the loop's empty start loses against both."""
    for pixel, rate in (("subtractive", lambda y, i: y * i / 256.0), ("rsir", pb.rsir_rate)):
        xs, ys = pb.rate_loss_inverse(64, 0.1, pixel)
        assert np.all(np.diff(ys) >= 0)
        for x in (0.3, 0.6, 1.0):
            loop = pb.hard_reset_rate(np.array([x * 64 / 256.0]), 0.1)[0]
            y = np.interp(x, xs, ys)
            assert rate(y, 64) == pytest.approx(loop, rel=2e-3), (pixel, x)
    xs, sub = pb.rate_loss_inverse(64, 0.1, "subtractive")
    _, rs = pb.rate_loss_inverse(64, 0.1, "rsir")
    mid = (xs >= 0.3) & (xs <= 1.0)
    assert np.all(sub[mid] / xs[mid] < 0.95)
    assert np.all(np.abs(rs[mid] / xs[mid] - 1) < 0.04)
    for pixel in pb.PIXELS:
        xs, ys = pb.rate_loss_inverse(16, 0.1, pixel)
        assert np.interp(0.1, xs, ys) < 0.07, pixel
    with pytest.raises(ValueError):
        pb.rate_loss_inverse(64, 0.1, "hard")


def test_pixel_of_refuses_a_sensor_it_has_no_mean_rate_for():
    from spikegen.sensor import Sensor

    assert pb.pixel_of(Sensor(kind="rsir")) == "rsir"
    assert pb.pixel_of(Sensor()) == "subtractive"
    with pytest.raises(pb.BadInput, match="no mean-rate model"):
        pb.pixel_of(Sensor(reset="zero"))
    with pytest.raises(pb.BadInput, match="gamma 0.8"):
        pb.pixel_of(Sensor(gamma=0.8))


def _fake_run(root: Path, ds: Path, method: str, predict) -> Path:
    """A run folder as spikenerf eval leaves it, with planted predictions ``predict(gt_linear)``."""
    from spikenerf.data import load_dataset
    from spikenerf.eval import reference

    run = root / method
    (run / "eval_test").mkdir(parents=True)
    data = load_dataset(ds)
    for view in data.splits["test"]:
        _, gt_x, _ = reference(data, view, data.height, data.width)
        write_png(run / "eval_test" / f"{view.name.replace('/', '_')}.png", linear_to_srgb(np.clip(predict(gt_x), 0, 1)))
    write_json_atomic(run / "config.json", {"dataset": str(ds), "method": method, "seed": 3, "frames": 256,
                                            "sensor_maps": ""})
    write_json_atomic(run / "metrics.json", {"split": "test", "resolution": [data.height, data.width],
                                             "iterations": 10, "psnr_object": 20.0, "views_from": "train every 8th"})
    return run


def test_the_bench_finds_a_planted_port_bias_and_leaves_an_unbiased_run_alone(dataset, tmp_path):
    """Predictions made as the port makes them on subtractive-reset data (the luminance the published loop
    needs to read the true count) score low as saved, near the 8-bit limit once the rate loss is undone,
    and need a gain below 1; predictions equal to the truth score best as saved and lose when 'undone'."""
    xs, hx = pb.rate_loss_inverse(64, 0.1)
    biased = _fake_run(tmp_path, dataset, "spikenerf-paper", lambda gt: np.interp(gt, hx, xs))
    fair = _fake_run(tmp_path, dataset, "spikelik", lambda gt: gt)
    b, f = pb.run_row(biased), pb.run_row(fair)
    assert b["sensor"] == "paper" and b["reset"] == "subtract" and b["intensity"] == 64 and b["views"] == 2
    assert b["psnr_object_rate_loss_undone"]["0.1"] > b["psnr_object_saved"] + 6
    assert b["psnr_object_rate_loss_undone"]["0.1"] > 35
    assert b["oracle_gain"] < 0.95 and b["psnr_object_oracle_gain"] > b["psnr_object_saved"]
    assert f["psnr_object_saved"] > 35 and f["oracle_gain"] == pytest.approx(1.0, abs=0.01)
    assert f["psnr_object_rate_loss_undone"]["0.1"] < f["psnr_object_saved"] - 6
    assert pb.eligible(tmp_path) == [fair, biased]                 # sorted by folder name


def test_the_bench_says_in_which_counts_the_error_lies(dataset, tmp_path):
    """The object pixels binned by the count they expect over the 256 frames (x I): the shares add to 1,
    the parts to the pooled object MSE (computed here from the saved images), and an error planted only
    in the pixels expecting fewer than 16 spikes shows in those bins and nowhere else."""
    from spikegen.spikeio import read_png, srgb_to_linear
    from spikenerf.data import load_dataset
    from spikenerf.eval import reference

    planted = _fake_run(tmp_path, dataset, "spikenerf-paper", lambda gt: np.where(gt * 64 < 16, gt + 0.05, gt))
    fair = _fake_run(tmp_path, dataset, "spikelik", lambda gt: gt)
    p, f = pb.run_row(planted)["by_expected_count"], pb.run_row(fair)["by_expected_count"]
    assert p["edges"] == list(pb.COUNT_EDGES) and p["pixels"] == f["pixels"]
    assert sum(p["pixels"]) == pytest.approx(1.0)
    low = np.asarray(pb.COUNT_EDGES) < 16
    assert sum(np.asarray(p["pixels"])[low]) > 0.05 and sum(np.asarray(p["pixels"])[~low]) > 0.05
    excess = np.subtract(p["mse_saved"], f["mse_saved"])
    assert np.all(excess[~low] == 0) and excess[low].sum() > 1e-3
    data = load_dataset(dataset)
    se, n = 0.0, 0
    for view in data.splits["test"]:
        _, gt_x, alpha = reference(data, view, data.height, data.width)
        img = read_png(planted / "eval_test" / f"{view.name.replace('/', '_')}.png")
        pred = srgb_to_linear(img[..., 0] if img.ndim == 3 else img)
        m = alpha > 0
        se += float(((linear_to_srgb(np.clip(pred[m], 0, 1)) - linear_to_srgb(gt_x[m])) ** 2).sum())
        n += int(m.sum())
    assert sum(p["mse_saved"]) == pytest.approx(se / n, rel=1e-9)
    assert pb.count_bin(np.array([0.0, 0.99, 1.0, 15.9, 16.0, 300.0]) / 64, 64).tolist() == [0, 0, 1, 4, 5, 5]


def test_on_rsir_data_the_bench_undoes_the_loss_against_rsir(rsir_dataset, tmp_path):
    """A port's predictions on `rsir` data (the luminance at which the loop reads what the rsir pixel read
    of the truth) come back to the truth when undone against the rsir pixel; the row names it."""
    xs, ys = pb.rate_loss_inverse(64, 0.1, "rsir")
    biased = _fake_run(tmp_path, rsir_dataset, "spikenerf-paper", lambda gt: np.interp(gt, ys, xs))
    b = pb.run_row(biased)
    assert b["sensor"] == "rsir" and b["pixel"] == "rsir"
    assert b["psnr_object_rate_loss_undone"]["0.1"] > 35
    assert b["psnr_object_rate_loss_undone"]["0.1"] > b["psnr_object_saved"] + 3


def test_cli_writes_every_row_or_nothing(dataset, tmp_path, capsys):
    run = _fake_run(tmp_path / "runs", dataset, "spikenerf-paper", lambda gt: gt)
    out = tmp_path / "bias.jsonl"
    assert pb.main([str(run), "--results", str(out)]) == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert sum(r["kind"] == "rate" for r in rows) == len(pb.INTENSITIES) * len(pb.LUMINANCES)
    assert [r["run"] for r in rows if r["kind"] == "run"] == ["spikenerf-paper"]
    before = out.read_bytes()
    (run / "eval_test" / "train_r_8.png").unlink()
    assert pb.main([str(run), "--results", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]   # beside tqdm's bar
    assert len(err) == 1 and err[0].startswith("error: ") and "train_r_8.png missing" in err[0]
    assert out.read_bytes() == before                              # nothing half-written
    assert pb.main(["--runs-dir", str(tmp_path / "nowhere"), "--results", str(out)]) == 2
    assert pb.main([str(tmp_path / "nowhere"), "--results", str(out)]) == 2
    assert out.read_bytes() == before
