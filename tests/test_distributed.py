"""``--workers N`` and ``--scheduler ADDRESS`` give the bytes of a single-process run (issue 6,
"Scale out").

A real Dask cluster is started on loopback as separate processes, the way docs/scaling.md
tells users to: one ``dask scheduler`` and two ``dask worker`` processes. ``spikegen
convert`` runs as a subprocess against it; the workers' own task counters show the views
really ran there.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from _scale_helpers import make_nerf, make_render, run_spikegen, tree

distributed = pytest.importorskip("distributed")

DASK = Path(sys.executable).parent / "dask"
VIEWS = 5  # per split (train + test) of the NeRF source


def _stop(procs) -> None:
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    deadline = time.monotonic() + 15
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """(scheduler address, client) of a scheduler + 2 single-thread workers on 127.0.0.1."""
    if not DASK.is_file():
        pytest.skip(f"the dask command line is not installed beside {sys.executable}")
    base = tmp_path_factory.mktemp("dask")
    sfile = base / "scheduler.json"
    common = dict(stdout=subprocess.DEVNULL, stderr=open(base / "cluster.log", "w"), start_new_session=True,
                  cwd=base)
    procs = [subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sfile)], **common)]
    try:
        deadline = time.monotonic() + 60
        while not sfile.is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert sfile.is_file(), (base / "cluster.log").read_text()[-2000:]
        for _ in range(2):
            procs.append(subprocess.Popen([str(DASK), "worker", "--scheduler-file", str(sfile), "--host", "127.0.0.1",
                                           "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                                           "--local-directory", str(base)], **common))
        client = distributed.Client(scheduler_file=str(sfile), timeout="30s")
        client.wait_for_workers(2, timeout=60)
        address = json.loads(sfile.read_text())["address"]
        yield address, client
        client.close()
    finally:
        _stop(procs[1:])
        _stop(procs[:1])


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    base = tmp_path_factory.mktemp("dist-src")
    return {"nerf": make_nerf(base / "scene", views=VIEWS, size=32, seed=8, splits=("train", "test")),
            "render": make_render(base / "render", views=3, size=16, subframes=4, seed=9)}


def _convert(source: Path, out: Path, *extra) -> dict:
    proc = run_spikegen("convert", source, "--out", out, "--intensity", "24", "--intensity", "40",
                        "--frames", "128", "--seed", "11", *extra, timeout=300)
    assert proc.returncode == 0, proc.stderr
    t = tree(out)
    assert t and not [k for k in t if k.endswith(".part") or ".spikegen-job" in k]
    return t


def _executed(client) -> dict:
    return client.run(lambda dask_worker: dask_worker.state.executed_count)


@pytest.mark.parametrize("kind", ["nerf", "render"])
def test_workers_and_dask_match_single_process(kind, sources, cluster, tmp_path):
    address, client = cluster
    src = sources[kind]
    single = _convert(src, tmp_path / "single")
    assert _convert(src, tmp_path / "workers2", "--workers", "2") == single
    before = _executed(client)
    assert _convert(src, tmp_path / "dask", "--scheduler", address) == single
    after = _executed(client)
    ran = {w: after[w] - before.get(w, 0) for w in after}
    views = len({k.split("/", 1)[1] for k in single if k.endswith(".dat")})
    assert sum(ran.values()) >= views, ran  # every view (all intensities in one task) ran on a worker
    assert len(ran) == 2 and all(n > 0 for n in ran.values()), ran  # and both workers took part


def test_dask_resumes_a_partial_folder(sources, cluster, tmp_path):
    """A folder interrupted in a local run is finished on the cluster with the same bytes."""
    address, client = cluster
    src = sources["nerf"]
    single = _convert(src, tmp_path / "single")
    partial = tmp_path / "partial"
    shutil.copytree(tmp_path / "single", partial)
    for folder in partial.iterdir():
        params = json.loads((folder / "manifest.json").read_text())["parameters"]
        (folder / ".spikegen-job.json").write_text(json.dumps({"parameters": params}))  # as if killed
        (folder / "manifest.json").unlink()
        for rel in ("train/r_1.dat", "test/r_3.dat", "test/r_4.png"):
            (folder / rel).unlink()
    kept = (partial / next(iter(sorted(p.name for p in partial.iterdir()))) / "train/r_0.dat").stat().st_ino
    before = sum(_executed(client).values())
    assert _convert(src, partial, "--scheduler", address) == single
    assert sum(_executed(client).values()) - before >= 2 * VIEWS  # every view (one task for all intensities)
    # was visited on a worker
    assert (partial / sorted(p.name for p in partial.iterdir())[0] / "train/r_0.dat").stat().st_ino == kept


def test_a_bad_view_on_a_worker_is_one_line(sources, cluster, tmp_path):
    """An input error raised on a Dask worker reaches the user as one line naming the file."""
    import numpy as np

    from spikegen.spikeio import write_exr

    address, client = cluster
    src = tmp_path / "render"
    shutil.copytree(sources["render"], src)
    bad = np.full((16, 16, 4), 0.5, np.float32)
    bad[2, 2, 0] = np.nan
    write_exr(src / "train/r_2_sub03.exr", bad)
    proc = run_spikegen("convert", src, "--out", tmp_path / "out", "--intensity", "24", "--frames", "64",
                        "--scheduler", address, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "r_2_sub03.exr" in lines[0] and "NaN" in lines[0], lines
    assert not list((tmp_path / "out").rglob("*.part")) and not list((tmp_path / "out").rglob("manifest.json"))


def _slow_or_failing(task):
    if task == 0:
        from spikegen.errors import InputError

        raise InputError("task 0: bad input")
    time.sleep(0.3)
    Path(task_marker_dir(), f"done_{task}").touch()
    return task


def task_marker_dir() -> str:
    return os.environ["SPIKEGEN_TEST_MARKERS"]


def test_first_failure_cancels_the_views_not_started(tmp_path, monkeypatch):
    from spikegen.errors import InputError
    from spikegen.parallel import run_tasks

    monkeypatch.setenv("SPIKEGEN_TEST_MARKERS", str(tmp_path))
    with pytest.raises(InputError, match="task 0"):
        run_tasks(_slow_or_failing, list(range(30)), workers=2, progress=False)
    done = len(list(tmp_path.glob("done_*")))
    assert done < 10, done  # the 29 others (0.3 s each) did not all run after the failure
