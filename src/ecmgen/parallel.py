"""Independent tasks of a build on a few processes, with the build's own rules kept.

:class:`Workers` runs module-level functions either here, one after the other
(``processes <= 1``), or on a pool of worker processes, forked from a fork server that has
loaded what the tasks import (where the platform has one; else freshly started, "spawn").
Either way:

- results come back in the order the tasks were given, and each task runs whole in one
  process, so the results do not depend on scheduling;
- a task's progress messages (the ``progress`` callable it is given) and its Python
  warnings are collected and handed back to this process when its result is taken:
  messages through the caller's ``progress``, warnings re-issued here, so that the
  warning filters of the caller (the command line's, pytest's ``-W error``) apply;
- an :class:`~ecmgen.errors.InputError` raised by a task is raised again here, as itself;
- a worker uses one BLAS thread (OPENBLAS/OMP/MKL_NUM_THREADS, unless set):
  the processes already use the cores.

The pool starts on the first task given to it (a build with one pulse test never starts
it). Scripts that call it must guard their top level with ``if __name__ == "__main__":``
(Python's rule for started processes); notebooks and the command line need nothing.

Why the standard library's pool and not Dask (which ``ecmgen fleet`` runs its builds on):
measured on the bundled build over temperature (bench/bench_parallel_engine.py, see
docs/results.md), Dask's local scheduler is itself a concurrent.futures process pool
underneath and costs the same CPU; a dask.distributed LocalCluster costs about 15 % more
CPU for the same tasks (its event loops, nannies and heartbeats) and would make Dask a
dependency of every build. A fleet runs each of its builds on one process (workers=1):
the fleet's workers already use the cores.
"""

from __future__ import annotations

import functools
import os
import threading
import warnings
from contextlib import contextmanager
from typing import Any, Callable

from .errors import InputError

# one BLAS thread: set in the workers and by the command line before numpy loads. The
# fits make many small BLAS calls: threads for them buy no speed and, spinning on cores
# other processes need, made four `ecmgen diagnose` side by side on two cores 7.9 times
# slower (bench/bench_blas_threads.py, docs/results.md)
ONE_BLAS_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
_BLAS_LOCK = threading.Lock()
_blas_depth = [0, None]          # calls inside one_blas_thread, and its limiter


def one_blas_thread(fn: Callable) -> Callable:
    """``fn`` with numpy's BLAS held to one thread while it runs (threadpoolctl), for a
    caller whose numpy loaded before the environment could say so: a notebook or script
    calling the library. The one-temperature fit of the 25 degC example from a notebook on
    a 2-core machine with one other busy process: 38.6 s with OpenBLAS's two threads, 3.2 s
    with one. The first call sets the limit, the last one out (of any thread) lifts it."""
    @functools.wraps(fn)
    def limited(*args, **kwargs):
        with _BLAS_LOCK:
            if _blas_depth[0] == 0:
                from threadpoolctl import threadpool_limits

                _blas_depth[1] = threadpool_limits(1, user_api="blas")
            _blas_depth[0] += 1
        try:
            return fn(*args, **kwargs)
        finally:
            with _BLAS_LOCK:
                _blas_depth[0] -= 1
                if _blas_depth[0] == 0:
                    _blas_depth[1].restore_original_limits()
                    _blas_depth[1] = None
    return limited


def _quiet(_msg: str) -> None:
    pass


def run_collected(fn: Callable, args: tuple) -> tuple:
    """Run ``fn(*args, progress=<collector>)``; returns (status, value, messages, warnings)
    with status "ok" (value = the result) or "input" (value = (path, message))."""
    messages: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            value = fn(*args, progress=messages.append)
            status = "ok"
        except InputError as exc:
            status, value = "input", (exc.path, exc.message)
    found = [(str(w.message), w.category, w.filename, w.lineno) for w in caught]
    return status, value, messages, found


class Task:
    """One submitted task; :meth:`result` gives its value (in this process)."""

    def __init__(self, future=None, done: tuple | None = None):
        self._future, self._done = future, done

    def result(self, progress: Callable[[str], None] = _quiet) -> Any:
        status, value, messages, found = (self._done if self._done is not None
                                          else self._future.result())
        for msg in messages:
            progress(msg)
        for message, category, filename, lineno in found:
            warnings.warn_explicit(message, category, filename, lineno)
        if status == "input":
            raise InputError(*value)
        return value


class Workers:
    """Run tasks here (``processes <= 1``) or on up to ``processes`` spawned processes.
    Use as a context manager; the pool (if any) is shut down on exit."""

    def __init__(self, processes: int = 2):
        self.processes = max(1, int(processes))
        self._pool = None

    @property
    def parallel(self) -> bool:
        return self.processes > 1

    def submit(self, fn: Callable, *args) -> Task:
        """``fn(*args, progress=...)`` (a module-level function: it is pickled by name)."""
        if not self.parallel:
            return Task(done=run_collected(fn, args))
        if self._pool is None:
            self._start()
        return Task(future=self._pool.submit(run_collected, fn, args))

    def map(self, fn: Callable, arg_tuples, progress: Callable[[str], None] = _quiet
            ) -> list:
        """``fn`` over every argument tuple; the results in order."""
        tasks = [self.submit(fn, *a) for a in arg_tuples]
        try:
            return [t.result(progress) for t in tasks]
        except BaseException:
            self.cancel(tasks)
            raise

    @staticmethod
    def cancel(tasks) -> None:
        for t in tasks:
            if t._future is not None:
                t._future.cancel()

    def _start(self) -> None:
        from concurrent.futures import ProcessPoolExecutor

        # workers are spawned as tasks arrive and read the environment when they start:
        # it holds until the pool is closed
        self._env = _worker_environment()
        self._env.__enter__()
        self._pool = ProcessPoolExecutor(max_workers=self.processes, mp_context=_context(),
                                         initializer=_adopt_environment,
                                         initargs=(dict(os.environ),))

    def close(self) -> None:
        if self._pool is not None:
            try:
                self._pool.shutdown(wait=True, cancel_futures=True)
            finally:
                self._pool = None
                self._env.__exit__(None, None, None)

    def __enter__(self) -> "Workers":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# what every worker of a build imports: loaded once, in the fork server the workers are
# forked from, instead of in each freshly started worker
PRELOAD = ["ecmgen.pipeline", "ecmgen.validation", "ecmgen.fit.curve", "scipy.optimize",
           "matplotlib.pyplot"]


def start_fork_server() -> None:
    """Start the fork server the workers are forked from now (where the platform has one),
    so that it loads PRELOAD beside the caller's own work (a command line's imports)
    rather than when the first task is given: the pool's first fork finds it running."""
    from multiprocessing import forkserver

    ctx = _context()
    if ctx.get_start_method() != "forkserver":
        return
    with _worker_environment():
        forkserver.ensure_running()


def _adopt_environment(env: dict) -> None:
    """A worker's environment is this process's when the pool starts (CC, ECMGEN_CACHE, ..),
    not the fork server's, which started with the first pool of the process."""
    os.environ.clear()
    os.environ.update(env)


def _context():
    """Workers forked from a fork server that has loaded PRELOAD (a clean, single-threaded
    process: not this one, whose state a fork would copy), else freshly started ones."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    return ctx


@contextmanager
def _worker_environment():
    # the workers draw PNGs only: the headless backend from the start (the fork server
    # loads pyplot before any worker sets it)
    env = {**ONE_BLAS_THREAD, "MPLBACKEND": "Agg"}
    old = {k: os.environ.get(k) for k in env}
    for k, v in env.items():
        os.environ.setdefault(k, v)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
