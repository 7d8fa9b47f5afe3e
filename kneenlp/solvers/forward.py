"""Forward laxity simulation: solve each trial's static equilibrium with a CasADi rootfinder.

Strategy per trial (all with the model's one residual function):

1. Newton (CasADi ``newton`` rootfinder with line search) from a warm start: the solution of the
   previous trial at the same flexion, else the no-load pose at that flexion, else the cold start
   (tibia 0.3 mm proximal of the reference pose, i.e. slightly penetrated, so that contact has
   stiffness from the first iteration);
2. if that fails, load ramping (homotopy): the load is applied in fractions 1/4, 1/2, 3/4, 1 from
   the no-load pose, each step warm-started from the last, with steps halved on failure;
3. a trial is *converged* only if the largest generalised force at the returned pose is below
   ``tol`` (default 1e-6 N / N m; the paper's 1e-3 is the ceiling) AND the pose lies in the
   physiological envelope (:data:`ENVELOPE`: |varus| <= 30 deg, |internal| <= 60 deg,
   |translation| <= 25 mm, some cartilage contact).  An "equilibrium" outside it (e.g. a 100 kN
   drawer force "balanced" by a dislocated tibia) is reported as not converged.  Trials that fail
   are reported with their residual and the reason, never silently kept as converged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from kneenlp.conventions import POSE_ENVELOPE_USER, TO_USER
from kneenlp.experiment.protocol import Trial
from kneenlp.model.elements import StagedElement
from kneenlp.model.kneemodel import KneeModel

COLD_START = np.array([0.0, 0.0, 0.0, 0.0, 0.3e-3])  # rad, m: slightly penetrated
#: Largest |coordinate| of a plausible knee pose (rad, rad, m, m, m).
ENVELOPE = POSE_ENVELOPE_USER / TO_USER


@dataclass
class TrialSolution:
    """Equilibrium of one trial (SI: rad, m, N)."""

    trial: Trial
    q: np.ndarray
    converged: bool
    max_residual: float  # N or N m
    strategy: str  # "newton", "ramp" or "failed"
    reason: str = ""  # why a trial did not converge
    #: every force element's outputs at the pose, by table column (SI: strain as a fraction, N, m)
    outputs: dict[str, float] = field(default_factory=dict)


class ForwardSolver:
    """Per-trial equilibrium solver for one model; the rootfinder is built once."""

    def __init__(self, model: KneeModel, tol: float = 1e-6, max_iter: int = 50):
        self.model = model
        self.tol = tol
        q = ca.MX.sym("q", 5)
        n = len(model.parameter_names)
        par = ca.MX.sym("par", n + 7 + model.ws_size)
        r = model.residual(q, par[:n], par[n : n + 6], par[n + 6], par[n + 7 :])
        g = ca.Function("equilibrium", [q, par], [r])
        opts = {"abstol": min(tol * 1e-3, 1e-9), "abstolStep": 1e-16, "max_iter": max_iter,
                "error_on_fail": False, "line_search": True}
        self.rootfinder = ca.rootfinder("forward", "newton", g, opts)
        self.eval_residual = g
        self._batch: dict[int, tuple[ca.Function, ca.Function]] = {}
        self._contact_columns = [o.column for e, o in model.outputs
                                 if isinstance(e, StagedElement) and o.name == "force"]

    def solve_batch(self, trials, theta: np.ndarray, q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Newton on all trials in one mapped CasADi call (fast path for repeated solves).

        Returns poses (T x 5, SI) and each trial's largest residual; trials above ``tol`` are
        retried one by one with :meth:`solve_trial` (load ramping) before being returned.
        """
        n = len(trials)
        fns = self._batch.get(n)
        if fns is None:
            fns = (self.rootfinder.map(n), self.eval_residual.map(n))
            self._batch[n] = fns
        q0 = np.asarray(q0, dtype=float)
        par = np.column_stack([self._par(theta, t.load, t.flexion, q0[i]) for i, t in enumerate(trials)])
        q = np.asarray(fns[0](q0.T, par)).T
        if self.model.ws_size:  # the residual with the working sets of the solution
            par = np.column_stack([self._par(theta, t.load, t.flexion, q[i]) for i, t in enumerate(trials)])
        res = np.max(np.abs(np.asarray(fns[1](q.T, par))), axis=0)
        res[~np.isfinite(res)] = np.inf
        for i in np.flatnonzero(~(res <= self.tol)):
            sol = self.solve_trial(trials[i], theta, q0[i], None)
            if sol.max_residual < res[i]:
                q[i], res[i] = sol.q, sol.max_residual
        return q, res

    def _par(self, theta: np.ndarray, load: np.ndarray, flexion: float, q_ws: np.ndarray | None = None) -> np.ndarray:
        """Rootfinder parameters; the contact working sets are those of pose ``q_ws``."""
        ws = self.model.working_set(q_ws, theta, flexion)[1] if self.model.ws_size else np.zeros(0)
        return np.concatenate([theta, load, [flexion], ws])

    def residual_norm(self, q: np.ndarray, theta: np.ndarray, trial: Trial, scale: float = 1.0) -> float:
        """Largest residual at pose ``q`` (N or N m), with the working sets of ``q`` itself; inf if
        a sample point outside them penetrates (the working sets are then too small)."""
        if self.model.ws_size:
            idx, _ = self.model.working_set(q, theta, trial.flexion)
            if self.model.left_out_penetration(q, theta, trial.flexion, idx) > 0:
                return np.inf
        r = self.eval_residual(q, self._par(theta, scale * trial.load, trial.flexion, q))
        val = float(np.max(np.abs(np.asarray(r))))
        return val if np.isfinite(val) else np.inf

    def _newton(self, q0: np.ndarray, theta: np.ndarray, trial: Trial, scale: float = 1.0):
        """Newton from ``q0`` with the working sets of ``q0``; while a point left out of them
        penetrates at the solution, again from the solution with its own working sets."""
        q_ws = q0
        for _ in range(4):
            q = np.asarray(self.rootfinder(q0, self._par(theta, scale * trial.load, trial.flexion, q_ws))).ravel()
            if not np.all(np.isfinite(q)):
                return q, np.inf
            if not self.model.ws_size:
                break
            idx, _ = self.model.working_set(q_ws, theta, trial.flexion)
            if self.model.left_out_penetration(q, theta, trial.flexion, idx) <= 0:
                break
            q0 = q_ws = q
        return q, self.residual_norm(q, theta, trial, scale)

    def solve_trial(self, trial: Trial, theta: np.ndarray, q0: np.ndarray | None = None,
                    q_unloaded: np.ndarray | None = None) -> TrialSolution:
        """Equilibrium of one trial at parameters ``theta`` (SI), warm-started from ``q0``."""
        start = COLD_START if q0 is None else q0
        q, res = self._newton(start, theta, trial)
        strategy = "newton"
        if not res <= self.tol:
            q, res = self._ramp(trial, theta, COLD_START if q_unloaded is None else q_unloaded)
            strategy = "ramp"
        sol = self._solution(trial, theta, q, bool(res <= self.tol), res, strategy)
        if not sol.converged:
            sol.strategy, sol.reason = "failed", f"residual {res:.3g} > tolerance {self.tol:g}"
        elif np.any(np.abs(q) > ENVELOPE) or not any(sol.outputs[c] > 0 for c in self._contact_columns):
            sol.converged, sol.strategy = False, "failed"
            sol.reason = "equilibrium found only at an implausible (dislocated) pose"
        return sol

    def _ramp(self, trial: Trial, theta: np.ndarray, q_start: np.ndarray, min_step: float = 1 / 64):
        q, res = self._newton(q_start, theta, trial, 0.0)
        if not res <= self.tol:
            return q, res
        done, step = 0.0, 0.25
        while done < 1.0:
            target = min(1.0, done + step)
            q_try, res = self._newton(q, theta, trial, target)
            if res <= self.tol:
                q, done = q_try, target
                step = min(2 * step, 0.5)
            else:
                step /= 2
                if step < min_step:
                    return q_try, self.residual_norm(q_try, theta, trial)
        return q, res

    def _solution(self, trial, theta, q, converged, res, strategy) -> TrialSolution:
        ws = self.model.working_set(q, theta, trial.flexion)[1]
        values = np.asarray(self.model.details(q, theta, trial.load, trial.flexion, ws)[1]).ravel()
        columns = [o.column for _, o in self.model.outputs]
        return TrialSolution(trial, q, converged, res, strategy, outputs=dict(zip(columns, values, strict=True)))

    def solve(self, trials: list[Trial] | tuple[Trial, ...], theta: np.ndarray,
              q_start: dict[str, np.ndarray] | None = None) -> list[TrialSolution]:
        """Solve all ``trials``; no-load trials first so that loaded ones warm-start from them.

        ``q_start`` optionally maps trial ids to starting poses (e.g. a previous solution).
        """
        q_start = q_start or {}
        unloaded: dict[float, np.ndarray] = {}
        last: dict[float, np.ndarray] = {}
        order = sorted(range(len(trials)), key=lambda i: (not _is_unloaded(trials[i]), i))
        out: dict[int, TrialSolution] = {}
        for i in order:
            t = trials[i]
            key = round(t.flexion_deg, 9)
            q0 = q_start.get(t.id, last.get(key, unloaded.get(key)))
            if key not in unloaded and not _is_unloaded(t):
                sol0 = self.solve_trial(_unloaded(t), theta, q0)
                if sol0.converged:
                    unloaded[key] = sol0.q
                    q0 = q_start.get(t.id, sol0.q)
            sol = self.solve_trial(t, theta, q0, unloaded.get(key))
            if sol.converged:
                last[key] = sol.q
                if _is_unloaded(t):
                    unloaded[key] = sol.q
            out[i] = sol
        return [out[i] for i in range(len(trials))]


def _is_unloaded(t: Trial) -> bool:
    return not any(v != 0 for v in t.loads.values())


def _unloaded(t: Trial) -> Trial:
    return Trial(f"none_flex{t.flexion_deg:g}", t.flexion_deg, {}, "none", 0.0)


def forward_solver(model: KneeModel, tol: float = 1e-6) -> ForwardSolver:
    """The model's forward solver for ``tol``, built once per model (kept in ``model.solvers``)."""
    key = ("forward", tol)
    if key not in model.solvers:
        model.solvers[key] = ForwardSolver(model, tol=tol)
    return model.solvers[key]
