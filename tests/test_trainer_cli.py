"""spikenerf train / eval end to end on a tiny converted dataset: learning, metrics.json,
resume, NaN handling, bad input."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from click.testing import CliRunner  # noqa: E402

from spikegen.spikeio import write_json_atomic, write_png  # noqa: E402
from spikenerf.cli import main  # noqa: E402
from spikenerf import methods  # noqa: E402
from spikenerf.train import TrainConfig, TrainError, train  # noqa: E402
import spikenerf.train as train_module  # noqa: E402

SIZE = 32
ANGLE_X = 0.6911112070083618
RADIUS = 0.9  # a grey sphere at the origin: every camera that looks at the origin sees a centred disc


def _pose(theta, phi, dist=4.0311):
    c = np.array([math.cos(phi) * math.cos(theta), math.cos(phi) * math.sin(theta), math.sin(phi)]) * dist
    z = c / np.linalg.norm(c)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, c
    return m


def _sphere_png(path, dist=4.0311):
    focal = 0.5 * SIZE / math.tan(0.5 * ANGLE_X)
    r_px = focal * math.tan(math.asin(RADIUS / dist))
    j, i = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    alpha = np.clip(r_px - np.hypot(i - SIZE / 2, j - SIZE / 2) + 0.5, 0, 1)
    rgba = np.zeros((SIZE, SIZE, 4))
    rgba[..., :3] = 0.35
    rgba[..., 3] = alpha
    write_png(path, rgba)


def sphere_dataset(tmp_path_factory, sensor: str = "paper", intensity: float = 64):
    """The sphere seen from 16 train views, converted with ``sensor`` at ``intensity`` (default i64): its dataset
    folder."""
    from spikegen.dataset import convert

    src = tmp_path_factory.mktemp(f"sphere_{sensor}")
    frames = []
    for k in range(16):
        name = f"./train/r_{k}"
        _sphere_png(src / f"train/r_{k}.png")
        frames.append({"file_path": name, "transform_matrix": _pose(0.4 * k, 0.2 + 0.05 * (k % 5)).tolist()})
    write_json_atomic(src / "transforms_train.json", {"camera_angle_x": ANGLE_X, "frames": frames})
    out = tmp_path_factory.mktemp(f"ds_{sensor}")
    (folder,) = convert(src, out, [intensity], sensor=sensor, progress=False)
    return folder


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return sphere_dataset(tmp_path_factory)


def _cfg(dataset, **kw):
    base = dict(dataset=str(dataset), iters=120, device="cpu", batch_rays=512, grid_start=16, grid_final=32,
                occupancy_after=20, occupancy_every=10)
    base.update(kw)
    return TrainConfig(**base)


def test_train_and_eval_learn_the_sphere(dataset, tmp_path):
    run = tmp_path / "run"
    res = CliRunner().invoke(main, ["train", str(dataset), "--iters", "150", "--device", "cpu", "--out", str(run),
                                    "--batch-rays", "512", "--quiet"])
    assert res.exit_code == 0, res.output
    assert "no test split; evaluating on train every 8th (2 views)" in res.output
    res = CliRunner().invoke(main, ["eval", str(run), "--quiet"])
    assert res.exit_code == 0, res.output
    m = json.loads((run / "metrics.json").read_text())
    for key in ("split", "views", "psnr", "ssim", "lpips", "psnr_object", "ssim_object", "lpips_object",
                "psnr_object50", "ssim_object50", "psnr_background", "ssim_background", "train_seconds"):
        assert key in m
    assert m["split"] == "test" and m["views"] == 2 and m["views_from"] == "train every 8th"
    assert [r["view"] for r in m["per_view"]] == ["train/r_0", "train/r_8"]
    assert m["psnr"] == pytest.approx(np.mean([r["psnr"] for r in m["per_view"]]))
    assert m["psnr_object50"] != m["psnr_object"] and m["psnr_background"] > m["psnr_object"]
    assert m["psnr"] > 22 and m["ssim"] > 0.8, m  # a blank white image scores about 9 dB here
    # the tone: most object pixels (alpha > 0.5) are the grey sphere's inside (its antialiased rim, lighter,
    # the rest): their bin's truth is the grey's level (0.1 linear, less the PNG's rounding)
    from spikegen.spikeio import png_to_radiance
    grey = float(png_to_radiance(np.array([[[0.35, 0.35, 0.35, 1.0]]]))[0][0, 0])
    filled = max(m["tone"], key=lambda r: r["pixels"])
    assert filled["truth"] == pytest.approx(grey, rel=0.02) and sum(r["pixels"] for r in m["tone"]) > filled["pixels"]
    assert abs(filled["bias"]) < 0.1 * grey and "tone_from" in m
    assert (run / "eval_test" / "train_r_0_gt_vs_pred.png").is_file()
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["method"] == "spikelik" and cfg["seed"] == 0


def test_resume_gives_the_same_field(dataset, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    train(_cfg(dataset, iters=50), a, progress=False, log=lambda m: None)
    train(_cfg(dataset, iters=50), b, progress=False, log=lambda m: None, stop_at=25)  # "interrupted" at 25
    msgs = []
    train(_cfg(dataset, iters=50), b, progress=False, log=msgs.append)
    assert any("resuming" in m and "25" in m for m in msgs)
    ca, cb = torch.load(a / "checkpoint.pt", weights_only=False), torch.load(b / "checkpoint.pt", weights_only=False)
    assert ca["iteration"] == cb["iteration"] == 50
    assert torch.equal(ca["state"]["grid"], cb["state"]["grid"])  # bit for bit
    assert torch.equal(ca["state"]["sh"], cb["state"]["sh"])  # the view-dependent grid too


def test_resume_with_error_rays_gives_the_same_field(dataset, tmp_path):
    """``--error-rays``: the error map and the sums since its last refresh travel in the checkpoint, so a run
    interrupted between two refreshes (errorrays.REFRESH = 50) draws on as the uninterrupted one."""
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    train(_cfg(dataset, iters=90, error_rays=0.5), a, progress=False, log=lambda m: None)
    train(_cfg(dataset, iters=90, error_rays=0.5), b, progress=False, log=lambda m: None, stop_at=65)
    train(_cfg(dataset, iters=90, error_rays=0.5), b, progress=False, log=lambda m: None)
    train(_cfg(dataset, iters=90), c, progress=False, log=lambda m: None)
    ca, cb, cc = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (a, b, c))
    assert torch.equal(ca["state"]["grid"], cb["state"]["grid"]) and torch.equal(ca["state"]["sh"], cb["state"]["sh"])
    assert torch.equal(ca["error_rays"]["error"], cb["error_rays"]["error"])
    assert (ca["error_rays"]["error"] >= 0).any() and "error_rays" not in cc
    assert not torch.equal(ca["state"]["grid"], cc["state"]["grid"])  # the mined rays changed the run


def test_resume_after_sigkill(dataset, tmp_path):
    run = tmp_path / "k"
    cmd = [sys.executable, "-m", "spikenerf.cli", "train", str(dataset), "--iters", "40", "--device", "cpu",
           "--out", str(run), "--batch-rays", "256", "--checkpoint-every", "3", "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    import time

    deadline = time.time() + 120
    while not (run / "checkpoint.pt").is_file() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.2)
    proc.kill()
    proc.wait()
    # A kill may land mid-write: its temporary (.checkpoint.pt.*.part) may remain, but the name we
    # read only ever appears by rename, so checkpoint.pt is whole.
    assert all(p.name.startswith(".checkpoint.pt.") for p in run.glob("*.part"))
    killed_at = torch.load(run / "checkpoint.pt", weights_only=False)["iteration"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)  # the same command again
    assert done.returncode == 0, done.stderr
    assert killed_at == 40 or f"resuming from {run / 'checkpoint.pt'} at iteration {killed_at}" in done.stderr
    assert torch.load(run / "checkpoint.pt", weights_only=False)["iteration"] == 40
    assert not list(run.glob("*.part"))  # the resumed run cleared what the killed one left


def test_resume_clears_a_killed_writes_temporary(dataset, tmp_path):
    run = tmp_path / "t"
    train(_cfg(dataset, iters=4, checkpoint_every=2), run, progress=False, log=lambda m: None, stop_at=2)
    (run / ".checkpoint.pt.x1y2z3.part").write_bytes(b"half a checkpoint")  # what SIGKILL mid-save leaves
    train(_cfg(dataset, iters=4, checkpoint_every=2), run, progress=False, log=lambda m: None)
    assert not list(run.glob("*.part"))
    assert torch.load(run / "checkpoint.pt", weights_only=False)["iteration"] == 4


def test_nan_loss_stops_and_keeps_last_checkpoint(dataset, tmp_path, monkeypatch):
    run = tmp_path / "nan"
    train(_cfg(dataset, iters=5, checkpoint_every=1), run, progress=False, log=lambda m: None)
    good = (run / "checkpoint.pt").read_bytes()
    method_loss = train_module.method_loss

    def poisoned(*args, **kw):  # the resumed run's loss turns NaN (as a diverging step makes it)
        loss, pred, obs = method_loss(*args, **kw)
        return loss * float("nan"), pred, obs

    monkeypatch.setattr(train_module, "method_loss", poisoned)
    with pytest.raises(TrainError, match="NaN"):
        train(_cfg(dataset, iters=10, checkpoint_every=1), run, progress=False, log=lambda m: None)
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["iteration"] == 5 and torch.isfinite(ck["state"]["grid"]).all()
    assert (run / "checkpoint.pt").read_bytes() == good  # the last good checkpoint is kept


def test_on_a_gpu_the_loss_check_waits_on_the_device_and_names_the_first_bad_iteration(dataset, tmp_path,
                                                                                     monkeypatch):
    """A GPU run keeps the loss check on the device (train.LossGuard, deferred): it stops at the next
    read (every 10 iterations, and before any save), names the first non-finite iteration and keeps
    the last good checkpoint. Run here on the CPU with the deferred guard forced."""
    run = tmp_path / "nan"
    train(_cfg(dataset, iters=5, checkpoint_every=1), run, progress=False, log=lambda m: None)
    good = (run / "checkpoint.pt").read_bytes()
    method_loss, calls = train_module.method_loss, []

    def poisoned(*args, **kw):  # infinite from the third resumed iteration on (iteration 7)
        loss, pred, obs = method_loss(*args, **kw)
        calls.append(1)
        return (loss * float("inf") if len(calls) >= 3 else loss), pred, obs

    class Deferred(train_module.LossGuard):
        def __init__(self, device, ck_path):
            super().__init__(device, ck_path)
            self.deferred = True

    monkeypatch.setattr(train_module, "method_loss", poisoned)
    monkeypatch.setattr(train_module, "LossGuard", Deferred)
    with pytest.raises(TrainError, match="infinite at iteration 7;"):
        train(_cfg(dataset, iters=30, checkpoint_every=1000), run, progress=False, log=lambda m: None)
    assert len(calls) == 6  # iterations 5 to 10: the read at iteration 10 stopped it
    assert (run / "checkpoint.pt").read_bytes() == good
    calls.clear()
    with pytest.raises(TrainError, match="infinite at iteration 7;"):  # before a save, too
        train(_cfg(dataset, iters=30, checkpoint_every=1), run, progress=False, log=lambda m: None)
    assert len(calls) == 3 and (run / "checkpoint.pt").read_bytes() != good  # saved after 5 and 6, not after 7
    assert torch.load(run / "checkpoint.pt", weights_only=False)["iteration"] == 7


def test_coarse_to_fine_reads_the_small_images_first_grows_and_resumes(dataset, tmp_path, monkeypatch):
    """``--coarse-to-fine 0.5``: the first half of the steps cast their rays through the 8 x 8 images (the
    32 x 32 ones box-downsampled 4 times a side), the rest through the 32 x 32 ones; the grid follows an 8 x 8
    run's schedule over the first half and grows to the final size where the full-size images start; a run
    interrupted in the coarse part ends bit for bit as the uninterrupted one."""
    sizes = []
    pixel_rays = train_module.pixel_rays

    def spy(poses, pix, h, w, camera):
        sizes.append((h, w, int(pix.max())))
        return pixel_rays(poses, pix, h, w, camera)

    monkeypatch.setattr(train_module, "pixel_rays", spy)
    a, b = tmp_path / "a", tmp_path / "b"
    cfg = _cfg(dataset, iters=60, coarse_to_fine=0.5, grid_final=48)
    train(cfg, a, progress=False, log=lambda m: None)
    assert [s[:2] for s in sizes] == [(8, 8)] * 30 + [(32, 32)] * 30
    assert max(s[2] for s in sizes[:30]) < 64 and max(s[2] for s in sizes[30:]) >= 64  # pixels of 8 x 8, then 32 x 32
    schedule = json.loads((a / "config.json").read_text())["grid_schedule"]
    assert schedule[-1] == [30, 48] and [s for _, s in schedule[:-1]] == [20, 25, 32]  # 16 -> 32 (an 8 x 8 run's)
    assert [i for i, _ in schedule[:-1]] == [3, 6, 9]  # at 0.1, 0.2, 0.3 of the coarse 30 iterations
    train(cfg, b, progress=False, log=lambda m: None, stop_at=20)
    train(cfg, b, progress=False, log=lambda m: None)
    ca, cb = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (a, b))
    assert torch.equal(ca["state"]["grid"], cb["state"]["grid"]) and torch.equal(ca["state"]["sh"], cb["state"]["sh"])
    # the images must shrink to at least 8 pixels across: one line, nothing written
    res = CliRunner().invoke(main, ["train", str(dataset), "--out", str(tmp_path / "bad"), "--resolution", "16",
                                    "--coarse-to-fine", "0.5", "--device", "cpu", "--quiet"])
    assert res.exit_code == 2 and "--coarse-to-fine" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "bad").exists()


def test_not_a_dataset_is_one_clear_line(tmp_path):
    res = CliRunner().invoke(main, ["train", str(tmp_path), "--out", str(tmp_path / "r")])
    assert res.exit_code == 2
    assert "not a spike dataset" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(main, ["eval", str(tmp_path)])
    assert res.exit_code == 2 and "checkpoint" in res.output


def test_lower_training_resolution_block_averages(dataset, tmp_path):
    run = tmp_path / "half"
    train(_cfg(dataset, iters=3, resolution=16), run, progress=False, log=lambda m: None)
    cfg = json.loads((run / "config.json").read_text())
    assert (cfg["height"], cfg["width"]) == (16, 16)
    with pytest.raises(Exception, match="by one integer factor"):
        train(_cfg(dataset, iters=3, resolution=20), tmp_path / "bad", progress=False, log=lambda m: None)


def test_sh_degree_from_the_command_line_and_resume_guard(dataset, tmp_path):
    run = tmp_path / "flat"
    res = CliRunner().invoke(main, ["train", str(dataset), "--out", str(run), "--iters", "3", "--sh-degree", "0",
                                    "--batch-rays", "256", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["field"]["sh_degree"] == 0 and "sh" not in ck["state"]
    # resuming that run with the default (degree 1) would silently keep degree 0: refused instead
    res = CliRunner().invoke(main, ["train", str(dataset), "--out", str(run), "--iters", "6", "--batch-rays", "256",
                                    "--device", "cpu", "--quiet"])
    assert res.exit_code == 2 and "sh_degree=0" in res.output and "Traceback" not in res.output


def test_learning_rate_factor_decays_to_the_fraction_asked():
    from spikenerf.train import learning_rate_factor
    assert learning_rate_factor(0, 100) == 1.0 and abs(learning_rate_factor(100, 100) - 0.1) < 1e-12  # the default
    assert abs(learning_rate_factor(50, 100, 0.25) - 0.5) < 1e-12 and learning_rate_factor(70, 100, 1.0) == 1.0


@pytest.mark.parametrize("option, value, key, bad", [("--lr-grid", "0.3", "lr_grid", ("0",)),
                                                     ("--lr-decay", "0.5", "lr_decay", ("0", "1.5")),
                                                     ("--stop-transmittance", "0", "stop_transmittance", ("-1", "1.5")),
                                                     ("--step-ratio", "1", "step_ratio", ("0", "3")),
                                                     ("--adam-eps", "1e-12", "adam_eps", ("0", "-1")),
                                                     ("--error-rays", "0.5", "error_rays", ("-0.1", "1")),
                                                     ("--coarse-to-fine", "0.5", "coarse_to_fine", ("-0.1", "1"))])
def test_run_options_from_the_command_line_and_resume_guard(dataset, tmp_path, option, value, key, bad):
    run = tmp_path / "lr"
    args = ["train", str(dataset), "--out", str(run), "--batch-rays", "256", "--device", "cpu", "--quiet"]
    res = CliRunner().invoke(main, args + ["--iters", "3", option, value])
    assert res.exit_code == 0, res.output
    assert json.loads((run / "config.json").read_text())[key] == float(value)
    if key == "step_ratio":  # the field samples its rays at that step (render.py reads it from the field)
        assert torch.load(run / "checkpoint.pt", weights_only=False)["field"]["step_ratio"] == float(value)
    res = CliRunner().invoke(main, args + ["--iters", "6"])  # the default would change the run's schedule
    assert res.exit_code == 2 and f"{key}={value}" in res.output and "Traceback" not in res.output
    for v in bad:
        res = CliRunner().invoke(main, ["train", str(dataset), "--out", str(tmp_path / "bad"), option, v])
        assert res.exit_code == 2 and option in res.output and not (tmp_path / "bad").exists()


@pytest.mark.parametrize("option, value, key, bad", [
    ("--tv-luminance", "linear", "tv_luminance", (["gamma"], ["srgb", "--tv-points", "64"])),
    ("--ray-order", "shuffled", "ray_order", (["random"], ["shuffled", "--error-rays", "0.5"]))])
def test_choice_options_from_the_command_line_and_resume_guard(dataset, tmp_path, option, value, key, bad):
    run = tmp_path / "choice"
    args = ["train", str(dataset), "--out", str(run), "--batch-rays", "256", "--device", "cpu", "--quiet"]
    res = CliRunner().invoke(main, args + ["--iters", "3", option, value])
    assert res.exit_code == 0, res.output
    assert json.loads((run / "config.json").read_text())[key] == value
    res = CliRunner().invoke(main, args + ["--iters", "6"])
    assert res.exit_code == 2 and f"{key}={value!r}" in res.output and "Traceback" not in res.output
    for rest in bad:
        res = CliRunner().invoke(main, ["train", str(dataset), "--out", str(tmp_path / "bad"), option, *rest])
        assert res.exit_code == 2 and option in res.output and "Traceback" not in res.output
        assert not (tmp_path / "bad").exists()


def test_srgb_weight_is_for_the_likelihood_methods(dataset, tmp_path):
    res = CliRunner().invoke(main, ["train", str(dataset), "--out", str(tmp_path / "bad"), "--method", "tfp32",
                                    "--srgb-weight", "10"])
    assert res.exit_code == 2 and "--srgb-weight" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "bad").exists()


def test_srgb_weight_defaults_to_400_for_the_likelihood_and_a_resume_keeps_its_own(dataset, tmp_path):
    """Not given, ``--srgb-weight`` is 400 for the likelihood methods and off for the others (config.json
    records the weight used); a run resumed without it keeps its own, a run from before the key (made with it
    off, the default then) included, and says so in one line; another weight on resume is refused in one line;
    a negative one before anything is made."""
    def args(run, *more):
        return ["train", str(dataset), "--out", str(run), "--batch-rays", "256", "--device", "cpu", *more]

    def weight(run):
        return json.loads((run / "config.json").read_text())["srgb_weight"]

    for method, want in (("spikelik", 400.0), ("spikelik-count", 400.0), ("tfp32", 0.0), ("oracle", 0.0)):
        res = CliRunner().invoke(main, args(tmp_path / method, "--iters", "3", "--quiet", "--method", method))
        assert res.exit_code == 0, res.output
        assert weight(tmp_path / method) == want
    old = tmp_path / "old"
    res = CliRunner().invoke(main, args(old, "--iters", "3", "--quiet", "--srgb-weight", "0"))
    assert res.exit_code == 0 and weight(old) == 0.0
    made = json.loads((old / "config.json").read_text())  # as a run from before the key left it
    del made["srgb_weight"]
    (old / "config.json").write_text(json.dumps(made))
    ck = torch.load(old / "checkpoint.pt", weights_only=False)
    del ck["config"]["srgb_weight"]
    torch.save(ck, old / "checkpoint.pt")
    res = CliRunner().invoke(main, args(old, "--iters", "6", "--quiet"))
    assert res.exit_code == 0, res.output
    assert "resuming with its --srgb-weight 0 (a new run would take 400)" in res.output
    assert weight(old) == 0.0 and torch.load(old / "checkpoint.pt", weights_only=False)["iteration"] == 6
    res = CliRunner().invoke(main, args(old, "--iters", "9", "--quiet", "--srgb-weight", "400"))
    assert res.exit_code == 2 and "srgb_weight=0.0" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(main, args(tmp_path / "spikelik", "--iters", "6", "--quiet"))  # its own 400: resumes
    assert res.exit_code == 0 and "resuming with its" not in res.output and weight(tmp_path / "spikelik") == 400.0
    res = CliRunner().invoke(main, args(tmp_path / "bad", "--srgb-weight", "-1"))
    assert res.exit_code == 2 and "--srgb-weight" in res.output and not (tmp_path / "bad").exists()


def test_srgb_weight_is_off_by_default_where_a_white_pixel_counts_fewer_than_16_spikes(dataset, tmp_path):
    """The default weight needs counts (methods.SRGB_LEAST_COUNT): the sphere at i64 counts 64 spikes at white in
    256 frames, 16 in the first 64 (weighted), 8 in the first 32 (off, said in one line), and 8 x 4 = 32 where a
    half-size target pixel averages 4 sensor pixels (weighted). A weight given is kept whatever the counts."""
    def weight(run, *more):
        res = CliRunner().invoke(main, ["train", str(dataset), "--out", str(run), "--batch-rays", "256", "--device",
                                        "cpu", "--iters", "2", "--quiet", *more])
        assert res.exit_code == 0, res.output
        return json.loads((run / "config.json").read_text())["srgb_weight"], res.output

    assert weight(tmp_path / "f64", "--frames", "64")[0] == 400.0
    w, out = weight(tmp_path / "f32", "--frames", "32")
    assert w == 0.0 and "a white pixel counts 8 spikes a count window, fewer than 16" in out
    assert len([line for line in out.splitlines() if "spikes a count window" in line]) == 1
    assert weight(tmp_path / "f32half", "--frames", "32", "--resolution", str(SIZE // 2))[0] == 400.0
    w, out = weight(tmp_path / "f32given", "--frames", "32", "--srgb-weight", "400")
    assert w == 400.0 and "spikes a count window" not in out
    assert weight(tmp_path / "count", "--frames", "32", "--method", "spikelik-count")[0] == 0.0
    assert methods.white_count(64, 32) == 8.0 and methods.white_count(64, 256, windows=4, binning=4) == 64.0
    assert methods.default_srgb_weight("spikelik", 15.9) == 0.0 and methods.default_srgb_weight("spikelik", 16) == 400
    assert methods.default_srgb_weight("tfp32", 64) == 0.0 and methods.default_srgb_weight("spikelik") == 400.0


def test_upsample_at_sets_the_grid_schedule_and_guards_resume(dataset, tmp_path):
    """``--upsample-at``: the grid grows once per fraction of the iterations, recorded in config.json; a
    resume with another schedule is refused with one line; a bad list is refused before anything is made."""
    run = tmp_path / "up"
    args = ["train", str(dataset), "--out", str(run), "--batch-rays", "256", "--device", "cpu", "--quiet"]
    res = CliRunner().invoke(main, args + ["--iters", "20", "--upsample-at", "0.25,0.5"])
    assert res.exit_code == 0, res.output
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["upsample_at"] == [0.25, 0.5]
    its, sizes = zip(*cfg["grid_schedule"])
    assert its == (5, 10) and cfg["grid_start"] < sizes[0] < sizes[1]
    res = CliRunner().invoke(main, args + ["--iters", "40"])  # the default schedule: three growths
    assert res.exit_code == 2 and "upsample_at=[0.25, 0.5]" in res.output and "Traceback" not in res.output
    for bad in ("0.5,0.2", "0", "0.1,1", "a,b", "", "0.1,0.1"):
        res = CliRunner().invoke(main, ["train", str(dataset), "--out", str(tmp_path / "bad"), "--upsample-at", bad])
        assert res.exit_code == 2 and "--upsample-at" in res.output and not (tmp_path / "bad").exists(), bad


def test_oracle_learns_the_sphere_from_its_images_and_needs_them(dataset, tmp_path):
    """``--method oracle`` fits the train views' ground-truth images; a view whose PNG is a
    reconstruction (an imported capture) has none: one line, exit 2, no run folder."""
    from spikenerf.eval import evaluate

    run = tmp_path / "oracle"
    train(_cfg(dataset, method="oracle"), run, progress=False)
    m = evaluate(run, progress=False)
    assert m["method"] == "oracle" and m["psnr"] > 25
    doc = json.loads((dataset / "transforms_train.json").read_text())
    fake = tmp_path / "recon_ds"
    import shutil
    shutil.copytree(dataset, fake)
    for fr in doc["frames"]:
        fr["image_kind"] = "reconstruction"
    (fake / "transforms_train.json").write_text(json.dumps(doc))
    r = CliRunner().invoke(main, ["train", str(fake), "--method", "oracle", "--out", str(tmp_path / "bad"), "--quiet"])
    assert r.exit_code == 2 and "no ground-truth image" in r.output and not (tmp_path / "bad").exists()


def test_oracle_does_not_depend_on_the_intensity_or_the_sensor(tmp_path):
    """The oracle reads the ground-truth images and poses, never the spikes or the sensor's maps: the
    same seed trains the same field, to the bit, from datasets of one scene at two intensities and from
    three sensors' datasets (bench/make_protocol.py lets one dataset's oracle runs stand for the others
    on this)."""
    from spikegen.dataset import convert
    from spikenerf.eval import evaluate

    src = tmp_path / "src"
    frames = []
    for k in range(6):
        _sphere_png(src / f"train/r_{k}.png")
        frames.append({"file_path": f"./train/r_{k}", "transform_matrix": _pose(1.0 * k, 0.3).tolist()})
    write_json_atomic(src / "transforms_train.json", {"camera_angle_x": ANGLE_X, "frames": frames})
    folders = convert(src, tmp_path / "ds", [16, 64], sensor="rsir", progress=False)
    folders += [convert(src, tmp_path / s, [64], sensor=s, progress=False)[0] for s in ("paper", "calibrated")]
    spikes = [(f / "train/r_0.dat").read_bytes() for f in folders]
    assert len(set(spikes)) == 4                                        # four different spike streams
    assert len({(f / "sensor.npz").read_bytes() for f in folders[1:]}) == 3  # three sensors' maps
    fields, metrics = [], []
    for k, folder in enumerate(folders):
        run = tmp_path / f"oracle{k}"
        train(_cfg(folder, method="oracle", iters=60), run, progress=False)
        ck = torch.load(run / "checkpoint.pt", weights_only=False)
        fields.append((ck["field"], ck["state"]))
        metrics.append(evaluate(run, progress=False))
    conf0, state0 = fields[0]
    assert sum(torch.is_tensor(v) for v in state0.values()) >= 3  # the grid and the decoder's weights
    for conf1, state1 in fields[1:]:
        assert conf0 == conf1 and state0.keys() == state1.keys()
        assert all(torch.equal(v, state1[k]) if torch.is_tensor(v) else v == state1[k] for k, v in state0.items())
    for m in metrics[1:]:
        assert metrics[0]["psnr"] == m["psnr"] and metrics[0]["per_view"] == m["per_view"]


def test_training_crops_the_grid_to_the_object(dataset, tmp_path):
    """With the fitted box (the default for an object on white) the grid ends up over a box that
    holds the sphere (radius 0.9) and is smaller than the cube [-1.5, 1.5]^3; without it, the cube."""
    for fit, run in ((True, tmp_path / "fit"), (False, tmp_path / "cube")):
        train(_cfg(dataset, fit_box=fit, iters=300), run, progress=False)
        ck = torch.load(run / "checkpoint.pt", weights_only=False)
        lo, hi = np.array(ck["field"]["aabb"])
        if fit:
            assert np.all(lo <= -RADIUS) and np.all(hi >= RADIUS) and np.all(hi - lo < 2.9), (lo, hi)
            assert ck["config"]["fit_box"] is True
        else:
            assert np.allclose(lo, -1.5) and np.allclose(hi, 1.5)


def test_iterations_default_follows_the_image_size(dataset, tmp_path):
    from spikenerf.config import ITERS_AT, default_iters

    (p100, n100), (p400, n400) = ITERS_AT
    assert default_iters(100, 100) == n100 and default_iters(400, 400) == n400
    assert default_iters(32, 32) == n100 and default_iters(800, 800) == n400  # the nearer one outside
    assert n100 < default_iters(200, 200) < n400 and default_iters(250, 400) % 100 == 0
    run = tmp_path / "auto"  # --iters 0: the run records the resolved count and its schedule follows it
    train(_cfg(dataset, iters=0), run, progress=False, log=lambda m: None, stop_at=1)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["iters"] == default_iters(SIZE, SIZE)
    assert cfg["grid_schedule"][0][0] == int(0.1 * cfg["iters"])


@pytest.mark.parametrize("total, n", [(1000, 64), (7, 20), (1, 3), (4096, 4096)])
def test_shuffled_rays_visit_every_ray_once_an_epoch(total, n):
    """``--ray-order shuffled``: the run's rays, step after step, are a permutation of the dataset's rays in each
    epoch, a different one each epoch and seed, and the same for the same seed (rayorder.py)."""
    from spikenerf.rayorder import shuffled_rays
    rays = torch.cat([shuffled_rays(i * n, n, total, 3) for i in range(-(-3 * total // n))])[:3 * total]
    epochs = rays.view(3, total)
    for e in epochs:
        assert torch.equal(e.sort().values, torch.arange(total))
    again = torch.cat([shuffled_rays(i * n, n, total, 3) for i in range(-(-3 * total // n))])[:3 * total]
    assert torch.equal(rays, again)
    if total >= 1000:
        assert not torch.equal(epochs[0], epochs[1]) and not torch.equal(epochs[0], torch.arange(total))
        assert not torch.equal(shuffled_rays(0, n, total, 4), rays[:n])


def test_shuffled_draw_gives_each_view_and_pixel_once_an_epoch():
    """Batch.draw with ``shuffled``: over one epoch of steps every (view, pixel) pair comes once; the uniform draw
    repeats some and misses others."""
    from spikenerf.train import Batch, iteration_generator
    batch = Batch.__new__(Batch)
    batch.values, batch.device = torch.zeros(5, 48), torch.device("cpu")
    n, steps = 16, 5 * 48 // 16
    for order in ("shuffled", "uniform"):
        pairs = []
        for it in range(steps):
            img, pix, jitter, weights = batch.draw(n, iteration_generator(0, it), None,
                                                   (it, 0) if order == "shuffled" else None)
            assert weights is None and jitter.shape == (n,)
            pairs += list(zip(img.tolist(), pix.tolist()))
        assert (len(set(pairs)) == 5 * 48) == (order == "shuffled")


def test_resume_with_shuffled_rays_gives_the_same_field(dataset, tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    train(_cfg(dataset, iters=50, ray_order="shuffled"), a, progress=False, log=lambda m: None)
    train(_cfg(dataset, iters=50, ray_order="shuffled"), b, progress=False, log=lambda m: None, stop_at=25)
    train(_cfg(dataset, iters=50, ray_order="shuffled"), b, progress=False, log=lambda m: None)
    train(_cfg(dataset, iters=50), c, progress=False, log=lambda m: None)
    ca, cb, cc = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (a, b, c))
    assert torch.equal(ca["state"]["grid"], cb["state"]["grid"]) and torch.equal(ca["state"]["sh"], cb["state"]["sh"])
    assert not torch.equal(ca["state"]["grid"], cc["state"]["grid"])  # the order changed the run

