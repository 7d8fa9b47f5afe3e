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

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import optimize

from kneenlp.solvers.forward import forward_solver

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


@dataclass
class ReducedResult:
    """Free parameter values (SI), equilibrium poses (T x 5, SI), objective, success, counts."""

    values: dict[str, float]
    q: np.ndarray
    objective: float
    success: bool
    evaluations: int
    seconds: float
    message: str


def reduced_least_squares(problem: IdentificationProblem, start: dict[str, float], *, q0: np.ndarray | None = None,
                          max_evaluations: int = 60, tol: float | None = None, threads: int = 2) -> ReducedResult:
    """Minimise the problem's weighted residual sum over its free parameters from ``start`` (SI),
    with every trial at equilibrium (module docstring); ``q0`` warm-starts the first poses (SI,
    default the measured ones).  Parameters scaled by their scales; stops at relative cost change
    ``tol`` (default :func:`tolerance`) or after ``max_evaluations`` residual evaluations;
    ``threads`` of the trials' Newton."""
    tol = tolerance(problem.model) if tol is None else tol
    t0 = time.perf_counter()
    solver = forward_solver(problem.model)
    scales, tol_eq = problem.scales, problem.equilibrium_tol
    w = np.sqrt(problem.weights).ravel()
    trials = problem.trials
    free_index = [problem.model.index(n) for n in problem.free]
    # every trial is solved from the poses of the best point so far (trf's current iterate: its steps
    # only ever lower the cost), never from a rejected trial point: a knee can have two equilibria,
    # and a warm start from far away switched branches (objective 25 -> 3221 at the same parameters)
    state = {"best": (np.inf, np.asarray(problem.data.q if q0 is None else q0, float).copy(), None), "last": None,
             "slope": None}

    def evaluate(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        theta = problem.theta(problem.from_scaled(x))
        retries = None if state["best"][0] == np.inf else int(MAX_RETRIED_SHARE * len(trials))
        _, q_best, theta_best = state["best"]
        guess = None
        if state["slope"] is not None and theta_best is not None and np.array_equal(state["slope"][0], theta_best):
            # Newton from the first-order prediction of the poses at theta (the best point's dq/dp)
            step = np.array([theta[i] - theta_best[i] for i in free_index])  # SI
            guess = q_best + state["slope"][1] @ step
        q, res = solver.solve_batch(trials, theta, q_best, threads, max_retries=retries, theta0=theta_best, guess=guess)
        bad = np.flatnonzero(~(res <= tol_eq))
        if len(bad) and (retries is None or len(bad) <= retries):  # try from the forward solver's own start
            for i, sol in zip(bad, solver.solve([trials[i] for i in bad], theta), strict=True):
                if sol.converged:
                    q[i], res[i] = sol.q, sol.max_residual
        ok = bool(np.all(res <= tol_eq))
        r = np.concatenate([problem.residuals(q, theta).ravel() * w, prior_rows_of(x)])
        state["last"] = (x.copy(), q, theta, ok)
        return r, q, theta, ok

    def fun(x: np.ndarray) -> np.ndarray:
        r, q, theta, ok = evaluate(x)
        if ok and r @ r < state["best"][0]:
            state["best"] = (float(r @ r), q.copy(), theta)
        return r if ok else r + 1e3  # no equilibrium: a large residual turns the step back

    def jac(x: np.ndarray) -> np.ndarray:
        if state["last"] is None or not np.array_equal(x, state["last"][0]):
            fun(x)
        _, q, theta, _ = state["last"]
        dy_dp, dq_dp = problem.sensitivities(q, theta, with_poses=True)
        if state["best"][2] is not None and np.array_equal(theta, state["best"][2]):
            state["slope"] = (theta, dq_dp)
        return np.vstack([dy_dp * scales * w[:, None], prior_jacobian_of(x)])

    def prior_rows_of(x: np.ndarray) -> np.ndarray:  # the priors' rows (none without priors)
        return problem.prior_residuals(problem.from_scaled(x)) if problem.priors else np.zeros(0)

    def prior_jacobian_of(x: np.ndarray) -> np.ndarray:  # d rows / d x (scaled)
        if not problem.priors:
            return np.zeros((0, len(x)))
        return problem.prior_jacobian(dict(zip(problem.free, problem.from_scaled(x), strict=True))) * scales

    lower, upper = problem.scaled_bounds
    x0 = np.clip(problem.to_scaled(start), lower, upper)
    out = optimize.least_squares(fun, x0, jac=jac, bounds=(lower, upper),
                                 method="trf", x_scale="jac", ftol=tol, xtol=tol, gtol=tol, max_nfev=max_evaluations)
    _, q, theta, ok = evaluate(out.x)  # from the best point's poses: out.x's own branch
    values = dict(zip(problem.free, problem.from_scaled(out.x), strict=True))
    return ReducedResult(values, q, problem.map_objective(q, theta), bool(out.status > 0 and ok), int(out.nfev),
                         time.perf_counter() - t0, str(out.message))
