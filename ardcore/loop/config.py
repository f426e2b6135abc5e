"""Settings of the closed loop (:func:`ardcore.loop.diagnose.diagnose`), with their documented defaults."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Literal

from pydantic import BaseModel, Field

from ..sampling.config import SETTINGS

if TYPE_CHECKING:  # the loop's context names the study spec; selection does not import the loop
    from ..selection.spec import StudySpec


class DiagnoseConfig(BaseModel):
    """Settings of :func:`diagnose` (documented defaults).

    Attributes
    ----------
    max_lag : int
        Autocorrelation lags shown and tested.
    ljung_box_lags : int
        Lags in the Ljung-Box statistic.
    peak_p : float
        A spectral bin is a peak when its power exceeds the local background by the
        (1 - peak_p) chi-square quantile (2 degrees of freedom per Welch segment pair).
    min_score : float
        Screened ln Bayes factor (nats, :mod:`ardcore.screening.screen`) a candidate needs to be confirmed by
        the full ARD re-selection (default 3: Kass and Raftery's "positive" evidence).
    top_k : int
        Candidates confirmed by the full re-selection per round (the best screened ones above
        ``min_score``).
    min_log_bf : float
        Evidence gain (nats) over the base model an added effect needs, on top of ARD keeping it; the gain is
        first divided by the factor by which the EKF understates its score's variance (``inflation`` of the
        screen: coloured innovations), so a likelihood that takes coloured noise as white cannot add a term.
    library_prior : bool
        Each of the N candidates the screen tried is a priori one of N equally likely additions, so its prior
        odds against "nothing missing" are 1/N and its ln Bayes factor must also pay ln N (Scott and Berger
        2010's multiplicity correction: the more candidates tried, the more one of them fits noise by chance).
        With the library on an oscillator, N ~ 25-35 and ln N ~ 3.5 nats. False: ``min_log_bf`` alone.
    init_samples : int
        Samples of a held-out record used to initialise the free run (filtered state).
    max_rounds : int
        Rounds at most (each re-traces the model's residual and makes one move: an effect, a law in another form; a
        round that takes a measurement-noise level alone does not count). A cap on the cost, not the stopping
        rule: the loop stops when no move the evidence supports free-runs better held out. On the real tanks record the physical model needs five
        moves (a noise level, a sensor law, two flow laws, tank 1 overflowing into tank 2); the default leaves
        room for that.
    split_z : float or None
        Stability check of a surviving effect: its coefficients are refitted (at the optimal alpha) on
        the first and the second half of the record. They disagree when they differ by more than
        ``split_z`` standard errors *and* by more than ``split_rel`` of their size (or change sign): a
        term that compensates for something that changes over the record rather than explaining it.
        On a long record the standard errors are tiny and any small misfit shows, so the size of
        the disagreement is judged against the effect's own size. None (default) skips the check: the
        held-out criterion judges what the halves would (a term that compensates free-runs worse on a block
        it did not see), and the check vetoed moves the criterion takes (on the real tanks record from the
        square-root model, tank 2's overflow into tank 1, z = 4.9: with it the loop ends at 0.34 V, without
        it at 0.53 V on the validation experiment).
    split_rel : float
        Relative disagreement of the halves (|a - b| / max(|a|, |b|)) that still counts as stable.
    alpha_start : float
        Starting ARD precision of a new (normalised) term in its confirmation. A new term's coefficient
        is 1 for an effect as large as the target's whole dynamics, so prior sd 1/sqrt(1e-2) = 10 is
        already flat for it; starting at the study's 1e-10 would only add trials in which ln Z climbs by
        the known 2.3 nats per two decades.
    posterior : {"laplace", "sample"}
        With a Laplace-evidence spec, the loop's fits report the Laplace posterior N(MAP, H^-1) that
        their evidence assumes ("laplace", default: it costs nothing) or sample it by MCMC ("sample").
        Chib-Jeliazkov specs always sample.
    joint : bool
        Add every distinct, stable survivor of a round at once: they are re-selected together under ARD
        (which prunes what the others make redundant) and added when that beats the best single effect by
        ``min_log_bf``. False adds one effect per round.
    workers : int
        Processes that run a round's confirmations and halves checks side by side (0: one per core, at
        most ``top_k``; 1: in this process).
    states : bool
        When no addition, law or lag is taken (the term families left what they cannot take up), offer the
        state families that could hold it, a hysteresis of each oscillator and a sensor's own dynamics
        (:mod:`ardcore.loop.states`), before the loop stops. False: the loop stops there.
    search_window : int or None
        The state families' Nelder-Mead searches (their screen's, and their full fits' from the prior) read
        the record's first this many samples; the Newton steps, the curvature and the evidence read all of it
        (``sampler.search_window``). On a longer record the searches then cost what they cost on one this
        long, and the state families what the term families cost (issue target: at most twice). None: the
        searches read the whole record.
    band_draws : int
        Posterior draws whose free runs make the 90 % prediction band of the free run (0: none).
    rival_nats : float
        A candidate the screen found redundant with a better one is still confirmed when their screened
        ln Bayes factors are within this many nats (the screen cannot tell the twins apart; the full
        evidence does). Of surviving twins the one with the higher evidence goes on.
    twin_nats : float
        Twins whose ln Bayes factors are within this many nats are a tie, and the one with fewer parameters
        goes on (a cubic stiffness beside a sine stiffness whose period the data never reach).
    rivals : int
        At most this many twins per picked candidate (the closest first): a cubic, a sine and an
        asymmetric stiffness can all explain the same softening until the evidence sees their higher orders.
    simulation_factors : tuple of float
        Factors of the process noise tried for the final model's **simulation fit**
        (:mod:`ardcore.loop.simulation_fit`: maximum likelihood at each, free run on the held-out last
        ``simulation_held_out`` of the estimation record; the best, if it beats the posterior's own noise by
        5 %, is refitted on the whole record). Empty: no simulation fit.
    simulation_held_out : float
        Share of the estimation record held out to choose the simulation fit's noise factor.
    """

    model_config = SETTINGS
    # the residual tests
    max_lag: int = Field(40, ge=1, le=10_000)
    ljung_box_lags: int = Field(20, ge=1, le=10_000)
    peak_p: float = Field(1e-4, gt=0, lt=1)
    init_samples: int = Field(50, ge=1, le=100_000)
    band_draws: int = Field(40, ge=0, le=10_000)
    # the trace
    min_score: float = 3.0
    top_k: int = Field(3, ge=1, le=10, description="candidates confirmed by evidence per round")
    min_log_bf: float = Field(3.0, ge=0)
    library_prior: bool = True
    max_rounds: int = Field(6, ge=0, le=10, description="rounds at most (each makes one move)")
    split_z: float | None = Field(None, gt=0)
    split_rel: float = Field(0.3, gt=0)
    alpha_start: float = Field(1e-2, gt=0)
    posterior: Literal["laplace", "sample"] = "laplace"
    joint: bool = True
    states: bool = True
    search_window: int | None = Field(2500, ge=100, le=10**9)
    workers: int = Field(0, ge=0, le=1024)
    rival_nats: float = Field(5.0, ge=0)
    rivals: int = Field(2, ge=0, le=10)
    twin_nats: float = Field(1.0, ge=0)
    # the simulation fit of the final model
    simulation_factors: tuple[float, ...] = (0.3, 0.1, 0.03)
    simulation_held_out: float = Field(0.3, gt=0, lt=1)


@dataclass(frozen=True)
class LoopContext:
    """What every step of one diagnosis shares: the study spec (its evidence method, sampler and maximiser
    settings), the loop's settings, the progress line ``say``, the ``mapper`` that runs re-selections side
    by side, the user's extra effects and the observed column the residuals are tested on."""

    spec: "StudySpec"
    config: DiagnoseConfig
    say: Callable[[str], None]
    mapper: Callable
    extra_effects: tuple = ()
    column: str = ""
    forced: set = field(default_factory=set)
    """The observed columns whose declared noise level has been confirmed unscreened once (a quiet channel,
    :func:`ardcore.loop.confirm.quiet_channels`): it is forced once, then the screen judges it."""
