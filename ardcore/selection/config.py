"""The evidence maximiser's settings (:class:`MaximiserConfig`): the study spec's ``maximiser`` section,
declared once with its bounds; :mod:`ardcore.selection.maximiser` runs the maximisation they describe."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, Field

from ..sampling.config import SETTINGS

# the units of the maximiser's settings, each with the bounds any setting in it must respect
Alpha = Annotated[float, Field(gt=0)]
"""An ARD precision (1 / prior variance of a term)."""
Decades = Annotated[float, Field(gt=0, le=10)]
"""A step of log10 alpha."""
SeMultiple = Annotated[float, Field(ge=0, le=10)]
"""A multiple of a standard error."""
Nats = Annotated[float, Field(ge=0, le=100)]
"""A difference of ln Z."""


class MaximiserConfig(BaseModel):
    """Evidence-maximisation settings, with their bounds: the study spec's ``maximiser`` section is this model.

    Attributes
    ----------
    alpha_start : float
        Initial alpha of every ARD parameter.
    step_decades, min_step_decades : float
        First and smallest line-search step in log10 alpha.
    noise_k : float
        The prune test keeps a term only when ln Z with it beats ln Z without it by more than
        noise_k * se of the difference (and ``min_gain``), plus ``keep_nats``; a pruned term
        is re-tested in a later sweep on the noise margin alone, then prune-tested again.
    step_noise_k : float
        The same multiple for a line-search step up in alpha (default 1, as the prune test).
        0 lets the point estimate decide, so a noisy baseline cannot stop a coordinate at its
        starting alpha; on the Sec 3.6 demo that walked unneeded terms up to large alpha one
        step at a time (demo 629 s instead of 394 s) without changing the pruning pattern.
    min_gain : float
        Smallest improvement in ln Z (nats) that counts as a line-search step.
    keep_nats : float
        A term survives its prune test only when ln Z with it beats ln Z without it
        by more than ``keep_nats + noise_k * se``: the lower 1-se bound of its log Bayes factor
        must pass 1 nat, where Kass and Raftery's "positive" evidence starts (2 ln B = 2).
        Below that the evidence for the term is "not worth more than a bare mention"; on the
        Sec 3.6 demo M3 kept theta^5 on a gain of 1.1 +- 0.4 nats without it.
    prune_alpha : float
        Default pruning threshold: past it, the term is tested for removal at once.
    prune_bound : bool
        Before a prune test is sampled, bound its evidence from above: the prior integrates to one, so
        ln Z without the term is at most the largest ln-likelihood without it, searched from each current
        chain's best point with the term at 0 (the largest maximum found, plus its gap to the next: the room
        the searches may have left). When that bound is below the current ln Z by more than the test's
        own margin (``keep_nats`` + ``noise_k`` se, at least ``min_gain``), the sampled test could only have
        kept the term too: it is kept without sampling, and the history records the bound (``bound``,
        ``method`` "likelihood bound"). Sampled evidence only (a Laplace prune test is itself a search).
    prune_bound_z : float
        The bound is tried only for a term whose posterior mean lies more than this many sd from 0: nearer,
        the nested model is not far enough behind for its likelihood's maximum to fall short of ln Z, and
        the searches would cost more than they save.
    prune_test : bool
        Test alpha = inf when a coordinate stops improving.
    max_trials : int
        Most evidence evaluations per model.
    max_sweeps : int
        Most passes over the ARD parameters.
    order : {"reverse", "declared"}
        Order in which the coordinates are visited. "reverse" (default) starts from the last
        declared ARD parameter: declare terms from the simplest up (a3 .. a6) and the most
        complex one is tested for removal first, while the simpler terms that can stand in for
        it are still free (backward elimination under the hierarchy principle). Visiting a3
        first on the Sec 3.6 study let theta^5 stand in for theta^3 in M1, and theta^4 theta'
        for theta^2 theta' in M3, so the wrong member of each pair was pruned.
    reweight : bool
        Line-search steps are first estimated by reweighting the draws of the last sampled trial
        (:mod:`ardcore.evidence.reweight`: the step changes only the ARD prior, so no likelihood is evaluated);
        a real trial (MCMC + Chib-Jeliazkov) runs only when that estimate is unreliable, for every
        prune test and re-test, and at the accepted optimum. With Laplace evidence the draws are those
        of the Laplace posterior N(MAP, H^-1) (the Gaussian the evidence assumes), and a real trial is a
        Newton fit.
    reweight_min_ess : float
        Smallest Kish effective sample size of the weights, as a share of the draws, for a reweighted
        step. Below about a quarter the new posterior's bulk sits where the old one has few draws and
        the estimate rests on a handful of them (its batch-means se is then itself unreliable).
    reweight_max_se : float
        Largest Monte Carlo se (nats, batch means) of a reweighted step; 0.2 is below the Chib-Jeliazkov
        se of a sampled trial in the reference studies, so a reweighted step is never the noisier one.
    reweight_min_step : float
        Smallest step (decades) tried by reweighting when a full step cannot be reweighted (see
        :func:`maximise`); such smaller steps cost no likelihood evaluation.
    """

    model_config = SETTINGS
    # the line search
    alpha_start: Alpha = 1e-10
    step_decades: Decades = 2.0
    min_step_decades: Decades = 1.0
    step_noise_k: SeMultiple = 1.0
    min_gain: Nats = 0.05
    order: Literal["reverse", "declared"] = Field(
        "reverse", description="visit the ARD parameters from the last declared (default) or the first")
    # the prune test
    prune_test: bool = True
    prune_alpha: Alpha = 1e12
    prune_bound: bool = True
    prune_bound_z: float = Field(5.0, ge=0, le=1000)
    noise_k: SeMultiple = 1.0
    keep_nats: Nats = 1.0
    max_trials: int = Field(60, ge=1, le=1000)
    max_sweeps: int = Field(2, ge=1, le=100)
    # reweighting between trials
    reweight: bool = True
    reweight_min_ess: float = Field(0.25, gt=0, le=1)
    reweight_max_se: float = Field(0.2, gt=0, le=100)
    reweight_min_step: Decades = 0.25
