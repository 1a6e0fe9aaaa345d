"""Run independent per-view tasks in this process, in local processes, or on a Dask cluster.

Every task carries its own seed (see :mod:`spikegen.seeding`), so where it runs does not
change what it writes.
"""
from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Callable, Iterable

from .errors import InputError


def run_tasks(fn: Callable, tasks: Iterable, workers: int = 1, scheduler: str | None = None,
              progress: bool = True, desc: str = "views") -> list:
    """Apply ``fn`` to every task; results in task order. Shows a tqdm bar when ``progress``."""
    tasks = list(tasks)
    if workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")
    bar = _bar(len(tasks), progress, desc)
    try:
        if scheduler:
            return _run_dask(fn, tasks, scheduler, bar)
        if workers == 1 or len(tasks) <= 1:
            out = []
            for t in tasks:
                out.append(fn(t))
                bar.update(1)
            return out
        results = [None] * len(tasks)
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = {pool.submit(fn, t): i for i, t in enumerate(tasks)}
            for fut in as_completed(futures):
                results[futures[fut]] = fut.result()
                bar.update(1)
        return results
    finally:
        bar.close()


def _run_dask(fn, tasks, address, bar):
    try:
        from distributed import Client, as_completed as dask_completed
    except ImportError:
        raise InputError("--scheduler needs dask.distributed (pip install 'dask[distributed]')") from None
    try:
        client = Client(address, timeout="10s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"--scheduler {address}: cannot connect to a Dask scheduler ({exc})") from None
    with client:
        futures = client.map(fn, tasks, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        results = [None] * len(tasks)
        for fut in dask_completed(futures):
            results[index[fut.key]] = fut.result()
            bar.update(1)
        return results


class _NoBar:
    def update(self, n=1):
        pass

    def close(self):
        pass


def _bar(total, progress, desc):
    if not progress:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="view", leave=False)
