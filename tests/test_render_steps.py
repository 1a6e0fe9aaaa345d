"""spikegen.render without Blender: a stand-in renderer drives render_steps, so resume, render.json,
temporaries and the conversion of a render folder are tested wherever the tests run."""
import json

import numpy as np
import pytest

from spikegen.errors import OutputError
from spikegen.formats import RenderDoc, RenderJob
from spikegen.render import RenderFolder, check_export, convert_all, render_steps, rig_of, view_paths
from spikegen.spikeio import write_png

pytest.importorskip("OpenEXR")
JOB = RenderJob("stand", 16, 16, (3, 1, 0), subframes=2, frames=32, motion_deg=4.0, engine="cycles", samples=1)


class StandIn:
    """Writes an image that depends only on the pose and the view seed (as Cycles' does)."""

    def __init__(self):
        self.seeds, self.calls = [], []

    def set_view_seed(self, seed):
        self.seeds.append(seed)

    def _image(self, pose):
        from spikegen.camera import project

        x, y = project(np.zeros((1, 3)), pose, 16, 16)[0]
        yy, xx = np.mgrid[0:16, 0:16]
        alpha = np.clip(4.0 - np.hypot(xx - x, yy - y), 0, 1)
        rgb = alpha[..., None] * np.array([0.8, 0.5, 0.2]) * (1 + (self.seeds[-1] % 7) / 100)
        return np.concatenate([rgb, alpha[..., None]], axis=2).astype(np.float32)

    def render_exr(self, pose, path):
        from spikegen.spikeio import write_exr

        self.calls.append(path)
        write_exr(path, self._image(pose))

    def render_png(self, pose, path):
        self.calls.append(path)
        write_png(path, np.clip(np.round(self._image(pose) * 255), 0, 255).astype(np.uint8))


def _run(out, job=JOB, stop_after=None):
    folder = RenderFolder.open(out, job)
    steps = render_steps(folder, StandIn())
    for n, _ in enumerate(steps, 1):
        if n == stop_after:
            steps.close()  # what Ctrl-C, Esc or an exception does between two images
            break
    return folder


def _tree(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_render_json_lists_every_view_as_the_rig_says(tmp_path):
    folder = _run(tmp_path)
    doc = RenderDoc.read(folder.path / "render.json")
    rig = rig_of(JOB)
    assert [(v.split, v.index) for v in doc.views] == [("train", 0), ("train", 1), ("train", 2), ("val", 0)]
    assert all(np.array_equal(v.subframe_poses, rig[v.split][v.index].subframe_poses) for v in doc.views)
    assert JOB.differences(doc.header) == [] and folder.complete()


def test_an_interrupted_render_leaves_no_partial_view_and_resumes_to_the_same_bytes(tmp_path):
    whole = _run(tmp_path / "a")
    part = _run(tmp_path / "b", stop_after=4)  # view 0 (2 EXR + PNG) and one EXR of view 1
    doc = json.loads((part.path / "render.json").read_text())
    assert [e["index"] for e in doc["splits"]["train"]] == [0]
    png, exrs = view_paths(part.path, rig_of(JOB)["train"][1])
    assert not any(p.exists() for p in [png, *exrs]) and not list(part.path.rglob("*.part"))
    resumed = RenderFolder.open(tmp_path / "b", JOB)
    assert [(v.split, v.index) for v in resumed.pending()] == [("train", 1), ("train", 2), ("val", 0)]
    _run(tmp_path / "b")
    assert _tree(whole.path) == _tree(resumed.path)


def test_temporaries_of_a_killed_write_are_removed_on_resume(tmp_path):
    folder = _run(tmp_path, stop_after=3)
    stale = folder.path / "train" / ".r_1_sub00.exr.12345.part"
    stale.write_bytes(b"half an image")
    RenderFolder.open(tmp_path, JOB)
    assert not stale.exists()


def test_a_finished_view_whose_file_was_deleted_is_rendered_again(tmp_path):
    folder = _run(tmp_path)
    before = _tree(folder.path)
    _, exrs = view_paths(folder.path, rig_of(JOB)["train"][2])
    exrs[1].unlink()
    again = RenderFolder.open(tmp_path, JOB)
    assert [(v.split, v.index) for v in again.pending()] == [("train", 2)]
    _run(tmp_path)
    assert _tree(folder.path) == before


def test_other_settings_or_a_foreign_folder_are_refused(tmp_path):
    _run(tmp_path)
    with pytest.raises(OutputError, match=r"other settings \(motion_deg\)"):
        RenderFolder.open(tmp_path, RenderJob("stand", 16, 16, (3, 1, 0), subframes=2, frames=32, samples=1))
    foreign = tmp_path / "x_render"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="not a render folder"):
        RenderFolder.open(tmp_path, RenderJob("x", 16, 16, (1, 0, 0)))


def test_a_render_folder_converts_to_verified_datasets_at_every_intensity(tmp_path):
    from spikegen.dataset import verify

    folder = _run(tmp_path)
    outs = convert_all(folder, tmp_path, [16, 32], sensor="ideal", progress=False)
    assert [o.name for o in outs] == ["stand_i16", "stand_i32"]
    assert all(verify(o) == [] for o in outs)
    t = json.loads((outs[1] / "transforms_train.json").read_text())
    assert t["spike"]["subframes"] == 2 and len(t["frames"][0]["subframe_transform_matrices"]) == 2
    man = json.loads((outs[1] / "manifest.json").read_text())
    assert man["parameters"]["render"]["motion_deg"] == 4.0 and man["parameters"]["intensity"] == 32


def test_convert_all_refuses_an_unfinished_folder(tmp_path):
    folder = _run(tmp_path, stop_after=4)  # view 0 recorded, view 1 cut short
    with pytest.raises(OutputError, match="3 views are not rendered yet"):
        convert_all(RenderFolder.open(tmp_path, JOB), tmp_path, [16], progress=False)
    assert folder.path.is_dir() and not (tmp_path / "stand_i16").exists()


def test_the_export_check_names_every_problem_before_rendering():
    bad = RenderJob("s", 10, 10, (0, 0, 0), samples=0)
    msgs = check_export(bad, [16, 5000, "x"], "papr", 0)
    assert len(msgs) == 6, msgs
    assert any("width*height a multiple of 8" in m for m in msgs) and any("--views" in m for m in msgs)
    assert any("--samples 0" in m for m in msgs) and any("above 4096" in m for m in msgs)
    assert any("'x': expected a number" in m for m in msgs) and any("unknown sensor 'papr'" in m for m in msgs)
    assert check_export(JOB, [16], "ideal", 0) == []


def test_the_device_is_recorded_and_a_folder_is_not_finished_on_another(tmp_path):
    gpu = RenderJob("stand", 16, 16, (2, 0, 0), subframes=2, frames=32, samples=1, device="gpu:CUDA")
    _run(tmp_path, gpu, stop_after=4)
    assert json.loads((tmp_path / "stand_render" / "render.json").read_text())["device"] == "gpu:CUDA"
    cpu = RenderJob("stand", 16, 16, (2, 0, 0), subframes=2, frames=32, samples=1)
    with pytest.raises(OutputError, match=r"other settings \(device\)"):
        RenderFolder.open(tmp_path, cpu)
    assert RenderFolder.open(tmp_path, gpu).pending()[0].index == 1


def test_a_render_json_from_before_the_device_key_resumes_as_a_cpu_render(tmp_path):
    folder = _run(tmp_path, stop_after=4)
    doc = json.loads((folder.path / "render.json").read_text())
    del doc["device"]
    (folder.path / "render.json").write_text(json.dumps(doc))
    assert [v.index for v in RenderFolder.open(tmp_path, JOB).pending()][:1] == [1]
    with pytest.raises(OutputError, match="device"):
        RenderFolder.open(tmp_path, RenderJob(**{**JOB.__dict__, "device": "gpu:OPTIX"}))
