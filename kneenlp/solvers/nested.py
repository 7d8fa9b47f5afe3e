"""The nested identification, as in the paper: a Complex optimizer around per-trial rootfinders.

For given parameters every trial's equilibrium is solved with the forward rootfinder (the model's
one residual function; warm-started from the previous evaluation's poses, all trials in one
mapped CasADi call, failures retried with load ramping), and the objective is the same
``Psi^T Psi`` (mm^2 + deg^2, optionally weighted) as the simultaneous NLP.  Constraints by
penalty, as in the paper: a trial whose largest equilibrium residual exceeds 1e-3 N or N m, and a
negative stiffness (in units of 1e4 N), add their squared violation times 100.

The optimizer is :func:`kneenlp.solvers.boxcomplex.minimize_complex` over the scaled parameters
(k / 1e4 N, strains / 1 %) within the NLP's bounds; by default its 2n+1 points are scattered
like the paper's population (+-500 N, +-0.02 around the knee's parameter set).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from kneenlp.solvers.boxcomplex import minimize_complex
from kneenlp.solvers.forward import forward_solver

if TYPE_CHECKING:
    from kneenlp.experiment.problem import IdentificationProblem

PENALTY = 100.0
#: N or N m: the paper's FDK tolerance, above which a trial's residual is penalised; looser than the
#: equilibrium tolerance of every other solver (:data:`~kneenlp.base.conventions.EQUILIBRIUM_TOL`) on purpose,
#: as in the paper (the fit's success is still judged at the equilibrium tolerance)
CONSTRAINT_TOL = 1e-3


class NestedObjective:
    """``Psi^T Psi`` (the problem's objective, with its priors' share: the MAP objective) + penalties,
    a function of the scaled free parameters."""

    def __init__(self, problem: IdentificationProblem, q_start: np.ndarray | None = None):
        self.problem = problem
        self.is_stiffness = [p.kind == "k" for p in problem.parameters]
        self.solver = forward_solver(problem.model)
        self.q_last = np.array(q_start) if q_start is not None else None
        self.trial_solves = 0

    def theta(self, x_scaled: np.ndarray) -> np.ndarray:
        return self.problem.theta(self.problem.from_scaled(x_scaled))

    def evaluate(self, x_scaled: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """(objective with penalties, poses T x 5 SI, residual per trial)."""
        theta = self.theta(x_scaled)
        trials = list(self.problem.trials)
        if self.q_last is None:
            sols = self.solver.solve(trials, theta)
            q = np.array([s.q for s in sols])
            res = np.array([s.max_residual for s in sols])
        else:
            q, res = self.solver.solve_batch(trials, theta, self.q_last)
        self.trial_solves += len(trials)
        ok = res <= CONSTRAINT_TOL
        if ok.all():
            self.q_last = q
        psi = self.problem.map_objective(q, theta)
        penalty = PENALTY * float(np.sum(np.where(ok, 0.0, np.minimum(res, 1e6)) ** 2))
        for stiff, v in zip(self.is_stiffness, x_scaled, strict=True):
            if stiff and v < 0:
                penalty += PENALTY * v**2
        return psi + penalty, q, res

    def __call__(self, x_scaled: np.ndarray) -> float:
        return self.evaluate(x_scaled)[0]


def nested_fit(problem: IdentificationProblem, initial: np.ndarray, *, seed: int = 0, max_evals: int = 20000,
               max_seconds: float | None = None, xtol: float = 1e-5, ftol: float = 1e-10) -> dict:
    """Run the Complex optimizer from the ``initial`` cloud (SI parameter values, k x n).

    Returns a dict with the best values (SI), poses, residuals, objective (without penalties when
    every trial is in equilibrium) and counters."""
    bounds = list(zip(*problem.scaled_bounds, strict=True))
    obj = NestedObjective(problem)
    t0 = time.perf_counter()
    cloud = problem.to_scaled(initial)
    obj.evaluate(cloud[0])  # cold solve once; later evaluations warm-start
    result = minimize_complex(obj, bounds, initial=cloud, seed=seed, max_evals=max_evals,
                              max_seconds=max_seconds, xtol=xtol, ftol=ftol)
    seconds = time.perf_counter() - t0
    f, q, res = obj.evaluate(result.x)
    return {"values": problem.from_scaled(result.x), "q": q, "residual": res, "objective": f, "seconds": seconds,
            "result": result, "trial_solves": obj.trial_solves}
