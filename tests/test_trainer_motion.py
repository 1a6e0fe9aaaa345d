"""spikelik on a moving camera: count windows with their own poses (a render folder, K = 4)."""
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from spikegen.spikeio import write_exr, write_json_atomic, write_png  # noqa: E402
from spikenerf.data import load_dataset  # noqa: E402
from spikenerf.methods import METHODS  # noqa: E402
from spikenerf.targets import build_targets  # noqa: E402
from spikenerf.train import TrainConfig, train  # noqa: E402

from test_trainer_cli import ANGLE_X, SIZE, _pose  # noqa: E402

CENTRE, RADIUS, K = np.array([0.5, 0.0, 0.2]), 0.6, 4


def _disc(pose):
    """Luminance on white and alpha [SIZE, SIZE] of a grey sphere at CENTRE seen from ``pose``."""
    focal = 0.5 * SIZE / math.tan(0.5 * ANGLE_X)
    c = np.linalg.inv(pose) @ np.append(CENTRE, 1.0)
    depth = -c[2]
    u, v = SIZE / 2 + focal * c[0] / depth, SIZE / 2 - focal * c[1] / depth
    r_px = focal * math.tan(math.asin(RADIUS / np.linalg.norm(c[:3])))
    j, i = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    alpha = np.clip(r_px - np.hypot(i - u, j - v) + 0.5, 0, 1)
    return alpha


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    from spikegen.dataset import convert

    root = tmp_path_factory.mktemp("render") / "ball_render"
    views = []
    for n in range(10):
        theta, phi = 0.6 * n, 0.3 + 0.04 * (n % 4)
        subs = [_pose(theta + 0.15 * (k - (K - 1) / 2), phi) for k in range(K)]  # 0.45 rad sweep per view
        base = f"train/r_{n}"
        for k, p in enumerate(subs):
            a = _disc(p)
            lum = 0.1 * a  # premultiplied linear RGBA, grey 0.1
            write_exr(root / f"{base}_sub{k:02d}.exr", np.stack([lum, lum, lum, a], axis=2).astype(np.float32))
        a = _disc(_pose(theta, phi))
        write_png(root / f"{base}.png", np.stack([np.full_like(a, 0.35)] * 3 + [a], axis=2))
        views.append({"index": n, "file_path": f"./{base}", "transform_matrix": _pose(theta, phi).tolist(),
                      "subframe_transform_matrices": [s.tolist() for s in subs]})
    write_json_atomic(root / "render.json", {
        "format": "spikegen-render/1", "scene": "ball", "camera_angle_x": ANGLE_X, "width": SIZE, "height": SIZE,
        "subframes": K, "frames": 256, "motion_deg": 0.45 * 180 / math.pi, "engine": "test", "samples": 1,
        "seed": 0, "splits": {"train": views, "val": [], "test": []}})
    (folder,) = convert(root, tmp_path_factory.mktemp("ds"), [64], sensor="paper", progress=False)
    return folder


def test_windows_get_their_own_poses(moving):
    ds = load_dataset(moving)
    tg = build_targets(ds, METHODS["spikelik-count"], SIZE, SIZE, progress=False, windows=8)
    n_train = len(ds.splits["train"])
    assert tg.values.shape == (8 * n_train, SIZE * SIZE) and np.all(tg.frames == 32)
    first, last = tg.poses[0], tg.poses[7]
    assert np.abs(first[:3, 3] - last[:3, 3]).max() > 0.5  # the camera moved between the windows
    whole = build_targets(ds, METHODS["spikenerf"], SIZE, SIZE, progress=False)
    assert whole.values.shape == (n_train, SIZE * SIZE)
    assert np.allclose(tg.values.reshape(n_train, 8, -1).sum(axis=1), whole.values)
    times = build_targets(ds, METHODS["spikelik"], SIZE, SIZE, progress=False, windows=8)  # each window's spike times
    assert times.statistic == "interval" and np.array_equal(times.poses, tg.poses)
    assert np.abs(times.values - tg.values).max() <= 1.0 and (times.values != tg.values).any()


def test_spikelik_trains_on_moving_views(moving, tmp_path):
    cfg = TrainConfig(dataset=str(moving), iters=60, device="cpu", batch_rays=512, grid_start=16, grid_final=32,
                      occupancy_after=20, occupancy_every=10)
    ck = train(cfg, tmp_path / "run", progress=False, log=lambda m: None)
    state = torch.load(ck, weights_only=False)
    assert state["iteration"] == 60 and torch.isfinite(state["state"]["grid"]).all()


class _Stream:
    """A view and its dataset as targets.image_motion_px reads them: a camera at distance 4 on the +z axis
    looking at the origin, moved along ``move`` (world units, over the whole stream) in K sub-frames."""

    def __init__(self, move, size=100, focal=140.0, frames=256, k=16):
        base = np.eye(4)
        base[2, 3] = 4.0
        self.subframe_poses = np.stack([base.copy() for _ in range(k)])
        for j in range(k):
            self.subframe_poses[j, :3, 3] += np.asarray(move, float) * ((j + 0.5) / k - 0.5)
        self.pose, self.frames, self.focal = base, frames, focal
        self.splits = {"train": [self]}

    def is_static(self):
        return bool(np.abs(self.subframe_poses - self.subframe_poses[:1]).max() <= 1e-6)

    def camera(self, height, width):
        return self.focal * width / 100


def test_image_motion_of_a_sideways_camera_is_focal_times_shift_over_depth():
    """A camera sliding by d along its image plane moves every point at depth D by f d / D pixels; the
    sub-frames sit at the centres of their slices, so the stream's ends see (K - 1) / K of the slide."""
    from spikenerf.targets import image_motion_px

    s = _Stream([0.04, 0.0, 0.0])
    expect = 140.0 * 0.04 * (15 / 16) / 4.0
    assert image_motion_px(s, s, 100, 100, 256) == pytest.approx(expect, rel=1e-6)
    assert image_motion_px(s, s, 400, 400, 256) == pytest.approx(4 * expect, rel=1e-6)  # pixels follow the size
    assert image_motion_px(s, s, 100, 100, 128) == pytest.approx(expect * (7.5 / 15), rel=1e-6)  # half the stream
    assert image_motion_px(_Stream([0, 0, 0]), _Stream([0, 0, 0]), 100, 100, 256) == 0.0
    behind = _Stream([0.04, 0, 0])
    behind.pose = behind.pose @ np.diag([-1.0, 1.0, -1.0, 1.0])  # turned round: the origin is behind it
    assert image_motion_px(behind, behind, 100, 100, 256) == float("inf")


def test_auto_windows_follow_the_motion():
    """The fewest windows that keep each one's motion within a pixel, capped by the method's count; an
    explicit count wins; methods without count targets have one."""
    from spikenerf.targets import MAX_WINDOW_BLUR_PX, count_windows, image_motion_px

    lik = METHODS["spikelik"]
    for shift in (0.004, 0.04, 0.1, 1.0):
        s = _Stream([shift, 0, 0])
        motion = image_motion_px(s, s, 100, 100, 256)
        want = min(8, max(1, math.ceil(motion / MAX_WINDOW_BLUR_PX)))
        assert count_windows(s, lik, 100, 100, 256) == want
    assert count_windows(_Stream([0.004, 0, 0]), lik, 100, 100, 256) == 1
    # 1.31 px of motion at 100 x 100 (one window: within MAX_WINDOW_BLUR_PX, measured harmless up to 2.25 px on
    # the procedural lego), 5.25 px at 400 x 400 (three windows of 1.75 px)
    slide = _Stream([0.04, 0, 0])
    assert count_windows(slide, lik, 100, 100, 256) == 1
    assert count_windows(slide, lik, 400, 400, 256) == 3
    assert count_windows(_Stream([1.0, 0, 0]), lik, 100, 100, 256) == 8
    assert count_windows(_Stream([0.004, 0, 0]), lik, 100, 100, 256, windows=4) == 4
    assert count_windows(_Stream([0.004, 0, 0]), lik, 100, 100, 3, windows=4) == 3  # no more windows than frames
    assert count_windows(_Stream([1.0, 0, 0]), METHODS["spikenerf"], 100, 100, 256) == 1
    assert count_windows(_Stream([1.0, 0, 0]), METHODS["tfp32"], 100, 100, 256, windows=4) == 1
    assert count_windows(_Stream([0, 0, 0]), lik, 100, 100, 256, windows=4) == 1  # static: one pose


def test_windows_help_states_the_rule():
    from click.testing import CliRunner
    from spikenerf.cli import main
    from spikenerf.targets import MAX_WINDOW_BLUR_PX

    out = CliRunner().invoke(main, ["train", "--help"], terminal_width=400).output
    assert f"moves by at most {MAX_WINDOW_BLUR_PX:g} pixels" in " ".join(out.split())


def test_auto_windows_resume_with_the_checkpoints_count(moving, tmp_path):
    """A run resumed with --windows 0 keeps the windows it was made with (a run made under an earlier rule
    is not refused for the rule's new count); an explicit other count is still refused."""
    from spikegen.errors import InputError
    from spikenerf.targets import count_windows

    ds = load_dataset(moving)
    auto = count_windows(ds, METHODS["spikelik"], SIZE, SIZE, 256)
    made = 2 if auto != 2 else 3
    cfg = TrainConfig(dataset=str(moving), iters=20, device="cpu", batch_rays=256, grid_start=16, grid_final=24,
                      windows=made)
    train(cfg, tmp_path / "run", progress=False, log=lambda m: None, stop_at=10)
    said = []
    ck = train(TrainConfig(**{**cfg.to_json(), "windows": 0}), tmp_path / "run", progress=False, log=said.append)
    assert torch.load(ck, weights_only=False)["iteration"] == 20
    assert any(f"resuming with its {made} count windows (a new run would take {auto})" in m for m in said)
    import json
    assert json.loads((tmp_path / "run" / "config.json").read_text())["windows"] == made
    with pytest.raises(InputError, match=f"windows={made}"):
        train(TrainConfig(**{**cfg.to_json(), "iters": 30, "windows": 5 - made}), tmp_path / "run", progress=False,
              log=lambda m: None)


def test_windows_option_sets_the_targets_and_is_kept_on_resume(moving, tmp_path):
    from spikegen.errors import InputError

    ds = load_dataset(moving)
    tg = build_targets(ds, METHODS["spikelik"], SIZE, SIZE, progress=False, windows=2)
    assert tg.values.shape == (2 * len(ds.splits["train"]), SIZE * SIZE) and np.all(tg.frames == 128)
    cfg = TrainConfig(dataset=str(moving), iters=20, device="cpu", batch_rays=256, grid_start=16, grid_final=24,
                      windows=2)
    train(cfg, tmp_path / "run", progress=False, log=lambda m: None, stop_at=10)
    import json
    assert json.loads((tmp_path / "run" / "config.json").read_text())["windows"] == 2
    with pytest.raises(InputError, match="windows=2"):
        train(TrainConfig(**{**cfg.to_json(), "upsample_at": (0.1, 0.2, 0.3), "windows": 3}), tmp_path / "run",
              progress=False, log=lambda m: None)
    ck = train(cfg, tmp_path / "run", progress=False, log=lambda m: None)
    assert torch.load(ck, weights_only=False)["iteration"] == 20
