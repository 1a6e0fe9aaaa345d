"""`spikegen convert` / `verify` / `info` / `preview`: dataset folders as dataset.md says."""
import json

import numpy as np
import pytest
from PIL import Image

from spikegen.cli import main
from spikegen.dataset import convert, verify
from spikegen.spikeio import read_dat, read_png


def _nerf_folder(root, n=3, size=16, value=255, alpha=255):
    (root / "train").mkdir(parents=True)
    frames = []
    for i in range(n):
        img = np.full((size, size, 4), value, np.uint8)
        img[..., 3] = alpha
        Image.fromarray(img).save(root / "train" / f"r_{i}.png")
        m = np.eye(4)
        m[2, 3] = 4.0311 + i
        frames.append({"file_path": f"./train/r_{i}", "rotation": 0.1, "transform_matrix": m.tolist()})
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.6911112070083618, "frames": frames}))
    return root


def test_white_input_gives_intensity_spikes_end_to_end(tmp_path):
    src = _nerf_folder(tmp_path / "white")
    assert main([
        "convert", str(src), "--intensity", "32", "--sensor", "ideal", "--out", str(tmp_path / "o")]) == 0
    for i in range(3):
        counts = read_dat(tmp_path / "o" / "white_i32" / "train" / f"r_{i}.dat", 16, 16).sum(0)
        assert counts.min() == counts.max() == 32


def test_lego_dataset_follows_the_spec(tmp_path, lego_dir):
    out = convert(lego_dir, tmp_path, [16, 64], sensor="paper", resolution=32, progress=False)
    assert [p.name for p in out] == ["nerf_synthetic_lego_400_i16", "nerf_synthetic_lego_400_i64"]
    d = out[1]
    doc = json.loads((d / "transforms_train.json").read_text())
    assert doc["camera_angle_x"] == pytest.approx(0.6911112070083618)
    assert doc["spike"] == {"height": 32, "width": 32, "frames": 256, "subframes": 1, "intensity": 64,
                            "readout_hz": 20000, "format": "dat", "background": "white"}
    assert isinstance(doc["spike"]["intensity"], int)  # written as the integer it was given
    assert len(doc["frames"]) == 100
    f0 = doc["frames"][0]
    assert f0["file_path"] == "./train/r_0" and f0["spike_path"] == "./train/r_0.dat"
    assert f0["subframe_transform_matrices"] == [f0["transform_matrix"]]
    src = json.loads((lego_dir / "transforms_train.json").read_text())["frames"][0]["transform_matrix"]
    np.testing.assert_allclose(f0["transform_matrix"], src)
    assert (d / "train" / "r_0.dat").stat().st_size == 256 * 32 * 32 // 8
    gt = read_png(d / "train" / "r_0.png")
    assert gt.shape == (32, 32, 4) and 0 < gt[..., 3].mean() < 1  # RGBA, object + transparent film
    assert (d / "sensor.json").is_file() and (d / "sensor.npz").is_file()
    man = json.loads((d / "manifest.json").read_text())
    assert man["parameters"]["intensity"] == 64 and man["seed"] == 0 and man["generator"].startswith("spikegen")
    # train and val: 100 views each, a PNG and a .dat per view; 2 transforms, the sensor pair, config.yaml
    assert len(man["files"]) == 2 * 100 * 2 + 2 + 2 + 1
    cfg = (d / "config.yaml").read_text()
    assert "spike_h: 32\nspike_w: 32\n" in cfg and "  - val/r_99.dat\n" in cfg
    assert verify(d) == []
    # brighter intensity, more spikes; object darker than background
    lo = read_dat(out[0] / "train" / "r_0.dat", 32, 32).mean()
    hi = read_dat(d / "train" / "r_0.dat", 32, 32).mean()
    assert 3.5 < hi / lo < 4.5


def test_convert_is_deterministic_and_resumable(tmp_path):
    src = _nerf_folder(tmp_path / "s", n=4, value=128, alpha=200)
    a = convert(src, tmp_path / "a", [32], progress=False)[0]
    b = convert(src, tmp_path / "b", [32], progress=False)[0]
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    (b / "train" / "r_2.dat").unlink()  # an interrupted run: rerun redoes only what is missing
    convert(src, tmp_path / "b", [32], progress=False)
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)


def test_verify_names_damaged_files(tmp_path, capsys):
    d = convert(_nerf_folder(tmp_path / "s"), tmp_path / "o", [32], progress=False)[0]
    assert main(["verify", str(d)]) == 0
    with open(d / "train" / "r_1.dat", "r+b") as fh:
        fh.truncate(10)
    (d / "train" / "r_0.png").write_bytes((d / "train" / "r_0.png").read_bytes()[:-1] + b"x")
    (d / "train" / "r_2.dat").unlink()
    assert main(["verify", str(d)]) == 1
    err = capsys.readouterr().err
    assert "truncated: train/r_1.dat" in err and "altered: train/r_0.png" in err and "missing: train/r_2.dat" in err


def test_info_and_preview(tmp_path, capsys):
    d = convert(_nerf_folder(tmp_path / "s", value=200), tmp_path / "o", [64], sensor="ideal", progress=False)[0]
    assert main(["info", str(d / "train" / "r_0.dat"), "--size", "16x16"]) == 0
    out = capsys.readouterr().out
    assert "frames: 256" in out and "size: 16x16" in out
    png = tmp_path / "p.png"
    assert main(["preview", str(d / "train" / "r_0.dat"), "--size", "16x16", "--out", str(png)]) == 0
    img = np.asarray(Image.open(png))
    assert img.shape == (16, 36) and img.max() > 200


def test_existing_folder_of_another_job_is_not_overwritten(tmp_path, capsys):
    src = _nerf_folder(tmp_path / "s")
    d = convert(src, tmp_path / "o", [32], progress=False)[0]
    before = {p: p.read_bytes() for p in d.rglob("*") if p.is_file()}
    assert main(["convert", str(src), "--intensity", "32", "--seed", "5", "--out", str(tmp_path / "o")]) == 3
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "other parameters" in err
    assert before == {p: p.read_bytes() for p in d.rglob("*") if p.is_file()}


def test_lower_resolution_is_the_pixel_area_mean():
    """A sensor pixel integrates the light on its area: --resolution block-averages (no ringing)."""
    from spikegen.dataset import _resize

    rng = np.random.default_rng(3)
    img = (rng.random((64, 64)) < 0.5).astype(np.float32) * 4.0  # sharp edges everywhere
    small = _resize(img, 16)
    np.testing.assert_allclose(small, img.reshape(16, 4, 16, 4).mean(axis=(1, 3)), atol=1e-6)
    odd = _resize(img, 24)  # not an integer factor: area weights, still within the input's range
    assert odd.shape == (24, 24) and odd.min() >= 0.0 and odd.max() <= 4.0
    assert abs(float(odd.mean()) - float(img.mean())) < 0.05  # area weights keep the mean (random input: ~1 %)
