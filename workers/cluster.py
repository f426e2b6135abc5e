"""Where a study's tasks run: an existing Dask scheduler, or an embedded LocalCluster."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import signal


WORKER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
}
"""How ardflow's own workers run. A chain's task spends most of its time in a compiled likelihood that
releases the interpreter lock, and between calls runs the sampler's Python, whose lock every wake-up of the
worker's other threads takes: Dask's statistical profiler (the dashboard's Profile page) samples every thread
every 10 ms, the event loop's blocked-loop check ticks every 20 ms, the memory and system monitors poll every
0.1 and 0.5 s. Measured on 2 cores (docs/benchmarks.md), a trial's tasks ran 6-8 % longer on a worker than
in a plain process with them, about as long with these settings. The dashboard keeps its task stream and
memory plots (coarser); a worker over its memory limit is stopped within 1 s. A scheduler someone else runs
keeps its own configuration."""

WORKER_ENV = {"DASK_" + k.upper().replace(".", "__").replace("-", "_"): str(v) for k, v in WORKER_CONFIG.items()}


class ClusterClient:
    """Context manager: a Dask client on an existing scheduler (``scheduler`` = its address), or on an
    embedded process-based LocalCluster with ``workers`` workers (default: one per core)."""

    def __init__(self, scheduler: str | None, workers: int | None, *, scheduler_process: bool = False):
        self.scheduler, self.workers, self.scheduler_process = scheduler, workers, scheduler_process
        self.env: dict = {}  # what a process must have in its environment to be a client of this cluster

    def __enter__(self):
        import os

        from distributed import Client, Security

        if self.scheduler:
            self.cluster = None
            self.client = Client(self.scheduler)
        else:
            n = self.workers or os.cpu_count() or 1
            with deaf_to_ctrl_c():
                self._start(n)
            self.client = Client(self.cluster, security=getattr(self.cluster, "security", None) or Security())
            # compute yields to the driver, the API and the scheduler on a shared machine
            self.client.run(os.nice, 10)
        self.client.ardflow_env = dict(self.env)  # for the processes the service starts as clients (drivers)
        print(f"[ardflow] Dask dashboard: {self.client.dashboard_link}", flush=True)
        return self.client

    def _start(self, n: int) -> None:
        """The embedded cluster with ``n`` workers (the dashboard has no authentication: loopback only), its
        workers configured by :data:`WORKER_CONFIG`."""
        import dask

        with dask.config.set(WORKER_CONFIG), exported(WORKER_ENV):  # a LocalCluster's nannies pass on this
            # process's config, a SubprocessCluster's processes read their environment
            self._start_cluster(n)

    def _start_cluster(self, n: int) -> None:
        if self.scheduler_process:
            # the service's scheduler in its own process (Dask's SubprocessCluster): it would otherwise share
            # the API's interpreter lock, and every task of every study would delay a status read. Its comms
            # are TLS with certificates only this service holds: a client of the scheduler runs code as the
            # service, and loopback alone does not keep the other users of a shared host out
            from distributed.deploy.subprocess import SubprocessCluster

            security, self.env = private_tls()
            with exported(self.env):  # the scheduler and workers inherit it as they start, this process does not keep it
                self.cluster = SubprocessCluster(host="127.0.0.1", n_workers=n, threads_per_worker=1,
                                                 dashboard_address="127.0.0.1:8787", silence_logs=40,
                                                 scheduler_kwargs={"protocol": "tls://"}, security=security)
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


TLS_ENV = "DASK_DISTRIBUTED__COMM__"
"""The prefix of the Dask settings :func:`private_tls` exports to this process's children."""


def private_tls():
    """TLS for the service's own cluster: a fresh certificate authority and certificate (Dask's
    ``Security.temporary``). Returns the ``Security`` of this process's client and the Dask settings
    (environment variables) its scheduler, workers and study drivers are started with; this process's own
    configuration is left alone (other clusters it runs stay plain). Encryption is required: a client without
    the certificate is refused by the scheduler.

    The certificates and keys travel in those settings as PEM text (Dask reads a value holding a newline as the
    certificate itself), never as files: a process's environment is readable by its own user only, as a 0600
    file is, and it goes with the process, where a file outlives a killed service with its keys."""
    from distributed import Security

    sec = Security.temporary()
    env = {"REQUIRE_ENCRYPTION": "True", "TLS__CA_FILE": sec.tls_ca_file}
    for who in ("client", "scheduler", "worker"):
        env[f"TLS__{who.upper()}__CERT"] = getattr(sec, f"tls_{who}_cert")
        env[f"TLS__{who.upper()}__KEY"] = getattr(sec, f"tls_{who}_key")
    return sec, {TLS_ENV + k: v for k, v in env.items()}


@contextlib.contextmanager
def exported(env: dict):
    """``env`` in this process's environment for the time of the ``with`` (the children started in it inherit
    it), then as it was."""
    import os

    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
