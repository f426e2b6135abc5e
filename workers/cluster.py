"""Where a study's tasks run: an existing Dask scheduler, or an embedded LocalCluster."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import signal


class ClusterClient:
    """Context manager: a Dask client on an existing scheduler (``scheduler`` = its address), or on an
    embedded process-based LocalCluster with ``workers`` workers (default: one per core)."""

    def __init__(self, scheduler: str | None, workers: int | None, *, scheduler_process: bool = False):
        self.scheduler, self.workers, self.scheduler_process = scheduler, workers, scheduler_process

    def __enter__(self):
        import os

        from distributed import Client

        if self.scheduler:
            self.cluster = None
            self.client = Client(self.scheduler)
        else:
            n = self.workers or os.cpu_count() or 1
            with deaf_to_ctrl_c():
                self._start(n)
            self.client = Client(self.cluster)
            # compute yields to the driver, the API and the scheduler on a shared machine
            self.client.run(os.nice, 10)
        print(f"[ardflow] Dask dashboard: {self.client.dashboard_link}", flush=True)
        return self.client

    def _start(self, n: int) -> None:
        """The embedded cluster with ``n`` workers (the dashboard has no authentication: loopback only)."""
        if self.scheduler_process:
            # the service's scheduler in its own process (Dask's SubprocessCluster): it would otherwise share
            # the API's interpreter lock, and every task of every study would delay a status read
            from distributed.deploy.subprocess import SubprocessCluster

            self.cluster = SubprocessCluster(host="127.0.0.1", n_workers=n, threads_per_worker=1,
                                             dashboard_address="127.0.0.1:8787", silence_logs=40)
        else:
            from distributed import LocalCluster

            self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                        dashboard_address="127.0.0.1:8787", silence_logs=40)

    def __exit__(self, *exc):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


@contextlib.contextmanager
def deaf_to_ctrl_c():
    """Child processes started inside do not hear a Ctrl-C meant for this one: a Ctrl-C in the terminal
    reaches the whole foreground process group, and each child would die on its own with its traceback while
    this process still talks to it. Inside, SIGINT is ignored (a child inherits that through exec, and Python
    keeps an ignored SIGINT) and the processes asyncio starts (Dask's ``dask spec`` scheduler and nannies,
    which install their own SIGINT handler) get a session of their own, and SIGTERM when this process dies
    (:func:`die_with_parent`: a killed service takes them along). This process stops them in order. Outside the main thread (where no signal handler can be set) only the latter applies."""
    start = asyncio.create_subprocess_exec
    asyncio.create_subprocess_exec = functools.partial(start, start_new_session=True, preexec_fn=die_with_parent)
    try:
        old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: no handler can be set here
        old = None
    try:
        yield
    finally:
        asyncio.create_subprocess_exec = start
        if old is not None:
            signal.signal(signal.SIGINT, old)


def die_with_parent() -> None:
    """In a child between fork and exec: the kernel sends it SIGTERM when the process that started it dies (a
    SIGKILLed service must not leave its drivers or its cluster running; a store's driver lock refuses a
    second driver anyway), and it ignores SIGINT (a Ctrl-C in the service's terminal reaches its whole
    process group: the service stops its children itself, each would otherwise print its own traceback).
    Linux only; elsewhere a no-op. (The kernel watches the thread that started the child: the children of an
    event loop's thread die with that loop.)"""
    import ctypes

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # inherited through exec: Python keeps an ignored SIGINT
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
