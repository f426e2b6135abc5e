"""Python client of the ardflow REST API.

    from ardflow.service.client import Client
    c = Client("http://127.0.0.1:8000", token="...")
    sid = c.submit("examples/sec33.json")
    summary = c.wait(sid)             # progress on stderr, then the summary
    post = c.posterior(sid, "M2true", as_xarray=True)
"""

from __future__ import annotations

import io
import json
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from ardflow.service.api.schemas import FINAL


class APIError(Exception):
    """An error answer of the service: ``status`` and the server's message."""

    def __init__(self, status: int, message: str):
        super().__init__(f"HTTP {status}: {message}")
        self.status, self.message = status, message


class Client:
    """A thin, typed wrapper over the REST API.

    Parameters
    ----------
    url : str
        Base URL of the service (``http://host:port``).
    token : str, optional
        API token (sent as ``X-API-Token``).
    timeout : float
        Seconds per request.
    """

    def __init__(self, url: str = "http://127.0.0.1:8000", token: str | None = None, timeout: float = 60.0):
        headers = {"X-API-Token": token} if token else {}
        self.http = httpx.Client(base_url=url.rstrip("/") + "/v1", headers=headers, timeout=timeout)

    def close(self) -> None:
        self.http.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _check(self, r: httpx.Response):
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail")
            except ValueError:
                detail = r.text
            if isinstance(detail, list):
                detail = "; ".join(f"{'.'.join(d.get('loc', []))}: {d.get('msg')}" for d in detail)
            if r.status_code == 401:
                detail = (f"{detail}: give the token `ardflow serve` wrote (in its --root, runs/service/token by "
                          "default) as ARDFLOW_TOKEN, --token or Client(token=...)")
            raise APIError(r.status_code, str(detail))
        return r

    # ---------------------------------------------------------------- calls
    def health(self) -> dict:
        return self._check(self.http.get("/health")).json()

    def upload(self, csv_path: str | Path) -> str:
        """Upload a CSV data set; returns its id (use it as ``data.dataset`` in a spec)."""
        body = Path(csv_path).read_bytes()
        return self._check(self.http.post("/datasets", content=body, params={"name": plain_name(csv_path)},
                                          headers={"Content-Type": "text/csv"})).json()["id"]

    def submit(self, spec: dict | str | Path, csv: str | Path | list | None = None) -> str:
        """Submit a study (a dict or a JSON file); with ``csv`` the file is uploaded first. Returns the study id.

        ``csv`` may be a list, one file per record: each replaces the source of the spec's record in the same
        place (a spec with one data entry gives its settings to every record, named after its file)."""
        if not isinstance(spec, dict):
            spec = json.loads(Path(spec).read_text())
        if csv is not None:
            files = list(csv) if isinstance(csv, (list, tuple)) else [csv]
            data = spec.get("data", {})
            given = data if isinstance(data, list) else [data] * len(files)
            if len(given) != len(files):
                from ardflow.ardcore.errors import SpecError

                raise SpecError(f"the spec has {len(given)} records and {len(files)} CSV files: give one per record")
            records = []
            for f, rec in zip(files, given):
                rec = {k: v for k, v in rec.items() if k not in ("path", "generator", "dataset")}
                if len(files) > 1:
                    rec.setdefault("name", plain_name(f)[:80])
                records.append({**rec, "dataset": self.upload(f)})
            spec = dict(spec, data=records if isinstance(data, list) or len(files) > 1 else records[0])
        return self._check(self.http.post("/studies", json=spec)).json()["id"]

    def studies(self) -> list[dict]:
        return self._check(self.http.get("/studies")).json()

    def status(self, sid: str) -> dict:
        return self._check(self.http.get(f"/studies/{sid}")).json()

    def cancel(self, sid: str) -> dict:
        return self._check(self.http.post(f"/studies/{sid}/cancel", json={})).json()

    def summary(self, sid: str) -> dict:
        return self._check(self.http.get(f"/studies/{sid}/summary")).json()

    def figure(self, sid: str, name: str = "evidence.png") -> bytes:
        return self._check(self.http.get(f"/studies/{sid}/figures/{name}")).content

    def wait(self, sid: str, *, poll_s: float = 2.0, timeout: float | None = None, progress: bool = True) -> dict:
        """Block until the study ends; shows one progress line per model on stderr.

        Returns
        -------
        dict
            The study's summary (:meth:`summary`, with ``"status": "done"``) when it finished; its final status
            when it was cancelled.

        Raises
        ------
        APIError
            When the study failed (with its reason), or on a refused request.
        TimeoutError
            When ``timeout`` seconds pass first.
        """
        def poll() -> dict | None:
            st = self.status(sid)
            if progress:
                sys.stderr.write(f"\r[{st['status']}] " + _progress_line(st) + " " * 8
                                 + ("\n" if st["status"] in FINAL else ""))
                sys.stderr.flush()
            if st["status"] == "failed":
                raise APIError(500, f"study {sid} failed: {st.get('error')}")
            return st if st["status"] in FINAL else None

        st = _until(poll, poll_s, timeout, lambda: f"study {sid} still running after {timeout} s")
        return {**self.summary(sid), "status": "done"} if st["status"] == "done" else st

    def diagnose(self, sid: str, model: str | None = None, *, test_csv: str | Path | list | None = None,
                 wait: bool = True, poll_s: float = 2.0, timeout: float | None = None, **settings) -> dict:
        """Close the loop on a model of a finished study; with ``wait`` returns the finished diagnosis.

        ``settings``: the loop's settings the service accepts (``top_k``, ``max_rounds``; defaults as in
        :class:`~ardflow.service.api.schemas.DiagnoseRequest`). The diagnosis (``report``: residual tests
        before/after, ranked candidates, effects added, errors before/after) is also available later from
        :meth:`diagnosis`.
        """
        body = dict(settings)
        if model:
            body["model"] = model
        if test_csv:
            files = list(test_csv) if isinstance(test_csv, (list, tuple)) else [test_csv]
            ids = [self.upload(f) for f in files]
            body["test_dataset"] = ids if len(ids) > 1 else ids[0]
        st = self._check(self.http.post(f"/studies/{sid}/diagnoses", json=body)).json()
        if not wait:
            return st
        def poll() -> dict | None:
            d = self.diagnosis(sid, st["model"])
            if d["status"] == "failed":
                raise APIError(500, f"diagnosis failed: {d.get('error')}")
            return d if d["status"] not in ("queued", "running") else None

        return _until(poll, poll_s, timeout, lambda: f"diagnosis of {st['model']} still running after {timeout} s")

    def diagnosis(self, sid: str, model: str) -> dict:
        """State (``queued``/``running``/``done``/``failed``/``cancelled``) and, when done, the ``report`` of a
        diagnosis."""
        return self._check(self.http.get(f"/studies/{sid}/diagnoses/{model}")).json()

    def cancel_diagnosis(self, sid: str, model: str) -> dict:
        """Stop a queued or running diagnosis."""
        return self._check(self.http.post(f"/studies/{sid}/diagnoses/{model}/cancel", json={})).json()

    def diagnosis_figure(self, sid: str, model: str, name: str = "free_run.png") -> bytes:
        """A PNG of a finished diagnosis (tests, process_noise, candidates, free_run)."""
        return self._check(self.http.get(f"/studies/{sid}/diagnoses/{model}/figures/{name}")).content

    def report(self, sid: str, out: str | Path) -> Path:
        """Download a finished study's report (``report.html`` and its PNG figures) into ``out``.

        Returns the local path of ``report.html``; it opens offline (no external assets).
        """
        import re

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        page = self._check(self.http.get(f"/studies/{sid}/report/report.html")).text
        for name in sorted(set(re.findall(r"<img src='([^'/]+\.png)'", page))):
            (out / name).write_bytes(self._check(self.http.get(f"/studies/{sid}/report/{name}")).content)
        (out / "report.html").write_text(page)
        return out / "report.html"

    def posterior(self, sid: str, model: str, *, as_xarray: bool = False, as_inference_data: bool = False,
                  log_likelihood: bool = False, max_draws: int | None = None):
        """Stationary posterior samples of ``model``'s optimal nested model.

        Returns ``(names, samples)`` with samples of shape (chain, draw, param); an ``xarray.Dataset``
        with named dimensions (``as_xarray``); or ArviZ data, an ``xarray.DataTree`` with groups
        posterior, sample_stats, observed_data and, with ``log_likelihood=True``, the EKF's pointwise
        one-step predictive log density for ``az.loo``/``az.compare`` (``as_inference_data``; needs arviz).
        ``max_draws`` thins every group to that many draws in all (default 1000 with ``log_likelihood``).
        """
        if as_inference_data:
            from ardflow.workers.inference import InferenceGroups

            params = {"log_likelihood": str(bool(log_likelihood)).lower()}
            if max_draws is not None:
                params["max_draws"] = int(max_draws)
            r = self._check(self.http.get(f"/studies/{sid}/inference_data/{model}", params=params))
            return InferenceGroups.from_npz(r.content).to_datatree()
        r = self._check(self.http.get(f"/studies/{sid}/posterior/{model}", params={"format": "npz"}))
        with np.load(io.BytesIO(r.content)) as z:
            names = [str(x) for x in z["names"]]
            samples, lp, ll = z["samples"], z["log_posterior"], z["log_likelihood"]
        if not as_xarray:
            return names, samples
        import xarray as xr

        return xr.Dataset(
            {"samples": (("chain", "draw", "param"), samples), "log_posterior": (("chain", "draw"), lp),
             "log_likelihood": (("chain", "draw"), ll)},
            coords={"param": names, "chain": np.arange(samples.shape[0]), "draw": np.arange(samples.shape[1])})


def _progress_line(st: dict) -> str:
    """One line for a study's status: per model its trials (of the search's cap: it usually stops well before,
    so no time left is promised), best ln Z and time so far."""
    parts = []
    for m, p in st["models"].items():
        be, cap, el = p.get("best_log_evidence"), p.get("max_trials"), p.get("elapsed_s")
        parts.append(f"{m}: {p.get('trials_done', 0)}" + (f" of at most {cap}" if cap and p.get("stage") != "model_done"
                                                         else "") + " trials"
                     + (f", best ln Z {be:.2f}" if be is not None else "") + (f", {el:.0f} s" if el else ""))
    return " | ".join(parts)


def plain_name(path: str | Path) -> str:
    """A file's name as a data set's name: printable, without '$', at most 120 characters."""
    import re

    return re.sub(r"[$\x00-\x1f\x7f]", "", Path(path).name)[:120]


def _until(poll, poll_s: float, timeout: float | None, what) -> dict:
    """Call ``poll`` every ``poll_s`` seconds until it returns a result; TimeoutError (``what()``) after
    ``timeout`` seconds."""
    t0 = time.monotonic()
    while True:
        out = poll()
        if out is not None:
            return out
        if timeout is not None and time.monotonic() - t0 > timeout:
            raise TimeoutError(what())
        time.sleep(poll_s)
