"""Where fan-out work runs: in this process, in local worker processes, or on a Dask cluster.

Every executor has one method, ``map(fn, items) -> iterator of results in item order``, so a
stage chooses the engine with one setting (``executor="local" | "serial" | "dask"``) and never
knows which one it got. ``fn`` must be a module-level function (picklable).

OpenGL: :func:`gtkit.render.renderer.gl_context` is one EGL context per *process*. Local
workers are started with the ``spawn`` method so no child ever inherits a parent's context;
each worker creates its own on first use. Dask's local cluster uses spawned processes too.
"""
from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

from ..errors import GtkitError

EXECUTORS = ("serial", "local", "dask")


def default_workers() -> int:
    return max(1, min(2, os.cpu_count() or 1))


class SerialExecutor:
    """Runs everything in this process (debugging, tiny jobs, one worker)."""

    name = "serial"

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        for it in items:
            yield fn(it)

    def close(self):
        pass


def _exit_with_parent(parent: int) -> None:
    """Worker initializer: leave when the process that started the pool is gone.

    A pool's workers outlive a parent killed with SIGKILL (each holds both ends of its task
    queue, so it never reads an end of file): they would sit idle, ~100 MB each, until the machine
    restarts. A daemon thread checks once a second whether the worker was orphaned.
    """
    import threading
    import time

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="gtkit-exit-with-parent", daemon=True).start()


class LocalExecutor:
    """A pool of spawned local processes (the default); they end with the process that started them."""

    name = "local"

    def __init__(self, workers: int):
        self.workers = workers
        self._pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                         initializer=_exit_with_parent, initargs=(os.getpid(),))

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        return self._pool.map(fn, list(items))

    def close(self):
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor:
    """Dask distributed: an existing scheduler (``address``) or a LocalCluster of ``workers``
    single-threaded worker processes. Needs the optional extra ``gtkit[distributed]``."""

    name = "dask"

    def __init__(self, workers: int, address: str | None = None):
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError:
            raise GtkitError("the Dask executor needs the optional extra: pip install 'gtkit[distributed]'") from None
        self._cluster = None
        if address:
            self._client = Client(address)
            self.workers = max(1, len(self._client.scheduler_info().get("workers", {})))
        else:
            self.workers = workers
            self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                         dashboard_address=None, silence_logs=40)
            self._client = Client(self._cluster)

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        from dask.distributed import as_completed  # noqa: F401 - keeps the import check local

        futures = self._client.map(fn, list(items), pure=False)
        for f in futures:  # item order
            yield f.result()

    def close(self):
        self._client.close()
        if self._cluster is not None:
            self._cluster.close()


@dataclass(frozen=True)
class ExecutorSettings:
    kind: str = "local"            # serial | local (spawned processes) | dask
    workers: int = 0               # 0 = min(2, CPU count); 1 with 'local' runs in this process
    address: str | None = None     # dask scheduler address; None = start a LocalCluster


def make_executor(settings: ExecutorSettings | str = "local", workers: int = 0, address: str | None = None):
    """An executor by name. ``local`` with one worker degrades to ``serial`` (no spawn cost)."""
    if isinstance(settings, str):
        settings = ExecutorSettings(settings, workers, address)
    n = settings.workers or default_workers()
    if settings.kind not in EXECUTORS:
        raise GtkitError(f"unknown executor {settings.kind!r} (choose from {', '.join(EXECUTORS)})")
    if settings.kind == "serial" or (settings.kind == "local" and n == 1):
        return SerialExecutor()
    if settings.kind == "local":
        return LocalExecutor(n)
    return DaskExecutor(n, settings.address)


def iter_map(executor, fn: Callable, items: list, progress: str | None = None) -> Iterator[Any]:
    """``executor.map`` with an optional tqdm progress bar, yielding results in item order as they
    come: a consumer that writes each one away holds one result at a time, not all of them (the
    medium sample's database features are ~9 GB in all), and keeps what is done if the run dies."""
    it = executor.map(fn, items)
    if progress:
        from ..progress import progress_bar

        it = progress_bar(len(items), progress, iterable=it)
    yield from it


def run_map(executor, fn: Callable, items: list, progress: str | None = None) -> list[Any]:
    """:func:`iter_map`, collected: the list of results (for small results only)."""
    return list(iter_map(executor, fn, items, progress))
