"""Build the "Export Spike Dataset" extension zip (documented in blender_addon/README.md).

    python blender_addon/build.py [--out dist] [--python-version 3.11] [--platform manylinux_2_28_x86_64]
                                  [--wheels blender_addon/wheels]

1. builds the project's own wheel (``pip wheel . --no-deps``) into ``blender_addon/wheels`` (or ``--wheels``);
2. downloads the wheels it needs that Blender does not bundle (click, tqdm, pillow, OpenEXR),
   binary only, for Blender's Python (3.11 for Blender 4.2 - 5.0) and the given platform
   (default: this machine's);
3. writes ``<out>/spike_dataset_export-<version>.zip``: ``blender_manifest.toml`` (with the
   ``wheels`` list filled in), ``__init__.py``, ``README.md`` and ``wheels/``.

Install it with Blender's Edit > Preferences > Get Extensions > Install from Disk, or
``blender --command extension install-file -r user_default <zip>``.
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RUNTIME = ["click", "tqdm", "pillow", "OpenEXR"]  # numpy ships with Blender
FILES = ["__init__.py", "README.md"]


def pip(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "pip", *args], check=True)


def build_wheels(wheels: Path, python_version: str, platforms: list[str]) -> list[Path]:
    """The project wheel plus the runtime wheels, in ``wheels`` (old ones removed)."""
    wheels.mkdir(parents=True, exist_ok=True)
    for old in wheels.glob("*.whl"):
        old.unlink()
    left_over = REPO / "build"  # setuptools builds in the source tree; leave no stale copy of the code there
    existed = left_over.exists()
    try:
        pip("wheel", str(REPO), "--no-deps", "--no-build-isolation", "-w", str(wheels))
    finally:
        if not existed:
            shutil.rmtree(left_over, ignore_errors=True)
    target = ["--python-version", python_version] + [a for p in platforms for a in ("--platform", p)]
    pip("download", *RUNTIME, "--only-binary=:all:", "--no-deps", "-d", str(wheels), *target)
    return sorted(wheels.glob("*.whl"))


def manifest_text(wheels: list[Path]) -> str:
    """blender_manifest.toml with its ``wheels`` list naming the built wheels."""
    text = (HERE / "blender_manifest.toml").read_text()
    listing = "wheels = [\n" + "".join(f'  "./wheels/{w.name}",\n' for w in wheels) + "]"
    return re.sub(r"^wheels = \[.*?\]", listing, text, count=1, flags=re.M | re.S)


def version() -> str:
    return re.search(r'^version = "([^"]+)"', (HERE / "blender_manifest.toml").read_text(), re.M).group(1)


def write_zip(dest: Path, wheels: list[Path]) -> Path:
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_suffix(".zip.part")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("blender_manifest.toml", manifest_text(wheels))
        for name in FILES:
            z.write(HERE / name, name)
        for w in wheels:
            z.write(w, f"wheels/{w.name}")
    tmp.replace(dest)
    return dest


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Build the Export Spike Dataset extension zip.")
    ap.add_argument("--out", type=Path, default=REPO / "dist", help="folder for the zip (default: dist/)")
    ap.add_argument("--python-version", default="3.11", help="Blender's Python version (default 3.11)")
    ap.add_argument("--platform", action="append", default=[],
                    help="pip platform tag of the wheels, e.g. manylinux_2_28_x86_64, win_amd64, "
                         "macosx_11_0_arm64 (default: this machine's)")
    ap.add_argument("--wheels", type=Path, default=HERE / "wheels",
                    help="folder the wheels are gathered in (default: blender_addon/wheels)")
    args = ap.parse_args(argv)
    wheels = build_wheels(args.wheels, args.python_version, args.platform)
    dest = write_zip(args.out / f"spike_dataset_export-{version()}.zip", wheels)
    print(dest)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
