"""Rendering through Blender: the six scenes, the render folder, resume, and the full path to a dataset."""
import json

import numpy as np
import pytest

pytest.importorskip("bpy")

from spikegen import camera as cm  # noqa: E402
from spikegen.cli import main as cli_main  # noqa: E402
from spikegen.render import RenderFolder, RenderJob, convert_all, render_steps, rig_of, view_paths  # noqa: E402
from spikegen.render_blender import BlenderRenderer, RenderSettings, build_bpy_scene, renderer_for  # noqa: E402
from spikegen.scenes import SCENES, build_scene  # noqa: E402
from spikegen.spikeio import read_exr, read_png, read_spikes  # noqa: E402

pytestmark = pytest.mark.blender
SMALL = dict(width=64, height=64, subframes=4, frames=64, samples=2, png_samples=4)


def _render(tmp, job, blend=None):
    folder = RenderFolder.open(tmp, job)
    for _ in render_steps(folder, renderer_for(job, blend)):
        pass
    return folder


@pytest.fixture(scope="module")
def six(tmp_path_factory):
    """64 x 64 renders of every scene, 2 views each (1 train, 1 test)."""
    out = tmp_path_factory.mktemp("six")
    return {n: _render(out, RenderJob(n, views=(1, 0, 1), **SMALL)) for n in SCENES}


@pytest.mark.parametrize("name", sorted(SCENES))
def test_object_visible_and_inside_the_frame(six, name):
    folder = six[name]
    for split in ("train", "test"):
        rgba = read_png(folder.path / split / "r_0.png")
        alpha = rgba[:, :, 3]
        assert rgba.shape == (64, 64, 4)
        assert alpha.mean() > 0.05, f"{name}: object too small or missing"
        border = np.concatenate([alpha[0], alpha[-1], alpha[:, 0], alpha[:, -1]])
        assert border.max() == 0, f"{name}: object touches the frame edge"
        exr = read_exr(folder.path / split / "r_0_sub00.exr")
        assert exr.shape == (64, 64, 4) and np.isfinite(exr).all()
        assert np.abs(exr[:, :, 3] - alpha).mean() < 0.05  # sub-frame and PNG show the same object


def test_scenes_differ(six):
    imgs = {n: read_png(f.path / "train" / "r_0.png") for n, f in six.items()}
    names = sorted(imgs)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert np.abs(imgs[a] - imgs[b]).mean() > 0.02, f"{a} and {b} look the same"


def test_render_json_lists_views_with_poses(six):
    doc = json.loads((six["lego"].path / "render.json").read_text())
    assert doc["format"] == "spikegen-render/1" and doc["scene"] == "lego"
    assert (doc["width"], doc["height"], doc["subframes"]) == (64, 64, 4)
    assert [e["index"] for e in doc["splits"]["train"]] == [0] and doc["splits"]["val"] == []
    entry = doc["splits"]["test"][0]
    view = cm.make_views("test", 1, subframes=4, motion_deg=cm.DEFAULT_MOTION_DEG)[0]
    assert np.allclose(entry["transform_matrix"], view.pose)
    assert np.allclose(entry["subframe_transform_matrices"], view.subframe_poses)


def test_blender_camera_matrices_equal_the_poses():
    scene, camera = build_bpy_scene(build_scene("mic"))
    r = BlenderRenderer(scene, camera, RenderSettings(32, 32, samples=1))
    for view in cm.make_views("train", 3, subframes=4, motion_deg=3.0):
        for pose in [view.pose, *view.subframe_poses]:
            r.set_pose(pose)
            assert np.allclose(r.camera_matrix(), pose, atol=1e-6)
    assert abs(r.camera_angle_x() - cm.CAMERA_ANGLE_X) < 1e-6


def test_subframes_of_a_static_view_are_identical(tmp_path):
    """One noise pattern per view: one pose rendered twice with the view's seed is the same bytes
    (noise that changed between sub-frames would turn into spurious spikes), so a static view's
    K sub-frames are rendered once and copied."""
    scene, camera = build_bpy_scene(build_scene("materials"))
    r = BlenderRenderer(scene, camera, RenderSettings(48, 48, samples=4))
    pose = cm.make_views("train", 1)[0].pose
    r.set_view_seed(5)
    r.render_exr(pose, tmp_path / "a.exr")
    r.render_exr(cm.make_views("train", 2)[1].pose, tmp_path / "other.exr")
    r.render_exr(pose, tmp_path / "b.exr")
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()

    class Counting:  # the real renderer, counting its renders
        def __getattr__(self, name):
            return getattr(real, name)

        def render_exr(self, pose, path):
            calls.append(path)
            real.render_exr(pose, path)

    job = RenderJob("materials", views=(1, 0, 0), motion_deg=0.0, **SMALL)
    real, calls = renderer_for(job), []
    folder = RenderFolder.open(tmp_path / "static", job)
    for _ in render_steps(folder, Counting()):
        pass
    png, exrs = view_paths(folder.path, rig_of(folder.job)["train"][0])
    assert calls == exrs[:1] and len(exrs) == SMALL["subframes"]
    data = [p.read_bytes() for p in exrs]
    assert all(d == data[0] for d in data)
    assert not list(folder.path.rglob("*.part"))


def _tree(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_interrupted_render_resumes_to_the_same_bytes(tmp_path):
    job = RenderJob("hotdog", views=(3, 0, 0), **SMALL)
    whole = _render(tmp_path / "a", job)
    folder = RenderFolder.open(tmp_path / "b", job)
    steps = render_steps(folder, renderer_for(job))
    for _ in range(7):  # one view (4 EXR + 1 PNG) and 2 images of the next
        next(steps)
    steps.close()  # an interruption inside the second view
    doc = json.loads((folder.path / "render.json").read_text())
    assert len(doc["splits"]["train"]) == 1
    assert not (folder.path / "train" / "r_1_sub00.exr").exists()  # no partial view left behind
    assert not list(folder.path.rglob("*.part"))
    resumed = RenderFolder.open(tmp_path / "b", job)
    assert [v.index for v in resumed.pending()] == [1, 2]
    for _ in render_steps(resumed, renderer_for(job)):
        pass
    assert _tree(whole.path) == _tree(resumed.path)


def test_other_settings_refuse_to_reuse_a_folder(tmp_path):
    _render(tmp_path, RenderJob("lego", views=(1, 0, 0), **SMALL))
    from spikegen.errors import OutputError

    with pytest.raises(OutputError, match="other settings"):
        RenderFolder.open(tmp_path, RenderJob("lego", views=(1, 0, 0), **{**SMALL, "samples": 3}))


def test_full_path_to_datasets(tmp_path):
    """Render once, convert to two intensities; folders validate against dataset.md."""
    from spikegen.dataset import verify

    job = RenderJob("lego", views=(2, 1, 1), **SMALL)
    folder = _render(tmp_path, job)
    outs = convert_all(folder, tmp_path, [16, 64], sensor="paper", progress=False)
    assert [o.name for o in outs] == ["lego_i16", "lego_i64"]
    counts = []
    for out in outs:
        assert verify(out) == []
        for split, n in zip(("train", "val", "test"), job.views):
            doc = json.loads((out / f"transforms_{split}.json").read_text())
            assert doc["camera_angle_x"] == pytest.approx(cm.CAMERA_ANGLE_X)
            assert doc["spike"]["width"] == 64 and doc["spike"]["frames"] == 64 and doc["spike"]["subframes"] == 4
            assert len(doc["frames"]) == n
            for i, fr in enumerate(doc["frames"]):
                assert fr["file_path"] == f"./{split}/r_{i}" and fr["spike_path"] == f"./{split}/r_{i}.dat"
                assert len(fr["subframe_transform_matrices"]) == 4
                dat = out / fr["spike_path"]
                assert dat.stat().st_size == 64 * 64 * 64 // 8
                assert (out / f"{split}/r_{i}.png").read_bytes() == (folder.path / f"{split}/r_{i}.png").read_bytes()
        counts.append(read_spikes(out / "train/r_0.dat", size=(64, 64)).sum())
    assert counts[1] > 2.5 * counts[0]  # four times the intensity, about four times the spikes


def test_workbench_preview(tmp_path):
    folder = _render(tmp_path, RenderJob("chair", views=(1, 0, 0), engine="workbench", **SMALL))
    alpha = read_png(folder.path / "train" / "r_0.png")[:, :, 3]
    assert alpha.mean() > 0.05 and alpha[0].max() == 0


def test_cli_render_quick_and_errors(tmp_path, capsys):
    args = ["render", "--scene", "ficus", "--intensity", "32", "--out", str(tmp_path), "--quick",
            "--views", "1,0,0", "--subframes", "2", "--frames", "32"]
    assert cli_main(args) in (0, None)
    assert (tmp_path / "ficus_i32" / "manifest.json").is_file()
    assert cli_main(["render", "--scene", "boat", "--intensity", "32", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("spikegen: error:") and "boat" in err[-1] and "Traceback" not in "".join(err)
    assert cli_main(["render", "--blend", str(tmp_path / "none.blend"), "--intensity", "32"]) == 2
    assert cli_main(["render", "--scene", "lego", "--intensity", "-1"]) == 2


def test_blend_file_is_rendered_under_its_name(tmp_path):
    import bpy

    build_bpy_scene(build_scene("hotdog"))
    blend = tmp_path / "myscene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    assert cli_main(["render", "--blend", str(blend), "--intensity", "16", "--out", str(tmp_path / "o"),
                     "--quick", "--views", "1,0,0", "--subframes", "2", "--frames", "16"]) in (0, None)
    doc = json.loads((tmp_path / "o" / "myscene_render" / "render.json").read_text())
    assert doc["scene"] == "myscene" and doc["source"].startswith("blend:")
    assert (tmp_path / "o" / "myscene_i16" / "manifest.json").is_file()


def test_a_blend_whose_camera_the_dataset_cannot_describe_is_refused(tmp_path, capsys):
    import bpy

    scene, camera = build_bpy_scene(build_scene("hotdog"))
    camera.data.type = "ORTHO"
    blend = tmp_path / "flat.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    assert cli_main(["render", "--blend", str(blend), "--intensity", "16", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("spikegen: error:") and "perspective" in err[-1]
    assert not (tmp_path / "o").exists()


def test_denoise_is_recorded_reproducible_and_smoother(tmp_path):
    """--denoise: render.json says so, a folder made without it refuses it, two runs give the same
    bytes, and the image is smoother than the raw render of the same samples."""
    from spikegen.errors import OutputError

    raw = _render(tmp_path / "raw", RenderJob("lego", views=(1, 0, 0), **SMALL))
    den = [_render(tmp_path / d, RenderJob("lego", views=(1, 0, 0), denoise=True, **SMALL)) for d in "ab"]
    assert json.loads((den[0].path / "render.json").read_text())["denoise"] is True
    assert json.loads((raw.path / "render.json").read_text())["denoise"] is False
    with pytest.raises(OutputError, match="other settings"):
        RenderFolder.open(tmp_path / "raw", RenderJob("lego", views=(1, 0, 0), denoise=True, **SMALL))
    name = "train/r_0_sub00.exr"
    assert (den[0].path / name).read_bytes() == (den[1].path / name).read_bytes()

    def roughness(img):  # mean absolute Laplacian of the luminance, inside the object
        y = img[:, :, :3].mean(axis=2)
        lap = np.abs(4 * y[1:-1, 1:-1] - y[:-2, 1:-1] - y[2:, 1:-1] - y[1:-1, :-2] - y[1:-1, 2:])
        return lap[img[1:-1, 1:-1, 3] > 0.99].mean()

    assert roughness(read_exr(den[0].path / name)) < 0.8 * roughness(read_exr(raw.path / name))


def test_thread_count_does_not_change_the_bytes(tmp_path):
    scene, camera = build_bpy_scene(build_scene("materials"))
    pose = cm.make_views("train", 1)[0].pose
    data = []
    for threads in (1, 2):
        r = BlenderRenderer(scene, camera, RenderSettings(48, 48, samples=4, threads=threads))
        r.set_view_seed(7)
        r.render_exr(pose, tmp_path / f"t{threads}.exr")
        data.append((tmp_path / f"t{threads}.exr").read_bytes())
    assert data[0] == data[1]


def test_ctrl_c_stops_between_images_and_the_rerun_completes(tmp_path):
    """SIGINT to a running `spikegen render`: exit 130, no partial view, a rerun gives the same bytes."""
    import signal
    import subprocess
    import sys
    import time

    args = ["render", "--scene", "lego", "--intensity", "16", "--resolution", "48", "--views", "30,0,0",
            "--subframes", "4", "--frames", "16", "--samples", "2"]
    code = "import sys; from spikegen.cli import main; raise SystemExit(main(sys.argv[1:]))"
    out = tmp_path / "a"
    proc = subprocess.Popen([sys.executable, "-c", code, *args, "--out", str(out)], stderr=subprocess.PIPE,
                            stdout=subprocess.DEVNULL)
    doc_path = out / "lego_render" / "render.json"
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if doc_path.is_file() and json.loads(doc_path.read_text() or "{}").get("splits", {}).get("train"):
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err.decode()[-500:]
    done = {e["index"] for e in json.loads(doc_path.read_text())["splits"]["train"]}
    assert 0 < len(done) < 30
    names = {p.name for p in (out / "lego_render" / "train").iterdir()}
    assert names == {f"r_{i}{s}" for i in done for s in (".png", "_sub00.exr", "_sub01.exr", "_sub02.exr",
                                                          "_sub03.exr")}
    assert not (out / "lego_i16").exists()
    assert cli_main([*args, "--out", str(out)]) in (0, None)
    assert cli_main([*args, "--out", str(tmp_path / "b")]) in (0, None)
    assert _tree(out) == _tree(tmp_path / "b")


def test_the_png_is_recorded_with_the_samples_it_is_rendered_with():
    """--png-samples is a floor under --samples: the record says what was used, so the command
    line and the add-on (which pass their settings differently) write the same header."""
    assert RenderJob("lego", samples=8, png_samples=16).header()["png_samples"] == 16
    assert RenderJob("lego", samples=32, png_samples=16).header()["png_samples"] == 32
    assert RenderJob("lego", samples=32, png_samples=16).header() == RenderJob("lego", samples=32,
                                                                               png_samples=32).header()


@pytest.mark.parametrize("name", SCENES)
def test_rendering_the_box_around_the_object_gives_the_full_frame_bytes(tmp_path, name):
    """The built-in scenes render only the box around the object's image: every file must be
    byte for byte the full-frame render (nothing the camera sees lies outside the box)."""
    desc = build_scene(name)
    scene, camera = build_bpy_scene(desc)
    views = [cm.make_views("train", 2, subframes=2)[1], cm.make_views("test", 1, subframes=2)[0]]
    settings = RenderSettings(64, 64, samples=4, png_samples=8)
    cropped = BlenderRenderer(scene, camera, settings, crop_points=desc.vertices())
    full = BlenderRenderer(scene, camera, settings)
    tight = 0  # pixels the full render touches outside the box without the filter's margin
    for view in views:
        for r in (cropped, full):
            r.set_view_seed(11)
            r.render_exr(view.subframe_poses[0], tmp_path / f"{id(r)}.exr")
            r.render_png(view.pose, tmp_path / f"{id(r)}.png")
        assert cropped.crop_box(view.pose) is not None and full.crop_box(view.pose) is None
        for ext in ("exr", "png"):
            assert (tmp_path / f"{id(cropped)}.{ext}").read_bytes() == (tmp_path / f"{id(full)}.{ext}").read_bytes()
        x0, x1, y0, y1 = cm.crop_window(desc.vertices(), view.subframe_poses[0], 64, 64)
        alpha = read_exr(tmp_path / f"{id(full)}.exr")[..., 3] > 0
        alpha[y0:y1, x0:x1] = False
        tight += alpha.sum()
    if name in ("lego", "mic"):  # here the pixel filter reaches past the geometry's box: the margin matters
        assert tight > 0
