"""The INCA coordinator as a Dask actor, and the proxy the sampler talks to.

The actor wraps :class:`ardcore.sampling.driver.AdaptationPool`: chain-round tasks report
their statistics to it at the end of every burn-in round, and the pooled
covariance for the next round comes from it. Dask actors are not resilient:
if the worker holding it dies, :class:`ActorPool` re-creates the actor on
another worker from the last synchronised state (it is also in every
trial checkpoint) and re-reports the round in flight, while the chains keep
the covariance they were given.
"""

from __future__ import annotations

import logging
import time

from ardflow.ardcore.sampling.adaptation import AdaptationPool

log = logging.getLogger(__name__)


class CoordinatorActor:
    """Dask actor holding one trial's :class:`AdaptationPool` (methods only: actors expose no attributes)."""

    def __init__(self, state: dict):
        self.pool = AdaptationPool.from_dict(state)

    def report(self, chain: int, round_index: int, halves, best) -> bool:
        return self.pool.report(chain, round_index, halves, best)

    def proposal(self, chain: int):
        return self.pool.proposal(chain)

    def state(self) -> dict:
        return self.pool.to_dict()


def actor_variable_name(prefix: str) -> str:
    return f"coordinator-{prefix}"


class ActorPool:
    """Pool interface of :func:`ardcore.sampling.driver.burnin_rounds`, backed by a :class:`CoordinatorActor`.

    Reads come from a local mirror synchronised after every committed round,
    so a lost actor never loses more than the round in flight.
    """

    def __init__(self, client, state: dict, prefix: str):
        from distributed import Variable

        self.client = client
        self.prefix = prefix
        self.mirror = AdaptationPool.from_dict(state)
        self.var = Variable(actor_variable_name(prefix), client=client)
        self.pending: dict[int, dict] = {}
        self.restarts = 0
        self._start()

    def _start(self) -> None:
        last = None
        for _attempt in range(5):
            wait_connected(self.client)
            try:
                fut = self.client.submit(CoordinatorActor, self.mirror.to_dict(), actor=True, pure=False)
                self.actor = fut.result()
                self._future = fut  # held: the actor lives as long as its future
                self.var.set(fut)
                return
            except Exception as exc:  # noqa: BLE001 - a dropped scheduler connection cancels the actor's future
                last = exc
                log.warning("starting the coordinator actor failed (%s); trying again", exc)
        raise RuntimeError(f"coordinator actor could not be started: {last}")

    def _call(self, method: str, *args):
        for attempt in range(3):
            try:
                return getattr(self.actor, method)(*args).result()
            except Exception as exc:  # the worker holding the actor was lost
                log.warning("coordinator actor unavailable (%s); restoring it from its last state", exc)
                self.restarts += 1
                self._start()
                for (c, r), rep in sorted(self.pending.items(), key=lambda kv: (kv[0][1], kv[0][0])):
                    getattr(self.actor, "report")(c, r, *rep).result()
        raise RuntimeError("coordinator actor could not be restored")

    # -- the AdaptationPool interface used by the sampler
    def report(self, chain: int, round_index: int, halves, best) -> bool:
        if round_index <= self.mirror.rounds:
            return True  # committed already (the chain task reported it to the actor itself)
        self.pending[(chain, round_index)] = (halves, best)
        done = self._call("report", chain, round_index, halves, best)
        if done:
            self.mirror = AdaptationPool.from_dict(self._call("state"))
            self.pending = {k: v for k, v in self.pending.items() if k[1] > self.mirror.rounds}
        return done

    _READ = frozenset({"proposal", "jump", "rounds", "cov", "best", "best_lp", "rhat_history", "rhat", "moved",
                       "converged", "to_dict"})

    def __getattr__(self, name: str):
        # what the driver reads is read from the mirror, which every committed round refreshes
        if name in ActorPool._READ:
            return getattr(self.mirror, name)
        raise AttributeError(name)

    def close(self) -> None:
        try:
            self.var.delete()
        except Exception:
            pass
        self._future = None


def wait_connected(client, timeout: float = 120.0) -> None:
    """Block while the client reconnects to the scheduler (it does so by itself after a dropped stream)."""
    deadline = time.monotonic() + timeout
    while client.status != "running":
        if client.status in ("closed", "closing") or time.monotonic() > deadline:
            raise RuntimeError(f"lost the Dask scheduler at {client.scheduler.address if client.scheduler else '?'} "
                               f"(client status {client.status!r})")
        time.sleep(0.2)
