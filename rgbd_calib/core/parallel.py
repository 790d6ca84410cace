"""Process pools that are safe with OpenCV, GTSAM (TBB) and Open3D loaded.

Forking a process that already runs library thread pools copies locks held by threads that do
not exist in the child: OpenCV's ``setNumThreads`` then deadlocks in the child (seen in the test
suite). Workers therefore start from a clean ``forkserver`` process.

A worker started that way re-imports the script that started it (as Python's multiprocessing
does for ``spawn`` and ``forkserver``): a script that calls the library at import time, without
an ``if __name__ == "__main__":`` guard, would calibrate again in every worker, which fails with
a long ``BrokenProcessPool`` traceback. :func:`process_context` stops that with one clear line.
"""

from __future__ import annotations

import asyncio
import functools
import multiprocessing
import os
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.context import BaseContext
from pathlib import Path
from typing import Any

from .errors import ConfigError, RgbdCalibError

GUARD = 'if __name__ == "__main__":'


def check_entry_point() -> None:
    """Refuse to start worker processes from a script without a ``__main__`` guard.

    In a worker that is still re-importing the script (the script called the library at import
    time anyway), exit quietly: the parent reports it. In the parent, a ``.py`` main script
    whose text has no ``__main__`` at all is refused before any worker starts."""
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        raise SystemExit(1)
    path = getattr(sys.modules.get("__main__"), "__file__", None)
    if not path or not str(path).endswith(".py"):
        return  # interactive, python -c, a notebook, a frozen entry point
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return
    if "__main__" not in text:
        raise ConfigError(
            f"{path}: calls rgbd-calib at import time, but its worker processes re-import this "
            f"script; put the calls in a function called under `{GUARD}` (README, Library use)"
        )


# imported once by the fork server, before it forks any worker: the modules of the pools'
# tasks (detection, rendering, depth pairs). Without it every worker of every pool
# imported them itself (cv2, open3d, gtsam): ~1.5 s per pool of 2 on a 2-core machine, paid
# by each calibrate, refine and synth stage
PRELOAD = ("rgbd_calib.pipelines.calibrate", "rgbd_calib.depth.stage", "rgbd_calib.synth.render")


def process_context() -> BaseContext:
    """The multiprocessing context every pool of the package uses (after
    :func:`check_entry_point`): forkserver (no fork of a threaded parent), its server
    preloading :data:`PRELOAD` (and the main script, as by default)."""
    check_entry_point()
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["__main__", *PRELOAD])
    return context


class WorkerPool(ProcessPoolExecutor):
    """The package's process pool: :func:`process_context` workers, and a worker that dies
    (the script re-imported without its guard, or the system out of memory) is one clear
    error instead of a ``BrokenProcessPool`` traceback."""

    def __init__(self, max_workers: int | None = None, **kwargs) -> None:
        super().__init__(max_workers, mp_context=process_context(), **kwargs)

    # a worker can die before the last task is even submitted (the script re-imported without
    # its guard exits at once): the pool is then broken at submit time, not only at result
    # time, so both are explained (seen in CI: map of 4 items, BrokenProcessPool from submit)
    def submit(self, fn, /, *args, **kwargs) -> Future:
        try:
            return super().submit(fn, *args, **kwargs)
        except BrokenProcessPool:
            raise self._explained() from None

    def map(self, fn, *iterables, timeout=None, chunksize=1) -> Iterator:
        results = super().map(fn, *iterables, timeout=timeout, chunksize=chunksize)  # submit

        def explained() -> Iterator:
            try:
                yield from results
            except BrokenProcessPool:
                raise self._explained() from None

        return explained()

    @staticmethod
    def _explained() -> RgbdCalibError:
        return RgbdCalibError(
            "a worker process stopped: when this runs from a script, put its calls in a "
            f"function called under `{GUARD}` (README, Library use); otherwise the machine "
            "may be out of memory: use fewer workers"
        )


# ----------------------------------------------------------------------------- one interface
def executor(workers: int | None = None, scheduler: str | None = None,
             initializer: Callable[..., Any] | None = None,
             initargs: tuple = ()) -> Executor:
    """The executor every parallel stage of the package uses: a local :class:`WorkerPool` of
    ``workers`` processes (default: all cores), or with ``scheduler`` (``tcp://HOST:8786``,
    config key ``scheduler``) the workers of that Dask distributed cluster, whatever their
    number (:class:`DaskExecutor`). ``initializer(*initargs)`` runs once in each worker before
    its first task, on either. Use it as a context manager: leaving it by an exception (Ctrl-C)
    cancels what has not run."""
    if scheduler:
        return DaskExecutor(scheduler, initializer, initargs)
    return WorkerPool(workers or os.cpu_count() or 1, initializer=initializer,
                      initargs=initargs)


DASK_HINT = "README, Running on a Dask cluster"
CONNECT_TIMEOUT_S = 10.0


def connect(scheduler: str, timeout_s: float | None = None):
    """A ``distributed.Client`` of the Dask scheduler at ``scheduler``, or a
    :class:`ConfigError` in one line (Dask not installed, nobody answering there) after at
    most ``timeout_s`` (default :data:`CONNECT_TIMEOUT_S`)."""
    timeout_s = CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
    try:
        from distributed import Client
        from distributed.comm import connect as open_comm
    except ImportError:
        raise ConfigError(
            f"--scheduler {scheduler}: Dask is not installed here; install the extra: "
            "pip install 'rgbd-calib[dask]' (versions pinned in requirements.lock)"
        ) from None

    async def probe() -> None:
        comm = await open_comm(scheduler, timeout=timeout_s)
        await comm.close()

    # probed first with one plain connection: a Client that fails to connect is left half
    # made, and its __del__ prints a traceback at exit; in a thread of its own, so that this
    # works under a running event loop too (a notebook)
    try:
        with ThreadPoolExecutor(1) as thread:
            thread.submit(asyncio.run, probe()).result()
    except (ValueError, TypeError) as exc:
        why = " ".join(str(exc).split()) or type(exc).__name__
        raise ConfigError(
            f"--scheduler {scheduler}: not a Dask scheduler address ({why}); give it as "
            f"tcp://HOST:8786 ({DASK_HINT})"
        ) from None
    except (OSError, TimeoutError) as exc:
        why = " ".join(str(exc).split()) or type(exc).__name__
        raise ConfigError(
            f"--scheduler {scheduler}: no Dask scheduler answered there within "
            f"{timeout_s:g} s ({why}); start one with `dask scheduler` and its workers with "
            f"`dask worker {scheduler}`, or fix the address, e.g. tcp://HOST:8786 ({DASK_HINT})"
        ) from None
    return Client(scheduler, timeout=timeout_s, set_as_default=False)


def check_scheduler(scheduler: str | None) -> None:
    """Fail early, before any long step or any file written, when ``scheduler`` is given and
    no Dask scheduler answers there."""
    if scheduler:
        connect(scheduler).close()


def _package_version() -> str:
    """Run on each Dask worker: the rgbd-calib version it imports."""
    from .. import __version__

    return __version__


# worker side: tokens of the initializers that already ran in this worker process
_INITIALISED: set[str] = set()
_INIT_LOCK = threading.Lock()


def _initialised_chunk(token: str, initializer: Callable[..., Any] | None, initargs: tuple,
                       fn: Callable[..., Any], chunk: list[tuple]) -> list[Any]:
    """Run on a Dask worker: ``initializer(*initargs)`` the first time this worker sees
    ``token`` (what a process pool's initializer does once per process), then ``fn`` on each
    argument tuple of ``chunk``."""
    if initializer is not None and token not in _INITIALISED:
        with _INIT_LOCK:
            if token not in _INITIALISED:
                initializer(*initargs)
                _INITIALISED.add(token)
    return [fn(*args) for args in chunk]


class DaskExecutor(Executor):
    """:class:`concurrent.futures.Executor` over a Dask distributed cluster (``submit``,
    ordered ``map`` with ``chunksize``, ``shutdown``), with a process pool's
    ``initializer``: its arguments are sent to every worker once (``scatter(broadcast=True)``)
    and it runs once per worker process, lazily, before that worker's first task of this
    executor. The scheduler spreads the tasks; nothing here schedules. Leaving the ``with``
    block by an exception (Ctrl-C) cancels every task not yet done and closes the client."""

    def __init__(self, scheduler: str, initializer: Callable[..., Any] | None = None,
                 initargs: tuple = ()) -> None:
        self.scheduler = scheduler
        self._client = connect(scheduler)
        try:
            self._check_workers()
        except BaseException:
            self._client.close()
            raise
        self._token = uuid.uuid4().hex
        self._initializer = initializer
        self._initargs: Any = ()
        if initializer is not None:
            [self._initargs] = self._client.scatter([tuple(initargs)], broadcast=True,
                                                    hash=False)
        self._futures: list[Any] = []

    def _check_workers(self) -> None:
        """At least one worker, each running this version of the package: tasks sent to a
        cluster without workers would wait forever, and a worker without the package fails
        every task."""
        try:
            self._client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except TimeoutError:
            raise ConfigError(
                f"--scheduler {self.scheduler}: no worker is connected to that scheduler; start "
                f"them with `dask worker {self.scheduler} --nthreads 1` on machines that see "
                f"the dataset ({DASK_HINT})") from None
        try:
            versions = self._client.run(_package_version)
        except Exception as exc:  # noqa: BLE001 - whatever the worker raised, in one line
            raise self._explained(exc) from None
        from .. import __version__

        if other := {w: v for w, v in versions.items() if v != __version__}:
            worker, version = next(iter(other.items()))
            raise ConfigError(
                f"--scheduler {self.scheduler}: worker {worker} runs rgbd-calib {version}, "
                f"this is {__version__}; install the same version on every worker and restart "
                f"them ({DASK_HINT})")

    def _submit_chunk(self, fn: Callable[..., Any], chunk: list[tuple]):
        future = self._client.submit(_initialised_chunk, self._token, self._initializer,
                                     self._initargs, fn, chunk, pure=False)
        self._futures.append(future)
        return future

    def submit(self, fn, /, *args, **kwargs) -> Future:
        if kwargs:
            fn = functools.partial(fn, **kwargs)
        dask_future = self._submit_chunk(fn, [args])
        future: Future = Future()

        def done(f) -> None:
            if f.cancelled() or f.status == "cancelled":
                future.cancel()
                future.set_running_or_notify_cancel()
                return
            try:
                future.set_result(f.result()[0])
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's result()
                future.set_exception(self._explained(exc))

        dask_future.add_done_callback(done)
        return future

    def map(self, fn, *iterables, timeout=None, chunksize=1) -> Iterator:
        items = list(zip(*iterables))
        size = max(1, int(chunksize))
        futures = [self._submit_chunk(fn, items[i:i + size]) for i in range(0, len(items), size)]

        def results() -> Iterator:
            for f in futures:
                try:
                    chunk = f.result(timeout=timeout)
                except Exception as exc:  # noqa: BLE001 - explained, then raised
                    raise self._explained(exc) from None
                yield from chunk

        return results()

    def _explained(self, exc: BaseException) -> BaseException:
        """A worker's failure that is the set-up's, not the data's, as one clear line."""
        if isinstance(exc, ImportError) or "rgbd_calib" in str(exc) and "No module" in str(exc):
            return RgbdCalibError(
                f"the Dask workers of {self.scheduler} cannot import rgbd_calib ({exc}): "
                f"install this package in the workers' environment ({DASK_HINT})")
        if isinstance(exc, (RgbdCalibError, OSError)):
            where = (f" (on a Dask worker of {self.scheduler}: the workers must see the dataset "
                     f"at the same path, {DASK_HINT})")
            return RgbdCalibError(f"{' '.join(str(exc).split())}{where}")
        return exc

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        pending = [f for f in self._futures if not f.done()]
        if pending and (cancel_futures or not wait):
            self._client.cancel(pending)
        elif pending:
            from distributed import wait as wait_for

            wait_for(pending)
        self._futures = []
        self._client.close()

    def __exit__(self, exc_type, exc, tb) -> bool:
        # an exception (Ctrl-C, an error in the caller's loop): nothing left runs on
        self.shutdown(wait=exc_type is None, cancel_futures=exc_type is not None)
        return False
