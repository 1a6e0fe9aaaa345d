"""The extension zip, built by the documented command and installed into a fresh Blender user folder:
the operator runs from the project's wheel inside the zip, not from this checkout."""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("bpy")

pytestmark = pytest.mark.blender
REPO = Path(__file__).resolve().parents[1]

INSTALL_AND_EXPORT = textwrap.dedent("""
    import json, os, sys
    import bpy
    bpy.context.preferences.system.use_online_access = False
    result = bpy.ops.extensions.package_install_files(filepath=sys.argv[1], repo="user_default",
                                                      enable_on_install=True)
    import spikegen
    bpy.ops.mesh.primitive_monkey_add()
    bpy.ops.object.camera_add()
    bpy.context.scene.camera = bpy.context.object
    export = bpy.ops.export_scene.spike_dataset(directory=sys.argv[2], intensities="32", resolution=32,
                                                views_train=1, views_val=0, views_test=1, subframes=2, frames=16,
                                                samples=1)
    print("RESULT " + json.dumps({"install": sorted(result), "export": sorted(export),
                                  "spikegen": spikegen.__file__}))
""")


def test_the_extension_zip_installs_and_exports_from_its_own_wheel(tmp_path):
    build = subprocess.run([sys.executable, str(REPO / "blender_addon" / "build.py"), "--out", str(tmp_path / "dist"),
                            "--wheels", str(tmp_path / "wheels")], capture_output=True, text=True)
    offline = ("NewConnectionError", "Temporary failure in name resolution", "Network is unreachable")
    if build.returncode and any(msg in build.stderr for msg in offline):
        pytest.skip("no network to download the extension's runtime wheels (click, tqdm, pillow, OpenEXR)")
    assert build.returncode == 0, build.stderr[-2000:]
    zips = list((tmp_path / "dist").glob("spike_dataset_export-*.zip"))
    assert len(zips) == 1
    script = tmp_path / "install.py"
    script.write_text(INSTALL_AND_EXPORT)
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": str(tmp_path),
           "BLENDER_USER_RESOURCES": str(tmp_path / "user")}  # no PYTHONPATH: the checkout is not importable
    run = subprocess.run([sys.executable, "-I", str(script), str(zips[0]), str(tmp_path / "out")], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=600)
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
    assert run.returncode == 0 and lines, (run.stdout + run.stderr)[-2000:]
    result = json.loads(lines[-1][len("RESULT "):])
    assert result["install"] == ["FINISHED"] and result["export"] == ["FINISHED"]
    assert Path(result["spikegen"]).is_relative_to(tmp_path / "user" / "extensions")

    from spikegen.dataset import verify

    assert verify(tmp_path / "out" / "scene_i32") == []
