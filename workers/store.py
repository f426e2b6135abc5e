"""The zarr result store of one study.

Layout (a zarr v3 group; dimension names are stored, so ``xarray.open_zarr``
gives labelled arrays)::

    STORE/                               attrs["ardflow"] = {version, spec, status, progress, summary}
      data/                              the data set used: t (time) and one array per column (time)
      models/<model>/                    attrs["history"] = every maximisation trial; attrs["result"]
        trials/<NNN>/                    one trial psi (NNN = iteration)
          samples        (chain, draw, param)   stationary samples, chunk = one chain x one round
          log_likelihood (chain, draw)
          log_prior      (chain, draw)
          param          (param)                parameter names
          attrs: psi, evidence (with per-chain values), diagnostics, done
      checkpoints/<model>/<NNN>.json     sampler checkpoint of a trial (atomic write-then-rename)
      summary.json, history.json         the study summary and every trial of every model (also in attrs)

Only the orchestrator creates arrays; chain tasks write their own chunks
(region writes to distinct chunks are safe across processes) and a re-run
task rewrites the same chunk.
"""

from __future__ import annotations

import json
import os
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import zarr
from ardflow.ardcore.errors import ArdflowError
from ardflow.ardcore.selection.fit import ModelFit
from ardflow.ardcore.selection.summary import StudySummary
from ardflow.ardcore.jsonio import atomic_write_text, to_jsonable

STORE_VERSION = 1

# zarr's own pools stay small: Dask provides the parallelism
zarr.config.set({"async.concurrency": 4, "threading.max_workers": 2})


class StoreBusy(ArdflowError):
    """Another driver holds this study's store."""


DATA_META = ("records", "initial_mean", "initial_std")
"""What of a data set's ``meta`` the store keeps beside its columns (with its record ``starts``)."""


class StudyStore:
    """Read and write one study's store (a local directory).

    Parameters
    ----------
    path : str or Path
        The store: a local directory, or any fsspec URL (``s3://bucket/study``,
        ``gcs://...``, ``memory://...``) that every worker can reach.
    """

    def __init__(self, path: str | Path):
        text = str(path)
        self.remote = "://" in text and not text.startswith("file://")
        if self.remote:
            import fsspec

            self.url = text.rstrip("/")
            self.fs, self.root = fsspec.core.url_to_fs(self.url)
            self.path = None
        else:
            self.path = Path(text[len("file://"):] if text.startswith("file://") else text)
            self.url = str(self.path)

    def __str__(self) -> str:
        return self.url

    # ---------------------------------------------------------------- side files (JSON beside the zarr group)
    def write_text(self, rel: str, text: str) -> None:
        """Write a side file: atomically (write, then rename) on local disks, one object remotely."""
        if self.remote:
            with self.fs.open(f"{self.root}/{rel}", "w") as fh:
                fh.write(text)
        else:
            atomic_write_text(self.path / rel, text)

    def read_text(self, rel: str) -> str | None:
        try:
            if self.remote:
                with self.fs.open(f"{self.root}/{rel}", "r") as fh:
                    return fh.read()
            return (self.path / rel).read_text()
        except FileNotFoundError:
            return None

    def append_line(self, rel: str, line: str) -> None:
        """Append one line (progress logs); remote stores rewrite the object."""
        if self.remote:
            old = self.read_text(rel) or ""
            self.write_text(rel, old + line + "\n")
        else:
            p = self.path / rel
            p.parent.mkdir(parents=True, exist_ok=True)
            with open(p, "a") as fh:
                fh.write(line + "\n")

    def read_from(self, rel: str, offset: int) -> bytes:
        """The bytes of a side file from ``offset`` on (a local file is not read from the start)."""
        try:
            if self.remote:
                with self.fs.open(f"{self.root}/{rel}", "rb") as fh:
                    fh.seek(offset)
                    return fh.read()
            with open(self.path / rel, "rb") as fh:
                fh.seek(offset)
                return fh.read()
        except FileNotFoundError:
            return b""

    def list_files(self, rel: str, suffix: str) -> list[str]:
        """Names of the side files in folder ``rel`` ending in ``suffix``."""
        if self.remote:
            try:
                names = [p.rsplit("/", 1)[-1] for p in self.fs.ls(f"{self.root}/{rel}", detail=False)]
            except FileNotFoundError:
                return []
        else:
            d = self.path / rel
            names = [p.name for p in d.iterdir()] if d.exists() else []
        return sorted(n for n in names if n.endswith(suffix))

    # ---------------------------------------------------------------- study level
    @classmethod
    def create(cls, path: str | Path, spec_json: dict, data=None) -> "StudyStore":
        s = cls(path)
        g = zarr.open_group(s.url, mode="a")
        meta = dict(g.attrs.get("ardflow", {}))
        meta.update({"version": STORE_VERSION, "spec": spec_json})
        meta.setdefault("status", "created")
        g.attrs["ardflow"] = to_jsonable(meta)
        if data is not None and "data" not in g:
            dg = g.require_group("data")
            dg.create_array("t", data=np.asarray(data.t), dimension_names=["time"])
            for k, v in data.columns.items():
                dg.create_array(k, data=np.asarray(v), dimension_names=["time"])
            # several records: where each starts, and each one's name, own time origin and initial state
            dg.attrs["ardflow"] = to_jsonable({"starts": list(data.starts), **{
                k: data.meta[k] for k in DATA_META if data.meta.get(k)}})
        return s

    def exists(self) -> bool:
        return self.read_text("zarr.json") is not None

    def group(self, mode: str = "a"):
        return zarr.open_group(self.url, mode=mode)

    @property
    def meta(self) -> dict:
        """The study's attributes (spec, status, error, ...). A local store's are read straight from the
        group's ``zarr.json`` (its ``attributes`` member in the zarr v3 format): the service reads them on
        every status request, and zarr's own open costs a round trip through its event-loop thread."""
        if not self.remote:
            doc = json.loads((self.path / "zarr.json").read_text())
            return dict(doc.get("attributes", {}).get("ardflow", {}))
        return dict(self.group("r").attrs.get("ardflow", {}))

    @contextmanager
    def driver_lock(self):
        """Held by the one driver of this study for as long as it runs (an exclusive ``flock`` on
        ``DRIVER.lock``, which the kernel releases when the process dies, however it dies): a second driver
        on the same store is refused (:class:`StoreBusy`) instead of racing the first. Stores behind an
        fsspec URL have no such lock."""
        if self.path is None:
            yield
            return
        import fcntl

        fd = os.open(self.path / "DRIVER.lock", os.O_RDWR | os.O_CREAT, 0o600)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                held = os.pread(fd, 64, 0).decode(errors="ignore").strip()
                raise StoreBusy(f"another driver is running this study (pid {held or '?'}); it is not started "
                                "twice") from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
            yield
        finally:
            os.close(fd)

    def update_meta(self, **kw) -> None:
        g = self.group()
        meta = dict(g.attrs.get("ardflow", {}))
        meta.update(to_jsonable(kw))
        g.attrs["ardflow"] = meta

    def load_data(self):
        from ardflow.ardcore.data import Dataset

        dg = self.group("r")["data"]
        cols = {k: np.asarray(dg[k][:]) for k in dg.array_keys() if k != "t"}
        # named as the study names its data (a file, an uploaded data set's name, a generator), not by the
        # store's place on this machine
        source = (self.meta.get("data") or {}).get("source") or f"{self.url}/data"
        extra = dict(dg.attrs.get("ardflow", {}))  # absent in stores written before records existed
        meta = {"source": source, **{k: extra[k] for k in DATA_META if k in extra}}
        return Dataset(np.asarray(dg["t"][:]), cols, meta, tuple(extra.get("starts", (0,))))

    def write_summary(self, summary: StudySummary, *, done: bool = True) -> None:
        """Write the summary; with ``done`` the study's status becomes ``done`` (a driver that renders a
        report afterwards marks it done itself once the report is written: done means all of it)."""
        js = summary.to_json()
        self.write_text("summary.json", json.dumps(js, indent=2))
        self.update_meta(**({"status": "done"} if done else {}), summary={k: v for k, v in js.items() if k != "spec"})

    def read_summary(self) -> StudySummary | None:
        """The study's :class:`StudySummary` (None before the comparison ran); a summary written by a newer
        ardflow raises :class:`~ardcore.errors.DataError`."""
        text = self.read_text("summary.json")
        return StudySummary.from_json(json.loads(text)) if text else None

    # ---------------------------------------------------------------- trials
    def trial_path(self, model: str, iteration: int) -> str:
        return f"models/{model}/trials/{iteration:03d}"

    def create_trial(self, model: str, iteration: int, names: list[str], n_chains: int, n_draws: int,
                     round_size: int, psi: dict) -> None:
        """Create (or keep, when chains and parameters match) the arrays of one trial. Kept arrays keep their
        length: a stationary stage that grew them past ``n_draws`` resumes with its draws."""
        g = self.group()
        path = self.trial_path(model, iteration)
        if path in g:
            tg = g[path]
            shape = tg["samples"].shape if "samples" in tg else None
            # a driver killed half-way through creating the trial leaves no "created" mark
            if tg.attrs.get("created") and shape is not None and (shape[0], shape[2]) == (n_chains, len(names)):
                return
            del g[path]
        tg = g.require_group(path)
        d = len(names)
        tg.create_array("samples", shape=(n_chains, n_draws, d), chunks=(1, round_size, d), dtype="f8",
                        fill_value=np.nan, dimension_names=["chain", "draw", "param"])
        for k in ("log_likelihood", "log_prior"):
            tg.create_array(k, shape=(n_chains, n_draws), chunks=(1, round_size), dtype="f8", fill_value=np.nan,
                            dimension_names=["chain", "draw"])
        tg.create_array("param", data=np.array(names, dtype="U32"), dimension_names=["param"])
        tg.create_array("chain", data=np.arange(n_chains), dimension_names=["chain"])
        tg.create_array("draw", data=np.arange(n_draws), dimension_names=["draw"])
        tg.attrs["psi"] = to_jsonable(psi)
        tg.attrs["done"] = False
        tg.attrs["created"] = True

    def write_round(self, model: str, iteration: int, chain: int, start: int, samples: np.ndarray,
                    lp: np.ndarray, ll: np.ndarray) -> None:
        """Write one chain's round of stationary samples into its own chunk (idempotent). ``start`` counts
        draws over the stage's passes (:data:`ardcore.sampling.driver.STRIDE` per pass: a redrawn stage writes its slots
        again): the slot is ``start mod STRIDE``."""
        from ardflow.ardcore.sampling.driver import STRIDE

        tg = self.group()[self.trial_path(model, iteration)]
        n = samples.shape[0]
        start %= STRIDE
        tg["samples"][chain, start:start + n, :] = samples
        tg["log_likelihood"][chain, start:start + n] = ll
        tg["log_prior"][chain, start:start + n] = lp - ll

    def resize_draws(self, model: str, iteration: int, n_draws: int, *, grow_only: bool = False) -> None:
        """Give a trial's arrays ``n_draws`` draws per chain (the stationary stage continues until its draws
        meet the quality target, and ends with exactly the draws it kept). Only the orchestrator calls it,
        before it submits the rounds that write beyond the end."""
        g = self.group()
        tg = g[self.trial_path(model, iteration)]
        cur = tg["samples"].shape[1]
        if n_draws == cur or (grow_only and n_draws < cur):
            return
        nc, _, d = tg["samples"].shape
        tg["samples"].resize((nc, n_draws, d))
        for k in ("log_likelihood", "log_prior"):
            tg[k].resize((nc, n_draws))
        if "draw" in tg:
            del tg["draw"]
        tg.create_array("draw", data=np.arange(n_draws), dimension_names=["draw"])

    def read_samples(self, model: str, iteration: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
        tg = self.group("r")[self.trial_path(model, iteration)]
        ll = np.asarray(tg["log_likelihood"][:])
        return (np.asarray(tg["samples"][:]), np.asarray(tg["log_prior"][:]) + ll, ll,
                [str(x) for x in tg["param"][:]])

    def finished_samples(self, model: str, iteration: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
        """:meth:`read_samples` of a finished trial, checked whole: a chunk cut short or garbled, or one removed
        (zarr would fill it in silently), raises :class:`~ardcore.errors.Damaged` naming the trial and how much
        of it is missing, never a NaN passed on as a draw (every draw of a finished trial is finite)."""
        from ardflow.ardcore.errors import Damaged

        where = f"model {model!r}, trial {iteration}"
        try:
            samples, lp, ll, names = self.read_samples(model, iteration)
        except KeyError:
            raise
        except Exception as exc:  # noqa: BLE001 - whatever the codec or the file system raises on a damaged chunk
            raise Damaged(f"the stored draws of {where} cannot be read ({type(exc).__name__}): the store is "
                          "damaged; the summary and the report stay readable") from None
        bad = int(np.sum(~np.isfinite(samples).all(axis=-1)) + np.sum(~np.isfinite(ll)))
        if bad:
            raise Damaged(f"the stored draws of {where} are damaged: {bad} of {samples.shape[0] * samples.shape[1]} "
                          "draws missing or not finite (a chunk removed or overwritten); the summary and the report "
                          "stay readable")
        return samples, lp, ll, names

    def finish_trial(self, model: str, iteration: int, trial: dict) -> None:
        tg = self.group()[self.trial_path(model, iteration)]
        tg.attrs["trial"] = to_jsonable(trial)
        tg.attrs["done"] = True

    def trial_record(self, model: str, iteration: int) -> dict | None:
        g = self.group("r")
        path = self.trial_path(model, iteration)
        if path not in g:
            return None
        tg = g[path]
        return dict(tg.attrs["trial"]) if tg.attrs.get("done") else None

    def model_result(self, model: str) -> tuple[int | None, ModelFit | None]:
        """The best iteration and the :class:`~ardcore.selection.fit.ModelFit` of ``model`` (None while it runs);
        KeyError: no such model."""
        mg = self.group("r")[f"models/{model}"]
        it = mg.attrs.get("best_iteration")
        row = mg.attrs.get("result")
        return (None if it is None else int(it)), (ModelFit.from_json(row) if row else None)

    def histories(self, models: list[str] | None = None) -> dict[str, list]:
        """Every maximisation trial so far, per model (``models``: these, in this order; default: all)."""
        g = self.group("r")
        if "models" not in g:
            return {m: [] for m in models or []}
        groups = dict(g["models"].groups())
        names = list(models) if models is not None else list(groups)
        return {m: list(groups[m].attrs.get("history", [])) if m in groups else [] for m in names}

    def set_model_attrs(self, model: str, **kw) -> None:
        """Attributes of ``model``'s group (``result``: its :class:`~ardcore.selection.fit.ModelFit`, stored as JSON)."""
        mg = self.group().require_group(f"models/{model}")
        for k, v in kw.items():
            mg.attrs[k] = v.to_json() if isinstance(v, ModelFit) else to_jsonable(v)

    # ---------------------------------------------------------------- checkpoints
    @staticmethod
    def _checkpoint_rel(model: str, iteration: int) -> str:
        return f"checkpoints/{model}/{iteration:03d}.json"

    def write_checkpoint(self, model: str, iteration: int, ck: dict) -> None:
        self.write_text(self._checkpoint_rel(model, iteration), json.dumps(to_jsonable(ck)))

    def read_checkpoint(self, model: str, iteration: int) -> dict | None:
        text = self.read_text(self._checkpoint_rel(model, iteration))
        return None if text is None else json.loads(text)
