"""The sampler's settings and its result: what :func:`ardcore.mcmc.sample` takes and gives."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class SamplerConfig:
    """Sampler settings (the study spec's ``sampler`` section maps onto this).

    Attributes
    ----------
    n_chains : int
    round_size : int
        W, samples per chain per round.
    min_burnin_rounds, max_burnin_rounds : int
    rhat_threshold : float
    n_stationary : int
        M, stationary samples per chain.
    n_proposal : int
        J, proposal draws at phi* per chain for Chib-Jeliazkov.
    dr_scale : float
    start_maxfev : int
        Budget of the local optimisation that places each chain's start.
    overdispersion : float
        Starts are drawn at this many posterior standard deviations around each local mode.
    inca : bool
        Pool the adaptation over all chains (INCA); False adapts each chain on its own history
        (for comparison only).
    outlier_nats : float
        During burn-in, a chain whose mean ln posterior over a round's latter half lies more than
        this many nats below the best chain's is moved to that chain's position (0 turns it off).
        Within one mode the round means of the chains differ by well under a nat for the
        models here; 10 nats is a chain stuck in a minor mode.
    """

    n_chains: int = 4
    round_size: int = 500
    min_burnin_rounds: int = 4
    max_burnin_rounds: int = 60
    rhat_threshold: float = 1.1
    n_stationary: int = 5000
    n_proposal: int = 5000
    dr_scale: float = 0.1
    start_maxfev: int = 3000
    overdispersion: float = 2.0
    inca: bool = True
    outlier_nats: float = 10.0


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
