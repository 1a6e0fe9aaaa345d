"""The "Export Spike Dataset" Blender add-on, driven headless through bpy.ops."""
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

bpy = pytest.importorskip("bpy")

from spikegen import camera as cm  # noqa: E402
from spikegen.render_blender import build_bpy_scene  # noqa: E402
from spikegen.scenes import build_scene  # noqa: E402

pytestmark = pytest.mark.blender
REPO = Path(__file__).resolve().parents[1]
SMALL = dict(intensities="16,32", resolution=32, views_train=2, views_val=1, views_test=1, subframes=2, frames=16,
             samples=1, seed=0)


@pytest.fixture
def addon():
    sys.path.insert(0, str(REPO))
    try:
        import blender_addon
    finally:
        sys.path.remove(str(REPO))
    blender_addon.register()
    yield blender_addon
    if hasattr(bpy.types.Scene, "spike_export"):
        blender_addon.unregister()


def _export_menu_funcs():
    return list(getattr(bpy.types.TOPBAR_MT_file_export.draw, "_draw_funcs", []))


def test_registers_and_unregisters_cleanly(addon):
    assert bpy.types.EXPORT_SCENE_OT_spike_dataset.bl_label == "Export Spike Dataset"
    assert hasattr(bpy.types.Scene, "spike_export") and hasattr(bpy.types, "SPIKE_PT_export")
    assert addon.menu_export in _export_menu_funcs()
    handlers = {name: len(getattr(bpy.app.handlers, name)) for name in dir(bpy.app.handlers)
                if isinstance(getattr(bpy.app.handlers, name), list)}
    addon.unregister()
    assert not hasattr(bpy.types.Scene, "spike_export")
    assert not hasattr(bpy.types, "EXPORT_SCENE_OT_spike_dataset") and not hasattr(bpy.types, "SPIKE_PT_export")
    assert addon.menu_export not in _export_menu_funcs()
    assert handlers == {name: len(getattr(bpy.app.handlers, name)) for name in handlers}
    addon.register()  # registering again after a clean unregister works


def test_export_writes_valid_datasets_and_restores_the_scene(addon, tmp_path):
    from spikegen.dataset import verify

    build_bpy_scene(build_scene("lego"))
    scene = bpy.context.scene
    scene.render.engine, scene.render.resolution_x = "BLENDER_EEVEE", 123
    assert bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), **SMALL) == {"FINISHED"}
    assert scene.render.engine == "BLENDER_EEVEE" and scene.render.resolution_x == 123  # user settings restored
    prefs = bpy.context.preferences.addons["cycles"].preferences
    expected = prefs.compute_device_type if prefs.get_num_gpu_devices() and prefs.has_active_device() else None
    device = json.loads((tmp_path / "scene_render" / "render.json").read_text())["device"]
    assert device == ("cpu" if expected in (None, "NONE") else f"gpu:{expected}")  # as the preferences select
    for level in (16, 32):
        out = tmp_path / f"scene_i{level}"
        assert verify(out) == []
        doc = json.loads((out / "transforms_train.json").read_text())
        assert doc["spike"]["width"] == 32 and doc["spike"]["subframes"] == 2 and len(doc["frames"]) == 2
        assert (out / "train" / "r_1.dat").stat().st_size == 16 * 32 * 32 // 8
        rig = cm.make_rig({"train": 2, "val": 1, "test": 1}, subframes=2, motion_deg=1.0, seed=0)
        for fr, view in zip(doc["frames"], rig["train"]):  # the same rig as `spikegen render`
            assert fr["transform_matrix"] == view.pose.tolist()
            assert fr["subframe_transform_matrices"] == [p.tolist() for p in view.subframe_poses]
    # run again: every view is already there, nothing is rendered, the bytes stay the same
    before = {p: p.read_bytes() for p in sorted(tmp_path.rglob("*")) if p.is_file()}
    assert bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), **SMALL) == {"FINISHED"}
    assert before == {p: p.read_bytes() for p in sorted(tmp_path.rglob("*")) if p.is_file()}


def test_errors_are_reported_and_cancelled(addon, tmp_path):
    build_bpy_scene(build_scene("mic"))
    with pytest.raises(RuntimeError, match="choose an output folder"):
        bpy.ops.export_scene.spike_dataset(directory="", **SMALL)
    with pytest.raises(RuntimeError, match="--intensity 'abc': expected a number"):
        bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), **{**SMALL, "intensities": "abc"})
    # the checks `spikegen render` makes, before anything is rendered
    with pytest.raises(RuntimeError, match="above 4096 every pixel saturates"):
        bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), **{**SMALL, "intensities": "16,5000"})
    with pytest.raises(RuntimeError, match="unknown sensor 'papr'"):
        bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), sensor="papr", **SMALL)
    with pytest.raises(RuntimeError, match="/nonexistent/cam.json: no such sensor file"):
        bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), sensor="/nonexistent/cam.json", **SMALL)
    if not bpy.context.preferences.addons["cycles"].preferences.get_num_gpu_devices():
        with pytest.raises(RuntimeError, match="--device gpu: Cycles finds no GPU backend"):
            bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), device="GPU", **SMALL)
    bpy.context.scene.camera = None
    with pytest.raises(RuntimeError, match="no active camera"):
        bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), **SMALL)
    assert not any(tmp_path.iterdir())


def test_cancel_leaves_no_partial_view(addon, tmp_path):
    """What Esc does in the modal operator: the view being rendered disappears, settings come back."""
    build_bpy_scene(build_scene("ficus"))
    scene = bpy.context.scene
    scene.render.resolution_x = 77
    session = addon.ExportSession(_props(tmp_path), bpy.context)
    assert session.total == 4 * 3  # 4 views x (2 sub-frames + PNG)
    for _ in range(4):  # view 0 done (3 images), 1 image of view 1
        assert session.step()
    session.cancel()
    assert scene.render.resolution_x == 77
    folder = tmp_path / "scene_render"
    doc = json.loads((folder / "render.json").read_text())
    assert [e["index"] for e in doc["splits"]["train"]] == [0]
    assert sorted(p.name for p in (folder / "train").iterdir()) == ["r_0.png", "r_0_sub00.exr", "r_0_sub01.exr"]


def _props(tmp_path):
    return SimpleNamespace(directory=str(tmp_path), sensor="paper", dataset_name="", motion_deg=1.0, denoise=False, device="PREFERENCES",
                           **SMALL)


class _FakeWindowManager:
    def __init__(self):
        self.progress, self.ended, self.timers_removed = [], False, []

    def progress_update(self, value):
        self.progress.append(value)

    def progress_end(self):
        self.ended = True

    def event_timer_remove(self, timer):
        self.timers_removed.append(timer)


class _FakeWorkspace:
    def __init__(self):
        self.status = []

    def status_text_set(self, text):
        self.status.append(text)


def _modal_operator(addon, session):
    """The operator's own modal(), _render_tick() and _end() on a stand-in for the Blender operator
    (a modal operator needs a window's event loop, which headless Blender has not)."""
    cls = addon.EXPORT_SCENE_OT_spike_dataset

    class Op:
        modal, _render_tick, _end = cls.modal, cls._render_tick, cls._end

        def __init__(self):
            self._session, self._timer, self.reports = session, "timer", []

        def report(self, level, message):
            self.reports.append((set(level), message))

    ctx = SimpleNamespace(window_manager=_FakeWindowManager(), workspace=_FakeWorkspace())
    return Op(), ctx


def test_modal_operator_shows_progress_and_finishes(addon, tmp_path):
    import time

    from spikegen.dataset import verify

    build_bpy_scene(build_scene("hotdog"))
    session = addon.ExportSession(_props(tmp_path), bpy.context)
    op, ctx = _modal_operator(addon, session)
    timer, other = SimpleNamespace(type="TIMER"), SimpleNamespace(type="MOUSEMOVE")
    assert op.modal(ctx, other) == {"PASS_THROUGH"}  # the interface stays responsive
    deadline = time.time() + 120
    result = {"RUNNING_MODAL"}
    while result == {"RUNNING_MODAL"} and time.time() < deadline:
        result = op.modal(ctx, timer)
        time.sleep(0.01)
    assert result == {"FINISHED"}, op.reports
    wm = ctx.window_manager
    # one step per image, in order; the tick that finds rendering finished reports the total again
    assert wm.progress == [*range(1, session.total + 1), session.total]
    assert wm.ended and wm.timers_removed == ["timer"] and op._timer is None
    assert ctx.workspace.status[0] == f"Spike dataset: image 1 / {session.total}"
    assert "converting to spikes" in ctx.workspace.status[-2] and ctx.workspace.status[-1] is None
    assert op.reports[-1][0] == {"INFO"} and "scene_i16" in op.reports[-1][1]
    assert verify(tmp_path / "scene_i16") == [] and verify(tmp_path / "scene_i32") == []


def test_modal_operator_esc_cancels_and_leaves_no_partial_view(addon, tmp_path):
    build_bpy_scene(build_scene("chair"))
    scene = bpy.context.scene
    scene.render.resolution_x = 91
    session = addon.ExportSession(_props(tmp_path), bpy.context)
    op, ctx = _modal_operator(addon, session)
    for _ in range(5):  # view 0 (3 images) and 2 images of view 1
        assert op.modal(ctx, SimpleNamespace(type="TIMER")) == {"RUNNING_MODAL"}
    assert op.modal(ctx, SimpleNamespace(type="ESC")) == {"CANCELLED"}
    assert ctx.window_manager.ended and ctx.window_manager.timers_removed == ["timer"]
    assert op.reports[-1][0] == {"WARNING"} and "cancelled" in op.reports[-1][1]
    assert scene.render.resolution_x == 91  # the user's settings are back
    folder = tmp_path / "scene_render"
    assert [e["index"] for e in json.loads((folder / "render.json").read_text())["splits"]["train"]] == [0]
    assert sorted(p.name for p in (folder / "train").iterdir()) == ["r_0.png", "r_0_sub00.exr", "r_0_sub01.exr"]
    assert not any(p.name.endswith(".part") for p in folder.rglob("*"))
    assert not (tmp_path / "scene_i16").exists()


def test_scene_settings_that_would_change_the_images_do_not(addon, tmp_path):
    """A render border, film exposure, a view layer's samples, a time limit, depth of field, a
    curve: the export renders the same bytes as from a plain scene, and gives every setting back."""
    build_bpy_scene(build_scene("lego"))
    scene = bpy.context.scene
    one = dict(SMALL, intensities="16", views_train=1, views_val=0, views_test=0)
    assert bpy.ops.export_scene.spike_dataset(directory=str(tmp_path / "plain"), **one) == {"FINISHED"}
    r, c, cam = scene.render, scene.cycles, scene.camera.data
    user = {(r, "use_border"): True, (r, "use_crop_to_border"): True, (r, "border_min_x"): 0.1,
            (r, "border_max_x"): 0.3, (r, "border_min_y"): 0.2, (r, "border_max_y"): 0.4,
            (c, "film_exposure"): 3.0, (c, "use_layer_samples"): "USE", (scene.view_layers[0], "samples"): 5,
            (c, "time_limit"): 0.001, (cam.dof, "use_dof"): True, (cam.dof, "focus_distance"): 0.5,
            (cam.dof, "aperture_fstop"): 0.1, (scene.view_settings, "use_curve_mapping"): True,
            (scene.view_settings, "exposure"): 1.5}
    for (owner, attr), value in user.items():
        setattr(owner, attr, value)
    assert bpy.ops.export_scene.spike_dataset(directory=str(tmp_path / "user"), **one) == {"FINISHED"}
    for (owner, attr), value in user.items():
        assert getattr(owner, attr) == (pytest.approx(value) if isinstance(value, float) else value), attr
    files = sorted(p.relative_to(tmp_path / "plain") for p in (tmp_path / "plain").rglob("*.*") if p.is_file())
    assert any(p.suffix == ".exr" for p in files) and any(p.suffix == ".png" for p in files)
    for p in files:
        assert (tmp_path / "plain" / p).read_bytes() == (tmp_path / "user" / p).read_bytes(), p


@pytest.mark.parametrize("change, message", [({"type": "ORTHO"}, "perspective"),
                                             ({"shift_x": 0.1}, "lens shift")])
def test_a_camera_the_dataset_cannot_describe_is_refused(addon, tmp_path, change, message):
    build_bpy_scene(build_scene("mic"))
    for attr, value in change.items():
        setattr(bpy.context.scene.camera.data, attr, value)
    with pytest.raises(RuntimeError, match=message):
        bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), **SMALL)
    assert not any(tmp_path.iterdir())
