"""The results of a study over HTTP: summary, posterior draws, ArviZ groups, figures and the report."""

from __future__ import annotations

import io
import json
import re

import numpy as np
from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import JSONResponse, Response

from ardflow.ardcore.errors import Damaged
from ardflow.service.api.auth import StudyAccess
from ardflow.service.api.registry import Registry
from ardflow.service.api.schemas import API_VERSION, ID_RE, finite_or_none

MAX_POINTWISE_DRAWS = 4000  # EKF passes one request may ask for


def results_router(reg: Registry, access: StudyAccess) -> APIRouter:
    """Routes that read a study's store (read only): its results, then its figures and report."""
    r = APIRouter()
    r.include_router(_results(reg, access))
    r.include_router(_figures(reg, access))
    return r


def _best_trial(reg: Registry, sid: str, model: str) -> int:
    """The iteration of a model's best trial (404 for an unknown model, 409 while it runs)."""
    if not ID_RE.match(model):
        raise HTTPException(404, f"no model {model!r}")
    try:
        it, _ = reg.store(sid).model_result(model)
    except Exception:  # noqa: BLE001 - missing group
        raise HTTPException(404, f"study {sid} has no model {model!r}") from None
    if it is None:
        raise HTTPException(409, f"model {model!r} of study {sid} is not finished")
    return it


def _results(reg: Registry, access: StudyAccess) -> APIRouter:
    """The summary, a model's posterior draws and its ArviZ groups."""
    r = APIRouter()
    v1 = f"/{API_VERSION}"

    @r.get(f"{v1}/studies/{{sid}}/summary", dependencies=[Depends(access)])
    def summary(sid: str) -> JSONResponse:
        reg.readable(sid)
        text = reg.store(sid).read_text("summary.json")
        if text is None:
            raise HTTPException(409, f"study {sid} has no summary yet (status {reg.readable(sid).get('status')})")
        try:
            return JSONResponse(json.loads(text))
        except ValueError as exc:
            raise HTTPException(409, f"study {sid}'s summary (summary.json) is damaged ({type(exc).__name__}); its "
                                     "draws stay readable per model (GET .../posterior/MODEL)") from None

    @r.get(f"{v1}/studies/{{sid}}/posterior/{{model}}", dependencies=[Depends(access)],
             responses={200: {"content": {"application/json": {}, "application/octet-stream": {}}}})
    def posterior(sid: str, model: str, format: str = "json", max_draws: int = 2000):
        reg.readable(sid)
        if format not in ("json", "npz"):
            raise HTTPException(422, "format must be 'json' or 'npz'")
        if not 1 <= max_draws <= 1_000_000:
            raise HTTPException(422, "max_draws must be between 1 and 1000000")
        it = _best_trial(reg, sid, model)
        try:
            samples, lp, ll, names = reg.store(sid).finished_samples(model, it)
        except (KeyError, FileNotFoundError):
            raise HTTPException(409, f"model {model!r} of study {sid} has no stored samples") from None
        except Damaged as exc:
            raise HTTPException(409, str(exc)) from None
        if format == "npz":
            buf = io.BytesIO()
            np.savez_compressed(buf, names=np.array(names), samples=samples, log_posterior=lp, log_likelihood=ll)
            return Response(buf.getvalue(), media_type="application/octet-stream",
                            headers={"Content-Disposition": f'attachment; filename="{sid}_{model}.npz"'})
        flat = samples.reshape(-1, samples.shape[-1])
        step = max(1, flat.shape[0] // max_draws)
        return JSONResponse({"model": model, "iteration": it, "names": names, "n_chains": samples.shape[0],
                             "thin": step, "samples": finite_or_none(flat[::step].tolist())})

    @r.get(f"{v1}/studies/{{sid}}/inference_data/{{model}}", dependencies=[Depends(access)],
           responses={200: {"content": {"application/octet-stream": {}}}})
    def inference_data(sid: str, model: str, log_likelihood: bool = False, max_draws: int | None = None):
        """ArviZ's groups (posterior, sample_stats, observed_data, optionally the pointwise log_likelihood) as
        NPZ; ``Client.posterior(..., as_inference_data=True)`` turns them into an ``xarray.DataTree``."""
        reg.readable(sid)
        _best_trial(reg, sid, model)
        if max_draws is not None and not 1 <= max_draws <= 1_000_000:
            raise HTTPException(422, "max_draws must be between 1 and 1000000")
        if log_likelihood and max_draws is not None and max_draws > MAX_POINTWISE_DRAWS:
            raise HTTPException(422, f"the pointwise log-likelihood is computed for at most {MAX_POINTWISE_DRAWS} "
                                     "draws (one EKF pass each): lower max_draws")
        from ardflow.workers.inference import inference_groups

        try:
            ig = inference_groups(reg.store(sid), model, log_likelihood=log_likelihood, max_draws=max_draws)
        except (LookupError, Damaged) as exc:
            raise HTTPException(409, str(exc)) from None
        return Response(ig.to_npz(), media_type="application/octet-stream",
                        headers={"Content-Disposition": f'attachment; filename="{sid}_{model}_arviz.npz"'})

    return r


def _figures(reg: Registry, access: StudyAccess) -> APIRouter:
    """The figures, rendered from the store, and the report written when the study finished."""
    r = APIRouter()
    v1 = f"/{API_VERSION}"

    @r.get(f"{v1}/studies/{{sid}}/figures/{{name}}", dependencies=[Depends(access)],
             responses={200: {"content": {"image/png": {}}}})
    def figure(sid: str, name: str):
        reg.readable(sid)
        from ardflow.service.reports.figures import FIGURES, render
        from ardflow.service.reports.plots import drawn_alone

        if name not in FIGURES:
            raise HTTPException(404, f"no figure {name!r} (available: {sorted(FIGURES)})")
        try:
            png = drawn_alone(render, name, reg.store(sid))
        except LookupError as exc:
            raise HTTPException(409, str(exc)) from None
        return Response(png, media_type="image/png")

    @r.get(f"{v1}/studies/{{sid}}/report/{{name}}", dependencies=[Depends(access)],
             responses={200: {"content": {"text/html": {}, "image/png": {}}}})
    def report_file(sid: str, name: str):
        """The study's report (``report.html``) and its figures (PNG), as written when the study finished."""
        meta = reg.readable(sid)
        d = reg.store(sid).path / "report"
        f = reg.file(d / name) if re.match(r"^[A-Za-z0-9_]{1,60}\.(png|html)$", name) else None
        if f is None:
            if meta.get("status") != "done":
                raise HTTPException(409, f"study {sid} is {meta.get('status')}: the report is written when it finishes")
            raise HTTPException(404, f"no report file {name!r}")
        kind = "text/html; charset=utf-8" if name.endswith(".html") else "image/png"
        return Response(f.read_bytes(), media_type=kind)

    return r
