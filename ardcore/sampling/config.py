"""The sampler's settings and its result: what :func:`ardcore.sampling.driver.sample` takes and gives."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

SETTINGS = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
"""Settings models: unknown fields refused, no NaN or infinity, immutable once built."""


class SamplerConfig(BaseModel):
    """Sampler settings, with their bounds: the study spec's ``sampler`` section is this model.

    Attributes
    ----------
    n_chains : int
        Chains run side by side (one task each per round).
    round_size : int
        W, samples per chain per round: a burn-in round adapts the kernel after it; the stationary stage
        (fixed kernel) stops only on whole rounds and draws up to four rounds in one task per chain
        (:data:`~ardcore.sampling.driver.STATIONARY_ROUNDS`), the same draws in fewer trips.
    min_burnin_rounds, max_burnin_rounds : int
        Burn-in lasts at least / at most this many rounds.
    burnin_rhat : float
        Burn-in (the adaptation) ends when the split R-hat of every parameter over the latter half of its
        rounds is below it. Over a window of a few rounds R-hat is noisy: with an integrated
        autocorrelation time of 50 draws, chains already in equilibrium show ~1.1 over 250-draw halves,
        so the strict test is made on the stationary draws instead (``rhat_threshold``).
    rhat_threshold : float
        Stationary draws whose rank R-hat exceeds it for some parameter had not settled: they count as more
        burn-in and are drawn again from where the chains are (``stationary_restarts``).
    stationary_restarts : int
        At most this many redraws of the stationary stage.
    n_stationary : int
        M, stationary samples per chain before the first look at their quality.
    max_rhat, min_ess : float
        The quality the stationary draws continue to (Vehtari et al. 2021; ArviZ's rank-normalised split
        R-hat, bulk and tail ESS of every parameter, over all chains).
    max_stationary : int, optional
        The budget: stationary draws per chain at most (default M: the draws are judged, not continued).
        When it runs out before the quality target, the result says so (``quality_met`` False, a warning)
        and the study reports it. In a study it applies to the reported posterior: the maximiser's trials
        draw M per chain (judged, redrawn when unsettled), and the chains of the trial it reports continue
        to the target (:meth:`judged`, :func:`~ardcore.sampling.driver.continuation`).
    n_proposal : int
        J, the most proposal draws at phi* per chain for Chib-Jeliazkov (the denominator).
    proposal_se_ratio : float
        The denominator's draws are independent, the numerator's M are autocorrelated: a chain's
        denominator stops (in blocks of 250) once its Monte Carlo error is below this fraction of the
        numerator's, so the error of ln Z grows by at most sqrt(1 + ratio^2) (12 % at 0.5) over
        J = infinity. 0 always draws J.
    dr_scale : float
        Delayed rejection in burn-in: the second-stage proposal is this fraction of the first (0 turns it
        off). It serves the first rounds of a start whose first proposal is a guess (cold or explicit
        starts); once the pooled covariance is adapted, and from the start of a warm start (which proposes
        from the previous posterior's covariance), a second stage costs an evaluation per rejection and
        saves no rounds (Sec 3.6 demo: M3's cold start took 13 rounds with and without it; 18 % of all
        evaluations were second stages).
    dr_rounds : int
        Burn-in rounds of a cold start that use delayed rejection.
    warm_dr : bool
        Delayed rejection in the first ``dr_rounds`` of warm starts as well.
    start_maxfev : int
        Budget of the local optimisation that places each chain's start.
    search_window : int, optional
        The Nelder-Mead searches that place a Laplace trial's cold start read only the record's first this
        many samples; the Newton steps, the curvature and the evidence read all of it (None, the default: the
        searches read all of it too). A search only has to land where Newton's steps converge, so on a long
        record it costs what it costs on a short one. A record of several experiments is always read whole.
    overdispersion : float
        Starts are drawn at this many posterior standard deviations around each local mode.
    inca : bool
        Pool the adaptation over all chains (INCA); False adapts each chain on its own history
        (for comparison only).
    jump_weight : float
        The share of steps that propose from an independence proposal (a multivariate t fitted to the
        pooled burn-in draws, :class:`~ardcore.sampling.proposal.Jump`) instead of the random walk: in burn-in once
        delayed rejection is over, and throughout the stationary stage (fixed there, so Chib-Jeliazkov holds
        with the mixture's density). 0 is the plain random walk of method.md. On Sec 3.6 it cut the
        integrated autocorrelation time of M2 from ~30 draws to a few and made M3's curved posterior mix.
    jump_df : float
        Degrees of freedom of that t (heavy tails, so the proposal covers the posterior's tails).
    outlier_nats : float
        During burn-in, a chain whose mean ln posterior over a round's latter half lies more than
        this many nats below the best chain's is moved to that chain's position (0 turns it off).
        Within one mode the round means of the chains differ by well under a nat for the
        models here; 10 nats is a chain stuck in a minor mode.
    """

    model_config = SETTINGS
    n_chains: int = Field(4, ge=2, le=64)
    round_size: int = Field(500, ge=20, le=100_000)
    min_burnin_rounds: int = Field(4, ge=1, le=10_000)
    max_burnin_rounds: int = Field(60, ge=1, le=10_000)
    burnin_rhat: float = Field(1.2, gt=1.0, le=2.0)
    rhat_threshold: float = Field(1.1, gt=1.0, le=2.0)
    stationary_restarts: int = Field(3, ge=0, le=100)
    n_stationary: int = Field(5000, ge=50, le=10_000_000)
    max_rhat: float = Field(1.01, gt=1.0, le=2.0)
    min_ess: float = Field(400.0, ge=0.0, le=1e7)
    max_stationary: int | None = Field(None, ge=50, le=10_000_000)
    n_proposal: int = Field(5000, ge=50, le=10_000_000)
    proposal_se_ratio: float = Field(0.5, ge=0.0, le=10.0)
    dr_scale: float = Field(0.1, ge=0.0, le=1.0)
    dr_rounds: int = Field(2, ge=0, le=10_000)
    warm_dr: bool = False
    start_maxfev: int = Field(3000, ge=10, le=1_000_000)
    search_window: int | None = Field(None, ge=100, le=10**9)
    overdispersion: float = Field(2.0, gt=0, le=10)
    inca: bool = True
    jump_weight: float = Field(0.5, ge=0.0, lt=1.0)
    jump_df: float = Field(5.0, ge=1.0, le=1000.0)
    outlier_nats: float = Field(10.0, ge=0, le=1e6,
                                description="burn-in: move chains this far below the best chain to it (0: off)")

    @property
    def stationary_budget(self) -> int:
        """Stationary draws per chain at most (``max_stationary``, default ``n_stationary``)."""
        return max(self.n_stationary, self.max_stationary or self.n_stationary)

    def judged(self) -> "SamplerConfig":
        """These settings without the extension: M draws per chain, judged (and redrawn once when unsettled)
        but not continued; what the maximiser's search trials use. (A trial still unsettled after one redraw
        is typically a bimodal posterior at a loose alpha: more redraws do not settle it, and its evidence
        is compared with its standard error, not reported.)"""
        return self.model_copy(update={"max_stationary": None,
                                       "stationary_restarts": min(1, self.stationary_restarts)})

    @model_validator(mode="after")
    def _rounds(self):
        if self.max_burnin_rounds < self.min_burnin_rounds:
            raise ValueError("sampler: max_burnin_rounds must be >= min_burnin_rounds")
        return self


@dataclass
class SamplerResult:
    """Output of :func:`sample`: stationary samples, phi*, diagnostics and the state to warm-start from."""

    names: list
    samples: np.ndarray          # (n_chains, M, d)
    lp: np.ndarray               # (n_chains, M)
    ll: np.ndarray               # (n_chains, M)
    phi_star: np.ndarray
    lp_star: float
    ll_star: float
    proposal_cov: np.ndarray
    states: list                 # ChainState
    rhat: np.ndarray
    rhat_history: list
    burnin_rounds: int
    converged: bool
    acceptance: float
    burnin_acceptance: float
    n_evaluations: int
    warnings: list = field(default_factory=list)
    jump: dict | None = None
    """The stationary stage's independence proposal (:class:`~ardcore.sampling.proposal.Jump` as a dict; None: the plain
    random walk), which the Chib-Jeliazkov ordinate needs with ``proposal_cov``."""
    diagnostics: dict = field(default_factory=dict)
    """ArviZ's rank R-hat, bulk and tail ESS and MCSE per parameter of the stationary draws
    (:func:`ardcore.sampling.diagnostics.convergence`)."""
    quality_met: bool = True
    """Whether every parameter reached ``max_rhat`` and ``min_ess`` within the budget."""
    adaptation: dict | None = None
    """The INCA coordinator's final state (:meth:`~ardcore.sampling.adaptation.AdaptationPool.to_dict`): with
    ``states`` and the draws, what continuing these chains needs (:func:`~ardcore.sampling.driver.continuation`)."""

    # what a trial record keeps beside the draws (which a store keeps in arrays of their own)
    _RECORD = ("names", "phi_star", "lp_star", "ll_star", "proposal_cov", "rhat", "rhat_history", "burnin_rounds",
               "converged", "acceptance", "burnin_acceptance", "n_evaluations", "warnings", "jump", "diagnostics",
               "quality_met", "adaptation")

    def to_json(self) -> dict:
        """Everything but the draws (``samples``, ``lp``, ``ll``), as JSON values: with the draws,
        :meth:`from_json` gives this result back."""
        from ..jsonio import to_jsonable

        return to_jsonable({**{k: getattr(self, k) for k in self._RECORD},
                            "states": [s.to_dict() for s in self.states]})

    @classmethod
    def from_json(cls, rec: dict, samples: np.ndarray, lp: np.ndarray, ll: np.ndarray) -> "SamplerResult":
        """The result :meth:`to_json` wrote, with its draws."""
        from .chains import ChainState

        return cls(
            names=list(rec["names"]), samples=samples, lp=lp, ll=ll, phi_star=np.array(rec["phi_star"]),
            lp_star=rec["lp_star"], ll_star=rec["ll_star"], proposal_cov=np.array(rec["proposal_cov"]),
            states=[ChainState.from_dict(s) for s in rec["states"]], rhat=np.array(rec["rhat"]),
            rhat_history=rec["rhat_history"], burnin_rounds=rec["burnin_rounds"], converged=rec["converged"],
            acceptance=rec["acceptance"], burnin_acceptance=rec["burnin_acceptance"],
            n_evaluations=rec["n_evaluations"], warnings=list(rec["warnings"]), jump=rec.get("jump"),
            diagnostics=rec.get("diagnostics", {}), quality_met=rec.get("quality_met", True),
            adaptation=rec.get("adaptation"))
