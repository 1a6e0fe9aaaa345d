"""Resume after SIGKILL (issue 6, "Resume and verify").

A real ``spikegen convert`` process is killed with SIGKILL at seeded random moments, then
rerun. After every kill, each file under its final name must already hold exactly the bytes
of an uninterrupted run (no half file); views finished before a kill are not redone (their
files keep their inode); and the final rerun ends with exactly the files and bytes of an
uninterrupted run (no temporaries, no job file left).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from _scale_helpers import cli_env, make_nerf, run_spikegen, spikegen_cmd, tree
from spikegen.dataset import JOB_FILE, convert

VIEWS, SIZE, FRAMES = 24, 64, 256
INTENSITIES = ("16", "32")
KILL_SEED = 20261121  # seeds the kill moments
ROUNDS = 6


def convert_args(src: Path, out: Path, *extra) -> list:
    args = ["convert", src, "--out", out, "--frames", FRAMES, "--seed", 3]
    for i in INTENSITIES:
        args += ["--intensity", i]
    return args + list(extra)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The source and an uninterrupted run of it; returns (source, reference out, its tree, duration_s)."""
    base = tmp_path_factory.mktemp("resume")
    src = make_nerf(base / "scene", views=VIEWS, size=SIZE, seed=5, splits=("train", "test"))
    t0 = time.perf_counter()
    proc = run_spikegen(*convert_args(src, base / "ref"))
    duration = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stderr
    return src, base / "ref", tree(base / "ref"), duration


def final_files(out: Path) -> dict:
    """Files under their final names (no temporaries of atomic writes, no job file)."""
    if not out.exists():
        return {}
    return {k: v for k, v in tree(out).items() if not Path(k).name.startswith(".")}


def done_views(out: Path) -> dict:
    """{view stem: (png inode, dat inode)} for views whose .png and .dat both exist."""
    out_views = {}
    if not out.exists():
        return out_views
    for dat in out.rglob("r_*.dat"):
        png = dat.with_suffix(".png")
        if png.is_file():
            out_views[dat.relative_to(out).with_suffix("").as_posix()] = (png.stat().st_ino, dat.stat().st_ino)
    return out_views


def count_dat(out: Path) -> int:
    return sum(1 for _ in out.rglob("r_*.dat")) if out.exists() else 0


def kill_when(args: list, out: Path, views_done: int, extra_s: float, workers: int = 1) -> bool:
    """Start ``spikegen convert``; once ``out`` holds ``views_done`` finished .dat files, wait
    ``extra_s`` more and SIGKILL its whole process group. True if killed, False if it ended first."""
    proc = subprocess.Popen(spikegen_cmd(*args, "--workers", workers), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, env=cli_env(), start_new_session=True)
    try:
        while proc.poll() is None and count_dat(out) < views_done:
            time.sleep(0.005)
        try:
            proc.wait(timeout=extra_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            return True
        assert proc.returncode == 0, proc.stderr.read()
        return False
    finally:
        proc.stderr.close()


def test_sigkill_at_random_moments_then_resume(reference, tmp_path):
    src, ref_out, ref_tree, duration = reference
    out = tmp_path / "out"
    args = convert_args(src, out)
    rng = np.random.default_rng(KILL_SEED)
    total_views = VIEWS * 2 * len(INTENSITIES)
    per_view_s = duration / total_views
    # round 0: during start-up or the claim of the folder; then after a seeded number of views
    # plus a seeded fraction of a view's time, so kills land inside writes and between them.
    targets = [0] + sorted(rng.choice(np.arange(1, total_views), ROUNDS - 1, replace=False).tolist())
    extras = [float(rng.uniform(0.0, 0.6))] + rng.uniform(0.0, 1.5 * per_view_s, ROUNDS - 1).tolist()
    mid_run_kills, history = 0, []
    for round_, (target, extra) in enumerate(zip(targets, extras)):
        before = done_views(out)
        killed = kill_when(args, out, target, extra, workers=2 if round_ == 3 else 1)
        # every file under a final name is complete: exactly the reference bytes
        for rel, digest in final_files(out).items():
            assert ref_tree.get(rel) == digest, f"round {round_}: {rel} differs from an uninterrupted run"
        # views finished before this round were skipped, not rewritten
        after = done_views(out)
        for view, inodes in before.items():
            assert after.get(view) == inodes, f"round {round_}: finished view {view} was redone"
        history.append((target, round(extra, 3), killed, len(after)))
        if killed and 0 < len(after) < total_views:
            mid_run_kills += 1
    assert mid_run_kills >= ROUNDS // 2, f"kills did not land while views were written: {history}"
    proc = run_spikegen(*args)
    assert proc.returncode == 0, proc.stderr
    assert tree(out) == ref_tree  # same files (no .part, no job file) and the same bytes
    for folder in sorted(out.iterdir()):
        assert run_spikegen("verify", folder).returncode == 0


def test_leftovers_of_a_kill_before_the_first_view(reference, tmp_path):
    """Killed while claiming the folder: only a temporary of the job file exists. The rerun
    must accept the folder and end with the reference bytes."""
    src, ref_out, ref_tree, _ = reference
    out = tmp_path / "out"
    for name in sorted({Path(k).parts[0] for k in ref_tree}):
        (out / name).mkdir(parents=True)
        (out / name / f"{JOB_FILE}.k3j9.part").write_text('{"parame')
    assert run_spikegen(*convert_args(src, out)).returncode == 0
    assert tree(out) == ref_tree


def test_leftover_temporaries_are_removed_on_resume(reference, tmp_path):
    """Killed mid-write: a half-written temporary beside a missing view, and a finished view.
    The rerun redoes only the missing view and leaves no temporary."""
    src, ref_out, ref_tree, _ = reference
    first = convert(src, tmp_path / "out", [INTENSITIES[0]], sensor="paper", frames=FRAMES, seed=3,
                    progress=False)[0]
    params = json.loads((first / "manifest.json").read_text())["parameters"]
    (first / JOB_FILE).write_text(json.dumps({"parameters": params}))  # as during a run
    (first / "manifest.json").unlink()
    (first / "train/r_3.dat").unlink()
    (first / "train/.r_3.dat.a1b2c3.part").write_bytes(b"\x00" * 100)
    (first / ".sensor.npz.zz.part").write_bytes(b"PK")
    keep = (first / "train/r_4.dat").stat().st_ino
    assert run_spikegen(*convert_args(src, tmp_path / "out")).returncode == 0
    assert tree(tmp_path / "out") == ref_tree
    assert (first / "train/r_4.dat").stat().st_ino == keep
