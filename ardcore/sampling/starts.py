"""Where chains start: local posterior modes (a few Nelder-Mead starts), overdispersed points around them,
a first proposal covariance from the finite-difference Hessian, or a warm start from a previous trial."""

from __future__ import annotations

import math
from typing import Callable, Generator

import numpy as np

from .chains import Batch, ChainState, Map, SamplerError, Step, run, serial_map
from .proposal import safe_cholesky
from .config import SamplerConfig, SamplerResult
from .transform import free_coordinates


# --------------------------------------------------------------------------- starts
def _neg_lp(target, center, scale):
    def f(z):
        v = target(center + scale * z).log_posterior
        return -v if v > -math.inf else 1e300
    return f


def fd_derivatives(f: Callable[[np.ndarray], float], x: np.ndarray,
                   h: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``f(x)``, its central-difference gradient and Hessian with steps ``h``, from d^2 + d + 1 evaluations.

    An off-diagonal element takes f(x + h_i e_i + h_j e_j) + f(x - h_i e_i - h_j e_j) less the diagonal
    points (Abramowitz & Stegun 25.3.27 in its symmetric form): second order like the four-point rule, at
    half its cost, and exact on quadratics.
    """
    d = x.size
    H = np.empty((d, d))
    f0 = f(x)
    E = np.diag(h)
    fp = np.array([f(x + E[i]) for i in range(d)])
    fm = np.array([f(x - E[i]) for i in range(d)])
    with np.errstate(invalid="ignore", over="ignore"):  # a point outside the support: inf - inf, left NaN
        for i in range(d):
            H[i, i] = (fp[i] - 2 * f0 + fm[i]) / h[i] ** 2
            for j in range(i + 1, d):
                pair = f(x + E[i] + E[j]) + f(x - E[i] - E[j])
                H[i, j] = H[j, i] = (pair - fp[i] - fm[i] - fp[j] - fm[j] + 2 * f0) / (2 * h[i] * h[j])
        return f0, (fp - fm) / (2 * h), H


def fd_hessian(f: Callable[[np.ndarray], float], x: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Central finite-difference Hessian of ``f`` at ``x`` with steps ``h`` (:func:`fd_derivatives`)."""
    return fd_derivatives(f, x, h)[2]


def local_mode(target, x0: np.ndarray, scale: np.ndarray, maxfev: int, *, xatol: float = 1e-6,
               fatol: float = 1e-8, passes: int = 2) -> tuple[np.ndarray, float]:
    """Nelder-Mead (in coordinates scaled by ``scale``) from ``x0``, restarted once (``passes``); ``xatol`` in
    those coordinates, ``fatol`` in nats (a search that Newton steps polish afterwards can stop far earlier)."""
    from scipy.optimize import minimize

    f = _neg_lp(target, x0, scale)
    z = np.zeros(x0.size)
    best = f(z)
    for _ in range(passes):
        simplex = np.vstack([z] + [z + 0.5 * e for e in np.eye(z.size)])
        r = minimize(f, z, method="Nelder-Mead",
                     options={"initial_simplex": simplex, "maxfev": maxfev // 2, "xatol": xatol, "fatol": fatol})
        if r.fun <= best:
            z, best = r.x, r.fun
    return x0 + scale * z, -best


def posterior_cov_estimate(target, x: np.ndarray, scale: np.ndarray) -> np.ndarray | None:
    """Inverse of the finite-difference Hessian of -log posterior (None if not positive definite)."""
    f = lambda v: -target(v).log_posterior  # noqa: E731
    h = 1e-3 * scale
    for _ in range(2):
        H = fd_hessian(f, x, h)
        if not np.all(np.isfinite(H)):
            return None
        try:
            C = np.linalg.inv(H)
            np.linalg.cholesky(C)
        except np.linalg.LinAlgError:
            return None
        h = 0.05 * np.sqrt(np.diag(C))  # refine the steps to the posterior's own scale
    return 0.5 * (C + C.T)


class Counted:
    """A target that counts its calls (likelihood evaluations), for the cost figures."""

    def __init__(self, target):
        self.target, self.calls = target, 0

    def __call__(self, x):
        self.calls += 1
        return self.target(x)

    def __getattr__(self, name):
        return getattr(self.target, name)


def _warm_task(args):
    """The first of ``points`` with a finite posterior density (else the last), with its density: a warm-started
    chain's position (its place in the warm trial, then the best point, then that point unmoved)."""
    target, points = args
    for x in points:
        lp, ll = target(x)
        if lp > -math.inf:
            break
    return x, lp, ll


def _start_task(args):
    target, x0, scale, maxfev, seed, overdispersion = args
    target = Counted(target)
    rng = np.random.default_rng(seed)
    xm, lpm = local_mode(target, x0, scale, maxfev)
    C = posterior_cov_estimate(target, xm, scale)
    if C is None:
        C = np.diag((0.01 * scale) ** 2)
    L = safe_cholesky(C)
    for k in range(30):
        # overdispersed start around the local mode, so R-hat is meaningful
        x = xm + (overdispersion * 0.8**k) * (L @ rng.standard_normal(xm.size))
        lp, ll = target(x)
        if lp > -math.inf:
            break
    else:
        x = xm
        lp, ll = target(x)
    return x, lp, ll, xm, lpm, C, target.calls



def new_parameter_start(p) -> float:
    """Where a parameter that a warm start does not know starts: 0 (a new term's coefficient) unless its
    prior excludes 0 (a new shape parameter, lognormal), then the prior's median."""
    return 0.0 if np.isfinite(p.logpdf(0.0)) else float(p.quantile(0.5))


def initial_scale(prior) -> np.ndarray:
    """A length scale per parameter for optimisation steps and fallbacks."""
    out = []
    for p in prior.priors:
        try:
            s = (p.quantile(0.75) - p.quantile(0.25)) / 1.349
        except ValueError:
            s = 1.0
        out.append(s if np.isfinite(s) and s > 0 else 1.0)
    return np.minimum(np.array(out), 1e3)


def initial_points(prior, n: int, rng: np.random.Generator, start_sd: dict | None = None) -> np.ndarray:
    """Dispersed initial points: essential parameters from the central 80 % of their priors,
    ARD parameters near 0 (their prior bulk is uninformative)."""
    pts = np.zeros((n, len(prior.priors)))
    for j, (name, p) in enumerate(zip(prior.names, prior.priors)):
        if p.kind == "ard" or p.kind == "flat":
            sd = (start_sd or {}).get(name, 0.0)
            pts[:, j] = sd * rng.standard_normal(n)
        else:
            pts[:, j] = [p.quantile(q) for q in rng.uniform(0.1, 0.9, n)]
    return pts



def warm_positions(target, warm: SamplerResult, scale: np.ndarray) -> tuple[list, list, np.ndarray]:
    """Where a warm start puts the chains of ``target``: the previous chains' positions, fallbacks (its best
    point moved as they are, then unmoved) and a first proposal covariance, mapped by parameter name.

    A parameter of ``warm`` that ``target`` lacks is now fixed (a prune test fixes a term at 0). The new
    posterior is then the previous one *conditioned* on that value, so each position is moved along the
    regression line of the previous proposal covariance (a Gaussian posterior's draws so moved are exact
    draws of its conditional) and the proposal is its Schur complement: taking the marginal instead
    starts the chains off the new posterior with too wide a proposal, and burn-in pays for both. A new
    parameter starts at 0 (at its prior's median if the prior excludes 0) with a small step (not the
    prior's width).
    """
    names = list(target.names)
    idx = {n: i for i, n in enumerate(warm.names)}
    keep = [idx.get(n) for n in names]
    known = [i for i in keep if i is not None]
    fixed = getattr(getattr(target, "spec", None), "fixed", None) or {}
    dropped = [i for n, i in idx.items() if n not in set(names) and n in fixed]
    v = np.array([float(fixed.get(warm.names[i], 0.0)) for i in dropped])
    P = np.asarray(warm.proposal_cov, float)
    B = None
    if dropped and known and np.all(np.isfinite(P)):
        try:
            B = np.linalg.solve(P[np.ix_(dropped, dropped)], P[np.ix_(dropped, known)]).T  # (known, dropped)
        except np.linalg.LinAlgError:
            B = None

    new = np.array([0.0 if a is not None else new_parameter_start(p) for a, p in zip(keep, target.prior.priors)])

    pos = [i for i, a in enumerate(keep) if a is not None]
    free = free_coordinates(target)

    def place(x, project: bool = True) -> np.ndarray:
        x = np.asarray(x, float)
        out = new.copy()
        out[pos] = x[known]
        if B is not None and project:
            # the regression is the proposal's, in the sampler's unconstrained coordinates
            z = free.to_free(out)
            z[pos] = z[pos] + B @ (v - x[dropped])
            out[pos] = free.from_free(z)[pos]
        return out

    # the proposal is in the sampler's unconstrained coordinates: a new parameter's small step too
    cov = free.cov_to_free(np.diag((0.01 * scale) ** 2), new)
    sub = P[np.ix_(known, known)]
    if B is not None:
        cond = sub - B @ P[np.ix_(dropped, known)]
        try:
            np.linalg.cholesky(cond)
            sub = cond * (len(warm.names) / max(len(names), 1))  # the 2.38^2 / d scaling of the smaller space
        except np.linalg.LinAlgError:
            pass
    cov[np.ix_(pos, pos)] = sub
    return ([place(s.x) for s in warm.states], [place(warm.phi_star), place(warm.phi_star, project=False)],
            cov)


def initial_states(target, config: SamplerConfig, *, seed: int, map_fn: Map = serial_map,
                   warm: SamplerResult | None = None, starts: np.ndarray | None = None) -> tuple[list, np.ndarray, int]:
    """Chain states, the first proposal covariance (cold, warm or explicit starts) and the likelihood
    evaluations that took: :func:`iter_initial_states` with the start optimisations on ``map_fn``."""
    return run(iter_initial_states(target, config, seed=seed, warm=warm, starts=starts), map_fn)


def iter_initial_states(target, config: SamplerConfig, *, seed: int, warm: SamplerResult | None = None,
                        starts: np.ndarray | None = None) -> Generator[Batch, list, tuple[list, np.ndarray, int]]:
    """:func:`initial_states` as a generator: a cold start yields its start optimisations as one
    :class:`~.chains.Batch`."""
    names = list(target.names)
    d = len(names)
    nc = config.n_chains
    child = np.random.SeedSequence(seed).spawn(nc + 1)
    scale = initial_scale(target.prior)
    n_eval = nc
    if warm is not None:
        X, fallbacks, cov = warm_positions(target, warm, scale)
        # evaluated where the chains run: the driver would otherwise compile (or load) every new structure's
        # kernel itself before a single chain could start
        res = yield Batch(_warm_task, [(target, [X[c % len(X)], *fallbacks]) for c in range(nc)], Step("warm"))
        states = [ChainState(c, x.tolist(), lp, ll, np.random.PCG64(child[c]).state, x.tolist(), lp, ll)
                  for c, (x, lp, ll) in enumerate(res)]
    elif starts is None:
        pts = initial_points(target.prior, nc, np.random.default_rng(child[nc]))
        tasks = [(target, pts[c], scale, config.start_maxfev, child[c].generate_state(1)[0] + c,
                  config.overdispersion) for c in range(nc)]
        res = yield Batch(_start_task, tasks, Step("start"))
        n_eval = sum(int(r[6]) for r in res)
        free = free_coordinates(target)
        cov = (2.38**2 / d) * np.mean([free.cov_to_free(r[5], r[3]) for r in res], axis=0)
        states = []
        for c, r in enumerate(res):
            x, lp, ll, xm, lpm, *_ = r
            # phi* comes from what the chains visit, never from the start optimiser alone (docs/method.md section 4):
            # a spike it found and no chain returns to would make every chain's posterior ordinate ~0
            states.append(ChainState(c, list(map(float, x)), float(lp), float(ll),
                                     np.random.PCG64(child[c]).state, list(map(float, x)), float(lp), float(ll)))
    else:
        states = []
        for c in range(nc):
            x = np.asarray(starts[c], dtype=float)
            lp, ll = target(x)
            states.append(ChainState(c, x.tolist(), lp, ll, np.random.PCG64(child[c]).state, x.tolist(), lp, ll))
        cov = free_coordinates(target).cov_to_free(np.diag((0.1 * scale) ** 2), np.asarray(starts[0], dtype=float))
    if not any(s.lp > -math.inf for s in states):
        raise SamplerError("no chain could start at a point of finite posterior density: "
                           "check the priors against the data and model")
    for s in states:
        if not s.lp > -math.inf:
            good = max(states, key=lambda q: q.lp)
            s.x, s.lp, s.ll = list(good.x), good.lp, good.ll
    return states, cov, n_eval


