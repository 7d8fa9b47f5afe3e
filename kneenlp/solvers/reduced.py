"""Reduced-space Gauss-Newton: least squares over the parameters alone, every pose at equilibrium.

The simultaneous NLP (:mod:`kneenlp.solvers.nlp`) lets IPOPT move poses and parameters together
and satisfy equilibrium only at the end.  From a start whose measured poses are far from the
model's equilibrium (cartilage four times softer than the model's: the measured poses penetrate
the stiff model's cartilage by millimetres) IPOPT can wander for its whole iteration budget.
Here the poses are eliminated instead: for parameters ``p`` every trial is solved
(:meth:`~kneenlp.solvers.forward.ForwardSolver.solve_batch`, warm-started from the last poses),
the residuals are the problem's own (:meth:`~kneenlp.experiment.problem.IdentificationProblem.residuals`)
and their Jacobian the implicit-function sensitivities
(:meth:`~kneenlp.experiment.problem.IdentificationProblem.sensitivities`); scipy's trust-region
reflective least squares takes the steps within the parameter bounds.  Every iterate is an
equilibrium, so it cannot wander off.  Used to rescue a failed simultaneous solve
(:func:`kneenlp.estimation.identify.identify`) and to solve the refits of model adequacy
(:func:`kneenlp.adequacy.candidates.refit_with`), which start at the base fit.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import optimize

from kneenlp.base.keywords import keyword_options
from kneenlp.solvers.forward import BatchStart, forward_solver
from kneenlp.solvers.result import SolverResult

#: After the first point at equilibrium, the trials a step loses are retried (load ramps, fresh
#: starts) only if they are at most this share of all trials; more lost means the step went too
#: far, and trf shrinks it (a 4 mm PCL attachment refit spent 6 of its 8 s retrying 30 lost
#: trials, none of which had an equilibrium).
MAX_RETRIED_SHARE = 0.25

#: Relative tolerance (cost, step, gradient) of smooth contact (spheres, analytic implants).
SMOOTH_TOLERANCE = 1e-8
#: ... and of mesh contact, whose working sets, retaken at every pose, make the cost noisy below
#: about 1e-5 of itself (S192803 calibration: 390.1 after 40 evaluations, 389.6 after 400, with
#: relative decreases of 1e-6..1e-5 per step in between; at 1e-8 no solve ever converged).
MESH_TOLERANCE = 1e-5

if TYPE_CHECKING:
    from kneenlp.experiment.problem import IdentificationProblem


def tolerance(model) -> float:
    """The relative tolerance the model's contact allows: :data:`MESH_TOLERANCE` where contact
    uses working sets (mesh contact), :data:`SMOOTH_TOLERANCE` otherwise."""
    return MESH_TOLERANCE if model.ws_size else SMOOTH_TOLERANCE


@dataclass(frozen=True, eq=False)
class Point:
    """One evaluated point: scaled free parameters ``x``, every parameter ``theta`` (SI), the trials'
    poses ``q`` (T x 5, SI), whether every trial is at equilibrium, and the weighted residual rows
    (mm or deg times the square root of the weights, then the priors' rows)."""

    x: np.ndarray
    theta: np.ndarray
    q: np.ndarray
    ok: bool
    rows: np.ndarray

    @property
    def cost(self) -> float:
        """The weighted residual sum plus the priors' share (mm^2 + deg^2)."""
        return float(self.rows @ self.rows)


class ReducedSpace:
    """The least-squares problem over the scaled free parameters alone: residual rows and their
    Jacobian, every trial at equilibrium (module docstring).

    Evaluating (:meth:`evaluate`, :meth:`differentiate`) reads what is kept between evaluations and
    never writes it; :meth:`remember` and :meth:`remember_slope` alone write it:

    * ``best``: the lowest-cost point with every trial at equilibrium so far, trf's current iterate
      (its steps only ever lower the cost).  Every trial is solved from its poses, never from a
      rejected trial point: a knee can have two equilibria, and a warm start from far away switched
      branches (objective 25 -> 3221 at the same parameters);
    * ``slope``: the best point's ``dq/dp`` (SI), whose first-order prediction of the poses starts Newton;
    * ``last``: the last point evaluated, the one trf differentiates next.

    :meth:`residuals` and :meth:`jacobian` are scipy's ``fun`` and ``jac``.
    """

    def __init__(self, problem: IdentificationProblem, q_start: np.ndarray, threads: int = 2):
        self.problem, self.threads = problem, threads
        self.solver = forward_solver(problem.model)
        self.sqrt_weights = np.sqrt(problem.weights).ravel()
        self.free_index = [problem.model.index(n) for n in problem.free]
        self.q_start = np.asarray(q_start, float).copy()  # SI, the first solve's poses
        self.best: Point | None = None
        self.slope: tuple[np.ndarray, np.ndarray] | None = None  # (theta, dq/dp) of the best point
        self.last: Point | None = None

    # ------------------------------------------------------------------ evaluating
    def evaluate(self, x: np.ndarray) -> Point:
        """Every trial solved at the scaled parameters ``x``, from the best point's poses (the
        start's before any), and the residual rows there."""
        problem, trials, tol_eq = self.problem, self.problem.trials, self.problem.equilibrium_tol
        theta = problem.theta(problem.from_scaled(x))
        retries = None if self.best is None else int(MAX_RETRIED_SHARE * len(trials))
        q_from = self.q_start if self.best is None else self.best.q
        theta_from = None if self.best is None else self.best.theta
        start = BatchStart(q_from, theta0=theta_from, guess=self.predicted_poses(theta))
        q, res = self.solver.solve_batch(trials, theta, start, self.threads, max_retries=retries)
        bad = np.flatnonzero(~(res <= tol_eq))
        if len(bad) and (retries is None or len(bad) <= retries):  # try from the forward solver's own start
            for i, sol in zip(bad, self.solver.solve([trials[i] for i in bad], theta, snap=False), strict=True):
                if sol.converged:
                    q[i], res[i] = sol.q, sol.max_residual
        rows = np.concatenate([problem.observed_residuals(q, theta).ravel() * self.sqrt_weights, self.prior_rows(x)])
        return Point(np.array(x, float), theta, q, bool(np.all(res <= tol_eq)), rows)

    def predicted_poses(self, theta: np.ndarray) -> np.ndarray | None:
        """The first-order prediction of the poses at ``theta`` (SI) from the best point's (its
        ``dq/dp``); None while the best point has no slope."""
        if self.slope is None or self.best is None or not np.array_equal(self.slope[0], self.best.theta):
            return None
        step = np.array([theta[i] - self.best.theta[i] for i in self.free_index])  # SI
        return self.best.q + self.slope[1] @ step

    def differentiate(self, point: Point) -> tuple[np.ndarray, np.ndarray]:
        """(d rows / d x, dq/dp in SI) at ``point``: the implicit-function sensitivities, scaled and
        weighted, then the priors' rows."""
        problem = self.problem
        dy_dp, dq_dp = problem.sensitivities(point.q, point.theta, with_poses=True)
        rows = np.vstack([dy_dp * problem.scales * self.sqrt_weights[:, None], self.prior_jacobian(point.x)])
        return rows, dq_dp

    def prior_rows(self, x: np.ndarray) -> np.ndarray:
        """The priors' rows at the scaled parameters ``x`` (none without priors)."""
        problem = self.problem
        return problem.prior_residuals(problem.from_scaled(x)) if problem.priors else np.zeros(0)

    def prior_jacobian(self, x: np.ndarray) -> np.ndarray:
        """d (priors' rows) / d x (scaled)."""
        problem = self.problem
        if not problem.priors:
            return np.zeros((0, len(x)))
        return problem.prior_jacobian(dict(zip(problem.free, problem.from_scaled(x), strict=True))) * problem.scales

    # ------------------------------------------------------------------ what is kept
    def remember(self, point: Point) -> None:
        """``point`` is the last evaluated, and the best if every trial is at equilibrium there and
        its cost is the lowest so far."""
        self.last = point
        if point.ok and (self.best is None or point.cost < self.best.cost):
            self.best = dataclasses.replace(point, q=point.q.copy())

    def remember_slope(self, point: Point, dq_dp: np.ndarray) -> None:
        """Keep ``dq/dp`` (SI) of ``point`` when it is the best point."""
        if self.best is not None and np.array_equal(point.theta, self.best.theta):
            self.slope = (point.theta, dq_dp)

    # ------------------------------------------------------------------ scipy's fun and jac
    def residuals(self, x: np.ndarray) -> np.ndarray:
        """The residual rows at ``x``, remembered; without equilibrium a large residual turns trf's step back."""
        point = self.evaluate(x)
        self.remember(point)
        return point.rows if point.ok else point.rows + 1e3

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """The rows' Jacobian at ``x``: at the last point (trf evaluates before it differentiates),
        else at ``x`` evaluated and remembered; the best point's ``dq/dp`` is kept."""
        if self.last is None or not np.array_equal(x, self.last.x):
            self.residuals(x)
        rows, dq_dp = self.differentiate(self.last)
        self.remember_slope(self.last, dq_dp)
        return rows


def start_poses(problem: IdentificationProblem, theta: np.ndarray, threads: int = 2) -> np.ndarray:
    """Each trial's starting equilibrium (SI) at ``theta``: of the one Newton finds from the
    measured pose and the one the forward solver reaches from the unloaded state (``predict``'s),
    the nearer to the measurement (weighted); the measured pose where neither converges.  Either
    alone failed on S192803: from the measured poses, Newton picked a branch by the start's last
    digits (registration fit: objective 1949 or 1800 for starts 1e-12 apart); from the unloaded
    state alone, the MAP calibration followed branches far from the data (MAP objective 731, not 452)."""
    tol = problem.equilibrium_tol
    solver = forward_solver(problem.model)
    measured, res = solver.solve_batch(problem.trials, theta, BatchStart(problem.measured_q), threads,
                                       max_retries=0)
    forward = problem.measured_q
    reached = np.zeros(len(forward), bool)
    for i, sol in enumerate(solver.solve(problem.trials, theta)):
        if sol.converged:
            forward[i], reached[i] = sol.q, True

    def misfit(q: np.ndarray) -> np.ndarray:
        return np.sum(problem.weights * problem.observed_residuals(q, theta) ** 2, axis=1)

    use_forward = reached & ((res > tol) | (misfit(forward) < misfit(measured)))
    return np.where(use_forward[:, None], forward, np.where((res <= tol)[:, None], measured, problem.measured_q))


@dataclass(frozen=True)
class ReducedSettings:
    """The settings of :func:`reduced_least_squares`: at most ``max_evaluations`` residual evaluations,
    the relative cost change ``tol`` it stops at (None: :func:`tolerance`), the ``threads`` of the
    trials' Newton."""

    max_evaluations: int = 60
    tol: float | None = None
    threads: int = 2



def reduced_least_squares(problem: IdentificationProblem, start: dict[str, float], *, q0: np.ndarray | None = None,
                          **options) -> SolverResult:
    """Minimise the problem's weighted residual sum over its free parameters from ``start`` (SI),
    with every trial at equilibrium (module docstring); ``q0`` warm-starts the first poses (SI,
    default :func:`start_poses`).  Parameters scaled by
    their scales; stops at relative cost change ``tol`` (default :func:`tolerance`) or after
    ``max_evaluations`` (60) residual evaluations; ``threads`` (2) of the trials' Newton
    (``options``: :class:`ReducedSettings`)."""
    settings = keyword_options(ReducedSettings, "reduced_least_squares", options)
    threads, max_evaluations = settings.threads, settings.max_evaluations
    tol = tolerance(problem.model) if settings.tol is None else settings.tol
    t0 = time.perf_counter()
    lower, upper = problem.scaled_bounds
    x0 = np.clip(problem.to_scaled(start), lower, upper)
    space = ReducedSpace(problem, start_poses(problem, problem.theta(problem.from_scaled(x0)), threads)
                         if q0 is None else q0, threads)
    # trf's first trust radius is the start's own (Jacobian-scaled) norm: a start at a neutral 0 plus
    # rounding got a radius of 1e-12 and stopped there (S192803, registration fit: objective 4437
    # instead of 1800).  Its variable is shifted so that the start is 1 in every scaled parameter:
    # the first radius is then one scale of each parameter, wherever the start lies
    shift = 1.0 - x0
    out = optimize.least_squares(lambda y: space.residuals(y - shift), x0 + shift,
                                 jac=lambda y: space.jacobian(y - shift), bounds=(lower + shift, upper + shift),
                                 method="trf", x_scale="jac", ftol=tol, xtol=tol, gtol=tol, max_nfev=max_evaluations)
    out.x = out.x - shift
    end = space.evaluate(out.x)  # from the best point's poses: out.x's own branch
    max_residual = float(np.max(space.solver.residual_norms(end.q, end.theta, problem.trials)))
    return SolverResult(solver="reduced", values=dict(zip(problem.free, problem.from_scaled(out.x), strict=True)),
                        q=end.q, objective=problem.map_objective(end.q, end.theta),
                        success=bool(out.status > 0 and end.ok), status=str(out.message), iterations=int(out.nfev),
                        evaluations=int(out.nfev), seconds=time.perf_counter() - t0, max_residual=max_residual)
