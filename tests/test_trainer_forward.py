"""spikenerf on a forward-facing capture laid out as `spikegen import` writes it (CaptureTransforms):
per-axis focal lengths and an off-centre principal point on non-square images, a scene that fills
the frame (no white composite), evaluation against each view's own reconstruction; a folder
without intrinsics keeps the NeRF-synthetic camera and the white composite."""
import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.torch

from click.testing import CliRunner  # noqa: E402

from spikegen.formats import CaptureTransforms, Intrinsics, SpikeBlock, ViewRecord  # noqa: E402
from spikegen.spikeio import linear_to_srgb, write_dat, write_json_atomic, write_png  # noqa: E402
from spikenerf.cli import main  # noqa: E402
from spikenerf.data import BLACK, WHITE, load_dataset  # noqa: E402
from spikenerf.eval import reference  # noqa: E402
from spikenerf.metrics import psnr  # noqa: E402
from spikenerf.render import pixel_rays  # noqa: E402

W, H, FRAMES, INTENSITY = 40, 24, 400, 64.0
K = Intrinsics(fl_x=36.0, fl_y=33.0, cx=18.5, cy=13.0, w=W, h=H)  # non-square pixels, off-centre
CAM_Z, CARD_Z, WALL_Z = 1.0, 0.0, -0.8  # cameras look down -z at a card in front of a textured wall
SUPER = 3  # supersampling of the analytic images (per axis)


def _radiance(pose: np.ndarray) -> np.ndarray:
    """Linear luminance [H, W] of the scene seen from ``pose`` (3 x 3 supersampled)."""
    s = (np.arange(SUPER) + 0.5) / SUPER
    col = (np.arange(W)[None, :, None, None] + s[None, None, None, :])
    row = (np.arange(H)[:, None, None, None] + s[None, None, :, None])
    d = np.stack(np.broadcast_arrays((col - K.cx) / K.fl_x, -(row - K.cy) / K.fl_y, -np.ones(1)), -1)
    d = d @ pose[:3, :3].T
    o = pose[:3, 3]
    t_card, t_wall = (CARD_Z - o[2]) / d[..., 2], (WALL_Z - o[2]) / d[..., 2]
    xc, yc = o[0] + t_card * d[..., 0], o[1] + t_card * d[..., 1]
    xw, yw = o[0] + t_wall * d[..., 0], o[1] + t_wall * d[..., 1]
    wall = 0.45 + 0.3 * np.sin(2.5 * xw) * np.cos(3.0 * yw)
    card = (np.abs(xc - 0.15) < 0.25) & (np.abs(yc + 0.05) < 0.2)
    return np.where(card, 0.95, wall).mean(axis=(2, 3))


def _spikes(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Ideal integrate-and-fire of rate (I/256) x per frame from a random initial charge: [T, H, W]."""
    lam = x * (INTENSITY / 256.0)
    charge = rng.uniform(0.0, 1.0, x.shape) + lam * np.arange(FRAMES + 1)[:, None, None]
    return np.diff(np.floor(charge), axis=0).astype(np.uint8)


def _poses(count: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Cameras on a jittered 5-column grid of a 0.6 x 0.4 patch at z = CAM_Z, looking down -z."""
    out = []
    for i in range(count):
        m = np.eye(4)
        m[:3, 3] = [-0.3 + 0.15 * (i % 5), 0.2 - 0.13 * (i // 5), CAM_Z] + rng.uniform(-0.03, 0.03, 3)
        out.append(m)
    return out


def make_capture(root, views: int = 20):
    """A capture folder as `spikegen import` writes it (ideal sensor, poses known)."""
    rng = np.random.default_rng(7)
    records = []
    for i, pose in enumerate(_poses(views, rng)):
        spikes = _spikes(_radiance(pose), rng)
        write_dat(root / f"train/r_{i}.dat", spikes)
        write_png(root / f"train/r_{i}.png", linear_to_srgb(np.clip(spikes.mean(0) / spikes.mean(0).max(), 0, 1)))
        records.append(ViewRecord("train", i, pose, pose[None]))
    bounds = np.tile([CAM_Z - CARD_Z, CAM_Z - WALL_Z], (views, 1)) * [0.9, 1.1]
    doc = CaptureTransforms(K, SpikeBlock(H, W, FRAMES, 1, INTENSITY, background=None), tuple(records), bounds,
                            tuple(f"v{i:02d}.dat" for i in range(views)), np.eye(4), "tfp")
    write_json_atomic(root / "transforms_train.json", doc.to_json())
    return root


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return make_capture(tmp_path_factory.mktemp("capture"))


def test_the_capture_is_read_with_its_intrinsics_and_no_background(capture):
    ds = load_dataset(capture)
    assert ds.intrinsics == K and ds.fills_frame and ds.background == BLACK
    assert ds.camera(H // 2, W // 2) == (18.0, 16.5, 9.25, 6.5)
    assert ds.splits["test"][0].extra["image_kind"] == "reconstruction"


def test_pixel_rays_with_intrinsics(capture):
    """(f, f, W/2, H/2) gives the centred camera's rays bit for bit; the principal point's ray is the axis."""
    pix = torch.arange(H * W)
    pose = torch.eye(4).expand(H * W, 4, 4)
    _, d_old = pixel_rays(pose, pix, H, W, 30.0)
    _, d_new = pixel_rays(pose, pix, H, W, (30.0, 30.0, W / 2, H / 2))
    assert torch.equal(d_old, d_new)
    # pixel (18, 12) has its centre at (18.5, 12.5): on the axis horizontally, 0.5 px above it vertically
    _, d = pixel_rays(torch.eye(4)[None], torch.tensor([12 * W + 18]), H, W, (36.0, 33.0, 18.5, 13.0))
    assert d[0, 0] == 0 and d[0, 1] == pytest.approx(0.5 / 33.0, rel=1e-3) and d[0, 2] < 0


def test_forward_facing_training_beats_a_constant_image(capture, tmp_path):
    run = tmp_path / "run"
    res = CliRunner().invoke(main, ["train", str(capture), "--iters", "400", "--device", "cpu", "--out", str(run),
                                    "--quiet", "--eval"])
    assert res.exit_code == 0, res.output
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["compared_with"] == "reconstruction"
    assert "no background" in metrics["compared_as"]
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert ck["background"] == BLACK and len(ck["focal_px"]) == 4
    ds = load_dataset(capture)
    refs = [linear_to_srgb(reference(ds, v, H, W)[1]) for v in ds.splits["test"]]
    constant = float(np.mean(refs))  # the best constant image for the held-out views together
    baseline = float(np.mean([psnr(np.full_like(r, constant), r) for r in refs]))
    assert metrics["views"] == 3 and metrics["psnr"] > baseline + 6.0, (metrics["psnr"], baseline)


def test_a_folder_without_intrinsics_keeps_the_synthetic_camera_and_white(capture, tmp_path):
    doc = json.loads((capture / "transforms_train.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        doc.pop(key)
    (tmp_path / "train").symlink_to(capture / "train")
    write_json_atomic(tmp_path / "transforms_train.json", doc)
    ds = load_dataset(tmp_path)
    assert ds.intrinsics is None and not ds.fills_frame and ds.background == WHITE
    assert ds.camera(H, W) == 0.5 * W / math.tan(0.5 * doc["camera_angle_x"])


@pytest.mark.parametrize("change, words", [({"fl_y": "wide"}, "must all be positive numbers"),
                                           ({"cx": -1.0}, "must all be positive numbers"),
                                           ({"w": 80}, "intrinsics are for 80x24 images")])
def test_bad_intrinsics_are_one_line(capture, tmp_path, change, words):
    doc = json.loads((capture / "transforms_train.json").read_text())
    doc.update(change)
    (tmp_path / "train").symlink_to(capture / "train")
    write_json_atomic(tmp_path / "transforms_train.json", doc)
    res = CliRunner().invoke(main, ["train", str(tmp_path), "--iters", "1", "--out", str(tmp_path / "r")])
    assert res.exit_code != 0 and words in res.output and len(res.output.strip().splitlines()) == 1, res.output


def test_a_training_width_that_does_not_divide_the_height_is_one_line(capture, tmp_path):
    # 40 / 8 = 5 divides the width but not the height (24): the message names both sides
    res = CliRunner().invoke(main, ["train", str(capture), "--iters", "1", "--resolution", "8",
                                    "--out", str(tmp_path / "r")])
    assert res.exit_code != 0 and "40 x 24" in res.output and len(res.output.strip().splitlines()) == 1, res.output
    assert not (tmp_path / "r" / "checkpoint.pt").exists()
