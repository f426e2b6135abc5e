"""Study specification and the serial/executor-driven model-selection run.

A study names a data set, candidate models (built-in names or full inline
declarations) with their essential priors and ARD parameters, sampler and
maximiser settings, and a seed. :func:`select` runs it: per model the ARD
evidence maximisation, then the comparison of the optimal nested models
(Eq. 7). The same spec is accepted unchanged by the REST API.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Annotated, Callable, Literal, Optional, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .ard import INF, EvidenceEvaluator, MaximiserConfig, MaximiserResult, maximise, posterior_summary
from .data import Dataset, read_dataset
from .errors import SpecError
from .library import builtin
from .mcmc import Map, SamplerConfig, serial_map
from .model import NAME_PATTERN, ModelSpec
from .priors import PriorSpec

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)
_S, _M = SamplerConfig, MaximiserConfig  # one place for the defaults
Name = Annotated[str, Field(pattern=NAME_PATTERN)]


class DataSpec(BaseModel):
    """Where the data come from: a file, or a documented generator."""

    model_config = _STRICT
    path: Optional[str] = Field(None, max_length=4096, description="CSV, NPZ or MAT file")
    dataset: Optional[str] = Field(None, pattern=r"^[a-f0-9]{16}$",
                                   description="id of a data set uploaded to the service (REST API)")
    generator: Optional[Literal["reference", "appendix_a"]] = Field(
        None, description="'reference': the paper's LCO data set; 'appendix_a': y = 3 + 5x + N(0, 0.3^2)")
    seed: int = Field(1, ge=0, le=2**32 - 1)
    time: Name = "t"
    fs: Optional[float] = Field(None, gt=0)
    rename: dict[str, Name] = Field(default_factory=dict, max_length=64)
    columns: Optional[list[Name]] = None
    start: Optional[int] = Field(None, ge=0)
    stop: Optional[int] = Field(None, ge=1)
    every: Optional[int] = Field(None, ge=1, le=100_000, description="keep every n-th row (after start/stop)")

    @model_validator(mode="after")
    def _one_source(self):
        if sum(x is not None for x in (self.path, self.generator, self.dataset)) != 1:
            raise ValueError("data: give exactly one of 'path', 'dataset' and 'generator'")
        if self.start is not None and self.stop is not None and self.stop <= self.start:
            raise ValueError(f"data: stop ({self.stop}) must be greater than start ({self.start})")
        return self

    def load(self, base: Path | None = None, datasets: Path | None = None) -> Dataset:
        if self.dataset is not None:
            if datasets is None:
                raise SpecError("data.dataset refers to an uploaded data set: use it through the service")
            p = datasets / f"{self.dataset}.csv"
            if not p.exists():
                raise SpecError(f"data.dataset: no uploaded data set {self.dataset!r}")
            ds = read_dataset(p, time=self.time, fs=self.fs, rename=self.rename, columns=self.columns)
            ds.meta["source"] = f"dataset:{self.dataset}"
        elif self.generator == "reference":
            from .simulate import simulate_reference

            ds = simulate_reference(self.seed)
        elif self.generator == "appendix_a":
            ds = appendix_a_data(self.seed)
        else:
            p = Path(self.path)
            if base is not None and not p.is_absolute():
                p = base / p
            ds = read_dataset(p, time=self.time, fs=self.fs, rename=self.rename, columns=self.columns)
        if self.start is not None or self.stop is not None:
            ds = ds.slice(self.start, self.stop)
        if self.every and self.every > 1:
            k = self.every
            ds = Dataset(ds.t[::k].copy(), {c: v[::k].copy() for c, v in ds.columns.items()}, dict(ds.meta))
        return ds


def appendix_a_data(seed: int, n: int = 100) -> Dataset:
    """Appendix A: x evenly spaced on [0, 2], y = 3 + 5 x + N(0, 0.3^2)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 2.0, n)
    y = 3.0 + 5.0 * x + 0.3 * rng.standard_normal(n)
    return Dataset(np.arange(n, dtype=float), {"x": x, "y": y},
                   {"source": f"appendix_a(seed={seed})", "true_params": {"a0": 3.0, "a1": 5.0, "gamma": 0.3}})


class ArdSettings(BaseModel):
    model_config = _STRICT
    prune_alpha: Optional[float] = Field(None, gt=0, description="pruning threshold for this parameter")


class CandidateSpec(BaseModel):
    """One candidate model with its priors."""

    model_config = _STRICT
    model: Union[Name, ModelSpec] = Field(description="a built-in model name or a full declaration")
    name: Optional[Name] = None
    priors: dict[Name, PriorSpec] = Field(default_factory=dict, max_length=64)
    ard: Union[list[Name], dict[Name, ArdSettings]] = Field(default_factory=list)
    fixed: dict[Name, float] = Field(default_factory=dict)
    constants: dict[Name, float] = Field(
        default_factory=dict, max_length=64,
        description="overrides of the model's known constants (e.g. the declared measurement-noise std 'gamma')")
    substeps: Optional[int] = Field(None, ge=1, le=10000)

    @model_validator(mode="after")
    def _check(self):
        spec = self.resolved()  # applies `constants` (unknown names rejected there; NaN by the schema)
        params = set(spec.parameters)
        label = self.label
        for where, names in (("priors", self.priors), ("ard", self.ard_names), ("fixed", self.fixed)):
            for n in names:
                if n not in params:
                    raise ValueError(f"model {label}: {where}: {n!r} is not a parameter of the model "
                                     f"(parameters: {spec.parameters})")
        both = set(self.priors) & set(self.ard_names)
        if both:
            raise ValueError(f"model {label}: {sorted(both)[0]!r} has both an essential prior and an ARD prior")
        spec = spec.with_fixed(**self.fixed) if self.fixed else spec
        missing = [p for p in spec.free_parameters if p not in self.priors and p not in self.ard_names]
        if missing:
            raise ValueError(f"model {label}: no prior for parameter {missing[0]!r} "
                             "(give it an essential prior, put it under 'ard', or fix it)")
        fixed_ard = set(self.fixed) & set(self.ard_names)
        if fixed_ard:
            raise ValueError(f"model {label}: {sorted(fixed_ard)[0]!r} is both fixed and ARD")
        return self

    @property
    def ard_names(self) -> list[str]:
        return list(self.ard) if isinstance(self.ard, list) else list(self.ard.keys())

    @property
    def label(self) -> str:
        if self.name:
            return self.name
        return self.model if isinstance(self.model, str) else self.model.name

    def resolved(self) -> ModelSpec:
        if isinstance(self.model, str):
            try:
                s = builtin(self.model)
            except Exception as exc:
                raise ValueError(str(exc)) from None
        else:
            s = self.model
        return s.with_constants(**self.constants) if self.constants else s

    def model_spec(self) -> ModelSpec:
        s = self.resolved()
        if self.fixed:
            s = s.with_fixed(**self.fixed)
        return s

    def thresholds(self) -> dict:
        if isinstance(self.ard, list):
            return {k: None for k in self.ard}
        return {k: v.prune_alpha for k, v in self.ard.items()}


class SamplerSpec(BaseModel):
    """The study's sampler settings; defaults are :class:`~ardcore.mcmc.SamplerConfig`'s."""

    model_config = _STRICT
    n_chains: int = Field(_S.n_chains, ge=2, le=64)
    round_size: int = Field(_S.round_size, ge=20, le=100_000)
    min_burnin_rounds: int = Field(_S.min_burnin_rounds, ge=1, le=10_000)
    max_burnin_rounds: int = Field(_S.max_burnin_rounds, ge=1, le=10_000)
    rhat_threshold: float = Field(_S.rhat_threshold, gt=1.0, le=2.0)
    n_stationary: int = Field(_S.n_stationary, ge=50, le=10_000_000)
    n_proposal: int = Field(_S.n_proposal, ge=50, le=10_000_000)
    dr_scale: float = Field(_S.dr_scale, ge=0.0, le=1.0)
    start_maxfev: int = Field(_S.start_maxfev, ge=10, le=1_000_000)
    overdispersion: float = Field(_S.overdispersion, gt=0, le=10)
    outlier_nats: float = Field(_S.outlier_nats, ge=0, le=1e6,
                                description="burn-in: move chains this far below the best chain to it (0: off)")

    @model_validator(mode="after")
    def _rounds(self):
        if self.max_burnin_rounds < self.min_burnin_rounds:
            raise ValueError("sampler: max_burnin_rounds must be >= min_burnin_rounds")
        return self

    def config(self) -> SamplerConfig:
        return SamplerConfig(**self.model_dump())


class MaximiserSpec(BaseModel):
    """The study's maximiser settings; defaults are :class:`~ardcore.ard.MaximiserConfig`'s."""

    model_config = _STRICT
    alpha_start: float = Field(_M.alpha_start, gt=0)
    step_decades: float = Field(_M.step_decades, gt=0, le=10)
    min_step_decades: float = Field(_M.min_step_decades, gt=0, le=10)
    noise_k: float = Field(_M.noise_k, ge=0, le=10)
    step_noise_k: float = Field(_M.step_noise_k, ge=0, le=10)
    min_gain: float = Field(_M.min_gain, ge=0, le=100)
    keep_nats: float = Field(_M.keep_nats, ge=0, le=100)
    prune_alpha: float = Field(_M.prune_alpha, gt=0)
    prune_test: bool = _M.prune_test
    max_trials: int = Field(_M.max_trials, ge=1, le=1000)
    max_sweeps: int = Field(_M.max_sweeps, ge=1, le=100)
    order: Literal["reverse", "declared"] = Field(
        _M.order, description="visit the ARD parameters from the last declared (default) or the first")

    def config(self) -> MaximiserConfig:
        return MaximiserConfig(**self.model_dump())


class StudySpec(BaseModel):
    """A model-selection study (JSON on the CLI and over REST)."""

    model_config = _STRICT
    name: Name = "study"
    description: str = Field("", max_length=4000)
    data: DataSpec
    models: list[CandidateSpec] = Field(min_length=1, max_length=16)
    evidence: Literal["chib-jeliazkov", "laplace"] = "chib-jeliazkov"
    sampler: SamplerSpec = Field(default_factory=SamplerSpec)
    maximiser: MaximiserSpec = Field(default_factory=MaximiserSpec)
    seed: int = Field(0, ge=0, le=2**32 - 1)
    true_values: dict[Name, float] = Field(default_factory=dict, description="for reports only")

    @model_validator(mode="after")
    def _unique(self):
        labels = [m.label for m in self.models]
        if len(set(labels)) != len(labels):
            raise ValueError("models: candidate names must be unique (set 'name')")
        return self


def load_spec(path: str | Path) -> StudySpec:
    """Read and validate a study spec; errors name the field."""
    p = Path(path)
    if not p.exists():
        raise SpecError(f"{p}: no such file")
    try:
        return StudySpec.model_validate_json(p.read_text())
    except ValidationError as exc:
        raise SpecError(f"{p}: invalid study spec:\n{format_validation_error(exc)}") from None


def format_validation_error(exc: ValidationError) -> str:
    lines = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e["loc"] if not str(x).startswith("function-after"))
        lines.append(f"  {loc or '(spec)'}: {e['msg']}")
    return "\n".join(lines)


# --------------------------------------------------------------------------- running
def model_probabilities(log_z: list[float], se: list[float], prior: list[float] | None = None,
                        n_draws: int = 4000, seed: int = 0) -> tuple[list[float], list[float]]:
    """P(M_r | d) by Eq. 7 and its standard deviation from the evidence standard errors."""
    lz = np.asarray(log_z, dtype=float)
    lp = np.log(np.asarray(prior, dtype=float) / np.sum(prior)) if prior else np.full(lz.size, -math.log(lz.size))
    w = lz + lp
    p = np.exp(w - np.logaddexp.reduce(w))
    rng = np.random.default_rng(seed)
    draws = lz[None, :] + np.asarray(se)[None, :] * rng.standard_normal((n_draws, lz.size)) + lp
    pd = np.exp(draws - np.logaddexp.reduce(draws, axis=1, keepdims=True))
    return p.tolist(), pd.std(axis=0).tolist()


def to_jsonable(x):
    """Plain JSON values: infinities as ``"inf"``/``"-inf"`` (pruned alphas), NaN as null, numpy as Python."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (float, np.floating)):
        x = float(x)
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        return None if math.isnan(x) else x
    if isinstance(x, np.integer):
        return int(x)
    return x


def run_candidate(cand: CandidateSpec, data: Dataset, spec: StudySpec, index: int, *, map_fn: Map = serial_map,
                  progress: Callable[[dict], None] | None = None, cancel=None,
                  evaluator_factory: Callable[..., EvidenceEvaluator] | None = None,
                  on_trial: Callable | None = None, warm=None,
                  final_posterior: str = "sample") -> tuple[dict, MaximiserResult]:
    """ARD evidence maximisation for one candidate; returns its summary row and the full result.

    ``evaluator_factory`` (same arguments as :class:`EvidenceEvaluator`) lets an
    orchestrator substitute its own evaluator (caching, checkpoints, remote chains);
    ``on_trial`` is called with every finished :class:`~ardcore.ard.Trial`; ``warm`` (a
    :class:`~ardcore.mcmc.SamplerResult`) warm-starts the first trial. With Laplace evidence,
    ``final_posterior="laplace"`` reports the Laplace posterior N(MAP, H^-1) instead of sampling it.
    """
    t0 = time.perf_counter()
    label = cand.label
    ms = cand.model_spec()
    essential = dict(cand.priors)
    cfg = spec.sampler.config()

    def prog(p):
        if progress:
            progress({"model": label, **p})

    factory = evaluator_factory or EvidenceEvaluator
    kw = {"final_posterior": final_posterior} if final_posterior != "sample" else {}
    ev = factory(ms, essential, data, cfg, method=spec.evidence, substeps=cand.substeps,
                 map_fn=map_fn, progress=prog, cancel=cancel, **kw)

    def trial_done(tr):
        prog({"stage": "trial", "iteration": tr.iteration, "action": tr.action,
              "psi": to_jsonable(tr.psi), "log_evidence": tr.evidence.log_evidence,
              "log_evidence_se": tr.evidence.log_evidence_se, "accepted": tr.accepted})
        if on_trial:
            on_trial(tr)

    seed = spec.seed * 1_000_003 + 7919 * index
    mr = maximise(ev, cand.thresholds(), spec.maximiser.config(), seed=seed, on_trial=trial_done, warm=warm)
    res, target = mr.sampler, mr.target
    if spec.evidence == "laplace":
        target, _, res = ev(mr.psi_opt, seed + 99991, mr.sampler, final=True)
        mr.sampler = res
    flat = res.samples.reshape(-1, len(res.names))
    post = posterior_summary(res.names, flat)
    best = mr.best
    row = {
        "name": label,
        "log_evidence": best.evidence.log_evidence,
        "log_evidence_se": best.evidence.log_evidence_se,
        "goodness_of_fit": best.evidence.goodness_of_fit,
        "information_gain": best.evidence.information_gain,
        "evidence_method": best.evidence.method,
        "psi_opt": {k: ("inf" if v == INF else v) for k, v in mr.psi_opt.items()},
        "kept": mr.kept,
        "pruned": mr.pruned,
        "map": dict(zip(res.names, map(float, res.phi_star))),
        "mean": {k: v["mean"] for k, v in post.items()},
        "sd": {k: v["sd"] for k, v in post.items()},
        "q005": {k: v["q005"] for k, v in post.items()},
        "q995": {k: v["q995"] for k, v in post.items()},
        "rhat": dict(zip(res.names, map(float, res.rhat))),
        "iterations": len(mr.history),
        "sampled_trials": sum(1 for t in mr.history if t.sampled),
        "reweighted_trials": sum(1 for t in mr.history if not t.sampled),
        "n_evaluations": sum(int(t.diagnostics.get("n_evaluations", 0)) for t in mr.history),
        "wall_s": time.perf_counter() - t0,
        "warnings": list(best.evidence.warnings),
        "per_chain_log_evidence": [c.log_evidence for c in best.evidence.per_chain],
    }
    return row, mr


def compare(rows: list[dict], spec: StudySpec, data_meta: dict, wall_s: float) -> dict:
    """The comparison of the optimal nested models (Eq. 7) and the study summary."""
    probs, psd = model_probabilities([r["log_evidence"] for r in rows], [r["log_evidence_se"] for r in rows],
                                     seed=spec.seed)
    for r, p, s in zip(rows, probs, psd):
        r["probability"] = p
        r["probability_sd"] = s
    return to_jsonable({
        "study": spec.name,
        "data": data_meta,
        "models": rows,
        "best_model": max(rows, key=lambda r: r["log_evidence"])["name"],
        "seed": spec.seed,
        "wall_s": wall_s,
        "spec": spec.model_dump(mode="json"),
    })


def select(spec: StudySpec, *, out: str | Path | None = None, map_fn: Map = serial_map,
           progress: Callable[[dict], None] | None = None, base: Path | None = None, cancel=None) -> dict:
    """Run a study in this process (or with ``map_fn`` over any executor).

    Returns the summary dict; with ``out``, writes ``out/summary.json``,
    ``out/history.json`` and ``out/posterior_<model>.npz``.
    """
    t0 = time.perf_counter()
    data = spec.data.load(base)
    rows, results = [], {}
    for i, cand in enumerate(spec.models):
        row, mr = run_candidate(cand, data, spec, i, map_fn=map_fn, progress=progress, cancel=cancel)
        rows.append(row)
        results[cand.label] = mr
    summary = compare(rows, spec, {"source": data.meta.get("source"), "n": len(data)}, time.perf_counter() - t0)
    history = {k: [t.to_dict() for t in mr.history] for k, mr in results.items()}
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        _atomic_write(out / "summary.json", json.dumps(summary, indent=2))
        _atomic_write(out / "history.json", json.dumps(to_jsonable(history), indent=2))
        for k, mr in results.items():
            np.savez(out / f"posterior_{k}.npz", names=np.array(mr.sampler.names), samples=mr.sampler.samples,
                     lp=mr.sampler.lp, ll=mr.sampler.ll)
    summary["_history"] = to_jsonable(history)
    return summary


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)
