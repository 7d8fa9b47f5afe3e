"""Detection limits: the smallest effect a protocol would flag, from the linearised test.

An effect that moves one parameter ``phi_j`` by ``d`` from its neutral value shifts the
measurements by ``d s_j`` (``s_j = d y / d phi_j`` through every trial's equilibrium, mm or deg
per SI unit); what the base parameters cannot absorb, ``M s_j``, makes the candidate's test
statistic noncentral chi-square on ``df`` (the effect's dimension) with noncentrality
``lambda = d^2 |M s_j|^2 / sigma^2``.  The detection limit is the ``d`` at which the test at
level ``level`` (the smallest level of the Holm procedure, ``alpha / m`` for ``m`` tests) flags
the effect with probability ``power`` (default 0.5: the size flagged in half of repeated
experiments).  Linearised: for effects strongly nonlinear at their neutral value (a slack bundle
switched on, a linear strain limit that moves the toe region) it can be optimistic.

:func:`simulated_limits` checks it without the linearisation: noise-free data are simulated with
the parameter moved by ``d`` from the base fit, the base model is refitted to them, and the
refit's weighted residual sum over ``sigma^2`` is the exact noncentrality ``lambda(d)``; ``d`` is
rescaled until ``lambda(d)`` meets the needed value (``lambda`` grows about as ``d^2``).  It costs
a simulation and a refit per step (about 1-2 s each on Set 4 of the synthetic knee).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, stats

from kneenlp.adequacy.candidates import base_projection, effect_sensitivity
from kneenlp.estimation.fit import Fit
from kneenlp.experiment.measured import MeasuredData

#: Probability of flagging at the detection limit.
POWER = 0.5
#: Most noncentrality evaluations of a simulated limit, and the relative noncentrality it stops within.
STEPS = 5
RTOL = 0.1


def noncentrality_needed(df: int, level: float, power: float = POWER) -> float:
    """Noncentrality at which a chi-square test on ``df`` degrees of freedom at ``level`` rejects
    with probability ``power``."""
    crit = stats.chi2.isf(level, df)

    def gap(lam: float) -> float:
        return float(stats.ncx2.sf(crit, df, lam)) - power

    return float(optimize.brentq(gap, 1e-9, 1e4))


@dataclass(frozen=True)
class DetectionTest:
    """The test a detection limit is for: noise sd ``sigma`` (mm or deg), ``df`` degrees of freedom
    (the effect's dimension), ``level`` and the ``power`` to flag with."""

    sigma: float
    df: int
    level: float
    power: float = POWER

    def noncentrality(self) -> float:
        """The noncentrality at which the test flags with its power (:func:`noncentrality_needed`)."""
        return noncentrality_needed(self.df, self.level, self.power)


def detection_limits(fit: Fit, test: DetectionTest, names: list[str]) -> dict[str, float]:
    """Smallest shift (display units) of each parameter in ``names`` alone that ``test`` flags with
    its power, at the base fit ``fit``; ``inf`` where the protocol cannot see the parameter (a limit
    beyond the parameter's whole range)."""
    sigma = test.sigma
    proj, _, _ = base_projection(fit)
    lam = test.noncentrality()
    s_e = proj @ effect_sensitivity(fit, names)
    out = {}
    for j, n in enumerate(names):
        norm2 = float(s_e[:, j] @ s_e[:, j])
        par = fit.model.parameter(n)
        limit = np.sqrt(lam * sigma**2 / norm2) if norm2 > 0 else np.inf
        if limit > par.bounds[1] - par.bounds[0]:  # beyond the parameter's whole range: not seen
            limit = np.inf
        out[n] = float(limit * par.to_user)
    return out


def exact_noncentrality(fit: Fit, name: str, shift: float, sigma: float) -> float:
    """Noncentrality (chi-square units) of moving parameter ``name`` by ``shift`` (SI) from its
    neutral value (the base fit's value for a base-model parameter): the weighted residual sum of
    the base model refitted to noise-free data simulated with the shift, over ``sigma^2``.  ``nan``
    when the simulation or the refit fails."""
    from kneenlp.estimation.identify import identify
    from kneenlp.solvers.forward import forward_solver

    model = fit.model
    theta = fit.theta.copy()
    par = model.parameter(name)
    i = model.index(name)
    theta[i] = (par.neutral if par.neutral is not None else theta[i]) + shift
    sols = forward_solver(model).solve(fit.data.trials, theta, q_start={t.id: q for t, q in
                                                                        zip(fit.data.trials, fit.q_pred, strict=True)})
    if not all(s.converged for s in sols):
        return float("nan")
    y = model.observe(np.array([s.q for s in sols]), theta, [s.trial.load for s in sols],
                      [s.trial.flexion for s in sols])
    data = MeasuredData.from_user(fit.data.trials, y, fit.data.protocol, "noise-free simulation")
    refit = identify(model, data, free=list(fit.free), start=dict(fit.params), fixed=fit.problem.fixed,
                     noise=fit.problem.noise, restarts=0)
    if not refit.success:
        return float("nan")
    return float(np.sum(refit.weights * refit.residuals**2)) / sigma**2


def simulated_limits(fit: Fit, test: DetectionTest, names: list[str], sign: float = 1.0) -> dict[str, float]:
    """Detection limits (display units) of ``names`` like :func:`detection_limits`, but from the
    exact noncentrality of simulated noise-free data (:func:`exact_noncentrality`) for a change of
    sign ``sign`` (a one-sided parameter, e.g. a stiffness at 0, only increases); starts at the
    linearised limit and rescales until within :data:`RTOL` of the needed noncentrality (at most
    :data:`STEPS` simulations).  ``inf`` beyond the parameter's range, ``nan`` where a simulation failed."""
    sigma = test.sigma
    lam = test.noncentrality()
    linear = detection_limits(fit, test, names)
    out = {}
    for n in names:
        par = fit.model.parameter(n)
        d = linear[n] / par.to_user
        s = 1.0 if par.one_sided else sign
        lo, hi = par.bounds
        origin = par.neutral if par.neutral is not None else fit.theta[fit.model.index(n)]
        room = (hi - origin) if s > 0 else (origin - lo)
        for _ in range(STEPS):
            if not np.isfinite(d) or d > room:
                d = np.inf
                break
            got = exact_noncentrality(fit, n, s * d, sigma)
            if not np.isfinite(got):
                d = np.nan
                break
            if abs(got / lam - 1) < RTOL:
                break
            d *= np.sqrt(lam / max(got, 1e-3 * lam)) if got > 0 else 10.0
        out[n] = float(d * par.to_user)
    return out


def simulated_limits_either_way(fit: Fit, test: DetectionTest, names: list[str]) -> dict[str, float]:
    """:func:`simulated_limits` for an increase of each parameter, and for a decrease where an
    increase is not seen (``inf``): the smallest change either way the protocol flags."""
    up = simulated_limits(fit, test, names, sign=1.0)
    unseen = [n for n in names if np.isinf(up[n]) and not fit.model.parameter(n).one_sided]
    if unseen:
        up |= simulated_limits(fit, test, unseen, sign=-1.0)
    return up
