"""The fixed conversion whose every output file is pinned by tests/data/golden_convert.json.

Regenerate the list (only when a change of bytes is intended, and say why in the commit) with
``python tests/_golden.py > tests/data/golden_convert.json``.
"""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _scale_helpers import make_nerf, make_render, tree  # noqa: E402


def golden_tree(root: Path) -> dict:
    """{relative path: sha256} of converting two fixed sources: a NeRF-synthetic folder (train and
    test splits) at intensities 16 and 64 through the ``paper`` sensor, and a render folder (two
    sub-frames a view) at 32 through ``calibrated`` (shot noise, its own maps)."""
    from spikegen.dataset import convert

    nerf = make_nerf(root / "src" / "blob_nerf", views=3, size=32, seed=7, splits=("train", "test"))
    rend = make_render(root / "src" / "blob_render", views=2, size=16, subframes=2, seed=3)
    convert(nerf, root / "out", [16, 64], sensor="paper", progress=False)
    convert(rend, root / "out", [32], sensor="calibrated", progress=False)
    return tree(root / "out")


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as tmp:
        print(json.dumps(golden_tree(Path(tmp)), indent=1, sort_keys=True))
