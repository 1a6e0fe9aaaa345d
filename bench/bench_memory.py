"""Peak memory of ``spikegen convert`` on a many-view scene (issue 6: "peak RSS under 2 GB").

Makes a synthetic NeRF-synthetic folder (RGBA PNGs, seeded) in a temporary folder, runs the
real ``spikegen convert`` on it as a subprocess and prints

- ``peak_rss_largest_process_mib``: ``ru_maxrss`` of the largest process of the run (kernel
  accounting, from ``getrusage(RUSAGE_CHILDREN)``);
- ``peak_rss_tree_mib``: the largest sum of RSS over the ``spikegen`` process and its worker
  processes, sampled from ``/proc`` every 0.1 s (counts shared pages once per process, so it
  is an upper bound of what the machine needed);
- wall time and views per second.

Usage::

    python bench/bench_memory.py                       # 400 views, 400 x 400, 256 frames, paper sensor
    python bench/bench_memory.py --views 100,400 --workers 2
    python bench/bench_memory.py --views 40 --size 64  # quick check
    python bench/bench_memory.py --dask                # on a local scheduler + 2 workers (--scheduler)

With ``--dask`` the figures also count the scheduler and worker processes
(``peak_rss_cluster_mib``: the largest sampled sum over them).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _scale_helpers import make_nerf, spikegen_cmd  # noqa: E402


def tree_rss_bytes(pid: int) -> int:
    """Sum of VmRSS of ``pid`` and all its descendants (Linux /proc)."""
    children = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
                children.setdefault(ppid, []).append(int(d))
            except (OSError, ValueError, IndexError):
                pass
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        todo.extend(children.get(p, []))
        try:
            with open(f"/proc/{p}/status") as fh:
                for line in fh:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) * 1024
        except OSError:
            pass
    return total


def run_convert(source: Path, out: Path, args, cluster=None) -> dict:
    cmd = spikegen_cmd("convert", source, "--intensity", args.intensity, "--out", out, "--sensor", args.sensor,
                       "--frames", args.frames, "--workers", args.workers)
    if cluster is not None:
        cmd += ["--scheduler", cluster[0]]
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak_tree = peak_cluster = 0
    while proc.poll() is None:
        peak_tree = max(peak_tree, tree_rss_bytes(proc.pid))
        if cluster is not None:
            peak_cluster = max(peak_cluster, sum(tree_rss_bytes(p.pid) for p in cluster[1]))
        time.sleep(0.1)
    wall = time.perf_counter() - t0
    stdout, stderr = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"spikegen convert failed ({proc.returncode}): {stderr.strip()[-500:]}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # KiB on Linux, max over children
    dataset = Path(stdout.strip().splitlines()[-1])
    dat_bytes = sum(p.stat().st_size for p in dataset.rglob("*.dat"))
    return {"wall_s": round(wall, 1), "peak_rss_largest_process_mib": round(after / 1024, 1),
            "peak_rss_largest_process_is_new": after > before,
            "peak_rss_tree_mib": round(peak_tree / 2**20, 1), "spike_bytes_written_mib": round(dat_bytes / 2**20, 1),
            **({"peak_rss_cluster_mib": round(peak_cluster / 2**20, 1)} if cluster is not None else {})}


def start_cluster(work: Path, n_workers: int = 2):
    """(address, processes) of ``dask scheduler`` + ``n_workers`` single-thread ``dask worker`` on 127.0.0.1."""
    dask = str(Path(sys.executable).parent / "dask")
    sfile = work / "scheduler.json"
    log = open(work / "cluster.log", "w")
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sfile)], stdout=log, stderr=log, start_new_session=True)]
    while not sfile.is_file():
        time.sleep(0.1)
    for _ in range(n_workers):
        procs.append(subprocess.Popen([dask, "worker", "--scheduler-file", str(sfile), "--nworkers", "1",
                                       "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1",
                                       "--local-directory", str(work)], stdout=log, stderr=log,
                                      start_new_session=True))
    from distributed import Client

    with Client(scheduler_file=str(sfile), timeout="60s") as c:
        c.wait_for_workers(n_workers, timeout=120)
    return json.loads(sfile.read_text())["address"], procs


def stop_cluster(procs) -> None:
    for p in reversed(procs):
        os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", default="400", help="comma-separated view counts to measure (default 400)")
    ap.add_argument("--size", type=int, default=400, help="image size N (N x N), default 400")
    ap.add_argument("--frames", type=int, default=256)
    ap.add_argument("--intensity", default="32")
    ap.add_argument("--sensor", default="paper")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--tmp", default=None, help="folder for the temporary source and output")
    ap.add_argument("--dask", action="store_true", help="convert on a local Dask scheduler + 2 workers")
    args = ap.parse_args(argv)
    counts = [int(v) for v in args.views.split(",")]
    work = Path(tempfile.mkdtemp(prefix="spikegen-bench-mem-", dir=args.tmp))
    cluster = start_cluster(work) if args.dask else None
    try:
        for n in counts:
            t0 = time.perf_counter()
            src = make_nerf(work / f"scene{n}", views=n, size=args.size, seed=0)
            made = time.perf_counter() - t0
            res = run_convert(src, work / f"out{n}", args, cluster)
            res.update({"views": n, "size": f"{args.size}x{args.size}", "frames": args.frames,
                        "workers": "dask 2" if cluster else args.workers, "sensor": args.sensor, "source_build_s": round(made, 1),
                        "views_per_s": round(n / res["wall_s"], 2)})
            print(json.dumps(res), flush=True)
            shutil.rmtree(work / f"out{n}")
            shutil.rmtree(src)
    finally:
        if cluster is not None:
            stop_cluster(cluster[1])
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
