"""Coverage of the posterior intervals: do the 95 % intervals cover the truth 95 % of the time?

Each simulated experiment draws its true parameters from the priors the fit uses (the shipped
defaults about the knee's values, docs/priors.md), simulates the protocol with them, adds seeded
noise, and identifies the MAP estimate with those priors and the declared noise (so the prior
weight is the noise variance: the posterior proper).  Averaged over the prior, a Bayesian
interval that is right covers the truth at its level; the Laplace intervals (the MAP Hessian,
:attr:`~kneenlp.estimation.fit.Fit.stderr`) are checked so (``benchmarks/bench_coverage.py``:
at least 200 experiments; a fast version in the tests).
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats

from kneenlp.base.keywords import keyword_options
from kneenlp.estimation.identify import identify
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import free_names, resolve_priors
from kneenlp.model.knee import Knee
from kneenlp.simulation import simulate

#: Draws of a truth outside a parameter's bounds are redrawn at most this often.
MAX_REDRAWS = 20


@dataclass(frozen=True)
class CoverageResult:
    """Which interval covered its truth, per experiment (rows) and parameter (columns)."""

    names: tuple[str, ...]
    covered: np.ndarray  # (experiments, parameters) bool
    level: float
    failed: tuple[str, ...]  # experiments left out, with why

    def rate(self) -> dict[str, float]:
        """The share of experiments whose interval of each parameter covered its truth."""
        return {n: float(c) for n, c in zip(self.names, self.covered.mean(axis=0), strict=True)}

    def overall(self) -> float:
        return float(self.covered.mean())

    def report(self) -> str:
        n = len(self.covered)
        lines = [f"{100 * self.level:g} % Laplace intervals, {n} experiments ({len(self.failed)} left out): "
                 f"coverage {100 * self.overall():.1f} %"]
        lines += [f"  {name:24s} {100 * r:5.1f} %" for name, r in self.rate().items()]
        lines += [f"  left out: {f}" for f in self.failed]
        return "\n".join(lines)


def draw_truth(model: KneeModel, priors: dict, rng: np.random.Generator) -> dict[str, float]:
    """True values (SI) of the prior's parameters, each drawn from its prior within its bounds."""
    out = {}
    for name, prior in priors.items():
        lo, hi = model.parameter(name).bounds
        for _ in range(MAX_REDRAWS):
            value = float(prior.sample(rng))
            if lo <= value <= hi:
                break
        out[name] = float(np.clip(value, lo, hi))
    return out


@dataclass(frozen=True)
class CoverageOptions:
    """:func:`coverage`'s keyword options (its docstring), checked in one place."""

    seed: int = 0
    noise: str = "gaussian:0.5"
    level: float = 0.95
    free: list[str] | None = None


def coverage(knee: Knee | KneeModel | None, protocol: str, experiments: int = 200, **options) -> CoverageResult:
    """``experiments`` simulated experiments of ``protocol`` on ``knee`` (module docstring), seeded
    by ``seed`` (default 0), measured with ``noise`` (default ``"gaussian:0.5"``, mm and deg), the
    intervals at ``level`` (default 0.95); ``free`` the identified parameters (default: the knee's
    default free ones)."""
    opts = keyword_options(CoverageOptions, "coverage", options)
    seed, noise, level, free = opts.seed, opts.noise, opts.level, opts.free
    model = KneeModel.of(knee or Knee.default())
    names = free_names(model, free)
    priors = resolve_priors(model, names, "default")
    z = float(stats.norm.ppf(0.5 + level / 2))
    rows, failed = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(experiments):
            rng = np.random.default_rng([seed, i])
            truth = draw_truth(model, priors, rng)
            sim = simulate(model, protocol, parameters=truth)
            if sim.failed:
                failed.append(f"experiment {i}: {len(sim.failed)} trial(s) without equilibrium at the truth")
                continue
            path = Path(tmp) / f"experiment_{i}.csv"
            sim.measured(noise, int(rng.integers(2**31))).to_csv(path, index=False)
            fit = identify(model, read_measured(path), free=names, noise=noise, priors="default", seed=i,
                           strategy="scatter")
            if not fit.success:
                failed.append(f"experiment {i}: the fit did not converge ({fit.status})")
                continue
            rows.append([abs(fit.params[n] - truth[n]) <= z * fit.stderr[n] for n in names])
    return CoverageResult(tuple(names), np.array(rows, bool).reshape(-1, len(names)), level, tuple(failed))
