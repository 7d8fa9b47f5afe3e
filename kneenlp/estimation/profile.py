"""Profile-likelihood intervals of fitted parameters (``kneenlp identify --profile NAMES``).

The interval of a parameter is the set of its values whose *profile*, the fit's negative log
posterior minimised over every other free parameter with this one held, rises at most
``chi2_1(level)`` above its minimum (Venzon and Moolgavkar 1988; the likelihood-ratio interval).
Unlike the Laplace standard error it follows the model's nonlinearity and the bounds: an interval
that reaches a bound before the profile rises enough ends at the bound, and says so.

The profiled function is the posterior the Laplace covariance approximates
(:meth:`~kneenlp.estimation.fit.Fit.with_prior_rows`): ``P = sum w r^2 / s^2 + sum z^2``, with
``s^2`` the fit's noise variance per unit weight (declared, or estimated from its residuals) and
``z`` the priors' standardised deviations (none for a least-squares fit).  A MAP fit weighed its
priors against ``prior_weight`` rather than ``s^2``; the profile's centre is therefore refitted at
``s^2`` first (the same point when the two agree).  Every point is a reduced-space fit
(:func:`~kneenlp.estimation.solve.reduced_fit`, every iterate at equilibrium) warm-started from its
neighbour, in steps of the Laplace standard error.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import stats

from kneenlp.base.errors import InputError, unknown_name
from kneenlp.estimation.fit import Fit
from kneenlp.estimation.solve import reduced_fit

#: The interval's level (two-sided), as the Laplace intervals of the report.
LEVEL = 0.95
#: Steps from the centre per side before a side is given up as open (its profile too flat).
MAX_STEPS = 10


@dataclass(frozen=True)
class ProfileInterval:
    """The profile-likelihood interval of one parameter (SI inside, display units in ``record``).

    ``lower``/``upper`` are NaN where the profile could not be followed (a point's fit failed) or
    stayed below the threshold for :data:`MAX_STEPS` steps; ``*_at_bound`` marks an end at the
    parameter's bound (the profile still below the threshold there)."""

    name: str
    estimate: float
    lower: float
    upper: float
    level: float
    lower_at_bound: bool
    upper_at_bound: bool
    #: (value SI, rise of the profile above its minimum) of every point computed, in value order
    points: tuple[tuple[float, float], ...]
    #: the display unit and the factor SI -> display
    unit: str
    to_user: float

    def record(self) -> dict:
        """JSON-ready, in the display unit."""
        def user(v: float) -> float | None:
            return None if not np.isfinite(v) else float(v * self.to_user)
        return {"name": self.name, "unit": self.unit, "level": self.level, "estimate": user(self.estimate),
                "lower": user(self.lower), "upper": user(self.upper), "lower_at_bound": self.lower_at_bound,
                "upper_at_bound": self.upper_at_bound,
                "profile": [[user(v), float(d)] for v, d in self.points]}

    def line(self) -> str:
        def end(v: float, at_bound: bool) -> str:
            if not np.isfinite(v):
                return "open"
            return f"{v * self.to_user:.4g}" + (" (bound)" if at_bound else "")
        return (f"{self.name:32s} {self.estimate * self.to_user:12.4g} [{end(self.lower, self.lower_at_bound)}, "
                f"{end(self.upper, self.upper_at_bound)}] {self.unit}")


def profile_lines(intervals: list[ProfileInterval]) -> list[str]:
    """The report's section of profile-likelihood intervals (empty without any)."""
    if not intervals:
        return []
    return [f"[[Profile-likelihood intervals ({100 * intervals[0].level:g} %)]]",
            *(f"    {i.line()}" for i in intervals)]


def check_profile_names(fit: Fit, names: list[str]) -> None:
    """Refuse a name the model does not have, or one the fit did not free (field ``--profile``)."""
    for n in names:
        if n not in fit.model.parameter_names:
            raise InputError(unknown_name("parameter", n, fit.free).message, field="--profile")
        if n not in fit.free:
            info = fit.model.parameter(n)
            raise InputError(f"'{n}' was not fitted (fixed at {fit.theta[fit.model.index(n)] * info.to_user:.4g} "
                             f"{info.unit}): profile one of the free parameters", field="--profile")


def profile(fit: Fit, names: list[str], level: float = LEVEL) -> list[ProfileInterval]:
    """The profile-likelihood intervals (module docstring) of the free parameters ``names`` of ``fit``."""
    check_profile_names(fit, names)
    s2 = float(np.mean((fit.noise_variance * fit.weights)[fit.problem.observed]))
    problem = dataclasses.replace(fit.problem, prior_weight=s2) if fit.problem.priors else fit.problem
    centre = fit
    if fit.problem.priors and not np.isclose(s2, fit.problem.prior_weight, rtol=1e-9):
        centre = reduced_fit(problem, fit.params, q0=fit.q_pred)
        if not centre.success:
            centre = dataclasses.replace(fit, problem=problem)  # the fit's own point as the centre
    base = (centre.objective + problem.prior_objective(centre.theta)) / s2  # P at the centre, priors weighed at s2
    profiled = _Profiled(centre, problem, base, s2, level)
    return [_interval(profiled, name) for name in names]


@dataclass(frozen=True)
class _Profiled:
    """What every interval of :func:`profile` is taken about: the ``centre`` fit, its ``problem`` (priors
    weighed at ``s2``, the misfit variance, mm^2 or deg^2), the objective P there over ``s2`` (``base``)
    and the interval's ``level``."""

    centre: Fit
    problem: object
    base: float
    s2: float
    level: float


def _interval(profiled: _Profiled, name: str) -> ProfileInterval:
    """The profile-likelihood interval of the free parameter ``name`` about ``profiled`` (module docstring)."""
    centre, problem, base, s2, level = profiled.centre, profiled.problem, profiled.base, profiled.s2, profiled.level
    threshold = float(stats.chi2.ppf(level, 1))
    info = centre.model.parameter(name)
    j = problem.free.index(name)
    estimate = centre.params[name]
    lo, hi = float(problem.lower[j]), float(problem.upper[j])
    sd = centre.stderr.get(name, np.nan)
    step = sd if np.isfinite(sd) and sd > 0 else 0.1 * (hi - lo if np.isfinite(hi - lo) else abs(estimate) or 1.0)
    held = dataclasses.replace(problem, free=[n for n in problem.free if n != name],
                               priors={n: p for n, p in problem.priors.items() if n != name})
    prior = problem.priors.get(name)
    points = [(estimate, 0.0)]
    ends = []
    for sign, bound in ((-1.0, lo), (1.0, hi)):
        start, q0 = {n: v for n, v in centre.params.items() if n != name}, centre.q_pred
        previous, end, at_bound = (estimate, 0.0), np.nan, False
        for k in range(1, MAX_STEPS + 1):
            value = estimate + sign * step * k
            last = (sign * (value - bound) >= 0)
            value = bound if last else value
            point = reduced_fit(dataclasses.replace(held, fixed=problem.fixed | {name: value}), start, q0=q0)
            if not point.success:
                break
            rise = (point.objective + point.prior_objective) / s2 - base
            if prior is not None:
                rise += float(prior.z(value) ** 2)
            points.append((value, rise))
            if rise >= threshold:  # linear in the signed root of the rise, exact for a quadratic profile
                r0, r1 = np.sqrt(max(previous[1], 0.0)), np.sqrt(rise)
                end = previous[0] + (value - previous[0]) * (np.sqrt(threshold) - r0) / (r1 - r0)
                break
            if last:
                end, at_bound = bound, True
                break
            previous, start, q0 = (value, rise), point.params, point.q_pred
        ends.append((end, at_bound))
    return ProfileInterval(name, estimate, ends[0][0], ends[1][0], level, ends[0][1], ends[1][1],
                           tuple(sorted(points)), info.unit, info.to_user)
