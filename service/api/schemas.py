"""Settings and the request and response schemas of the REST service."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Any, Optional, Union

from pydantic import BaseModel, ConfigDict, Field

from ardflow.ardcore.loop.config import DiagnoseConfig

DatasetId = Annotated[str, Field(pattern=r"^[a-f0-9]{16}$")]
"""An uploaded data set's id."""

API_VERSION = "v1"
ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
FINAL = {"done", "failed", "cancelled", "damaged"}


class Settings(BaseModel):
    """Service settings (``ardflow serve`` options)."""

    model_config = ConfigDict(extra="forbid")
    root: Path = Field(description="directory holding the registry, data sets and study stores")
    token: Optional[str] = Field(None, description="API token; None (and no `tokens`) disables authentication")
    tokens: Optional[dict[str, str]] = Field(None, description="more API tokens by owner name (each owner's "
                                                               "active studies are limited separately)")
    admins: list[str] = Field(["admin"], description="owners (names in `tokens`; `default` is the --token's) "
                                                     "who see and act on every study; the others see their own")
    max_active_per_token: int = Field(20, ge=1, description="queued + running studies one token may have")
    max_body_mb: float = Field(20.0, gt=0)
    max_upload_rows: int = Field(2_000_000, gt=0)
    max_running: int = Field(2, ge=1, description="study drivers running at once; the others wait queued")
    max_queued: int = Field(100, ge=1, description="studies waiting at most (more: 429)")
    max_study_cost: float = Field(1e13, gt=0, description="estimated likelihood evaluations x data rows x "
                                                          "sub-steps a study may cost (more: 413 with the estimate)")
    check_timeout_s: float = Field(30.0, gt=0, description="time allowed to compile a study's models at submit")
    check_memory_mb: int = Field(2048, ge=256, description="memory allowed to compile a study's models")
    cancel_grace_s: float = Field(10.0, ge=0, description="a cancelled driver is killed after this")
    max_task_s: float = Field(21600.0, gt=0, description="a chain task running longer fails its study "
                                                         "(the backstop behind cancellation)")
    allowed_hosts: Optional[list[str]] = Field(None, description="Host header names served (None: any)")


# ------------------------------------------------------------------ response schemas
class Health(BaseModel):
    status: str
    version: str
    workers: int


class DatasetInfo(BaseModel):
    id: str
    rows: int
    columns: list[str]


class StudyCreated(BaseModel):
    id: str
    status: str


class Progress(BaseModel):
    model: Optional[str] = None
    stage: Optional[str] = None
    iteration: Optional[int] = None
    psi: Optional[dict[str, Any]] = None
    best_log_evidence: Optional[float] = None
    rhat: Optional[list[Optional[float]]] = None
    trials_done: int = 0
    max_trials: Optional[int] = Field(None, description="the ARD search's cap; it usually stops well before")
    elapsed_s: float = 0.0
    eta_s: Optional[float] = Field(None, description="an upper bound on the time left (at the pace so far, if "
                                                     "the search ran all max_trials); not an estimate")


class StudyStatus(BaseModel):
    id: str
    name: str
    status: str
    created: float
    error: Optional[str] = None
    models: dict[str, Progress] = Field(default_factory=dict)


class DiagnoseRequest(BaseModel):
    """Close the loop on one model of a finished study (``ardflow diagnose`` on the study's store)."""

    model_config = ConfigDict(extra="forbid")
    model: Optional[str] = Field(None, pattern=r"^[A-Za-z][A-Za-z0-9_]{0,31}$",
                                 description="default: the study's best model")
    # the loop's own settings, bounds and defaults (a request runs at least one round)
    top_k: int = DiagnoseConfig.model_fields["top_k"]
    max_rounds: int = Field(DiagnoseConfig.model_fields["max_rounds"].default, ge=1, le=10,
                            description=DiagnoseConfig.model_fields["max_rounds"].description)
    test_dataset: Optional[Union[DatasetId, Annotated[list[DatasetId], Field(min_length=1, max_length=16)]]] = Field(
        None, description="uploaded held-out record for the free run, or a list of them (one per record)")

    @property
    def test_datasets(self) -> list[str]:
        """The held-out records' data set ids (none, one or several)."""
        t = self.test_dataset
        return [] if t is None else [t] if isinstance(t, str) else list(t)


class DiagnosisStatus(BaseModel):
    model: str
    status: str
    error: Optional[str] = None
    verdict: Optional[str] = None
    figures: list[str] = Field(default_factory=list)


class DashboardLink(BaseModel):
    url: Optional[str]


def finite_or_none(x):
    if isinstance(x, dict):
        return {k: finite_or_none(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite_or_none(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def reason(exc: Exception) -> str:
    """What went wrong reading a file, as a user may read it: without the server's paths."""
    text = str(exc).splitlines()[0][:160] if str(exc) else ""
    return f"{type(exc).__name__}: {re.sub(r'(/[^/ ]+)+/?', '<file>', text)}" if text else type(exc).__name__
