"""Where a study's tasks run: ``serial`` (this process), ``process`` (local cores) or ``dask`` (dask.distributed).

One small protocol, so the runner does not care which: ``submit(fn, *args) -> handle``, ``wait(handles) -> done`` (at
least one finished handle), ``result(handle)``, ``close(cancel)``. Results always come back to the runner, which alone
writes the store, so a remote Dask worker needs no shared file system.
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import signal

from ..errors import ConfigError

BACKENDS = ("serial", "process", "dask")


class _Deferred:
    """A task of the serial backend: run when the runner first waits on it."""

    __slots__ = ("fn", "args", "value", "exc", "done")

    def __init__(self, fn, args):
        self.fn, self.args = fn, args
        self.value = self.exc = None
        self.done = False


class SerialBackend:
    """Run each task in this process, in submission order, one at a time."""

    name = "serial"

    def __init__(self):
        self.jobs = 1

    def submit(self, fn, *args):
        return _Deferred(fn, args)

    def wait(self, handles):
        task = next(iter(handles))  # the oldest: handles is an insertion-ordered dict or sequence
        try:
            task.value = task.fn(*task.args)
        except Exception as exc:  # re-raised by result(), as a future would
            task.exc = exc
        task.done = True
        return [task]

    def result(self, handle):
        if handle.exc is not None:
            raise handle.exc
        return handle.value

    def close(self, cancel: bool = False) -> None:
        pass


#: prctl's option that sends the calling process a signal when its parent dies (Linux, <linux/prctl.h>)
PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    """Ask Linux to send this worker SIGTERM when the runner dies (a runner killed with SIGKILL cannot stop its
    workers, which would wait on the task queue forever, orphaned); elsewhere, nothing. A runner already gone before
    the request took effect: exit at once."""
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):
        return
    if parent and os.getppid() != parent:
        os._exit(1)


def _worker_signals(jobs: int = 0, parent: int = 0) -> None:
    # Workers leave Ctrl-C to the runner, which stops them itself after the store is consistent; SIGTERM (how the
    # runner stops them) must kill them outright, whatever handler a forked worker inherited from its parent.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _die_with_parent(parent)
    if jobs:  # the compiled filters split a batch over threads (socbench.kernels.engine): the workers share the cores
        from ..kernels.engine import share_cores

        share_cores(jobs)


class ProcessBackend:
    """A local :class:`concurrent.futures.ProcessPoolExecutor` with ``jobs`` worker processes."""

    name = "process"

    def __init__(self, jobs: int | None = None):
        self.jobs = int(jobs or os.cpu_count() or 1)
        self.pool = cf.ProcessPoolExecutor(max_workers=self.jobs, initializer=_worker_signals,
                                           initargs=(self.jobs, os.getpid()))

    def submit(self, fn, *args):
        return self.pool.submit(fn, *args)

    def wait(self, handles):
        return list(cf.wait(list(handles), return_when=cf.FIRST_COMPLETED).done)

    def result(self, handle):
        return handle.result()

    def close(self, cancel: bool = False) -> None:
        if not cancel:
            self.pool.shutdown(wait=True)
            return
        # Interrupted: drop queued tasks and stop the running ones now (their results were never stored).
        procs = list((getattr(self.pool, "_processes", None) or {}).values())
        self.pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(timeout=5)
            if p.is_alive():
                p.kill()
                p.join(timeout=5)


class DaskBackend:
    """A dask.distributed client: on the scheduler at ``address``, or on a LocalCluster of ``jobs`` processes."""

    name = "dask"

    def __init__(self, jobs: int | None = None, address: str | None = None):
        try:
            import distributed
        except ImportError:  # pragma: no cover - dask is a declared optional dependency
            raise ConfigError("the dask backend needs dask.distributed: pip install 'socbench[dask]'") from None
        self._distributed = distributed
        self.cluster = None
        if address:
            try:
                self.client = distributed.Client(address, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise ConfigError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
        else:
            n = int(jobs or os.cpu_count() or 1)
            self.cluster = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                    dashboard_address=None)
            self.client = distributed.Client(self.cluster)
        self._submitted = []
        self.jobs = max(1, sum(w.get("nthreads", 1) for w in self.client.scheduler_info()["workers"].values()))

    def submit(self, fn, *args):
        fut = self.client.submit(fn, *args, pure=False)
        self._submitted.append(fut)
        return fut

    def wait(self, handles):
        return list(self._distributed.wait(list(handles), return_when="FIRST_COMPLETED").done)

    def result(self, handle):
        return handle.result()

    def close(self, cancel: bool = False) -> None:
        try:
            if cancel:
                self.client.cancel([f for f in self._submitted if not f.done()])
        finally:
            self.client.close()
            if self.cluster is not None:
                self.cluster.close()


def make_backend(name: str, jobs: int | None = None, scheduler: str | None = None):
    if name not in BACKENDS:
        raise ConfigError(f"unknown backend '{name}'; known: {', '.join(BACKENDS)}")
    if scheduler and name != "dask":
        raise ConfigError("--scheduler needs --backend dask")
    if jobs is not None and jobs < 1:
        raise ConfigError(f"--jobs must be at least 1, got {jobs}")
    if name == "serial":
        return SerialBackend()
    if name == "process":
        return ProcessBackend(jobs)
    return DaskBackend(jobs, scheduler)
