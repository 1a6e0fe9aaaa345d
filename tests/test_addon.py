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
    with pytest.raises(RuntimeError, match="intensities"):
        bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), **{**SMALL, "intensities": "abc"})
    bpy.context.scene.camera = None
    with pytest.raises(RuntimeError, match="no active camera"):
        bpy.ops.export_scene.spike_dataset(directory=str(tmp_path), **SMALL)
    assert not any(tmp_path.iterdir())


def test_cancel_leaves_no_partial_view(addon, tmp_path):
    """What Esc does in the modal operator: the view being rendered disappears, settings come back."""
    build_bpy_scene(build_scene("ficus"))
    scene = bpy.context.scene
    scene.render.resolution_x = 77
    props = SimpleNamespace(directory=str(tmp_path), sensor="paper", dataset_name="", motion_deg=1.0, **SMALL)
    session = addon.ExportSession(props, bpy.context)
    assert session.total == 4 * 3  # 4 views x (2 sub-frames + PNG)
    for _ in range(4):  # view 0 done (3 images), 1 image of view 1
        assert session.step()
    session.cancel()
    assert scene.render.resolution_x == 77
    folder = tmp_path / "scene_render"
    doc = json.loads((folder / "render.json").read_text())
    assert [e["index"] for e in doc["splits"]["train"]] == [0]
    assert sorted(p.name for p in (folder / "train").iterdir()) == ["r_0.png", "r_0_sub00.exr", "r_0_sub01.exr"]
