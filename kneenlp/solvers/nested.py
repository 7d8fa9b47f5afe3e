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

Every evaluation's rootfinder starts from fixed reference equilibria, solved once: those at the
point of the Complex's first population nearest to the evaluated one, predicted to first order
(``dq/dp`` at the reference).  The objective is then a function of the parameters alone.  Starting
from the last evaluation's poses instead made it depend on the order of the evaluations before it:
a knee can have two equilibria, and which one Newton reached depended on where the previous point
had left it (Set 1, seed 1: objective 1.817766 and a parameter 12.9 % from the simultaneous
estimate, against 1.816239 and 0.001 % from a fixed start).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from kneenlp.base.keywords import keyword_options
from kneenlp.solvers.boxcomplex import minimize_complex
from kneenlp.solvers.forward import BatchStart, forward_solver
from kneenlp.solvers.result import SolverResult

if TYPE_CHECKING:
    from kneenlp.experiment.problem import IdentificationProblem

PENALTY = 100.0
#: N or N m: the paper's FDK tolerance, above which a trial's residual is penalised; looser than the
#: equilibrium tolerance of every other solver (:data:`~kneenlp.base.conventions.EQUILIBRIUM_TOL`) on purpose,
#: as in the paper (the fit's success is still judged at the equilibrium tolerance)
CONSTRAINT_TOL = 1e-3


@dataclass(frozen=True, eq=False)
class Reference:
    """A reference point of the nested objective: scaled free parameters ``x``, every parameter
    ``theta`` (SI), the trials' equilibria ``q`` (T x 5, SI) and their derivative ``dq_dp`` (T x 5 x
    n_free, SI; None where a trial has no equilibrium: no prediction from there)."""

    x: np.ndarray
    theta: np.ndarray
    q: np.ndarray
    dq_dp: np.ndarray | None


class NestedObjective:
    """``Psi^T Psi`` (the problem's objective, with its priors' share: the MAP objective) + penalties,
    a function of the scaled free parameters alone (module docstring).

    ``references`` (k x n_free, scaled; or one point): the points whose equilibria start the
    rootfinder, solved once here from the forward solver's cold start (default the problem's own
    values), or given as ``q_references`` (k x T x 5 or T x 5, SI).  Every evaluation starts Newton at
    the first-order prediction of its poses from the nearest reference (scaled distance), and
    trials that fail from there at that reference's equilibria."""

    def __init__(self, problem: IdentificationProblem, references: np.ndarray | None = None,
                 q_references: np.ndarray | None = None):
        self.problem = problem
        self.is_stiffness = [p.kind == "k" for p in problem.parameters]
        self.solver = forward_solver(problem.model)
        self.free_index = [problem.model.index(n) for n in problem.free]
        #: trial equilibria solved so far (a count; the objective does not depend on it)
        self.trial_solves = 0
        if references is None:
            references = problem.to_scaled(problem.values(problem.theta()))
        xs = np.atleast_2d(np.asarray(references, float))
        qs = None if q_references is None else np.asarray(q_references, float).reshape(len(xs), -1, 5)
        self.references = [self._reference(x, None if qs is None else qs[i]) for i, x in enumerate(xs)]

    def _reference(self, x: np.ndarray, q: np.ndarray | None) -> Reference:
        """The reference at ``x`` (scaled), its equilibria ``q`` (T x 5, SI) solved when not given."""
        theta, trials = self.theta_of_scaled(x), list(self.problem.trials)
        if q is None:
            sols = self.solver.solve(trials, theta)
            q = np.array([s.q for s in sols])
            self.trial_solves += len(sols)
        at_equilibrium = np.all(self.solver.residual_norms(q, theta, trials) <= self.problem.equilibrium_tol)
        dq_dp = self.problem.sensitivities(q, theta, with_poses=True)[1] if at_equilibrium else None
        return Reference(x.copy(), theta, q, dq_dp)

    def theta_of_scaled(self, x_scaled: np.ndarray) -> np.ndarray:
        """The full parameter vector (SI) of the scaled free parameters ``x_scaled``."""
        return self.problem.theta(self.problem.from_scaled(x_scaled))

    def start(self, x_scaled: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(the nearest reference's equilibria, the first-order prediction of the poses at ``theta``
        from them or None), both T x 5, SI: where the rootfinder starts at ``x_scaled``."""
        distances = [np.linalg.norm(np.asarray(x_scaled, float) - r.x) for r in self.references]
        ref = self.references[int(np.argmin(distances))]
        if ref.dq_dp is None:
            return ref.q, None
        step = np.array([theta[i] - ref.theta[i] for i in self.free_index])  # SI
        return ref.q, ref.q + ref.dq_dp @ step

    def evaluate(self, x_scaled: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """(objective with penalties, poses T x 5 SI, residual per trial, N or N m), every trial
        solved from :meth:`start`."""
        theta = self.theta_of_scaled(x_scaled)
        trials = list(self.problem.trials)
        q_ref, guess = self.start(x_scaled, theta)
        q, res = self.solver.solve_batch(trials, theta, BatchStart(q_ref, guess=guess))
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


@dataclass(frozen=True)
class NestedSettings:
    """The Complex search of :func:`nested_fit` (:func:`~kneenlp.solvers.boxcomplex.minimize_complex`'s
    options of the same names): its ``seed``, budgets ``max_evals`` (objective evaluations) and
    ``max_seconds`` (s, None: none), tolerances ``xtol`` (relative spread of the scaled parameters) and
    ``ftol`` (objective, mm^2 + deg^2)."""

    seed: int = 0
    max_evals: int = 20000
    max_seconds: float | None = None
    xtol: float = 1e-5
    ftol: float = 1e-10



def nested_fit(problem: IdentificationProblem, initial: np.ndarray, **options) -> SolverResult:
    """Run the Complex optimizer from the ``initial`` cloud (SI parameter values, k x n); every
    rootfinder starts from the equilibria of the nearest point of that cloud (:class:`NestedObjective`).
    ``options``: ``seed`` (0), ``max_evals`` (20000), ``max_seconds`` (None), ``xtol`` (1e-5) and ``ftol``
    (1e-10), as :class:`NestedSettings`.

    The result's objective is without penalties when every trial is in equilibrium; its
    evaluations are the Complex's objective evaluations, ``equilibrium_solves`` the trial
    equilibria solved, ``residuals`` the largest residual per trial (N or N m) at the best point."""
    settings = keyword_options(NestedSettings, "nested_fit", options)
    bounds = list(zip(*problem.scaled_bounds, strict=True))
    t0 = time.perf_counter()
    cloud = problem.to_scaled(initial)
    obj = NestedObjective(problem, cloud)
    result = minimize_complex(obj, bounds, initial=cloud, seed=settings.seed, max_evals=settings.max_evals,
                              max_seconds=settings.max_seconds, xtol=settings.xtol, ftol=settings.ftol)
    seconds = time.perf_counter() - t0
    f, q, res = obj.evaluate(result.x)
    return SolverResult(solver="complex", values=dict(zip(problem.free, problem.from_scaled(result.x), strict=True)),
                        q=q, objective=f, success=bool(result.success), status=str(result.message),
                        iterations=int(result.nit), evaluations=int(result.nfev), seconds=seconds,
                        max_residual=float(np.max(res)), equilibrium_solves=obj.trial_solves, residuals=res,
                        history=np.asarray(result.history, float).reshape(-1, 2))
