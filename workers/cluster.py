"""Where a study's tasks run: an existing Dask scheduler, or an embedded LocalCluster."""

from __future__ import annotations


class ClusterClient:
    """Context manager: a Dask client on an existing scheduler (``scheduler`` = its address), or on an
    embedded process-based LocalCluster with ``workers`` workers (default: one per core)."""

    def __init__(self, scheduler: str | None, workers: int | None):
        self.scheduler, self.workers = scheduler, workers

    def __enter__(self):
        import os

        from distributed import Client, LocalCluster

        if self.scheduler:
            self.cluster = None
            self.client = Client(self.scheduler)
        else:
            n = self.workers or os.cpu_count() or 1
            # the dashboard has no authentication: loopback only
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
