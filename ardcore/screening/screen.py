"""Evidence screen of every candidate effect on every target (docs/method.md section 8, step 3).

Every (effect, target) pair of the library is scored by an approximate log Bayes
factor against the fitted model, computed from the EKF itself rather than from a
regression on a residual:

* the candidates' terms are added to one *screening model* (a few at a time), each
  **normalised**: written ``k * (scale * term)`` with ``scale`` = rms of the target's
  drift (or of the observed signal) / rms of the term along the filtered states, so
  ``k = 1`` is an effect as large as the target's own dynamics whatever the term's
  units;
* at the fitted parameters and ``k = 0`` the innovations ``e_k`` and their variances
  ``S_k`` are differentiated (central differences of the filter) with respect to
  every model parameter and every ``k``; this gives the score ``g`` and the Fisher
  (Gauss-Newton) information ``I`` of the EKF likelihood;
* the model's own parameters are profiled out (Schur complement: a term that a refit
  of the existing parameters would absorb gets no credit, one that they cannot mimic
  keeps it), and with a N(0, 1) prior on the normalised coefficients the Laplace
  log Bayes factor of adding the effect is
  ``0.5 g' (I + 1)^-1 g - 0.5 ln det(1 + I)``;
* shape parameters (a free-play width, a friction velocity scale, a saturation
  level, a forcing frequency) are chosen by maximising that log Bayes factor over a
  grid and then a golden-section refinement (a profile over the shape).

It costs two filter runs per parameter and per candidate term, so the whole library
is screened (not only the best few of a ranking). The candidates sent to the full ARD
re-selection are chosen by forward selection on the screened evidence
(:func:`distinct_candidates`): each next one is the best given those picked, scored
jointly from the sensitivities already computed. The score and information machinery
lives in :mod:`ardcore.screening.score`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..sampling.chains import serial_map
from ..data import Dataset
from ..effects.base import Effect, with_columns
from ..model.declaration import ModelSpec
from .robust import innovation_background, spectral_score_cov
from .score import Basis, Screener, bayes_factor, nuisance_map

COHERENCE_P = 1e-3
"""A forcing whose coefficients differ between segments of the record beyond this p-value is not a forcing."""

SHAPE_OCCAM = 2.0
"""Least nats taken off a shaped effect's screened ln BF (see :func:`_shape_occam`): its shape is the profile
maximum, not integrated over its prior."""


@dataclass
class Screened:
    """One screened (effect, target) pair.

    Attributes
    ----------
    effect : Effect
        With its shape parameter fixed.
    target : str
        State (drift) or observed column (measurement effect).
    log_bayes_factor : float
        Laplace estimate of ln p(d | model + effect) - ln p(d | model), parameters profiled.
    delta_loglik : float
        Estimated gain of the maximised log-likelihood.
    coefficients : list of float
        Estimated normalised coefficients (posterior mean under the screen's prior).
    scales : list of float
        Normalisation of each term (physical coefficient = normalised coefficient x scale).
    """

    effect: Effect
    target: str
    log_bayes_factor: float
    delta_loglik: float
    coefficients: list
    scales: list
    shape_profile: list = field(default_factory=list)
    inflation: float = 1.0
    """How much the EKF likelihood understates the variance of this candidate's score (its innovations are
    coloured; :func:`~ardcore.screening.robust.sandwich`): the confirmation divides its ln Bayes factor by it."""
    coherence_p: float | None = None
    """A forcing's coherence over the record (:func:`_coherence_p`; None for other effects)."""
    shape_occam: float = 0.0
    """Nats the profiled shape costs (already taken off ``log_bayes_factor``; the confirmation, which holds
    the shape fixed, takes them off its ln BF too)."""
    conditional_log_bayes_factor: float | None = None
    """ln BF given the candidates picked before it (:func:`distinct_candidates`; None if not scored so)."""
    source: Effect | None = field(default=None, repr=False)
    """The library's effect with its shape free (None for an effect without a shape)."""
    shape_value: float | None = None
    """The profile's maximum (the value ``effect`` fixes the shape at)."""
    rows: tuple | None = field(default=None, repr=False)
    basis: Basis | None = field(default=None, repr=False)

    @property
    def physical(self) -> list[float]:
        return [float(c * s) for c, s in zip(self.coefficients, self.scales)]

    def to_json(self) -> dict:
        return {"effect": self.effect.name, "kind": self.effect.kind, "terms": list(self.effect.terms),
                "target": self.target, "where": self.effect.where,
                "log_bayes_factor": float(self.log_bayes_factor), "score": float(self.log_bayes_factor),
                "shape_occam": float(self.shape_occam), "coherence_p": self.coherence_p,
                "inflation": float(self.inflation),
                "conditional_log_bayes_factor": None if self.conditional_log_bayes_factor is None
                else float(self.conditional_log_bayes_factor),
                "delta_loglik": float(self.delta_loglik),
                "coefficients": self.physical, "normalised_coefficients": [float(c) for c in self.coefficients],
                "scales": [float(s) for s in self.scales]}


BATCH_SIZE = 12
"""Candidate terms per screening model (bounds the size of the generated kernel)."""

SHAPE_GRID = 7
"""Grid points over a shape parameter's range before golden-section refinement."""


@dataclass(frozen=True)
class ScreenInput:
    """What a screen starts from: the fitted model ``spec`` at its parameter values ``phi`` (posterior mean
    or MAP), the estimation ``data``, the fit's ``substeps``, and ``robust``: each candidate's evidence
    adjusted to the actual variance of its score under the innovations' own spectrum
    (:func:`~ardcore.screening.robust.sandwich`), so that coloured innovations do not pass for support."""

    spec: ModelSpec
    phi: dict
    data: Dataset
    substeps: int | None = None
    robust: bool = True

    def screener(self) -> "Screener":
        return Screener(self.spec, self.phi, self.data, self.substeps, self.robust)


def screen_effects(inp: ScreenInput, effects: list[Effect], targets: list[str], obs_targets: list[str], *,
                   progress=None, map_fn=None) -> list[Screened]:
    """Screen every effect on every target; sorted by log Bayes factor (best first).

    Parameters
    ----------
    inp : ScreenInput
        The fitted model, its parameter values and the estimation data.
    effects : list of Effect
        Drift effects go to every state in ``targets``; measurement effects (``where="observation"``)
        to every column in ``obs_targets``.
    map_fn : callable, optional
        ``map_fn(fn, tasks)`` profiles the shaped effects (a process pool's map; default: one after another).
        Each profile is 15-70 screening fits, most of a round's screen.
    """
    say = progress or (lambda s: None)
    sc, data = inp.screener(), inp.data
    k = len(sc.theta)
    pairs = [(e, t) for e in effects if e.where == "drift" for t in targets]
    pairs += [(e, c) for e in effects if e.where in ("observation", "noise") for c in obs_targets]
    pairs += [(e, e.between[0]) for e in effects if e.where == "flow" and e.between[0] in targets]
    out: list[Screened] = []
    plain = [(e, t) for e, t in pairs if not e.shape]
    shaped = [(e, t) for e, t in pairs if e.shape]
    items = []
    for e, t in plain:
        s = sc.term_scale(e, t, data)
        if s is not None:
            items.append((e, t, s))
    for b in range(0, len(items), BATCH_SIZE):
        chunk = items[b:b + BATCH_SIZE]
        groups, g, Inf, C = sc.batch(chunk)
        for (e, t, s), grp, rows in zip(chunk, groups, sc.last_rows):
            lbf, gain, coef, infl = bayes_factor(g, Inf, k, grp, C, sc.eps)
            out.append(Screened(e, t, lbf, gain, [float(c) for c in coef], s, inflation=infl, rows=rows,
                                basis=sc.basis))
    say(f"screened {len(items)} plain candidates")
    # on a pool only once the model's own sensitivities are known (else each worker would compute them)
    run = map_fn if map_fn is not None and sc.basis is not None else serial_map
    for b in run(_shape_task, [(sc, e, t, data, k, SHAPE_GRID) for e, t in shaped]):
        if b is not None:
            if b.basis is not None:
                b.basis = sc.basis  # a worker's copy: one basis, as the joint scoring expects
            out.append(b)
    say(f"screened {len(shaped)} shaped candidates")
    out.sort(key=lambda c: -c.log_bayes_factor)
    return out


def _shape_occam(e: Effect, cache: dict, data: Dataset) -> float:
    """Occam factor of a profiled shape parameter: ln(prior range / (sqrt(2 pi) sd)) in log(shape), the
    Laplace approximation of integrating the ln BF over a log-uniform prior instead of taking its maximum.

    The sd comes from the curvature of the profile around its maximum. A forcing frequency was picked from
    the whole spectrum (any peak between 1/T and the Nyquist frequency), so that band is its prior range:
    the look-elsewhere penalty that keeps a peak of coloured noise from passing as a forcing.
    """
    pts = sorted((math.log(v), r.log_bayes_factor) for v, r in cache.items() if r is not None)
    if e.shape[0] == "f":
        T = float(data.t[-1] - data.t[0])
        lo, hi = 1.0 / T, 0.5 / float(np.median(np.diff(data.t)))
    else:
        lo, hi = e.shape[1], e.shape[2]
    rng = math.log(hi / lo)
    top = max(p[1] for p in pts)
    near = [(x, y) for x, y in pts if y > top - 10]
    sd = None
    if len(near) >= 3:
        x = np.array([p[0] for p in near])
        y = np.array([p[1] for p in near])
        c = np.polyfit(x - x[np.argmax(y)], y, 2)[0]
        if c < 0:
            sd = 1.0 / math.sqrt(-2 * c)
    if sd is None:  # a flat or one-sided profile: the shape is barely determined, no Occam gain beyond the floor
        return SHAPE_OCCAM
    return max(SHAPE_OCCAM, math.log(rng / (math.sqrt(2 * math.pi) * sd)))


def _shape_task(task) -> Screened | None:
    """:func:`_screen_shape` of one (screener, effect, target, data, k, grid) (a picklable unit of work)."""
    return _screen_shape(*task)


def _screen_shape(sc: Screener, e: Effect, t: str, data: Dataset, k: int, n_grid: int) -> Screened | None:
    """Profile a shaped effect over its shape parameter: grid (log-spaced), then golden-section refinement."""
    _, lo, hi = e.shape
    cache: dict[float, Screened | None] = {}

    def at(v: float) -> Screened | None:
        v = float(f"{v:.6g}")
        if v in cache:
            return cache[v]
        ef = e.at(v)
        s = sc.term_scale(ef, t, data)
        r = None
        if s is not None:
            groups, g, Inf, C = sc.batch([(e, t, s)], [v])
            lbf, gain, coef, infl = bayes_factor(g, Inf, k, groups[0], C, sc.eps)
            r = Screened(ef, t, lbf, gain, [float(c) for c in coef], s, inflation=infl, rows=sc.last_rows[0],
                         basis=sc.basis)
        cache[v] = r
        return r

    if e.shape[0] == "f":
        # a line's ln BF falls off over ~1/T around its frequency (a cycle of phase over the record): the grid
        # is spaced at half that, so the profile cannot step over the line
        T = float(data.t[-1] - data.t[0])
        grid = np.linspace(lo, hi, int(np.clip((hi - lo) * 2.0 * T + 1, n_grid, 61)))
    else:
        grid = np.geomspace(lo, hi, n_grid) if lo > 0 else np.linspace(lo, hi, n_grid)
    vals = [at(v) for v in grid]
    score = [v.log_bayes_factor if v is not None else -math.inf for v in vals]
    if not np.isfinite(max(score)):
        return None
    i = int(np.argmax(score))
    # golden-section on log(shape) between the neighbours of the best grid point
    a = math.log(grid[max(i - 1, 0)])
    b = math.log(grid[min(i + 1, len(grid) - 1)])
    gr = (math.sqrt(5) - 1) / 2

    def f(x):
        r = at(math.exp(x))
        return r.log_bayes_factor if r is not None else -math.inf

    c, d = b - gr * (b - a), a + gr * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(6):
        if fc > fd:
            b, d, fd = d, c, fc
            c = b - gr * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + gr * (b - a)
            fd = f(d)
    best_v, best = max(((v, r) for v, r in cache.items() if r is not None), key=lambda vr: vr[1].log_bayes_factor)
    best.source, best.shape_value = e, float(best_v)
    best.shape_occam = _shape_occam(e, cache, data)
    best.log_bayes_factor -= best.shape_occam
    best.shape_profile = sorted((float(v), float(r.log_bayes_factor)) for v, r in cache.items() if r is not None)
    if e.shape[0] == "f" and sc.eps is not None:
        best.coherence_p = _coherence_p(sc, e, best, t, k)
        if best.coherence_p < COHERENCE_P:
            # a narrow-band random process (a lightly damped mode driven by noise), not a forcing: its phase
            # wanders over the record, which a sinusoid of fixed amplitude and phase cannot follow
            best.log_bayes_factor = min(best.log_bayes_factor, 0.0)
    return best


def _coherence_p(sc: Screener, e: Effect, c: Screened, target: str, k: int) -> float:
    """p-value of a forcing's coherence over the record: its sine/cosine coefficients estimated on K segments
    (at least 10 cycles and 200 samples each, K <= 8) must agree within their noise (chi-square on 2(K-1)
    degrees of freedom, each segment's variance from the innovations' spectrum as in the screen)."""
    from scipy import stats

    n = sc.eps.size
    cycles = c.effect.frequency * float(sc.data.t[-1] - sc.data.t[0])
    K = int(min(8, cycles // 10, n // 200))
    if K < 2:
        return 1.0
    groups, g, Inf, psi = sc.batch([(e, target, c.scales)], [c.effect.frequency])  # e: the profiled kernel
    grp = groups[0]
    eff = psi[grp] - nuisance_map(Inf, k, grp) @ psi[np.arange(k)]
    H = eff @ eff.T
    k_hat = np.linalg.pinv(H, rcond=1e-10) @ (-(eff @ sc.eps))
    psd = innovation_background(sc.eps + eff.T @ k_hat)
    if psd is None:
        return 1.0
    est, prec = [], []
    for seg in np.array_split(np.arange(n), K):
        P, e = eff[:, seg], sc.eps[seg]
        Hs = P @ P.T
        Vs = spectral_score_cov(P, psd)
        Hinv = np.linalg.pinv(Hs, rcond=1e-10)
        est.append(Hinv @ (-(P @ e)))
        prec.append(np.linalg.pinv(Hinv @ Vs @ Hinv, rcond=1e-10))
    W = sum(prec)
    mean = np.linalg.pinv(W, rcond=1e-10) @ sum(p @ x for p, x in zip(prec, est))
    chi2 = float(sum((x - mean) @ p @ (x - mean) for p, x in zip(prec, est)))
    return float(stats.chi2.sf(chi2, len(grp) * (K - 1)))


def conditional_log_bayes_factor(c: Screened, given: list[Screened]) -> float:
    """Screened ln BF of ``c`` with the coefficients of ``given`` profiled out with the model's own (from the
    sensitivities the screen stored: no filter pass)."""
    b = c.basis
    rows = [b.De] + [p.rows[0] for p in given] + [c.rows[0]]
    srows = [b.DS] + [p.rows[1] for p in given] + [c.rows[1]]
    g, Inf, psi = b.score(np.vstack(rows), np.vstack(srows))
    n = g.size
    grp = np.arange(n - c.rows[0].shape[0], n)
    lbf = bayes_factor(g, Inf, n - grp.size, grp, psi, b.eps)[0] - c.shape_occam
    if c.coherence_p is not None and c.coherence_p < COHERENCE_P:
        lbf = min(lbf, 0.0)  # an incoherent "forcing" stays rejected whatever is profiled with it
    return lbf


def distinct_candidates(inp: ScreenInput, screened: list[Screened], k: int, min_log_bf: float, *,
                        look: int = 40) -> list[Screened]:
    """Up to ``k`` candidates by forward selection on the screened evidence.

    The first is the best screened one; each next one is the candidate with the highest ln BF *conditional
    on* those already picked (their coefficients profiled out with the model's own), as long as that
    exceeds ``min_log_bf``. So a candidate that only explains what a better one explains (a constant on the
    velocity equation and a bias on the measurement, a cubic and a saturating stiffness) is not confirmed
    twice, and one that explains what the first leaves over (an even stiffness next to the cubic one) is
    found even when on its own it ranks low. Candidates of the first ``look`` that are left out because the
    picked ones explain them get ``conditional_on``. The joint score comes from the sensitivities the screen
    computed (:class:`Basis`): no further filter pass.
    """
    if not screened or screened[0].rows is None or screened[0].basis is None:
        return _distinct_by_refit(inp, screened, k, min_log_bf)
    # a candidate whose terms are not finite along the fit has no stored rows: it cannot be scored jointly
    pool = [c for c in screened[:look] if c.rows is not None and c.basis is screened[0].basis]
    for c in pool:  # explained by what this selection picks, not by an earlier one's
        c.conditional_on = None
    picked: list[Screened] = []
    if pool and pool[0].log_bayes_factor > min_log_bf:
        picked.append(pool[0])
    while picked and len(picked) < k:
        best, best_lbf = None, min_log_bf
        for c in pool:
            if c in picked:
                continue
            c.conditional_log_bayes_factor = conditional_log_bayes_factor(c, picked)
            if c.conditional_log_bayes_factor > best_lbf:
                best, best_lbf = c, c.conditional_log_bayes_factor
        if best is None:
            break
        picked.append(best)
    for c in pool:
        if c in picked or c.log_bayes_factor <= min_log_bf:
            continue
        lbf = conditional_log_bayes_factor(c, picked)
        if lbf <= min_log_bf:
            c.conditional_on = [p.effect.name for p in picked]
    return picked


def _distinct_by_refit(inp: ScreenInput, screened, k, min_log_bf, *, look=12):
    """:func:`distinct_candidates` for candidates screened elsewhere (no stored sensitivities): greedy in
    screened order, each conditional score from a new batch."""
    sc, data = inp.screener(), inp.data
    base = len(sc.theta)
    picked: list[Screened] = []
    for c in [c for c in screened if c.log_bayes_factor > min_log_bf][:look]:
        if len(picked) >= k:
            break
        if picked:
            items = [(p.effect, p.target, p.scales) for p in picked] + [(c.effect, c.target, c.scales)]
            with_data = data
            for p in picked + [c]:
                with_data = with_columns(with_data, p.effect)
            groups, g, Inf, C = sc.batch(items, data=with_data)
            nuis = base + sum(len(gr) for gr in groups[:-1])
            lbf, *_ = bayes_factor(g, Inf, nuis, groups[-1], C, sc.eps)
            if lbf <= min_log_bf:
                c.conditional_on = [p.effect.name for p in picked]
                continue
        picked.append(c)
    return picked
