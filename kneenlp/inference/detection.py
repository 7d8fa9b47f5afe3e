"""Detection limits: the smallest effect a protocol would flag, from the linearised test.

An effect that moves one parameter ``phi_j`` by ``d`` from its neutral value shifts the
measurements by ``d s_j`` (``s_j = d y / d phi_j`` through every trial's equilibrium, mm or deg
per SI unit); what the base parameters cannot absorb, ``M s_j``, makes the candidate's test
statistic noncentral chi-square on ``df`` (the effect's dimension) with noncentrality
``lambda = d^2 |M s_j|^2 / sigma^2``.  The detection limit is the ``d`` at which the test at
level ``level`` (the smallest level of the Holm procedure, ``alpha / m`` for ``m`` tests) flags
the effect with probability ``power`` (default 0.5: the size flagged in half of repeated
experiments).  Linearised: for effects strongly nonlinear at their neutral value (a slack bundle
switched on) it is a lower bound.
"""

from __future__ import annotations

import numpy as np
from scipy import optimize, stats

from kneenlp.inference.candidates import base_projection, effect_sensitivity
from kneenlp.inference.fit import Fit

#: Probability of flagging at the detection limit.
POWER = 0.5


def noncentrality_needed(df: int, level: float, power: float = POWER) -> float:
    """Noncentrality at which a chi-square test on ``df`` degrees of freedom at ``level`` rejects
    with probability ``power``."""
    crit = stats.chi2.isf(level, df)

    def gap(lam: float) -> float:
        return float(stats.ncx2.sf(crit, df, lam)) - power

    return float(optimize.brentq(gap, 1e-9, 1e4))


def detection_limits(fit: Fit, sigma: float, names: list[str], df: int, level: float,
                     power: float = POWER) -> dict[str, float]:
    """Smallest shift (display units) of each parameter in ``names`` alone that a test on ``df``
    degrees of freedom at ``level`` flags with probability ``power`` (noise sd ``sigma``, mm or
    deg), at the base fit ``fit``; ``inf`` where the protocol cannot see the parameter (a limit
    beyond the parameter's whole range)."""
    proj, _, _ = base_projection(fit)
    lam = noncentrality_needed(df, level, power)
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
