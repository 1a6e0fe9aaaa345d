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
    tg = build_targets(ds, METHODS["spikelik"], SIZE, SIZE, progress=False)
    n_train = len(ds.splits["train"])
    assert tg.values.shape == (8 * n_train, SIZE * SIZE) and np.all(tg.frames == 32)
    first, last = tg.poses[0], tg.poses[7]
    assert np.abs(first[:3, 3] - last[:3, 3]).max() > 0.5  # the camera moved between the windows
    whole = build_targets(ds, METHODS["spikenerf"], SIZE, SIZE, progress=False)
    assert whole.values.shape == (n_train, SIZE * SIZE)
    assert np.allclose(tg.values.reshape(n_train, 8, -1).sum(axis=1), whole.values)


def test_spikelik_trains_on_moving_views(moving, tmp_path):
    cfg = TrainConfig(dataset=str(moving), iters=60, device="cpu", batch_rays=512, grid_start=16, grid_final=32,
                      occupancy_after=20, occupancy_every=10)
    ck = train(cfg, tmp_path / "run", progress=False, log=lambda m: None)
    state = torch.load(ck, weights_only=False)
    assert state["iteration"] == 60 and torch.isfinite(state["state"]["grid"]).all()
