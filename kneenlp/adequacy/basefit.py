"""The base fit of model adequacy: identify's fit with the noise model, restarted until its misfit
is either plausible for the noise or reproducible.

A misfit the noise cannot explain (chi-square p < 1e-9) has two causes: a wrong local minimum of
the optimiser or a model that cannot fit the data.  Every statistic of
:mod:`kneenlp.adequacy.diagnosis` assumes the second, so the base fit restarts from fresh scatter
draws until the misfit is plausible, or two converged starts agree on it (relative objective
difference below ``agree``: the same minimum, reached twice, is the model's).  A clean dataset
costs one solve, an inadequate model two.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from kneenlp.base.keywords import keyword_options
from kneenlp.estimation.fit import Fit
from kneenlp.estimation.identify import identify
from kneenlp.estimation.solve import implausible_misfit
from kneenlp.estimation.starts import best_fit, run_starts
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.noise import NoiseModel
from kneenlp.model.knee import Knee

#: Relative objective difference below which two starts count as the same minimum.
AGREE = 1e-3
#: IPOPT iterations per start: clean data take 9-40; a start that needs more is usually wandering
#: (a model far from the data), and the scatter strategy's rescue (reduced-space Gauss-Newton, then IPOPT
#: again) reaches the minimum sooner than 150 iterations would.
MAX_ITER = 60


@dataclass(frozen=True)
class BaseFitOptions:
    """:func:`base_fit`'s keyword options (its docstring), checked in one place."""

    seed: int = 0
    max_starts: int = 5
    agree: float = AGREE
    free: list[str] | None = None


def base_fit(knee: Knee | KneeModel | None, data: MeasuredData | str | Path, noise: str | NoiseModel,
             **options) -> Fit:
    """Fit the base model (k and reference strain of every ligament, or ``free``) to ``data`` with
    the noise model ``noise`` (mm, deg), restarting as the module docstring says (from ``seed``, at
    most ``max_starts`` starts, ``agree`` the relative objective difference of the same minimum); the
    best converged fit is returned, its ``starts`` say how many starts it took."""
    opts = keyword_options(BaseFitOptions, "base_fit", options)
    seed, agree, free = opts.seed, opts.agree, opts.free

    def solve(i: int) -> Fit:
        return identify(knee, data, seed=seed + 7919 * i, noise=noise, restarts=0, free=free,
                        solver_options={"ipopt": {"max_iter": MAX_ITER}})

    def done(fits: list[Fit]) -> bool:
        if fits[-1].success and not implausible_misfit(fits[-1]):
            return True
        ok = sorted((f for f in fits if f.success), key=lambda f: f.objective)
        return len(ok) >= 2 and ok[1].objective - ok[0].objective <= agree * ok[0].objective

    fits = run_starts(solve, at_least=1, at_most=opts.max_starts, done=done)
    converged = any(f.success for f in fits)
    best = best_fit([f for f in fits if f.success or not converged], lambda f: -f.objective)
    return dataclasses.replace(best, starts=len(fits))
