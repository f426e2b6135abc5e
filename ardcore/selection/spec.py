"""A study as data: where the data come from, the candidate models with their priors and ARD terms, the
sampler and maximiser settings (pydantic, strict: no extra fields, no NaN or infinity, bounded sizes)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .config import MaximiserConfig
from ..data import DATA_ENV, Dataset, external_path, read_dataset
from ..errors import DataError, SpecError, did_you_mean
from ..model.library import builtin
from ..sampling.config import SamplerConfig
from ..model.declaration import NAME_PATTERN, ModelSpec
from ..model.priors import PriorSpec

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)
Name = Annotated[str, Field(pattern=NAME_PATTERN)]
PLAIN_TEXT = r"^[^$\x00-\x1f\x7f]*$"
"""A unit or a label: printable text without '$' (math mode in the figures)."""


class DataSpec(BaseModel):
    """Where the data come from: a file, or a documented generator. A study of several records (separate
    experiments of one system) gives a list of these, each with its own initial state and constants."""

    model_config = _STRICT
    name: Optional[str] = Field(None, max_length=80, pattern=PLAIN_TEXT, description="the record's name")
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
    # plain text: a '$' would switch the figures' renderer to math mode, where an unknown macro fails the report
    units: dict[Name, Annotated[str, Field(max_length=32, pattern=PLAIN_TEXT)]] = Field(
        default_factory=dict, max_length=64, description="unit of each column and of time (t), for reports: "
                                                           "{'t': 's', 'y': 'V'}")
    labels: dict[Name, Annotated[str, Field(max_length=80, pattern=PLAIN_TEXT)]] = Field(
        default_factory=dict, max_length=64, description="what each column is, for reports: "
                                                           "{'y': 'output voltage'}")
    initial_mean: dict[Name, float] = Field(default_factory=dict, max_length=64,
                                            description="this record's initial state mean, by state (default: "
                                                        "the model's)")
    initial_std: dict[Name, Annotated[float, Field(gt=0)]] = Field(
        default_factory=dict, max_length=64, description="this record's initial state std, by state")
    constants: dict[Name, float] = Field(default_factory=dict, max_length=64,
                                         description="values held for the whole record (an airspeed, an input "
                                                     "level), given to the model as input columns of that name")

    def axis_label(self, column: str) -> str:
        """``"output voltage y [V]"``: the column's declared label and unit (the reference problem's own
        names for its generated data; otherwise the column's name alone where none is declared)."""
        defaults = {"y": ("pitch angle theta", "rad"), "t": ("non-dimensional time tau", "")} \
            if self.generator == "reference" else {}
        label, unit = defaults.get(column, ("time" if column == "t" else column, ""))
        if column in self.labels:
            label = self.labels[column] if column == "t" else f"{self.labels[column]} {column}"
        unit = self.units.get(column, unit)
        return f"{label} [{unit}]" if unit else label

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
            name = uploaded_name(ds)
            ds.meta["source"] = f"{name} (uploaded data set {self.dataset})" if name else \
                f"uploaded data set {self.dataset}"
        elif self.generator == "reference":
            from ..likelihood.simulate import simulate_reference

            ds = simulate_reference(self.seed)
        elif self.generator == "appendix_a":
            ds = appendix_a_data(self.seed)
        else:
            p = Path(self.path)
            if base is not None and not p.is_absolute():
                p = base / p
            if not p.exists() and not Path(self.path).is_absolute():
                # a record ardflow does not ship: under $ARDFLOW_DATA
                p = external_path(self.path) or p
                if not p.exists():
                    raise DataError(f"{self.path}: no such file (relative paths are read beside the spec, "
                                    f"then under ${DATA_ENV})")
            ds = read_dataset(p, time=self.time, fs=self.fs, rename=self.rename, columns=self.columns)
        if self.start is not None or self.stop is not None:
            ds = ds.slice(self.start, self.stop)
        if self.every and self.every > 1:
            k = self.every
            ds = Dataset(ds.t[::k].copy(), {c: v[::k].copy() for c, v in ds.columns.items()}, dict(ds.meta))
        if self.units:
            ds.meta["units"] = {**ds.meta.get("units", {}), **self.units}
        for name, v in self.constants.items():
            if name in ds.columns:
                raise DataError(f"{ds.meta.get('source', 'data')}: constant {name!r} is also a column")
            ds.columns[name] = np.full(len(ds), float(v))
        for k in ("initial_mean", "initial_std"):
            if getattr(self, k):
                ds.meta[k] = dict(getattr(self, k))
        return ds


def uploaded_name(ds: Dataset) -> str | None:
    """The name a data set was uploaded to the service under, when the service recorded one (beside the file,
    in the sidecar :func:`~ardcore.data.read_dataset` reads into ``meta["sidecar"]``)."""
    side = ds.meta.get("sidecar")
    name = side.get("name") if isinstance(side, dict) else None
    return name if isinstance(name, str) and name else None


def appendix_a_data(seed: int, n: int = 100) -> Dataset:
    """Appendix A: x evenly spaced on [0, 2], y = 3 + 5 x + N(0, 0.3^2)."""
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 2.0, n)
    y = 3.0 + 5.0 * x + 0.3 * rng.standard_normal(n)
    return Dataset(np.arange(n, dtype=float), {"x": x, "y": y},
                   {"source": f"appendix_a(seed={seed})", "true_params": {"a0": 3.0, "a1": 5.0, "gamma": 0.3}})


RECORD_INPUT = "record_"
"""Prefix of the record indicator inputs ``record_0``, ``record_1``, ... (1 in that record, 0 elsewhere) that
per-record parameters are written over."""


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
    per_record: list[Name] = Field(default_factory=list, max_length=16, description=(
        "parameters with one value per record (an offset, a sensor gain): in a study of K records each becomes "
        "K parameters NAME_0 ... NAME_K-1 with NAME's prior; the others are shared"))

    @model_validator(mode="after")
    def _check(self):
        spec = self.resolved()  # applies `constants` (unknown names rejected there; NaN by the schema)
        params = set(spec.parameters)
        label = self.label
        for where, names in (("priors", self.priors), ("ard", self.ard_names), ("fixed", self.fixed),
                             ("per_record", self.per_record)):
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
        if set(self.fixed) & set(self.per_record):
            raise ValueError(f"model {label}: {sorted(set(self.fixed) & set(self.per_record))[0]!r} is both fixed "
                             "and per record")
        return self

    def for_records(self, k: int) -> "CandidateSpec":
        """This candidate on ``k`` records: each ``per_record`` parameter P becomes P_0 ... P_k-1, one per record,
        each with P's prior (or ARD setting), and P a derived quantity ``P_0*record_0 + ...`` over the record
        indicator inputs ``record_r`` (1 in record r, 0 elsewhere: :meth:`StudySpec.load_data` adds them).
        Unchanged without ``per_record`` or for one record (its one value is the shared one)."""
        if not self.per_record or k < 2:
            return self
        ms = self.resolved()
        names = set(self.per_record)
        copies = {p: [f"{p}_{r}" for r in range(k)] for p in self.per_record}
        taken = set(ms.parameters) | set(ms.inputs) | set(ms.constants) | set(ms.derived) | set(ms.states)
        for p, cs in copies.items():
            clash = [c for c in cs if c in taken]
            if clash:
                raise ValueError(f"model {self.label}: per_record {p!r} needs the name {clash[0]!r}, which the model "
                                 "already uses")
        indicators = [f"{RECORD_INPUT}{r}" for r in range(k)]
        params = [c for p in ms.parameters for c in (copies[p] if p in names else [p])]
        derived = {p: " + ".join(f"{c}*{i}" for c, i in zip(copies[p], indicators)) for p in self.per_record}
        # an undeclared hold stays undeclared: the records decide it (:mod:`.hold`)
        model = ms.model_dump(mode="json", exclude=set() if "input_hold" in ms.model_fields_set else {"input_hold"})
        model.update(parameters=params, derived={**derived, **ms.derived},
                     inputs=ms.inputs + [i for i in indicators if i not in ms.inputs], constants=ms.constants)
        spread = lambda d: {c: v for p, v in d.items() for c in (copies[p] if p in names else [p])}  # noqa: E731
        ard = spread(self.ard) if isinstance(self.ard, dict) else [c for p in self.ard for c in (
            copies[p] if p in names else [p])]
        return CandidateSpec.model_validate({
            **self.model_dump(mode="json", exclude={"model", "constants", "per_record", "priors", "ard"}),
            "name": self.label, "model": model,
            "priors": {k2: v.model_dump(mode="json") for k2, v in spread(self.priors).items()},
            "ard": ard if isinstance(ard, list) else {k2: v.model_dump(mode="json") for k2, v in ard.items()}})

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


SamplerSpec = SamplerConfig
"""The study's ``sampler`` section (one declaration: :class:`~ardcore.sampling.config.SamplerConfig`)."""
MaximiserSpec = MaximiserConfig
"""The study's ``maximiser`` section (one declaration: :class:`~ardcore.selection.maximiser.MaximiserConfig`)."""


class StudySpec(BaseModel):
    """A model-selection study (JSON on the CLI and over REST)."""

    model_config = _STRICT
    name: Name = "study"
    description: str = Field("", max_length=4000)
    data: Union[DataSpec, Annotated[list[DataSpec], Field(min_length=1, max_length=64)]] = Field(
        description="one record, or a list of records (separate experiments of one system: the likelihood is "
                    "the sum over records, each filtered from its own start)")
    models: list[CandidateSpec] = Field(min_length=1, max_length=16)
    evidence: Literal["chib-jeliazkov", "laplace"] = "chib-jeliazkov"
    sampler: SamplerConfig = Field(default_factory=SamplerConfig)
    maximiser: MaximiserConfig = Field(default_factory=MaximiserConfig)
    seed: int = Field(0, ge=0, le=2**32 - 1)
    true_values: dict[Name, float] = Field(default_factory=dict, description="for reports only")

    @model_validator(mode="after")
    def _unique(self):
        if any(m.per_record for m in self.models) and len(self.records) > 1:
            # written out once: the stored spec shows the parameters that ran, and validating it again is a no-op
            self.models = [m.for_records(len(self.records)) for m in self.models]
        labels = [m.label for m in self.models]
        if len(set(labels)) != len(labels):
            raise ValueError("models: candidate names must be unique (set 'name')")
        # the evidence integrates the likelihood against the prior: an improper one has no evidence
        for i, m in enumerate(self.models):
            for name, p in m.priors.items():
                if not p.proper:
                    raise ValueError(f"models[{i}].priors.{name}: a {p.kind} prior is improper and the evidence "
                                     "needs a proper one (uniform, normal or lognormal)")
        return self

    @property
    def records(self) -> list[DataSpec]:
        """The data's records (one for a single data spec)."""
        return list(self.data) if isinstance(self.data, list) else [self.data]

    @property
    def naming(self) -> DataSpec:
        """The record whose units and labels name the columns in reports (the first)."""
        return self.records[0]

    def load_data(self, base: Path | None = None, datasets: Path | None = None) -> Dataset:
        """The study's data: its one record, or its records joined (:func:`~ardcore.data.join_records`)."""
        from ..data import join_records

        recs = self.records
        loaded = [r.load(base, datasets) for r in recs]
        for r, ds in enumerate(loaded):
            for i in self.record_inputs:  # the per-record parameters' indicators (CandidateSpec.for_records)
                ds.columns[i] = np.full(len(ds), float(i == f"{RECORD_INPUT}{r}"))
        return join_records(loaded, [r.name for r in recs])

    @property
    def record_inputs(self) -> list[str]:
        """The record indicator inputs the candidates' per-record parameters are written over (none without)."""
        return sorted({i for m in self.models for i in m.model_spec().inputs if i.startswith(RECORD_INPUT)})

    def held_out(self, ds: Dataset) -> Dataset:
        """A held-out record (a further experiment) as the models take it: a per-record parameter takes the
        records' mean there (each indicator ``record_r`` = 1/K), the best guess for an experiment not fitted."""
        used = self.record_inputs
        if not used or all(i in ds.columns for i in used):
            return ds
        cols = dict(ds.columns)
        for i in used:
            cols.setdefault(i, np.full(len(ds), 1.0 / len(used)))
        return ds.with_columns(cols)

    def check_data(self, data) -> None:
        """Refuse a data set no candidate can be fitted to: each candidate's observed columns present with at
        least one value, its inputs present and complete (:meth:`Dataset.arrays`). Raises DataError naming
        the candidate and the column."""
        from ..errors import DataError, ModelError
        from ..likelihood.ekf import record_priors

        for i, m in enumerate(self.models):
            ms = m.model_spec()
            try:
                data.arrays(ms.observed_columns, ms.inputs)
                record_priors(data, list(ms.states), ms.name)
            except (DataError, ModelError) as exc:
                raise DataError(f"models[{i}] ({m.label}): {exc}") from None


def load_spec(path: str | Path) -> StudySpec:
    """Read and validate a study spec; errors name the field."""
    p = Path(path)
    if not p.exists():
        raise SpecError(f"{p}: no such file")
    try:
        return StudySpec.model_validate_json(p.read_text())
    except ValidationError as exc:
        raise SpecError(f"{p}: invalid study spec:\n{format_validation_error(exc)}") from None


def _field_names(model=None, seen=None) -> set:
    """Every field name of the study spec and the settings it holds (what a mistyped key is matched to)."""
    import typing

    model, seen = model or StudySpec, seen if seen is not None else set()
    if model in seen:
        return set()
    seen.add(model)
    names = set(model.model_fields)
    for f in model.model_fields.values():
        stack = [f.annotation]
        while stack:
            t = stack.pop()
            if isinstance(t, type) and issubclass(t, BaseModel):
                names |= _field_names(t, seen)
            stack.extend(typing.get_args(t))
    return names


def format_validation_error(exc: ValidationError) -> str:
    """One line per error, naming the field (a mistyped key with the closest valid one)."""
    lines = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e["loc"] if not str(x).startswith("function-after"))
        hint = did_you_mean(e["loc"][-1], _field_names()) if e["type"] == "extra_forbidden" and e["loc"] else ""
        lines.append(f"  {loc or '(spec)'}: {e['msg']}{hint}")
    return "\n".join(lines)


