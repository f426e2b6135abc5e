"""Kinks the filter can live with: ``abs``, ``sign`` (and ``max``/``min``, written with ``abs``) smoothed over
the filter's own uncertainty.

A kink in a drift makes the EKF log-likelihood rough: the Jacobian, so the covariance, jumps whenever a sub-step
evaluation crosses the kink, and the likelihood jumps by a little with every tiny change of the parameters
(finite differences, the Laplace curvature and a sampler's small steps all see these jumps as a posterior
10^4 times too narrow). The filter does not know the state better than its own covariance says, so it rounds
each kink over its own spread of the kink's argument ``a``::

    |a|     ->  sqrt(m^2 + (2/pi) w^2)
    sign a  ->  m / sqrt(m^2 + (2/pi) w^2)

with m the argument at the current mean and ``w^2 = g^T P g`` its variance under the forecast covariance P (g the
argument's gradient in the states), taken at the start of each sub-step: a hyperbola equal to the expectation
E|a| of a ~ N(m, w^2) at the kink and to |a| far from it (within 0.142 w of that expectation everywhere: the
largest gap, 0.1415 w, is at |m| = 1.64 w). The width is therefore tied to the noise level: it is what the
data leave unknown about the argument, and it shrinks as the data pin the state down. ``w = 0`` (a kink in
known inputs and parameters only, or a state the filter knows exactly) is the exact kink with d sign/dx = 0.
The simulation (the free run) has no covariance: it integrates the exact model.
"""

from __future__ import annotations

import sympy as sp


class SmoothAbs(sp.Function):
    """|a| rounded over the spread w of a ~ N(m, w^2); |m| at w = 0."""

    nargs = 2

    def fdiff(self, argindex=1):
        if argindex != 1:
            raise sp.ArgumentIndexError(self, argindex)
        return SmoothSign(*self.args)


class SmoothSign(sp.Function):
    """sign(a) rounded over the spread w (the slope of :class:`SmoothAbs`); sign(m) at w = 0."""

    nargs = 2

    def fdiff(self, argindex=1):
        if argindex != 1:
            raise sp.ArgumentIndexError(self, argindex)
        return SmoothDelta(*self.args)


class SmoothDelta(sp.Function):
    """The slope of :class:`SmoothSign`; 0 at w = 0 (the exact kink's decision)."""

    nargs = 2

    def fdiff(self, argindex=1):
        if argindex != 1:
            raise sp.ArgumentIndexError(self, argindex)
        m, w = self.args
        return -3 * m / (m**2 + 2 * w**2 / sp.pi) * self


NUMBA_HELPERS = [
    "@njit(cache=True, nogil=True, inline='always')",
    "def _sign(v):",
    "    return 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)",
    "",
    "@njit(cache=True, nogil=True, inline='always')",
    "def _sabs(m, w):",
    "    return sqrt(m * m + 0.6366197723675814 * w * w)",
    "",
    "@njit(cache=True, nogil=True, inline='always')",
    "def _ssign(m, w):",
    "    if not (w > 0.0):",
    "        return _sign(m)",
    "    return m / sqrt(m * m + 0.6366197723675814 * w * w)",
    "",
    "@njit(cache=True, nogil=True, inline='always')",
    "def _sdelta(m, w):",
    "    if not (w > 0.0):",
    "        return 0.0",
    "    r = m * m + 0.6366197723675814 * w * w",
    "    return 0.6366197723675814 * w * w / (r * sqrt(r))",
    "",
]
"""The generated module's scalar helpers: one square root each, which the compiler shares between the drift and
its Jacobian once they are inlined (the Gaussian expectation's erf and exp made a kinked model's filter four
times slower)."""


def smooth(exprs, states, start: int = 0) -> tuple[list, list]:
    """``exprs`` with every ``Abs(a)`` and ``sign(a)`` whose argument depends on the states replaced by its
    expectation over a width ``kw<k>`` (one symbol per distinct argument, numbered from ``start``).

    Parameters
    ----------
    exprs : sequence of sympy.Expr
    states : sequence of sympy.Symbol
    start : int
        First width number (the drift's and the observations' widths are numbered apart).

    Returns
    -------
    (list of sympy.Expr, list of (sympy.Symbol, sympy.Expr))
        The smoothed expressions and each width's symbol with the argument it is the spread of.
    """
    sset = set(states)
    widths: dict[sp.Expr, sp.Symbol] = {}

    def width(a):
        if a not in widths:
            widths[a] = sp.Symbol(f"kw{start + len(widths)}", positive=True)
        return widths[a]

    def swap(e):
        a = e.args[0]
        if not (a.free_symbols & sset):
            return e
        return (SmoothAbs if isinstance(e, sp.Abs) else SmoothSign)(a, width(a))

    out = [sp.sympify(e).replace(lambda x: isinstance(x, (sp.Abs, sp.sign)), swap) for e in exprs]
    return out, [(w, a) for a, w in widths.items()]


def variance(arg: sp.Expr, states, Psym) -> sp.Expr:
    """g^T P g, the variance of ``arg`` under the covariance ``Psym`` (g its gradient in ``states``)."""
    g = [sp.diff(arg, s) for s in states]
    n = len(states)
    return sp.expand(sum((g[i] * g[j] * Psym[i][j] for i in range(n) for j in range(n) if g[i] != 0 and g[j] != 0),
                         sp.S.Zero))
