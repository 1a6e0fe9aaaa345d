"""The records every tool passes on (spikegen.formats): round trips, value checks, golden bytes."""
import json
import math
import shutil

import numpy as np
import pytest

from _golden import golden_tree
from _scale_helpers import make_nerf, run_spikegen
from spikegen import formats as F
from spikegen.camera import make_views
from spikegen.dataset import convert
from spikegen.errors import InputError
from spikegen.spikeio import read_spikes

GOLDEN = F.Path(__file__).resolve().parent / "data" / "golden_convert.json"


def test_conversion_bytes_match_the_checked_in_digests(tmp_path):
    """Every file of a fixed conversion, byte for byte (tests/_golden.py says how to regenerate)."""
    expected = json.loads(GOLDEN.read_text())
    got = golden_tree(tmp_path)
    assert sorted(got) == sorted(expected)
    assert [k for k in expected if got[k] != expected[k]] == []


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("fmt")
    src = make_nerf(root / "src" / "blob", views=3, size=16, seed=1, splits=("train", "test"))
    return convert(src, root / "out", [32], sensor="ideal", frames=16, progress=False)[0]


def _copy(dataset, tmp_path):
    dst = tmp_path / "ds"
    shutil.copytree(dataset, dst)
    return dst


def _edit(path, change):
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


# ---------------------------------------------------------------------- round trips
def test_view_record_round_trips_through_render_json_and_transforms(tmp_path):
    v = make_views("train", 2, subframes=3, motion_deg=2.0)[1]
    entry = json.loads(json.dumps(v.render_entry()))
    back = F.ViewRecord.from_render_entry(entry, "train", 1, 3, tmp_path, "render.json train view 1")
    assert back.index == 1 and np.array_equal(back.pose, v.pose) and np.array_equal(back.subframe_poses,
                                                                                    v.subframe_poses)
    assert back.exrs[2] == tmp_path / "train" / "r_1_sub02.exr" and back.png == tmp_path / "train" / "r_1.png"
    frame = json.loads(json.dumps(v.transforms_frame()))
    assert list(frame) == ["file_path", "transform_matrix", "spike_path", "subframe_transform_matrices"]
    again = F.ViewRecord.from_transforms_frame(frame, "train", 1, tmp_path, "t.json frame 1")
    assert again.spikes == tmp_path / "train" / "r_1.dat" and np.array_equal(again.subframe_poses, v.subframe_poses)
    assert not again.is_static() and F.ViewRecord("train", 0, v.pose, v.pose[None]).is_static()


def test_spike_block_writes_integer_intensities_and_reads_old_blocks():
    block = F.SpikeBlock(400, 400, 256, 16, 32.0)
    d = block.to_json()
    assert d["intensity"] == 32 and isinstance(d["intensity"], int) and d["background"] == "white"
    assert F.SpikeBlock(8, 8, 4, 1, 12.5).to_json()["intensity"] == 12.5
    old = {k: v for k, v in d.items() if k != "background"}  # written before the key existed
    back = F.SpikeBlock.from_json(old, "old.json")
    assert back.background is None and back.intensity == 32.0 and back.dat_bytes == 256 * 400 * 400 // 8


def test_render_job_header_and_its_differences():
    job = F.RenderJob("lego", 64, 64, (2, 1, 1), samples=4, png_samples=2)
    header = json.loads(json.dumps(job.header()))
    assert header["format"] == F.RENDER_FORMAT and header["png_samples"] == 4  # never below the sub-frames'
    assert header["views"] == {"train": 2, "val": 1, "test": 1} and job.differences(header) == []
    assert F.RenderJob("lego", 64, 64, (2, 1, 1), samples=8).differences(header) == ["samples", "png_samples"]


def test_convert_params_match_across_int_and_float_intensity():
    p = F.ConvertParams("src", "nerf", "lego", 32.0, "paper", 256, 1, 8, 8, 0)
    assert p.to_json()["intensity"] == 32 and p.matches({**p.to_json(), "intensity": 32.0})
    assert not p.matches({**p.to_json(), "seed": 1}) and not p.matches(None)


def test_manifest_round_trip_and_malformed_entries(tmp_path):
    m = F.Manifest("spikegen 0", {"seed": 0}, 0, (F.FileEntry("a.dat", 3, "ab"),))
    path = tmp_path / "manifest.json"
    doc = m.to_json()
    doc["files"].append({"path": "b.dat"})  # no size, no digest
    path.write_text(json.dumps(doc))
    back, bad = F.Manifest.read(path)
    assert back.digests() == {"a.dat": "ab"} and bad == [{"path": "b.dat"}]


def test_spikecv_config_names_the_size_and_the_files(tmp_path):
    text = F.spikecv_config(F.SpikeBlock(250, 400, 100, 1, 64), ["train/r_0.dat"])
    (tmp_path / "config.yaml").write_text(text)
    assert F.read_spikecv_size(tmp_path / "config.yaml") == (400, 250)
    assert "  - train/r_0.dat\n" in text


# ---------------------------------------------------------------------- values, not only keys
@pytest.mark.parametrize("bad, why", [
    (np.full((4, 4), np.nan), "non-finite"),
    (np.diag([2.0, 2.0, 2.0, 1.0]), "not rigid"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "not rigid"),  # a reflection
    (np.eye(3), "must be 4 x 4"),
    ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "0 0 0 1"),
])
def test_bad_poses_are_refused_with_a_reason(bad, why):
    m, msg = F.pose_problem(bad)
    assert m is None and why in msg
    assert F.pose_problem(np.eye(4))[1] is None


@pytest.mark.parametrize("change, words", [
    (lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(0, math.nan), ["frame 1", "non-finite"]),
    (lambda d: d["frames"][2].__setitem__("transform_matrix", (3 * np.eye(4)).tolist()), ["frame 2", "not rigid"]),
    (lambda d: d["spike"].__setitem__("width", 0), ["spike width must be a positive integer"]),
    (lambda d: d.__setitem__("camera_angle_x", -0.5), ["camera_angle_x"]),
    (lambda d: d["spike"].__setitem__("frames", 32), ["frame 0", "r_0.dat is 512 bytes", "32 frames"]),
    (lambda d: d["frames"][0].__setitem__("subframe_transform_matrices", [[[1.0]]]), ["frame 0", "K x 4 x 4"]),
])
def test_trainer_refuses_a_dataset_whose_values_are_wrong(dataset, tmp_path, change, words):
    from spikenerf.data import load_dataset

    ds = _copy(dataset, tmp_path)
    _edit(ds / "transforms_train.json", change)
    with pytest.raises(InputError) as err:
        load_dataset(ds)
    assert "transforms_train.json" in str(err.value) and all(w in str(err.value) for w in words)


def test_spikenerf_train_on_a_nan_pose_exits_with_one_line(dataset, tmp_path):
    pytest.importorskip("torch")
    from click.testing import CliRunner

    from spikenerf.cli import main

    ds = _copy(dataset, tmp_path)
    _edit(ds / "transforms_train.json", lambda d: d["frames"][0]["transform_matrix"][1].__setitem__(2, math.nan))
    res = CliRunner().invoke(main, ["train", str(ds), "--iters", "2", "--out", str(tmp_path / "run"), "--quiet"])
    assert res.exit_code == 2 and res.output.count("\n") == 1 and "frame 0" in res.output
    assert not (tmp_path / "run").exists()


def test_an_old_dataset_folder_still_loads_in_the_trainer(dataset, tmp_path):
    """Folders written before the background key and config.yaml, with the intensity as a float."""
    from spikenerf.data import load_dataset, read_view_spikes

    ds = _copy(dataset, tmp_path)
    (ds / "config.yaml").unlink()
    for split in ("train", "test"):
        def old(d):
            del d["spike"]["background"]
            d["spike"]["intensity"] = 32.0
        _edit(ds / f"transforms_{split}.json", old)
    loaded = load_dataset(ds)
    assert loaded.intensity == 32.0 and loaded.spike.background is None and len(loaded.splits["test"]) == 3
    assert read_view_spikes(loaded, loaded.splits["train"][0]).shape == (16, 16, 16)


def test_a_dat_read_at_another_size_than_its_config_fails_loudly(dataset):
    dat = dataset / "train" / "r_0.dat"
    assert read_spikes(dat).shape == (16, 16, 16)  # the size comes from config.yaml
    with pytest.raises(InputError, match="config.yaml says the streams are 16x16"):
        read_spikes(dat, size=(8, 32))  # 256 bits a frame either way: it would decode silently
    res = run_spikegen("info", dat, "--size", "32x8")
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "16x16" in res.stderr


def test_a_split_whose_spike_block_disagrees_is_refused(dataset, tmp_path):
    from spikenerf.data import load_dataset

    ds = _copy(dataset, tmp_path)
    _edit(ds / "transforms_test.json", lambda d: d["spike"].update(width=8, height=32))
    with pytest.raises(InputError, match="transforms_test.json: spike block says 16 frames of 8x32"):
        load_dataset(ds)


def test_a_val_split_is_the_held_out_set_when_there_is_no_test_split(tmp_path):
    """As NeRF papers report: train on every train view, evaluate on views never trained on."""
    from spikenerf.data import load_dataset

    src = make_nerf(tmp_path / "src" / "tv", views=9, size=16, seed=2, splits=("train", "val"))
    ds = load_dataset(convert(src, tmp_path / "out", [32], sensor="ideal", frames=8, progress=False)[0])
    assert ds.heldout == "val" and not ds.holdout
    assert len(ds.splits["train"]) == 9 and [v.name for v in ds.splits["test"]] == [f"val/r_{i}" for i in range(9)]
    only_train = make_nerf(tmp_path / "src" / "t", views=9, size=16, seed=2)
    ds = load_dataset(convert(only_train, tmp_path / "out", [32], sensor="ideal", frames=8, progress=False)[0])
    assert ds.heldout == "train every 8th" and [v.name for v in ds.splits["test"]] == ["train/r_0", "train/r_8"]
    assert len(ds.splits["train"]) == 7


def test_training_with_calibrated_maps_uses_them_and_a_bad_file_is_one_line(dataset, tmp_path):
    pytest.importorskip("torch")
    from click.testing import CliRunner

    from spikegen.sensor import Sensor
    from spikegen.sensorfile import save_sensor
    from spikenerf.cli import main
    from spikenerf.data import load_dataset, load_sensor_maps

    resp = np.full((16, 16), 1.25)
    json_path, _ = save_sensor(Sensor("cal", responsivity=resp, dark_rate=np.full((16, 16), 0.01)), tmp_path / "cal")
    maps = load_sensor_maps(load_dataset(dataset), str(json_path))
    assert np.allclose(maps.resp, 1.25) and np.allclose(maps.dark, 0.01) and maps.kind == "if"
    run = tmp_path / "run"
    res = CliRunner().invoke(main, ["train", str(dataset), "--iters", "2", "--out", str(run), "--quiet",
                                    "--sensor-maps", str(json_path), "--batch-rays", "64"])
    assert res.exit_code == 0, res.output
    assert json.loads((run / "config.json").read_text())["sensor_maps"] == str(json_path.resolve())
    res = CliRunner().invoke(main, ["train", str(dataset), "--iters", "2", "--out", str(tmp_path / "bad"),
                                    "--quiet", "--sensor-maps", str(tmp_path / "none.json")])
    assert res.exit_code == 2 and "none.json" in res.output and not (tmp_path / "bad").exists()
