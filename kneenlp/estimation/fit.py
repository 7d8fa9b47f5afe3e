"""The result of an identification: estimates, uncertainty, residuals, diagnostics."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import TypeVar

import numpy as np
import pandas as pd

from kneenlp.base.conventions import COORDINATE_UNITS, COORDINATES, coordinate_columns
from kneenlp.base.forked import forked_map
from kneenlp.estimation.statistics import (
    chi_square_test,
    gauss_newton_covariance,
    information_criteria,
    noise_variance,
    svd_rank,
    weighted_svd,
)
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.model.parameters import Parameter
from kneenlp.solvers.result import SolverResult


@dataclass(frozen=True)
class Fit:
    """Identified parameters of a knee from measured laxity data (lmfit's MinimizerResult).

    Values are SI inside (``params``, ``stderr``: N per unit strain, fractions, N/m^3); the
    report, tables and JSON use the display units (N, %, GN/m^3).  ``q_pred`` are the model's
    poses at the estimate (SI), ``residuals`` the model minus measured coordinates (mm, deg).
    ``objective`` is the problem's weighted sum of squared residuals at the estimate, whatever the
    method (mm^2 + deg^2 times the weights).  The fit holds the solves it took (:attr:`result`, the
    one it judged, after its :attr:`stages`) and derives its counts and times from them.
    """

    problem: IdentificationProblem
    method: str
    params: dict[str, float]
    theta: np.ndarray  # full parameter vector (SI) at the estimate
    objective: float
    status: str  # the judged status (the solver's, or why the fit is not a success)
    success: bool  # the judgement: the solver's success, every trial at equilibrium, ...
    max_residual: float  # largest equilibrium residual at the solution (N or N m)
    q_pred: np.ndarray  # (T, 5) SI
    sensitivity: np.ndarray  # (5T, n_free): d y / d p (mm or deg per SI parameter unit)
    noise_variance: np.ndarray  # (T, 5), mm^2 / deg^2
    noise_source: str  # "given" or "estimated"
    start: dict[str, float] = field(default_factory=dict)
    message: str = ""
    solver: str = "ipopt"
    #: the solve this fit judged, as the solver left it (its objective, timings, the nested method's
    #: history); None for a fit built from parameters and poses alone
    result: SolverResult | None = field(default=None, repr=False, compare=False)
    #: the solves that led to it, in order (a calibration's reduced fit before its NLP, a rescue's
    #: failed try): counted in :attr:`iterations`, :attr:`evaluations`, :attr:`seconds`
    stages: tuple[SolverResult, ...] = field(default=(), repr=False, compare=False)
    #: starts the fit took (the scatter strategy's starts and restarts, the base fit's starts)
    starts: int = 1
    #: the priors' share of what the fit minimised (``prior_weight * sum z^2``; 0 without priors)
    prior_objective: float = 0.0
    #: trials whose fitted equilibrium is not the one ``predict`` reaches by loading from the
    #: unloaded state (a calibration's global search checks every end; empty: none, or not checked)
    off_path: tuple[str, ...] = ()
    #: trials whose fitted equilibrium is unstable (:func:`~kneenlp.estimation.calibrated.unstable`;
    #: empty: none, or not checked)
    unstable: tuple[str, ...] = ()

    @classmethod
    def build(cls, problem: IdentificationProblem, method: str, theta: np.ndarray, q: np.ndarray,
              **kwargs: object) -> Fit:
        """A fit at parameters ``theta`` and poses ``q`` (SI): objective, sensitivities and noise
        variance all from the problem's one observation function."""
        objective = problem.objective(q, theta)
        variance, source = noise_variance(problem.noise, objective, problem.weights, problem.n_free)
        return cls(problem, method, problem.values(theta), np.asarray(theta, float), objective,
                   q_pred=np.asarray(q, float), sensitivity=problem.sensitivities(q, theta),
                   noise_variance=variance, noise_source=source, prior_objective=problem.prior_objective(theta),
                   **kwargs)

    def with_note(self, note: str, **changes) -> Fit:
        """A new fit with ``note`` appended to the message (``"; "`` between notes) and the fields
        ``changes`` replaced."""
        message = "; ".join(filter(None, [self.message, note]))
        return dataclasses.replace(self, message=message, **changes)

    def after(self, *earlier: Fit) -> Fit:
        """This fit with the solves of ``earlier`` fits (in order) before its own."""
        solves = tuple(r for f in earlier for r in f.solves)
        return dataclasses.replace(self, stages=(*solves, *self.stages))

    # ------------------------------------------------------------------ its solves
    @property
    def solves(self) -> tuple[SolverResult, ...]:
        """Every solve the fit took, in order, the judged one last (none: built from parameters)."""
        return (*self.stages, *(() if self.result is None else (self.result,)))

    @property
    def iterations(self) -> int:
        """The solvers' own iterations, summed over its solves (IPOPT's, the Complex method's; the
        reduced-space fit counts its residual evaluations)."""
        return sum(r.iterations for r in self.solves)

    @property
    def evaluations(self) -> int:
        """Objective (or residual) evaluations, summed over its solves."""
        return sum(r.evaluations for r in self.solves)

    @property
    def equilibrium_solves(self) -> int:
        """Trial equilibria the nested method solved, summed over its solves (0 for the others)."""
        return sum(r.equilibrium_solves for r in self.solves)

    @property
    def seconds(self) -> float:
        """Time in the solvers, summed over its solves (s; their builds apart)."""
        return float(sum(r.seconds for r in self.solves))

    @property
    def build_seconds(self) -> float:
        """Time building the solvers, summed over its solves (s; 0 when they were built before)."""
        return float(sum(r.build_seconds for r in self.solves))

    @property
    def map_objective(self) -> float:
        """What the fit minimised: the weighted sum of squares plus the priors' share."""
        return self.objective + self.prior_objective

    # ------------------------------------------------------------------ the problem's parts
    @property
    def model(self) -> KneeModel:
        return self.problem.model

    @property
    def free(self) -> list[str]:
        return self.problem.free

    @property
    def weights(self) -> np.ndarray:
        return self.problem.weights

    @property
    def data(self) -> MeasuredData:
        return self.problem.data

    # ------------------------------------------------------------------ derived
    @property
    def predicted_user(self) -> np.ndarray:
        """The model's measured coordinates (T x 5, mm and deg), including any measurement bias."""
        return self.problem.observe(self.q_pred, self.theta)

    @property
    def residuals(self) -> np.ndarray:
        """Model minus measured coordinates (T x 5, mm and deg)."""
        return self.problem.residuals(self.q_pred, self.theta)

    @property
    def scales(self) -> np.ndarray:
        return self.problem.scales

    @property
    def n_observations(self) -> int:
        """The measured coordinates (those the experiment observes) of every trial."""
        return int(self.problem.observed.sum())

    @property
    def dof(self) -> int:
        """Degrees of freedom of the residuals: observations minus free parameters."""
        return max(self.n_observations - len(self.free), 1)

    def chi_square(self, sigma: float | None = None) -> float:
        """Weighted residual sum over the noise variance (given, else estimated)."""
        return chi_square_test(self.residuals, self.weights, self.noise_variance if sigma is None else sigma**2,
                               len(self.free))[0]

    @property
    def reduced_chi_square(self) -> float:
        return self.chi_square() / self.dof

    @property
    def aic(self) -> float:
        """Akaike information criterion of the (weighted) least-squares fit, ``N ln(WRSS/N) + 2 p``
        (:func:`~kneenlp.estimation.statistics.information_criteria`)."""
        return information_criteria(self.objective, self.n_observations, len(self.free))[0]

    @property
    def bic(self) -> float:
        """Bayesian information criterion, ``N ln(WRSS/N) + p ln N``."""
        return information_criteria(self.objective, self.n_observations, len(self.free))[1]

    @cached_property
    def _all_sensitivities(self) -> np.ndarray:
        """``d y / d p`` (5T x every model parameter) at the estimate, computed once: the
        candidate effects' tests and detection limits all take their columns from it."""
        return self.problem.sensitivities(self.q_pred, self.theta, self.model.parameter_names)

    def sensitivities_of(self, names: list[str]) -> np.ndarray:
        """``d y / d p`` (5T x len(names); mm or deg per SI unit) of any model parameters at the
        estimate, free or not."""
        return self._all_sensitivities[:, [self.model.index(n) for n in names]]

    @cached_property
    def _svd(self):
        """SVD of the weighted, scaled sensitivity matrix (computed once)."""
        return weighted_svd(self.sensitivity, self.weights, self.scales)

    @property
    def rank(self) -> int:
        """Numerical rank of the (weighted, scaled) sensitivity matrix: how many parameter
        directions the data determine (relative singular-value threshold 1e-6)."""
        return svd_rank(self._svd[1])

    @property
    def identifiable(self) -> bool:
        return self.rank == len(self.free)

    def unidentifiable_directions(self) -> list[dict[str, float]]:
        """Parameter combinations (scaled units) the data cannot determine."""
        vt = self._svd[2]
        return [{n: float(c) for n, c in zip(self.free, vt[i], strict=True) if abs(c) > 0.05}
                for i in range(self.rank, len(self.free))]

    def with_prior_rows(self, variance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sensitivities, weights, variances) of the data's rows (``variance``: T x 5 or a number,
        mm^2 or deg^2) followed by one row per prior, ``sqrt(prior_weight) z``, of weight 1 and
        variance ``prior_weight``: the linearised MAP problem whose Gauss-Newton covariance is the
        Laplace approximation of the posterior (the data's rows alone without priors)."""
        s, w = np.asarray(self.sensitivity, float), np.asarray(self.weights, float).ravel()
        var = np.broadcast_to(np.asarray(variance, float), self.weights.shape).ravel()
        if not self.problem.priors:
            return s, w, var
        jp = self.problem.prior_jacobian(self.params)
        rows = jp[np.any(jp != 0, axis=1)]
        return (np.vstack([s, rows]), np.concatenate([w, np.ones(len(rows))]),
                np.concatenate([var, np.full(len(rows), self.problem.prior_weight)]))

    @cached_property
    def covariance(self) -> np.ndarray:
        """Gauss-Newton (linearised) covariance of the free parameters (SI units); with priors the
        posterior's Laplace approximation (:meth:`with_prior_rows`); directions neither the data
        nor a prior determine get infinite variance (see :func:`gauss_newton_covariance`)."""
        return gauss_newton_covariance(*self.with_prior_rows(self.noise_variance), self.scales, self.free)

    @property
    def stderr(self) -> dict[str, float]:
        """Standard errors (SI) of the free parameters."""
        return {n: float(np.sqrt(v)) for n, v in zip(self.free, np.diag(self.covariance), strict=True)}

    @property
    def rms(self) -> float:
        """RMS of all observed coordinate residuals (mm and deg together)."""
        return float(np.sqrt(np.mean(self.residuals[self.problem.observed] ** 2)))

    # ------------------------------------------------------------------ presentation
    def info(self, name: str) -> Parameter:
        """The metadata of parameter ``name`` (unit, display factor, kind)."""
        return self.model.parameter(name)

    def params_user(self) -> dict[str, float]:
        return {n: self.params[n] * self.info(n).to_user for n in self.free}

    def stderr_user(self) -> dict[str, float]:
        return {n: v * self.info(n).to_user for n, v in self.stderr.items()}

    def table(self) -> pd.DataFrame:
        """Per trial: measured and predicted coordinates and residuals (mm, deg)."""
        df = pd.DataFrame({"trial": [t.id for t in self.data.trials]})
        pred = self.predicted_user
        for j, col in enumerate(coordinate_columns()):
            df[f"measured_{col}"] = self.data.q_user[:, j]
            df[f"predicted_{col}"] = pred[:, j]
            df[f"residual_{col}"] = pred[:, j] - self.data.q_user[:, j]
        return df

    def summary(self) -> dict:
        return {
            "method": self.method,
            "solver": self.solver,
            "status": self.status,
            "success": self.success,
            "params": {n: self.params[n] for n in self.free},
            "stderr": self.stderr,
            "params_display": self.params_user(),
            "stderr_display": self.stderr_user(),
            "units_display": {n: self.info(n).unit for n in self.free},
            "objective": self.objective,
            "chi_square": self.chi_square(),
            "reduced_chi_square": self.reduced_chi_square,
            "aic": self.aic,
            "bic": self.bic,
            "rms": self.rms,
            "iterations": self.iterations,
            "evaluations": self.evaluations,
            "equilibrium_solves": self.equilibrium_solves,
            "solves": len(self.solves),
            "seconds": self.seconds,
            "build_seconds": self.build_seconds,
            "max_residual": self.max_residual,
            "rank": self.rank,
            "identifiable": self.identifiable,
            "unidentifiable_directions": self.unidentifiable_directions(),
            "at_bounds": self.at_bounds(),
            "priors": {n: p.record(self.info(n).to_user, self.info(n).unit) | {"source": p.source}
                       for n, p in self.problem.priors.items()},
            "prior_weight": self.problem.prior_weight if self.problem.priors else None,
            "prior_objective": self.prior_objective,
            "outside_prior": self.outside_prior(),
            "noise_variance_source": self.noise_source,
            "trials": len(self.data),
            "data": self.data.source,
            "start": self.start,
            "message": self.message,
        }

    def to_json(self) -> str:
        from kneenlp.base.serialize import dumps

        return dumps(self.summary())

    def at_bounds(self, kinds: tuple[str, ...] | None = None, tol: float = 1e-3) -> list[str]:
        """The free parameters (of ``kinds``, default every kind) that sit on a bound, within ``tol``
        of their range (the reduced-space fit's trust region approaches a bound without reaching
        it: S192803's tibial origin stopped 0.005 mm inside its 10 mm bound): the least squares
        optimum lies beyond, so their standard errors (which assume an interior optimum) do not hold."""
        out = []
        for p in self.problem.parameters:
            if kinds is not None and p.kind not in kinds:
                continue
            lo, hi = p.bounds
            if min(self.params[p.name] - lo, hi - self.params[p.name]) <= tol * (hi - lo):
                out.append(p.name)
        return out

    def outside_prior(self, priors: dict | None = None) -> list[str]:
        """The free parameters outside their prior's 99.7 % range (:meth:`~kneenlp.model.priors.Prior.interval`);
        ``priors`` (by name) to judge a fit by other priors than its own (e.g. a least-squares fit's)."""
        out = []
        for name, prior in (self.problem.priors if priors is None else priors).items():
            lo, hi = prior.interval()
            if not lo <= self.params[name] <= hi:
                out.append(name)
        return out

    def report(self) -> str:
        """lmfit-like text report (:func:`fit_report`)."""
        return fit_report(self)


Item = TypeVar("Item")
Result = TypeVar("Result")


def forked_fits(work: Callable[[Item], Result], items: list[Item], workers: int, model: KneeModel,
                fit_of: Callable[[Result], Fit] = lambda r: r) -> list[Result]:
    """``[work(item) for item in items]`` over ``workers`` forked processes
    (:func:`~kneenlp.base.forked.forked_map`), each result holding a :class:`Fit` (``fit_of(result)``)
    of ``model``: the fit's problem is sent without the model (compiled functions, not picklable)
    and gets ``model`` back here."""

    def with_model(result: Result, value: KneeModel | None) -> Result:
        fit_of(result).problem.model = value
        return result

    return forked_map(work, items, workers, pack=lambda r: with_model(r, None), unpack=lambda r: with_model(r, model))


def _rank_note(fit: Fit) -> str:
    """What the rank (of the data's sensitivities) leaves: with a prior on every free parameter the
    priors determine the directions the data do not."""
    if fit.identifiable:
        return ""
    if fit.problem.priors and all(n in fit.problem.priors for n in fit.free):
        return f" from the data; the priors determine the other {len(fit.free) - fit.rank} direction(s)"
    return "  ** NOT ALL PARAMETERS IDENTIFIABLE **"


def _prior_lines(fit: Fit) -> list[str]:
    if not fit.problem.priors:
        return []
    outside = set(fit.outside_prior())
    lines = [f"[[Priors]] MAP estimate: the priors' share of the objective {fit.prior_objective:.4g}, weighed "
             f"against a misfit variance of {fit.problem.prior_weight:.4g} (mm^2, deg^2)"]
    for name in fit.free:
        prior = fit.problem.priors.get(name)
        if prior is None:
            lines.append(f"    {name:18s}   none (the data alone)")
            continue
        info = fit.info(name)
        flag = "  ** OUTSIDE ITS PRIOR'S 99.7 % RANGE **" if name in outside else ""
        lines.append(f"    {name:18s}   {prior.describe(info.to_user, info.unit)} ({prior.source}){flag}")
    return lines


def fit_report(fit: Fit) -> str:
    """lmfit-like text report of ``fit`` (display units: N per unit strain, %, GN/m^3; mm and deg)."""
    lines = [
        f"[[Fit]] {fit.method} ({fit.solver}) on {fit.data.source or 'data'}",
        f"    status          = {fit.status} ({'success' if fit.success else 'FAILED'})",
        f"    trials          = {len(fit.data)}  (observations {fit.n_observations}, "
        f"free parameters {len(fit.free)})",
        f"    objective       = {fit.objective:.6g}  (sum of squared residuals, mm^2 + deg^2)",
        f"    RMS residual    = {fit.rms:.4g} (mm, deg)",
        f"    chi-square      = {fit.chi_square():.4g}  reduced = {fit.reduced_chi_square:.4g}  "
        f"(dof {fit.dof})",
        f"    AIC, BIC        = {fit.aic:.4g}, {fit.bic:.4g}",
        f"    iterations      = {fit.iterations}   evaluations = {fit.evaluations}"
        + (f"   trial equilibria solved = {fit.equilibrium_solves}" if fit.equilibrium_solves else "")
        + (f"   (over {len(fit.solves)} solves)" if len(fit.solves) > 1 else ""),
        f"    time            = {fit.seconds:.3f} s (build {fit.build_seconds:.3f} s)",
        f"    max equilibrium residual = {fit.max_residual:.2e} (N, N m)",
        f"    rank            = {fit.rank} of {len(fit.free)}" + _rank_note(fit),
        f"    noise variance  = {fit.noise_source}",
        "[[Parameters]]",
    ]
    pu, su, bound = fit.params_user(), fit.stderr_user(), set(fit.at_bounds())
    for n in fit.free:
        unit = fit.info(n).unit
        se = su[n]
        rel = f"({100 * se / abs(pu[n]):.2f}%)" if np.isfinite(se) and pu[n] != 0 else ""
        se_txt = f"+/- {se:.4g} {rel}" if np.isfinite(se) else "+/- (not identifiable)"
        if n in bound:
            se_txt = "AT ITS BOUND (the optimum lies beyond; no standard error)"
        start = fit.start.get(n)
        init = f"(init = {start * fit.info(n).to_user:.6g})" if start is not None else ""
        lines.append(f"    {n:18s} = {pu[n]:12.6g} {unit:7s} {se_txt} {init}")
    for d in fit.unidentifiable_directions():
        lines.append(("    direction the data do not determine (its priors do): " if fit.problem.priors else
                      "    unidentified direction: ") + ", ".join(f"{v:+.2f} {k}" for k, v in d.items()))
    lines += _prior_lines(fit)
    lines.append("[[Residuals]] largest |model - measured| per coordinate")
    res = fit.residuals
    for j, (c, u) in enumerate(zip(COORDINATES, COORDINATE_UNITS, strict=True)):
        if np.isnan(res[:, j]).all():
            lines.append(f"    {c:22s} not observed")
            continue
        i = int(np.nanargmax(np.abs(res[:, j])))
        lines.append(f"    {c:22s} {res[i, j]:+8.3f} {u}  ({fit.data.trials[i].id})")
    if fit.message:
        lines.append(f"[[Message]] {fit.message}")
    return "\n".join(lines)
