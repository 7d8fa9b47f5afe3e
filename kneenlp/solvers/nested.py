"""The nested identification, as in the paper: a Complex optimizer around per-trial rootfinders.

For given parameters every trial's equilibrium is solved with the forward rootfinder (the model's
one residual function; all trials in one mapped CasADi call, failures retried with load ramping),
and the objective is the same
``Psi^T Psi`` (mm^2 + deg^2, optionally weighted) as the simultaneous NLP.  Constraints by
penalty, as in the paper: a trial whose largest equilibrium residual exceeds 1e-3 N or N m, and a
negative stiffness (in units of 1e4 N), add their squared violation times 100.

The optimizer is :func:`kneenlp.solvers.boxcomplex.minimize_complex` over the scaled parameters
(k / 1e4 N, strains / 1 %) within the NLP's bounds; by default its 2n+1 points are scattered
like the paper's population (+-500 N, +-0.02 around the knee's parameter set).

Every evaluation's rootfinder starts at the same poses: the equilibria at a reference parameter
set (the Complex's first point), solved once.  The objective is then a function of the parameters
alone.  Starting from the last evaluation's poses instead made it depend on the order of the
evaluations before it: a knee can have two equilibria, and which one Newton reached depended on
where the previous point had left it.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from kneenlp.solvers.boxcomplex import minimize_complex
from kneenlp.solvers.forward import forward_solver
from kneenlp.solvers.result import SolverResult

if TYPE_CHECKING:
    from kneenlp.experiment.problem import IdentificationProblem

PENALTY = 100.0
#: N or N m: the paper's FDK tolerance, above which a trial's residual is penalised; looser than the
#: equilibrium tolerance of every other solver (:data:`~kneenlp.base.conventions.EQUILIBRIUM_TOL`) on purpose,
#: as in the paper (the fit's success is still judged at the equilibrium tolerance)
CONSTRAINT_TOL = 1e-3


class NestedObjective:
    """``Psi^T Psi`` (the problem's objective, with its priors' share: the MAP objective) + penalties,
    a function of the scaled free parameters alone (module docstring).

    ``reference``: the scaled free parameters whose equilibria start every evaluation's rootfinder
    (default the problem's own values); ``q_reference``: those equilibria (T x 5, SI) when known,
    else solved once here from the forward solver's cold start."""

    def __init__(self, problem: IdentificationProblem, reference: np.ndarray | None = None,
                 q_reference: np.ndarray | None = None):
        self.problem = problem
        self.is_stiffness = [p.kind == "k" for p in problem.parameters]
        self.solver = forward_solver(problem.model)
        #: trial equilibria solved so far (a count; the objective does not depend on it)
        self.trial_solves = 0
        if reference is None:
            reference = problem.to_scaled(problem.values(problem.theta()))
        if q_reference is None:
            sols = self.solver.solve(list(problem.trials), self.theta(reference))
            q_reference = np.array([s.q for s in sols])
            self.trial_solves += len(sols)
        self.q_reference = np.array(q_reference, float)

    def theta(self, x_scaled: np.ndarray) -> np.ndarray:
        return self.problem.theta(self.problem.from_scaled(x_scaled))

    def evaluate(self, x_scaled: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """(objective with penalties, poses T x 5 SI, residual per trial, N or N m), every trial
        solved from :attr:`q_reference`."""
        theta = self.theta(x_scaled)
        trials = list(self.problem.trials)
        q, res = self.solver.solve_batch(trials, theta, self.q_reference)
        self.trial_solves += len(trials)
        ok = res <= CONSTRAINT_TOL
        psi = self.problem.map_objective(q, theta)
        penalty = PENALTY * float(np.sum(np.where(ok, 0.0, np.minimum(res, 1e6)) ** 2))
        for stiff, v in zip(self.is_stiffness, x_scaled, strict=True):
            if stiff and v < 0:
                penalty += PENALTY * v**2
        return psi + penalty, q, res

    def __call__(self, x_scaled: np.ndarray) -> float:
        return self.evaluate(x_scaled)[0]


def nested_fit(problem: IdentificationProblem, initial: np.ndarray, *, seed: int = 0, max_evals: int = 20000,
               max_seconds: float | None = None, xtol: float = 1e-5, ftol: float = 1e-10) -> SolverResult:
    """Run the Complex optimizer from the ``initial`` cloud (SI parameter values, k x n); every
    rootfinder starts at the equilibria of its first point.

    The result's objective is without penalties when every trial is in equilibrium; its
    evaluations are the Complex's objective evaluations, ``equilibrium_solves`` the trial
    equilibria solved, ``residuals`` the largest residual per trial (N or N m) at the best point."""
    bounds = list(zip(*problem.scaled_bounds, strict=True))
    t0 = time.perf_counter()
    cloud = problem.to_scaled(initial)
    obj = NestedObjective(problem, cloud[0])
    result = minimize_complex(obj, bounds, initial=cloud, seed=seed, max_evals=max_evals,
                              max_seconds=max_seconds, xtol=xtol, ftol=ftol)
    seconds = time.perf_counter() - t0
    f, q, res = obj.evaluate(result.x)
    return SolverResult(solver="complex", values=dict(zip(problem.free, problem.from_scaled(result.x), strict=True)),
                        q=q, objective=f, success=bool(result.success), status=str(result.message),
                        iterations=int(result.nit), evaluations=int(result.nfev), seconds=seconds,
                        max_residual=float(np.max(res)), equilibrium_solves=obj.trial_solves, residuals=res,
                        history=np.asarray(result.history, float).reshape(-1, 2))
