"""Where a study's tasks run: an existing Dask scheduler, or an embedded LocalCluster."""

from __future__ import annotations


class ClusterClient:
    """Context manager: a Dask client on an existing scheduler (``scheduler`` = its address), or on an
    embedded process-based LocalCluster with ``workers`` workers (default: one per core)."""

    def __init__(self, scheduler: str | None, workers: int | None, *, scheduler_process: bool = False):
        self.scheduler, self.workers, self.scheduler_process = scheduler, workers, scheduler_process

    def __enter__(self):
        import os

        from distributed import Client, LocalCluster

        if self.scheduler:
            self.cluster = None
            self.client = Client(self.scheduler)
        else:
            n = self.workers or os.cpu_count() or 1
            # the dashboard has no authentication: loopback only
            if self.scheduler_process:
                # the service's scheduler in its own process (Dask's SubprocessCluster): it would otherwise
                # share the API's interpreter lock, and every task of every study would delay a status read
                from distributed.deploy.subprocess import SubprocessCluster

                self.cluster = SubprocessCluster(host="127.0.0.1", n_workers=n, threads_per_worker=1,
                                                 dashboard_address="127.0.0.1:8787", silence_logs=40)
            else:
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                            dashboard_address="127.0.0.1:8787", silence_logs=40)
            self.client = Client(self.cluster)
            # compute yields to the driver, the API and the scheduler on a shared machine
            self.client.run(os.nice, 10)
        print(f"[ardflow] Dask dashboard: {self.client.dashboard_link}", flush=True)
        return self.client

    def __exit__(self, *exc):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
