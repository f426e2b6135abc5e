"""The Laplace evidence at the MAP (docs/method.md, Appendices A-B): Newton steps with finite-difference
Hessians reused as chords, after a Nelder-Mead search where a warm start does not converge."""

from __future__ import annotations

import math

import numpy as np

from ..sampling.starts import fd_derivatives, fd_hessian, local_mode
from .estimators import Evidence, collapse_drops, collapse_warning, collapsed


CHORD_STEPS = 4
"""Newton steps :func:`laplace` takes with one finite-difference Hessian before taking it again."""
QUASI_STEPS = 12
"""Steps :func:`newton` takes from one stand-in curvature, each correcting it (BFGS), before taking it again."""
BACKTRACKS = 8
"""Halvings of a Newton step that does not descend before the Hessian is taken afresh."""
PROFILE_FALL = 2.0
"""Nats the log posterior falls, along a direction whose curvature at the steps' scale is no curvature, at the
distance its curvature is measured over instead: two sd of a Gaussian, the scale a Laplace evidence integrates."""
PROFILE_BAND = (0.5 * PROFILE_FALL, 2 * PROFILE_FALL)
"""The fall at 2 sd that a curvature is taken to describe (a Gaussian's is :data:`PROFILE_FALL`), and the fall a
profile's distance is bracketed to."""
PROFILE_TRIES = 40
"""Evaluations a profile may spend bracketing its distance (factors of 4, then bisection in the logarithm)."""
LOWER_NATS = 0.1
"""A point this much below the mode, beyond the likelihood's rounding noise, shows it is no mode."""


def _same_scale(a, b) -> bool:
    """Steps within a factor 2 of each other in every coordinate."""
    return bool(np.all((a > 0.5 * b) & (a < 2 * b)))


def newton(f, x: np.ndarray, h: np.ndarray, iters: int, curvature=None):
    """Newton steps minimising ``f`` from ``x`` with finite-difference steps ``h``; returns x, h, whether it
    converged (step < 1e-3 sd) and the last Hessian when it was taken at the returned x's predecessor
    (else None).

    ``curvature``: ``(x, h) -> H``, a cheaper stand-in for ``f``'s Hessian (:func:`record_curvature`) that the
    steps start from with ``f``'s own gradient, corrected after each step by the gradients' change (BFGS) and
    taken afresh every :data:`QUASI_STEPS` steps; they then converge to ``f``'s mode, and no Hessian is
    returned (none of ``f``'s own was taken).

    A Hessian (with its gradient) costs d^2 evaluations and a gradient alone 2 d, so a Hessian is reused
    for up to ``CHORD_STEPS`` steps (a chord method: near the mode it barely changes) and taken afresh when
    a step fails to descend or the chord steps do not converge; ``iters`` bounds the Hessians. Far from the
    mode a step is halved until it descends, and where the Hessian is not positive definite the step
    uses its eigenvalues' magnitudes (a descent direction; the Hessian is taken afresh after it)."""
    H = C = None
    hessians = chords = 0
    while True:
        if H is None:
            if hessians == iters:
                return x, h, False, None
            if curvature is None:
                fx, g, H = fd_derivatives(f, x, h)
            else:
                fx, g = f(x), _gradient(f, x, h)
                H = curvature(x, h)
            hessians, chords = hessians + 1, 0
            if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
                return x, h, False, None  # a step left the posterior's support
            C, ok = _newton_inverse(H)
            if C is None:
                return x, h, False, None
            sd = np.sqrt(np.diag(C))
            h_used, h = h, np.where(np.isfinite(sd) & (sd > 0), 0.01 * sd, h)
        fresh = chords == 0
        if not fresh:
            g_was, g = g, _gradient(f, x, h_used)
            if curvature is not None:
                H = _bfgs(H, moved, g - g_was)
                C, ok = _newton_inverse(H)
                sd = np.sqrt(np.abs(np.diag(C)))
        step = C @ g
        f_new = f(x - step)
        descends = f_new <= fx
        small = ok and np.all(np.abs(step) < 1e-3 * sd)
        if small:
            # converged: a step this small may not descend only by the likelihood's rounding noise
            x = x - step if descends else x
            # a fresh Hessian a step of < 1e-3 sd away, taken with steps of its own sd's size, is the
            # mode's (the final one would be the same up to finite-difference error)
            return x, h, True, (H if fresh and curvature is None and _same_scale(h_used, h) else None)
        for _ in range(0 if descends else BACKTRACKS):
            # far from the mode the quadratic model overshoots: halve the step until it descends
            step = 0.5 * step
            f_new = f(x - step)
            if f_new <= fx:
                descends = True
                break
        if descends:
            x, fx, moved = x - step, f_new, -step
            chords += 1
            if chords >= (CHORD_STEPS if curvature is None else QUASI_STEPS) or not ok:
                H = None
        elif fresh and _same_scale(h_used, h):
            return x, h, False, None
        else:
            # an old curvature misled the step, or a fresh one taken with steps far from its own sd's
            # size (the first, with the caller's steps): take it afresh here
            H = None


def _bfgs(H: np.ndarray, s: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``H`` corrected by the BFGS update for a step ``s`` whose gradient changed by ``y``; as it is where the
    change shows no positive curvature along the step (finite-difference noise near the mode)."""
    Hs = H @ s
    sy, sHs = float(s @ y), float(s @ Hs)
    if not (sy > 1e-12 * np.linalg.norm(s) * np.linalg.norm(y) and sHs > 0):
        return H
    return H - np.outer(Hs, Hs) / sHs + np.outer(y, y) / sy


def _gradient(f, x: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Central-difference gradient of ``f`` at ``x`` with steps ``h`` (2 d evaluations)."""
    return np.array([(f(x + h[i] * e) - f(x - h[i] * e)) / (2 * h[i]) for i, e in enumerate(np.eye(x.size))])


def record_curvature(target, window):
    """The Hessian of ``target``'s negative log posterior read off ``window`` (``target`` on its record's first
    samples, :meth:`~ardcore.likelihood.posterior.Target.window`): the window's likelihood curvature scaled by
    the record's length over the window's, plus the prior's own. None when the window is the whole record.

    A likelihood's curvature grows with the samples it reads, so on a stationary record the window's, scaled,
    is the record's up to the window's sampling error, at the window's cost: what Newton steps towards the
    record's mode need (:func:`newton`'s ``curvature``; its gradient is the record's, so they converge to the
    record's own mode). The Laplace evidence still takes the record's own Hessian at that mode."""
    n, big = len(getattr(window, "data", ())), len(getattr(target, "data", ()))
    if window is target or not 0 < n < big:
        return None
    ratio = big / n

    def prior(v):
        return -target.prior.logpdf(v)

    def curvature(x, h):
        H_prior = fd_hessian(prior, x, h)
        # a step out of the support makes it infinite there (inf - inf): newton sees a curvature that is not
        # finite and takes the record's own, so the arithmetic's warning says nothing a user could act on
        with np.errstate(invalid="ignore", over="ignore"):
            return H_prior + ratio * (fd_hessian(lambda v: -window(v).log_posterior, x, h) - H_prior)
    return curvature


def _newton_inverse(H: np.ndarray) -> tuple[np.ndarray | None, bool]:
    """(H^-1, True) when it is a covariance; else the inverse with H's eigenvalues' magnitudes (a descent
    direction for a Newton step) and False; (None, False) when H has no usable eigenvalue."""
    try:
        C = np.linalg.inv(H)
        if np.all(np.isfinite(C)) and np.all(np.diag(C) > 0):
            return C, True
    except np.linalg.LinAlgError:
        pass
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    if not np.all(np.isfinite(w)) or np.max(np.abs(w)) == 0:
        return None, False
    return (V / np.maximum(np.abs(w), 1e-10 * np.max(np.abs(w)))) @ V.T, False


def curvature_at_scale(f, x: np.ndarray, H: np.ndarray, sd: np.ndarray) -> tuple[np.ndarray | None,
                                                                                 np.ndarray | None]:
    """``H`` with the curvature along each of its eigenvectors taken over the posterior's own width wherever
    the one taken at the steps' scale is not it.

    A likelihood rough at the scale of a finite-difference Hessian's steps (jumps where a sub-step crosses a
    kink, a threshold's location read through a filter that smooths its kinks only over the states' spread) has
    a curvature of any size and sign there, while over its posterior's width it rises as a mode does. Along an
    eigenvector with eigenvalue w > 0, ``f`` rises by :data:`PROFILE_FALL` at 2/sqrt(w) on each side when w is
    the posterior's curvature; where it rises less than half or more than twice that (or w <= 0), the
    curvature is measured instead where ``f`` has risen by about :data:`PROFILE_FALL` on each side (that of the
    parabola through ``x`` and the two points). A Gaussian posterior keeps ``H`` as it is.

    Returns (the Hessian, None); (None, a lower point) when a profile finds ``f`` lower than at ``x`` (``x`` is
    no mode); (None, None) when no distance gives a usable rise (a flat or unbounded direction)."""
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    fx = f(x)
    changed = False
    lo, hi = PROFILE_BAND
    for i in range(w.size):
        v = V[:, i]
        if w[i] > 0:
            d0 = 2 / math.sqrt(w[i])
            rises = [f(x + d0 * v) - fx, f(x - d0 * v) - fx]
            if all(lo <= r <= hi for r in rises):
                continue
        else:
            d0 = 2 * float(np.sqrt(np.sum((v * sd) ** 2)))  # two of the sd the steps were taken for
        ends = []
        for side in (1.0, -1.0):
            end = _rise_at(f, x, fx, side * v, d0)
            if isinstance(end, np.ndarray):
                return None, end
            if end is None:
                return None, None
            ends.append(end)
        # the parabola through the mode and the two ends: its curvature; a vertex between the ends that it puts
        # clearly below f(x) is looked at (a lower point there: x is no mode), never extrapolated to
        (dp, rp), (dm, rm) = ends
        a = (rp * dm + rm * dp) / (dp * dm * (dp + dm))
        b = (rp * dm**2 - rm * dp**2) / (dp * dm * (dp + dm))
        vertex = -b / (2 * a)
        if -dm < vertex < dp and b**2 / (4 * a) > LOWER_NATS:
            y = x + vertex * v
            if f(y) - fx < -LOWER_NATS:
                return None, y
        w[i] = 2 * a
        changed = True
    return (V * w) @ V.T if changed else H, None


def _rise_at(f, x, fx, v, dist):
    """(distance, rise) along ``v`` where ``f`` has risen into :data:`PROFILE_BAND` (the distance bracketed and
    bisected in its logarithm); a point lower than ``x`` if the profile meets one; None if
    :data:`PROFILE_TRIES` evaluations find no such distance."""
    lo, hi = PROFILE_BAND
    short = long = None
    for _ in range(PROFILE_TRIES):
        y = x + dist * v
        rise = f(y) - fx
        if rise < -LOWER_NATS:
            return y
        if not math.isfinite(rise) or rise > hi:
            long = dist
        elif rise < lo:
            short = dist
        else:
            return dist, rise
        dist = math.sqrt(short * long) if short and long else (dist * 4 if long is None else dist / 4)
    return None


def _drops(target, x: np.ndarray, lp: float, H: np.ndarray) -> list[float] | None:
    """How far the log posterior (``lp`` at ``x``) falls 3 of ``H``'s sd out per parameter
    (:func:`~.estimators.collapse_drops`); None when ``H`` is no curvature of a mode (not finite, or not positive
    definite)."""
    if not np.all(np.isfinite(H)) or not np.all(np.linalg.eigvalsh(0.5 * (H + H.T)) > 0):
        return None
    return collapse_drops(target, x, lp, np.sqrt(np.diag(np.linalg.inv(H))))


def _trusted(drops: list[float] | None) -> bool:
    """A curvature that is the posterior's (:func:`_drops`): positive definite, and the log posterior falls 3 of
    its sd out as a Gaussian's must. Only one that is not is re-measured, so every fit whose Laplace evidence was a
    result stays exactly what it was."""
    return drops is not None and not collapsed(range(len(drops)), drops)


def _at_scale(target, f, x: np.ndarray, h: np.ndarray, H: np.ndarray, polish: int):
    """(x, h, H) with the curvature re-measured over the posterior's width (:func:`curvature_at_scale`): Newton
    again from a lower point a profile meets (once), then the Hessian taken again with steps of the re-measured
    sd for the correlations the profiles' axes miss, kept where it passes the same check unchanged."""
    for _ in range(2):
        if not np.all(np.isfinite(H)):
            return x, h, H
        scaled, lower = curvature_at_scale(f, x, H, 100 * h)  # newton's steps are 0.01 sd
        if lower is not None:
            x, h, _, H = newton(f, lower, h, polish)
            H = fd_hessian(f, x, h) if H is None else H
            if _trusted(_drops(target, x, -f(x), H)):
                return x, h, H
            continue
        if scaled is None:
            return x, h, H
        h_wide = np.sqrt(np.maximum(np.diag(np.linalg.inv(scaled)), 0))
        wide = fd_hessian(f, x, h_wide) if np.all(h_wide > 0) else None
        if wide is not None and np.all(np.isfinite(wide)) and curvature_at_scale(f, x, wide, h_wide)[0] is wide:
            return x, h_wide, wide
        return x, h, scaled  # a step of one sd leaves the support, or its Hessian is rough too
    return x, h, H


def laplace(target, x0: np.ndarray, scale: np.ndarray | None = None, *, maxfev: int = 4000,
            polish: int = 3, warm: bool = False, search=None) -> tuple[Evidence, np.ndarray, np.ndarray]:
    """Laplace evidence ln p(d) ~ L(MAP) + d/2 ln 2 pi - 1/2 ln |H| (Appendices A-B).

    With ``warm`` (``x0`` from a neighbouring trial), Newton steps start at ``x0`` and Nelder-Mead runs only
    when they do not converge. ``search``: the target the Nelder-Mead search climbs (default ``target``; a
    window of its record, :meth:`~ardcore.likelihood.posterior.Target.window`): the Newton steps from where
    it stops read ``target``.

    Returns
    -------
    evidence : Evidence
    phi_map : ndarray
    cov : ndarray
        H^{-1}, the Laplace posterior covariance.
    """
    x0 = np.asarray(x0, dtype=float)
    d = x0.size
    if scale is None:
        scale = np.maximum(np.abs(x0) * 0.1, 1e-3)
    f = lambda v: -target(v).log_posterior  # noqa: E731

    # on a record longer than the search's window, Newton steps with the window's curvature scaled to the record
    # (record_curvature) take x to the record's mode first, so the record's own Hessian is taken there alone
    curvature = record_curvature(target, search) if search is not None else None

    def steps(x, h, iters):
        if curvature is not None:
            x, h, _, _ = newton(f, x, h, iters + 5, curvature)
        return newton(f, x, h, iters)

    converged, H = False, None
    if warm:
        # a warm start is near the mode: Newton from there, Nelder-Mead only if Newton does not converge
        x, h, converged, H = steps(x0.copy(), 1e-3 * scale, polish + 5)
    if not converged:
        x, _ = local_mode(search if search is not None else target, x0, scale, maxfev)
        x, h, _, H = steps(x, 1e-3 * scale, polish)
    if H is None:
        H = fd_hessian(f, x, h)
    lp, ll = target(x)
    drops = _drops(target, x, lp, H)
    if not _trusted(drops):
        # a curvature that is not the posterior's (not positive definite, or collapsed: measured on a likelihood
        # rough at the scale of the steps): the one over the posterior's width, where it is a mode
        x, h, H = _at_scale(target, f, x, h, H, polish)
        lp, ll = target(x)
        drops = _drops(target, x, lp, H)
    warnings = []
    if np.all(np.isfinite(H)):
        sign, logdet = np.linalg.slogdet(H)
    else:  # a curvature that could not be measured (a step out of the support): no determinant to take
        sign, logdet = 0.0, math.nan
    if sign <= 0:
        warnings.append("Hessian at the MAP is not positive definite: Laplace evidence invalid")
    log_z = lp + 0.5 * d * math.log(2 * math.pi) - 0.5 * logdet
    ev = Evidence(float(log_z), 0.0, float(ll), float(ll - log_z), "laplace", [], warnings)
    try:
        C = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        C = np.full((d, d), np.nan)
    var = np.diag(C)
    # (a determinant's positive sign does not make a curvature positive definite: two negative eigenvalues)
    sd = np.sqrt(var) if np.all(np.isfinite(C)) and sign > 0 and np.all(var > 0) else None
    if sd is not None and np.isfinite(lp):
        # a curvature from finite differences over a rough likelihood (kinks at the scale of its steps) is far
        # too large: 3 of its sd out the log posterior has barely moved
        # (the drops the trust check measured at this curvature, taken again only for one it found no mode's)
        warnings += collapse_warning(getattr(target, "names", [f"x{i}" for i in range(d)]),
                                     drops if drops is not None else collapse_drops(target, x, lp, sd),
                                     "the curvature was measured on a likelihood rough at the scale of its steps")
    return ev, x, C
