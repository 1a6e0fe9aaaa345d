"""Run independent per-view tasks in this process, in local processes, or on a Dask cluster.

Every task carries its own seed (see :mod:`spikegen.seeding`), so where it runs does not
change what it writes.
"""
from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor, as_completed
from functools import partial
from typing import Callable, Iterable

from .errors import InputError, OutputError


class Stopped(OutputError):
    """A run asked to stop (``stop``) before its last task."""


def run_tasks(fn: Callable, tasks: Iterable, workers: int = 1, scheduler=None,
              progress: bool = True, desc: str = "views", shared: dict | None = None, stop=None) -> list:
    """Apply ``fn`` to every task; results in task order. Shows a tqdm bar when ``progress``
    (and stderr is a terminal).

    ``scheduler``: a Dask scheduler address or a connected ``distributed.Client`` (see
    :func:`connect`). ``shared``: keyword arguments common to every task (e.g. a sensor with its
    maps), passed as ``fn(task, **shared)`` where it runs; on Dask they are sent to the workers once.
    On the first failing task the tasks not yet started are cancelled and its error raised.
    ``stop``: a callable checked before each task of an in-process run; when it returns True the
    run ends with :class:`Stopped` (tasks already finished keep what they wrote).
    """
    tasks = list(tasks)
    if workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")
    shared = dict(shared or {})
    bar = _bar(len(tasks), progress, desc)
    try:
        if scheduler is not None:
            if isinstance(scheduler, str):
                with connect(scheduler) as client:
                    return _run_dask(fn, tasks, client, bar, shared)
            return _run_dask(fn, tasks, scheduler, bar, shared)
        call = partial(_with_shared, fn, shared=shared)
        if workers == 1 or len(tasks) <= 1:
            out = []
            for t in tasks:
                if stop is not None and stop():
                    raise Stopped("stopped before the end; finished views are kept, rerun to finish")
                out.append(call(t))
                bar.update(1)
            return out
        return _run_pool(call, tasks, workers, bar)
    finally:
        bar.close()


def _with_shared(fn: Callable, task, shared: dict | None = None):
    return fn(task, **shared) if shared else fn(task)


def _run_pool(call, tasks, workers, bar):
    results = [None] * len(tasks)
    pool = ProcessPoolExecutor(max_workers=workers)
    try:
        futures = {pool.submit(call, t): i for i, t in enumerate(tasks)}
        for fut in as_completed(futures):
            results[futures[fut]] = fut.result()
            bar.update(1)
    except BaseException:
        pool.shutdown(wait=True, cancel_futures=True)  # views already running finish; none start
        raise
    pool.shutdown(wait=True)
    return results


def connect(address: str):
    """A ``distributed.Client`` connected to the scheduler at ``address`` (one clear error if not)."""
    try:
        from distributed import Client
    except ImportError:
        raise InputError("--scheduler needs dask.distributed (pip install 'dask[distributed]')") from None
    try:
        return Client(address, timeout="10s")
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        raise InputError(f"--scheduler {address}: cannot connect to a Dask scheduler ({exc})") from None


def _run_dask(fn, tasks, client, bar, shared):
    from distributed import as_completed as dask_completed

    shared_future = client.scatter([shared], broadcast=True, hash=False)[0] if shared else None
    futures = client.map(partial(_with_shared, fn), tasks, shared=shared_future, pure=False)
    index = {f.key: i for i, f in enumerate(futures)}
    results = [None] * len(tasks)
    try:
        for fut in dask_completed(futures):
            results[index[fut.key]] = fut.result()
            bar.update(1)
    except BaseException:
        client.cancel(futures)
        raise
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

    return tqdm(total=total, desc=desc, unit="view", leave=False, disable=None)  # None: off when not a tty
