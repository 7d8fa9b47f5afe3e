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

import numpy as np

from kneenlp.conventions import coords_to_user
from kneenlp.experiment.measured import MeasuredData
from kneenlp.model.kneemodel import KneeModel
from kneenlp.solvers.boxcomplex import minimize_complex
from kneenlp.solvers.forward import ForwardSolver

PENALTY = 100.0
CONSTRAINT_TOL = 1e-3  # N or N m, the paper's FDK tolerance


class NestedObjective:
    """``Psi^T Psi`` + penalties as a function of the scaled free parameters."""

    def __init__(self, model: KneeModel, data: MeasuredData, free: list[str], weights: np.ndarray,
                 q_start: np.ndarray | None = None):
        self.model, self.data, self.free, self.weights = model, data, list(free), weights
        infos = [model.parameter_info[model.index(n)] for n in free]
        self.scales = np.array([i.scale for i in infos])
        self.is_stiffness = [n.endswith(".k") for n in free]
        self.solver = ForwardSolver(model)
        self.q_last = np.array(q_start) if q_start is not None else None
        self.trial_solves = 0

    def theta(self, x_scaled: np.ndarray) -> np.ndarray:
        return self.model.theta(dict(zip(self.free, np.asarray(x_scaled) * self.scales, strict=True)))

    def evaluate(self, x_scaled: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """(objective with penalties, poses T x 5 SI, residual per trial)."""
        theta = self.theta(x_scaled)
        trials = self.data.trials
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
        diff = coords_to_user(q) + self.model.bias_user(theta) - self.data.q_user
        psi = float(np.sum(self.weights * diff**2)) if np.all(np.isfinite(diff)) else np.inf
        penalty = PENALTY * float(np.sum(np.where(ok, 0.0, np.minimum(res, 1e6)) ** 2))
        for stiff, v in zip(self.is_stiffness, x_scaled, strict=True):
            if stiff and v < 0:
                penalty += PENALTY * v**2
        return psi + penalty, q, res

    def __call__(self, x_scaled: np.ndarray) -> float:
        return self.evaluate(x_scaled)[0]


def nested_fit(model: KneeModel, data: MeasuredData, free: list[str], weights: np.ndarray,
               initial: np.ndarray, *, seed: int = 0, max_evals: int = 20000, max_seconds: float | None = None,
               xtol: float = 1e-5, ftol: float = 1e-10) -> dict:
    """Run the Complex optimizer from the ``initial`` cloud (SI parameter values, k x n).

    Returns a dict with the best values (SI), poses, residuals, objective and counters."""
    infos = [model.parameter_info[model.index(n)] for n in free]
    scales = np.array([i.scale for i in infos])
    bounds = [(i.lower / i.scale, i.upper / i.scale) for i in infos]
    obj = NestedObjective(model, data, free, weights)
    t0 = time.perf_counter()
    obj.evaluate(initial[0] / scales)  # cold solve once; later evaluations warm-start
    result = minimize_complex(obj, bounds, initial=initial / scales, seed=seed, max_evals=max_evals,
                              max_seconds=max_seconds, xtol=xtol, ftol=ftol)
    seconds = time.perf_counter() - t0
    f, q, res = obj.evaluate(result.x)
    return {"values": result.x * scales, "q": q, "residual": res, "objective": f, "seconds": seconds,
            "result": result, "trial_solves": obj.trial_solves}
