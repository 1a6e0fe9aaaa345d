"""manifest.json and ``spikegen verify`` (issue 6, "Resume and verify").

The manifest must list every file of the dataset with its size and sha256 (checked here
against hashes computed independently), and ``verify`` must name each missing, truncated,
altered or unlisted file and exit non-zero, while an intact folder passes.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from _scale_helpers import make_nerf, make_render, run_spikegen
from spikegen.cli import main
from spikegen.dataset import convert, verify


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    base = tmp_path_factory.mktemp("verify")
    nerf = make_nerf(base / "scene", views=3, size=16, seed=4, splits=("train", "val"))
    render = make_render(base / "render", views=2, size=16, subframes=3, seed=5)
    a = convert(nerf, base / "out", [16, 48], sensor="paper", frames=32, progress=False)
    b = convert(render, base / "out", [32], sensor="ideal", frames=32, progress=False)
    return a + b


@pytest.fixture()
def dataset(made, tmp_path):
    dst = tmp_path / made[0].name
    shutil.copytree(made[0], dst)
    return dst


def sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_manifest_lists_every_file_with_size_and_hash(made):
    for folder in made:
        doc = json.loads((folder / "manifest.json").read_text())
        listed = {e["path"]: e for e in doc["files"]}
        on_disk = sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*")
                         if p.is_file() and p.name != "manifest.json")
        assert sorted(listed) == on_disk  # every file, nothing else (no job file, no temporaries)
        for rel, e in listed.items():
            assert e["bytes"] == (folder / rel).stat().st_size
            assert e["sha256"] == sha(folder / rel)
        assert doc["seed"] == doc["parameters"]["seed"]
        assert doc["generator"].startswith("spikegen ")
        for name in ("transforms_train.json", "sensor.json"):
            assert name in listed
        assert any(k.endswith(".dat") for k in listed) and any(k.endswith(".png") for k in listed)


def test_intact_dataset_passes(made, capsys):
    for folder in made:
        assert verify(folder) == []
        assert main(["verify", str(folder)]) == 0
        assert "OK" in capsys.readouterr().out


def _cli(folder, capsys):
    code = main(["verify", str(folder)])
    return code, capsys.readouterr().err.splitlines()


def test_missing_file_is_named(dataset, capsys):
    (dataset / "train/r_2.dat").unlink()
    code, lines = _cli(dataset, capsys)
    assert code != 0 and lines == [f"{dataset}: missing: train/r_2.dat"]


def test_truncated_file_is_named(dataset, capsys):
    p = dataset / "val/r_1.dat"
    p.write_bytes(p.read_bytes()[:-1])
    code, lines = _cli(dataset, capsys)
    assert code != 0 and len(lines) == 1 and "truncated: val/r_1.dat" in lines[0]


def test_one_flipped_bit_is_named(dataset, capsys):
    p = dataset / "train/r_0.dat"
    data = bytearray(p.read_bytes())
    data[17] ^= 0x10
    p.write_bytes(bytes(data))
    code, lines = _cli(dataset, capsys)
    assert code != 0 and lines == [f"{dataset}: altered: train/r_0.dat (sha256 differs)"]


def test_grown_file_is_named(dataset, capsys):
    with open(dataset / "sensor.json", "a") as fh:
        fh.write(" ")
    code, lines = _cli(dataset, capsys)
    assert code != 0 and len(lines) == 1 and "altered: sensor.json" in lines[0]


def test_unlisted_and_leftover_files_are_named(dataset, capsys):
    (dataset / "train/r_99.dat").write_bytes(b"\x00" * 8)
    (dataset / "train/.r_0.png.abcd.part").write_bytes(b"\x89PNG")
    code, lines = _cli(dataset, capsys)
    assert code != 0 and len(lines) == 2
    assert any("unlisted: train/r_99.dat" in ln for ln in lines)
    assert any("unlisted: train/.r_0.png.abcd.part (left by an interrupted write)" in ln for ln in lines)


def test_every_problem_is_listed(dataset, capsys):
    (dataset / "train/r_1.png").unlink()
    (dataset / "transforms_val.json").write_text("{}")
    p = dataset / "sensor.npz"
    p.write_bytes(p.read_bytes()[:10])
    code, lines = _cli(dataset, capsys)
    assert code != 0 and len(lines) == 3
    joined = "\n".join(lines)
    for rel in ("train/r_1.png", "transforms_val.json", "sensor.npz"):
        assert rel in joined


def test_malformed_manifest_entry_is_reported(dataset, capsys):
    m = dataset / "manifest.json"
    doc = json.loads(m.read_text())
    doc["files"][0] = {"path": doc["files"][0]["path"]}  # no size, no hash
    m.write_text(json.dumps(doc))
    code, lines = _cli(dataset, capsys)
    assert code != 0 and len(lines) == 1 and "malformed entry" in lines[0]


def test_verify_real_process(dataset):
    ok = run_spikegen("verify", dataset)
    assert ok.returncode == 0 and ok.stdout.strip() == f"{dataset}: OK" and ok.stderr == ""
    (dataset / "train/r_0.png").unlink()
    bad = run_spikegen("verify", dataset)
    assert bad.returncode != 0 and bad.stderr.strip() == f"{dataset}: missing: train/r_0.png"
    assert "Traceback" not in bad.stderr
