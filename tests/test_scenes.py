"""The six built-in scenes as pure data (no Blender): valid, deterministic, distinct, in frame."""
import numpy as np
import pytest

from spikegen import camera as cm
from spikegen.errors import InputError
from spikegen.scenes import SCENES, build_scene
from spikegen.scenes.description import MAX_RADIUS

NAMES = ["chair", "ficus", "hotdog", "lego", "materials", "mic"]


@pytest.fixture(scope="module")
def scenes():
    return {n: build_scene(n) for n in NAMES}


def test_registry_has_the_six_paper_scenes():
    assert sorted(SCENES) == NAMES


def test_unknown_scene_is_one_clear_error():
    with pytest.raises(InputError, match="unknown scene 'boat'"):
        build_scene("boat")


@pytest.mark.parametrize("name", NAMES)
def test_scene_is_valid_mesh_data(scenes, name):
    s = scenes[name]
    assert s.name == name
    for m in s.meshes:
        assert m.vertices.dtype == np.float32 and m.vertices.shape[1] == 3
        assert m.faces.dtype == np.int32 and m.faces.shape[1] == 3
        assert m.faces.min() >= 0 and m.faces.max() < len(m.vertices)
        assert np.isfinite(m.vertices).all()
        assert m.material in s.materials
    assert s.bounding_radius() <= MAX_RADIUS + 1e-6


@pytest.mark.parametrize("name", NAMES)
def test_scene_is_deterministic(scenes, name):
    again = build_scene(name)
    for a, b in zip(scenes[name].meshes, again.meshes):
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)


@pytest.mark.parametrize("name", NAMES)
def test_scene_stays_inside_every_rig_view(scenes, name):
    """Every vertex projects inside a 400 x 400 frame from every train, val and test camera."""
    pts = scenes[name].vertices()
    rig = cm.make_rig({"train": 30, "val": 10, "test": 20}, subframes=3, motion_deg=5.0)
    for views in rig.values():
        for v in views:
            for pose in v.subframe_poses:
                xy = cm.project(pts, pose, 400, 400)
                assert np.isfinite(xy).all()
                assert xy.min() > 0 and xy.max() < 400


def test_scenes_differ(scenes):
    sizes = {n: (s.triangle_count(), tuple(np.round(np.ptp(s.vertices(), axis=0), 3))) for n, s in scenes.items()}
    assert len(set(sizes.values())) == len(NAMES)


def test_what_makes_each_scene_hard_is_there(scenes):
    lego = scenes["lego"]
    assert {"yellow", "rubber"} <= set(lego.materials)
    ficus_leaves = next(m for m in scenes["ficus"].meshes if m.name == "leaves")
    assert len(ficus_leaves.faces) // 4 >= 300  # hundreds of 4-triangle leaves
    mats = scenes["materials"].materials.values()
    assert any(m.metallic == 1 for m in mats) and any(m.transmission == 1 for m in mats)
    assert min(m.roughness for m in mats) < 0.1 < 0.8 < max(m.roughness for m in mats)
    grill = next(m for m in scenes["mic"].meshes if m.name == "grill")
    assert len(grill.faces) > 2000  # many thin wires
    tex = scenes["chair"].materials["upholstery"].texture
    assert tex is not None and tex.ndim == 3 and tex.std() > 0.1  # a real pattern, not a flat colour
    hotdog = scenes["hotdog"]
    assert {"bun", "sausage", "plate", "mustard"} <= set(hotdog.materials)


def test_original_blend_files_are_recognised_by_sha256(tmp_path, monkeypatch):
    from spikegen import scenes
    from spikegen.render import identify_blend
    from spikegen.spikeio import sha256_file

    f = tmp_path / "some_copy.blend"
    f.write_bytes(b"BLENDER-v500 not really")
    assert identify_blend(f)[0] == "some_copy"  # unknown file: its own name
    monkeypatch.setitem(scenes.ORIGINAL_BLEND_SHA256, sha256_file(f), "ficus")
    assert identify_blend(f) == ("ficus", sha256_file(f))
    with pytest.raises(InputError, match="no such file"):
        identify_blend(tmp_path / "missing.blend")


def test_scene_and_render_orchestration_never_import_bpy():
    import subprocess
    import sys

    code = ("import sys, spikegen.scenes, spikegen.camera, spikegen.render, spikegen.cli_render; "
            "spikegen.scenes.build_scene('lego'); assert 'bpy' not in sys.modules, 'bpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True)
