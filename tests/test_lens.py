"""The radial lens (spikegen.lens): the model, the generator's warp, the trainer's rays, the formats."""
import json

import numpy as np
import pytest
import torch
from PIL import Image

from spikegen import lens
from spikegen.cli import main
from spikegen.errors import InputError
from spikegen.formats import Intrinsics, SpikeBlock
from spikegen.spikeio import read_dat, read_png


@pytest.mark.parametrize("k1", [-1.0, -0.25, -0.05, 0.05, 0.3, 1.0])
def test_undistort_inverts_distort_up_to_the_fold(k1):
    reach = min(0.8, 0.999 * lens.max_distorted_radius(k1))
    rng = np.random.default_rng(int(abs(k1) * 100))
    r, phi = reach * np.sqrt(rng.random(4000)), 2 * np.pi * rng.random(4000)
    xd, yd = r * np.cos(phi), r * np.sin(phi)
    xu, yu = lens.undistort(xd, yd, k1)
    back = lens.distort(xu, yu, k1)
    np.testing.assert_allclose(back[0], xd, rtol=0, atol=1e-14)
    np.testing.assert_allclose(back[1], yd, rtol=0, atol=1e-14)
    assert np.all(np.hypot(xu, yu) * k1 <= np.hypot(xd, yd) * k1 + 1e-15)  # pincushion pulls in, barrel pushes out
    # the same function on torch tensors (the trainer's rays) gives the same numbers
    t = lens.undistort(torch.from_numpy(xd), torch.from_numpy(yd), k1)
    np.testing.assert_array_equal(t[0].numpy(), xu)


def test_a_barrel_that_folds_before_the_corners_is_refused():
    w, h, f = 400, 250, 300.0
    corner = lens.corner_radius(w, h, f, f, 200.0, 125.0)
    k_fold = -4.0 / (27.0 * corner ** 2)  # max_distorted_radius(k) == corner
    assert lens.max_distorted_radius(k_fold) == pytest.approx(corner)
    assert lens.lens_problem(k_fold * 0.99, w, h, f, f, 200.0, 125.0) is None
    assert "folds" in lens.lens_problem(k_fold * 1.01, w, h, f, f, 200.0, 125.0)
    assert "finite" in lens.lens_problem(float("nan"), w, h, f, f, 200.0, 125.0)


def test_warp_reads_the_pinhole_image_where_the_lens_looks():
    h, w, f, k1 = 50, 80, 60.0, 0.2
    v, u = np.mgrid[0:h, 0:w] + 0.5
    ramp = np.stack([u, v]).astype(np.float32)  # two images: each pixel centre's own coordinates
    out = lens.warp_to_lens(ramp, k1, f, f, w / 2, h / 2)
    xu, yu = lens.undistort((u - w / 2) / f, (v - h / 2) / f, k1)
    # bilinear interpolation is exact on a linear image: every output pixel holds where it looked
    np.testing.assert_allclose(out[0], xu * f + w / 2, atol=1e-4)
    np.testing.assert_allclose(out[1], yu * f + h / 2, atol=1e-4)
    assert np.array_equal(lens.warp_to_lens(ramp, 0.0, f, f, w / 2, h / 2), ramp)  # no lens: the image itself
    # a pincushion lens shows less of the scene: the corner pixel looks inside the pinhole image
    assert out[0, 0, 0] > 0.5 and out[1, 0, 0] > 0.5


@pytest.mark.parametrize("k1", [0.0, 0.15, -0.1])
def test_trainer_rays_land_on_their_pixels_through_the_generator_lens(k1):
    from spikenerf.render import pixel_rays

    h, w = 30, 44
    fx, fy, cx, cy = 40.0, 42.0, 21.3, 15.8
    rot = torch.tensor(np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))[0], dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3], pose[:3, 3] = rot, torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    pix = torch.arange(h * w)
    cam = (fx, fy, cx, cy, k1) if k1 else (fx, fy, cx, cy)
    o, d = pixel_rays(pose.expand(h * w, 4, 4), pix, h, w, cam)
    p = o + 2.5 * d  # a point on each ray, in the camera's frame (OpenGL axes: -z forward, y up) ...
    local = (p - pose[:3, 3]) @ rot
    xu, yu = local[:, 0] / -local[:, 2], -local[:, 1] / -local[:, 2]  # ... to normalised, y down
    xd, yd = lens.distort(xu.numpy(), yu.numpy(), k1)  # imaged through the generator's lens model
    np.testing.assert_allclose(xd * fx + cx, (pix % w).numpy() + 0.5, atol=1e-9)
    np.testing.assert_allclose(yd * fy + cy, (pix // w).numpy() + 0.5, atol=1e-9)


def test_intrinsics_write_and_read_k1_as_nerfstudio_does():
    spike = SpikeBlock(250, 400, 100, 1, 64.0, background=None)
    k = Intrinsics(300.0, 301.0, 200.0, 125.0, 400, 250, 0.08)
    doc = k.to_json()
    assert doc["camera_model"] == "OPENCV" and doc["k1"] == 0.08
    assert Intrinsics.from_json(doc, "t.json", spike) == k
    assert "k1" not in Intrinsics(300.0, 301.0, 200.0, 125.0, 400, 250).to_json()  # pinhole: no lens keys
    with pytest.raises(InputError, match="k2 = 0.01 is not modelled"):
        Intrinsics.from_json({**doc, "k2": 0.01}, "t.json", spike)
    assert Intrinsics.from_json({**doc, "k2": 0.0, "p1": 0}, "t.json", spike) == k  # zeros are no lens
    with pytest.raises(InputError, match="folds the image"):
        Intrinsics.from_json({**doc, "k1": -2.0}, "t.json", spike)


def _textured_nerf(root, n=2, size=24):
    (root / "train").mkdir(parents=True)
    frames = []
    v, u = np.mgrid[0:size, 0:size]
    for i in range(n):
        img = np.zeros((size, size, 4), np.uint8)
        img[..., :3] = (((u // 4 + v // 4 + i) % 2) * 200 + 30)[..., None]
        img[..., 3] = 255
        Image.fromarray(img).save(root / "train" / f"r_{i}.png")
        m = np.eye(4)
        m[2, 3] = 4.0 + i
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": m.tolist()})
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.6911112070083618, "frames": frames}))
    return root


def test_convert_through_a_lens_warps_the_views_and_the_trainer_reads_k1(tmp_path, capsys):
    src = _textured_nerf(tmp_path / "tex")
    args = ["convert", str(src), "--intensity", "64", "--sensor", "ideal", "--frames", "64"]
    assert main(args + ["--out", str(tmp_path / "pin")]) == 0
    assert main(args + ["--out", str(tmp_path / "lens"), "--lens-k1", "0.2"]) == 0
    pin, bent = tmp_path / "pin" / "tex_i64", tmp_path / "lens" / "tex_i64"
    doc = json.loads((bent / "transforms_train.json").read_text())
    f = 0.5 * 24 / np.tan(0.5 * 0.6911112070083618)
    assert doc["k1"] == 0.2 and doc["camera_model"] == "OPENCV" and doc["fl_x"] == pytest.approx(f)
    assert (doc["cx"], doc["cy"], doc["w"], doc["h"]) == (12.0, 12.0, 24, 24)
    assert "k1" not in json.loads((pin / "transforms_train.json").read_text())
    manifest = json.loads((bent / "manifest.json").read_text())["parameters"]
    assert manifest["lens_k1"] == 0.2 and "lens_k1" not in json.loads((pin / "manifest.json").read_text())["parameters"]
    # the spikes and the ground truth are the warped image's: equal to a warp of the pinhole PNG
    want = lens.warp_to_lens(np.moveaxis(read_png(src / "train" / "r_0.png") * 255.0, -1, 0), 0.2, f, f, 12.0, 12.0)
    got = np.moveaxis(read_png(bent / "train" / "r_0.png") * 255.0, -1, 0)
    np.testing.assert_allclose(got, np.clip(np.round(want), 0, 255), atol=0)
    assert not np.array_equal(read_dat(bent / "train" / "r_0.dat", 24, 24), read_dat(pin / "train" / "r_0.dat", 24, 24))
    from spikenerf.data import load_dataset

    cam = load_dataset(bent).camera(12, 12)
    assert cam == pytest.approx((f / 2, f / 2, 6.0, 6.0, 0.2))
    assert main(["verify", str(bent)]) == 0
    capsys.readouterr()
    # a barrel lens cannot be made from a pinhole render: one line, nothing written
    assert main(args + ["--out", str(tmp_path / "barrel"), "--lens-k1", "-0.1"]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "barrel" in err and not (tmp_path / "barrel").exists()


def test_a_field_trains_and_evaluates_through_the_lens(tmp_path):
    from spikenerf.config import TrainConfig
    from spikenerf.eval import evaluate
    from spikenerf.train import checkpoint_camera, load_checkpoint, train

    src = _textured_nerf(tmp_path / "tex", n=3)
    assert main(["convert", str(src), "--intensity", "64", "--sensor", "ideal", "--frames", "64", "--lens-k1", "0.2",
                 "--out", str(tmp_path / "lens")]) == 0
    run = tmp_path / "run"
    train(TrainConfig(dataset=str(tmp_path / "lens" / "tex_i64"), iters=3, device="cpu", batch_rays=64), run,
          progress=False, log=lambda *a: None)
    ck = load_checkpoint(run / "checkpoint.pt", "cpu")
    assert checkpoint_camera(ck)[2][4] == 0.2  # the lens travels with the checkpoint to eval and render
    metrics = evaluate(run, device="cpu", progress=False)
    assert np.isfinite(metrics["psnr"])
