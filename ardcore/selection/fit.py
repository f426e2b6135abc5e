"""One candidate's result at its evidence optimum: the row of a study's summary, typed.

:func:`ardcore.selection.study.run_candidate` returns a :class:`ModelFit`; the loop (:mod:`ardcore.loop.diagnose`), the
comparison and the stores read its attributes, and its JSON (:meth:`ModelFit.to_json`) is the summary's
``models`` entry and the store's model result. A pruned term's alpha is ``math.inf`` here; only the JSON
spells it (:mod:`ardcore.jsonio`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

from ..jsonio import decode_alpha, to_jsonable


NO_FIT = "could not be fitted"
"""The warning of a candidate no chain could fit (:meth:`ModelFit.failed`)."""


@dataclass(frozen=True)
class ModelFit:
    """A candidate's ARD evidence maximisation, summarised.

    Attributes
    ----------
    name : str
        The candidate's label.
    log_evidence, log_evidence_se : float
        ln Z at the optimal psi and its Monte Carlo standard error (0 for Laplace).
    goodness_of_fit, information_gain : float
        The evidence's two parts (ln Z = goodness_of_fit - information_gain).
    evidence_method : str
        ``chib_jeliazkov`` or ``laplace``.
    psi_opt : dict
        Optimal alpha per ARD term (``math.inf``: pruned).
    kept, pruned : list of str
        ARD terms kept and pruned at psi_opt.
    map, mean, sd, q005, q995, rhat : dict
        Posterior summaries per free parameter at psi_opt (q005/q995: the 99 % interval; rhat ArviZ's rank
        R-hat).
    diagnostics : dict
        Per free parameter, ArviZ's ``r_hat``, ``ess_bulk``, ``ess_tail``, ``mcse_mean`` and ``mcse_sd`` of
        the reported draws (:mod:`ardcore.sampling.diagnostics`).
    converged : bool
        Whether every parameter reached the sampler's quality target (R-hat <= max_rhat, bulk and tail ESS
        >= min_ess) within its budget; False is said in ``warnings`` too.
    iterations, sampled_trials, reweighted_trials, n_evaluations : int
        The maximiser's trials and the likelihood evaluations they spent.
    wall_s : float
    warnings : list of str
    per_chain_log_evidence : list of float
    """

    name: str
    log_evidence: float
    log_evidence_se: float
    goodness_of_fit: float = math.nan
    information_gain: float = math.nan
    evidence_method: str = ""
    psi_opt: dict = field(default_factory=dict)
    kept: list = field(default_factory=list)
    pruned: list = field(default_factory=list)
    map: dict = field(default_factory=dict)
    mean: dict = field(default_factory=dict)
    sd: dict = field(default_factory=dict)
    q005: dict = field(default_factory=dict)
    q995: dict = field(default_factory=dict)
    rhat: dict = field(default_factory=dict)
    iterations: int = 0
    sampled_trials: int = 0
    reweighted_trials: int = 0
    n_evaluations: int = 0
    wall_s: float = 0.0
    warnings: list = field(default_factory=list)
    per_chain_log_evidence: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    converged: bool = True

    def to_json(self) -> dict:
        """The summary's row (a pruned alpha spelt as :mod:`ardcore.jsonio` spells infinity)."""
        return to_jsonable(asdict(self))

    @classmethod
    def from_json(cls, d: dict) -> "ModelFit":
        """From :meth:`to_json` (keys the row does not own, such as a comparison's probability, are ignored)."""
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        kw["psi_opt"] = {k: decode_alpha(a) for k, a in d.get("psi_opt", {}).items()}
        for k in ("log_evidence", "log_evidence_se", "goodness_of_fit", "information_gain"):
            if k in kw:
                kw[k] = math.nan if kw[k] is None else float(kw[k])
        return cls(**kw)

    def point(self, names) -> dict:
        """Posterior means of ``names`` (a parameter point, e.g. the free parameters of the fitted model)."""
        return {k: float(self.mean[k]) for k in names}

    def physical(self, name: str, scale: float) -> dict:
        """Posterior summary of a normalised coefficient in physical units (scale > 0)."""
        return {"mean": self.mean[name] * scale, "sd": self.sd[name] * scale,
                "q005": self.q005[name] * scale, "q995": self.q995[name] * scale}

    @classmethod
    def failed(cls, name: str, reason: str, wall_s: float = 0.0) -> "ModelFit":
        """A candidate that could not be fitted at all (no chain found a finite posterior): no evidence, and the
        reason as its warning, so that the comparison refuses it (:meth:`degenerate`)."""
        return cls(name, math.nan, math.nan, wall_s=wall_s, converged=False, warnings=[f"{NO_FIT}: {reason}"])

    def summary(self, keys) -> dict:
        """The attributes ``keys`` as a dict (a report's excerpt)."""
        return {k: getattr(self, k) for k in keys}

    def degenerate(self) -> str | None:
        """What makes this fit no result, or None: a sampled parameter whose posterior has no spread (sd 0 or
        not finite: the chains never moved it) or a sampled evidence without a finite, positive standard
        error; an evidence that is not a finite number, or a Laplace evidence whose curvature at the optimum is not
        positive definite (its log-determinant, and so ln Z and every sd, are then placeholders). (A Laplace
        evidence states no Monte Carlo error: its 0 is not a defect.)"""
        if not math.isfinite(self.log_evidence):
            failed = next((str(w) for w in self.warnings if str(w).startswith(NO_FIT)), None)
            return f"{self.name}: {failed or f'the evidence is not a finite number (ln Z = {self.log_evidence})'}"
        from ..evidence.estimators import COLLAPSED

        collapsed = next((str(w) for w in self.warnings if COLLAPSED in str(w)), None)
        if collapsed:
            return f"{self.name}: {collapsed}"
        if any("not positive definite" in str(w) for w in self.warnings):
            return (f"{self.name}: the likelihood's curvature at the optimum is not positive definite, so its Laplace "
                    "evidence and posterior sd are not a result")
        flat = [k for k, v in self.sd.items() if not (math.isfinite(v) and v > 0)]
        if flat:
            return (f"{self.name}: the posterior of {', '.join(flat[:5])} has no spread (sd "
                    f"{self.sd[flat[0]]:g}): the chains did not move, so neither the intervals nor the evidence "
                    "are a result")
        se = self.log_evidence_se
        if self.evidence_method == "chib-jeliazkov" and not (math.isfinite(se) and se > 0):
            return f"{self.name}: the evidence has no finite Monte Carlo error (se {se:g}): the chains did not move"
        return None
