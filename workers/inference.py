"""A finished study as ArviZ data (``xarray.DataTree`` in ArviZ's InferenceData layout).

``to_inference_data(store, model)`` gives the optimal nested model's stationary posterior
with these groups, so ``az.summary``, ``az.plot_trace``, ``az.loo`` and ``az.compare`` work:

- ``posterior``: one variable per free parameter, dims (chain, draw);
- ``sample_stats``: ``lp`` (log posterior) and ``log_likelihood`` (total) per draw; the trial's psi,
  evidence and sampler diagnostics (acceptance, burn-in rounds, evaluations, R-hat) are attributes;
- ``observed_data``: the observed columns, dim ``time`` (the sample times as coordinate);
- ``log_likelihood`` (on request): the EKF's one-step predictive log density of every
  observation, ln p(d_k | d_1..d_{k-1}, phi), for a thinned set of draws. These terms sum to
  ln p(d | phi), but they are not conditionally independent given phi, so PSIS-LOO on them
  estimates the one-step-ahead predictive accuracy of each observation given the *whole*
  record's posterior (it leaves out the term, not the sample's influence on the state
  estimate); read ``az.loo`` as a predictive score beside the evidence, not as its substitute.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass

import numpy as np
from ardflow.ardcore.likelihood.ekf import compile_model
from ardflow.ardcore.selection.fit import ModelFit
from ardflow.ardcore.jsonio import to_jsonable
from ardflow.ardcore.selection.spec import StudySpec

from .store import StudyStore

MAX_POINTWISE_DRAWS = 1000
"""Draws (all chains together) for which the pointwise log-likelihood is computed by default."""


def _best(store: StudyStore, model: str) -> tuple[int, ModelFit]:
    try:
        it, row = store.model_result(model)
    except KeyError:
        raise LookupError(f"the study has no model {model!r}") from None
    if it is None or not row:
        raise LookupError(f"model {model!r} of the study is not finished")
    return it, row


def _candidate(store: StudyStore, model: str):
    spec = StudySpec.model_validate(store.meta["spec"])
    cand = next((c for c in spec.models if c.label == model), None)
    if cand is None:
        raise LookupError(f"the study has no model {model!r}")
    return cand


def pointwise_log_likelihood(cand, row: ModelFit, data, samples: np.ndarray,
                             names: list[str]) -> dict[str, np.ndarray]:
    """One-step predictive log density of every observation for each draw of ``samples``.

    Parameters
    ----------
    cand : CandidateSpec
        The study's candidate; ``row`` its summary row (the optimal psi fixes the pruned terms at 0).
    data : Dataset
        The study's data.
    samples : ndarray, shape (chain, draw, param)
        Draws of the optimal nested model's free parameters, in the order of ``names``.

    Returns
    -------
    dict of column name to ndarray of shape (chain, draw, time).
    """
    from ardflow.ardcore.loop.freerun import fitted_spec

    ms = fitted_spec(cand, row)
    if list(ms.free_parameters) != list(names):
        raise LookupError(f"the stored draws of {cand.label!r} do not match its model's free parameters")
    lik = compile_model(ms).bind(data, cand.substeps)
    cols = ms.observed_columns
    nc, nd, _ = samples.shape
    out = {c: np.full((nc, nd, len(data)), np.nan) for c in cols}
    for c in range(nc):
        for d in range(nd):
            fr = lik.filter(samples[c, d])
            # ln N(e; 0, S) per observation; a missing observation contributes 0
            terms = -0.5 * (np.log(fr.innovation_var) + fr.innovations ** 2 / fr.innovation_var + np.log(2 * np.pi))
            for j, col in enumerate(cols):
                out[col][c, d] = np.nan_to_num(terms[:, j], nan=0.0)
    return out


@dataclass(frozen=True)
class InferenceGroups:
    """ArviZ's groups as plain arrays (what crosses the REST API as NPZ); :meth:`to_datatree` needs ArviZ."""

    groups: dict[str, dict[str, np.ndarray]]
    dims: dict[str, list[str]]
    coords: dict[str, np.ndarray]
    attrs: dict

    def to_datatree(self):
        """The ``xarray.DataTree`` that ``az.summary``, ``az.loo`` and ``az.compare`` take."""
        try:
            import arviz as az
        except ImportError:
            raise ImportError("ArviZ data needs arviz: pip install arviz") from None
        dt = az.from_dict(self.groups, dims=self.dims, coords=self.coords)
        dt.attrs.update(self.attrs)
        return dt

    def to_npz(self) -> bytes:
        arrays = {f"{g}/{v}": a for g, vs in self.groups.items() for v, a in vs.items()}
        arrays.update({f"coords/{k}": v for k, v in self.coords.items()})
        head = json.dumps({"dims": self.dims, "attrs": self.attrs})
        buf = io.BytesIO()
        np.savez_compressed(buf, __head__=np.array(head), **arrays)
        return buf.getvalue()

    @classmethod
    def from_npz(cls, raw: bytes) -> "InferenceGroups":
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            head = json.loads(str(z["__head__"]))
            groups: dict[str, dict[str, np.ndarray]] = {}
            coords = {}
            for key in z.files:
                if key == "__head__":
                    continue
                g, v = key.split("/", 1)
                if g == "coords":
                    coords[v] = z[key]
                else:
                    groups.setdefault(g, {})[v] = z[key]
        return cls(groups, head["dims"], coords, head["attrs"])


def inference_groups(store, model: str, *, log_likelihood: bool = False,
                     max_draws: int | None = None) -> InferenceGroups:
    """ArviZ's groups of ``model``'s optimal nested model in a finished study store.

    Parameters
    ----------
    store : StudyStore, str or Path
        The study's store (a directory or fsspec URL).
    model : str
        The candidate's label (``M2`` ...).
    log_likelihood : bool
        Also compute the pointwise log-likelihood group (one EKF pass per kept draw).
    max_draws : int, optional
        Thin every group to at most this many draws in all (same draws in every group).
        Default: all draws, or ``MAX_POINTWISE_DRAWS`` when ``log_likelihood`` is asked for.
    """
    store = store if isinstance(store, StudyStore) else StudyStore(store)
    it, row = _best(store, model)
    samples, lp, ll, names = store.finished_samples(model, it)
    nc, nd, _ = samples.shape
    if max_draws is None and log_likelihood:
        max_draws = MAX_POINTWISE_DRAWS
    step = 1 if not max_draws else max(1, int(np.ceil(nc * nd / max_draws)))
    samples, lp, ll = samples[:, ::step], lp[:, ::step], ll[:, ::step]
    rec = store.trial_record(model, it) or {}
    groups = {"posterior": {n: samples[..., i] for i, n in enumerate(names)},
              "sample_stats": {"lp": lp, "log_likelihood": ll}}
    data = store.load_data()
    cand = _candidate(store, model)
    cols = cand.model_spec().observed_columns
    groups["observed_data"] = {c: data.columns[c] for c in cols}
    # which record each observation belongs to: LOO read per record, or a record's pointwise terms summed
    # for leave-one-record-out
    record = np.zeros(len(data), dtype=np.int64)
    for r, sl in enumerate(data.record_slices()):
        record[sl] = r
    groups["constant_data"] = {"record": record}
    if log_likelihood:
        groups["log_likelihood"] = pointwise_log_likelihood(cand, row, data, samples, names)
    attrs = {"model": model, "iteration": it, "thin": step,
             "psi": json.dumps(rec.get("psi", to_jsonable(row.psi_opt))),
             "log_evidence": float(row.log_evidence), "source": str(store.url)}
    # the trial's sampler diagnostics (stationary acceptance, burn-in rounds, evaluations, R-hat, warnings)
    for k in ("acceptance", "burnin_acceptance", "burnin_rounds", "n_evaluations", "converged"):
        if isinstance(rec.get(k), (int, float, bool)):
            attrs[k] = rec[k]
    if rec.get("rhat") is not None:
        attrs["max_rhat"] = float(np.max(np.asarray(rec["rhat"], float)))
    if rec.get("warnings"):
        attrs["warnings"] = "; ".join(map(str, rec["warnings"]))
    attrs["records"] = json.dumps(data.record_names())
    return InferenceGroups(groups, {**{c: ["time"] for c in cols}, "record": ["time"]}, {"time": data.t}, attrs)


def to_inference_data(store, model: str, *, log_likelihood: bool = False, max_draws: int | None = None):
    """ArviZ data (``xarray.DataTree``) of ``model``'s optimal nested model; see :func:`inference_groups`."""
    return inference_groups(store, model, log_likelihood=log_likelihood, max_draws=max_draws).to_datatree()


def psis_loo(dt) -> dict:
    """PSIS-LOO of ArviZ data with a pointwise ``log_likelihood`` group (one observed variable).

    ArviZ's Pareto smoothing refuses an observation whose log density is the same for every draw (the
    first observation when the initial state is not a parameter: its one-step density does not depend
    on phi). Leaving such an observation out changes nothing, so its elpd term is its log density,
    exactly; the others go through ``az.loo``.

    Returns
    -------
    dict with ``elpd_loo``, ``elpd_se``, ``p_loo``, ``pareto_k_high`` (k > 0.7: PSIS unreliable there),
    ``n``, ``n_constant`` and the pointwise terms ``elpd_i``.
    """
    import arviz as az

    ll = dt["log_likelihood"]
    (var,) = list(ll.data_vars)
    a = ll[var]
    flat = a.values.reshape(-1, a.sizes["time"])
    const = (flat.max(0) - flat.min(0)) <= 1e-12 * np.maximum(1.0, np.abs(flat[0]))
    elpd_i = flat[0].copy()
    k_high = 0
    p_loo = 0.0
    if (~const).any():
        sub = dt.copy()
        sub["log_likelihood"] = ll.isel(time=np.flatnonzero(~const))
        res = az.loo(sub, pointwise=True)
        elpd_i[~const] = np.asarray(res.elpd_i).ravel()
        k_high = int(np.sum(np.asarray(res.pareto_k).ravel() > 0.7))
        p_loo = float(res.p)
    n = elpd_i.size
    out = {"elpd_loo": float(elpd_i.sum()), "elpd_se": float(np.sqrt(n * np.var(elpd_i))), "p_loo": p_loo,
           "pareto_k_high": k_high, "n": n, "n_constant": int(const.sum()), "elpd_i": elpd_i}
    if "constant_data" in dt.children and "record" in dt["constant_data"].data_vars:
        rec = np.asarray(dt["constant_data"]["record"].values).ravel()
        names = json.loads(dt.attrs.get("records", "[]")) or [f"record {r}" for r in range(int(rec.max()) + 1)]
        if len(names) > 1:
            out["elpd_records"] = {names[r]: float(elpd_i[rec == r].sum()) for r in range(len(names))}
    return out


def loo_beside_evidence(store, *, max_draws: int = MAX_POINTWISE_DRAWS) -> list[dict]:
    """PSIS-LOO (:func:`psis_loo`) of every finished model of a study beside its log evidence and
    posterior probability: one dict per model with ``model``, ``log_evidence``, ``probability``, the
    :func:`psis_loo` fields, ``loo_rank`` (0 = best by LOO) and ``elpd_diff``/``diff_se``: the difference
    to the best model by LOO and its standard error from the pointwise differences. Needs arviz.
    """
    store = store if isinstance(store, StudyStore) else StudyStore(store)
    summary = store.read_summary()
    rows = []
    for r in (summary.to_json()["models"] if summary is not None else []):
        dt = to_inference_data(store, r["name"], log_likelihood=True, max_draws=max_draws)
        rows.append({"model": r["name"], "log_evidence": r["log_evidence"], "probability": r.get("probability"),
                     **psis_loo(dt)})
    order = sorted(rows, key=lambda x: -x["elpd_loo"])
    for i, x in enumerate(order):
        d = order[0]["elpd_i"] - x["elpd_i"]
        x.update(loo_rank=i, elpd_diff=float(d.sum()), diff_se=float(np.sqrt(d.size * np.var(d))))
    for x in rows:
        del x["elpd_i"]
    return rows
