"""Forward laxity simulation: solve each trial's static equilibrium.

Strategy per trial (all with the model's one residual function):

1. Newton (:mod:`kneenlp.solvers.newton`: damped, affine-invariant step control, the contact
   working sets retaken at every iterate) from a warm start: the solution of the
   previous trial at the same flexion, else the no-load pose at that flexion, else the cold start
   (tibia 0.3 mm proximal of the reference pose, i.e. slightly penetrated, so that contact has
   stiffness from the first iteration);
2. if that fails, load ramping (homotopy): the load is applied in fractions 1/4, 1/2, 3/4, 1 from
   the no-load pose, each step warm-started from the last, with steps halved on failure;
3. if that fails too, at parameters other than the knee's own: the trial solved at the knee's own
   parameter set and followed from there to the parameters asked for (parameter homotopy,
   :meth:`ForwardSolver.continue_parameters`; strategy ``continuation``): a load path can pass a
   fold that no load ramp crosses while the equilibrium at the end exists;
4. a trial is *converged* only if the largest generalised force at the returned pose is below
   ``tol`` (default :data:`~kneenlp.base.conventions.EQUILIBRIUM_TOL`, 1e-6 N / N m; the paper's 1e-3 is
   the ceiling) AND the pose lies in the
   physiological envelope (:data:`ENVELOPE`: |varus| <= 30 deg, |internal| <= 60 deg,
   |translation| <= 25 mm, some cartilage contact).  An "equilibrium" outside it (e.g. a 100 kN
   drawer force "balanced" by a dislocated tibia) is reported as not converged.  Trials that fail
   are reported with their residual and the reason, never silently kept as converged.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from kneenlp.base.conventions import EQUILIBRIUM_TOL, POSE_ENVELOPE_USER, coords_from_user, coords_to_user
from kneenlp.base.modes import SolveStrategy
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.protocol import Trial
from kneenlp.model.elements import StagedElement
from kneenlp.model.mesh_contact import RIM_SHARE
from kneenlp.solvers.newton import EquilibriumNewton

if TYPE_CHECKING:
    from kneenlp.experiment.problem import IdentificationProblem

COLD_START = np.array([0.0, 0.0, 0.0, 0.0, 0.3e-3])  # rad, m from the reference pose: slightly penetrated
#: Flexion step (deg) of the passive path from a knee's reference pose (:meth:`ForwardSolver.cold_start`).
PASSIVE_STEP_DEG = 10.0
#: Single-trial Newton solves a forward solver remembers (:meth:`ForwardSolver._newton`): a fit's
#: retries ask for the same solve again (S192803 calibration: 2211 solves, 1478 distinct, 3.5 s of 9.8 s).
NEWTON_MEMORY = 4096
#: Largest |coordinate| of a plausible knee pose from the knee's reference pose (rad, rad, m, m, m).
ENVELOPE = coords_from_user(POSE_ENVELOPE_USER)


@dataclass
class TrialSolution:
    """Equilibrium of one trial (SI: rad, m, N)."""

    trial: Trial
    q: np.ndarray
    converged: bool
    max_residual: float  # N or N m
    strategy: SolveStrategy
    reason: str = ""  # why a trial did not converge
    #: every force element's outputs at the pose, by table column (SI: strain as a fraction, N, m)
    outputs: dict[str, float] = field(default_factory=dict)
    #: the equilibrium is stable by :func:`unstable_equilibria` (a converged trial may be an unstable
    #: one: Newton converges to any root; :meth:`ForwardSolver.solve` checks, predict says so)
    stable: bool = True


class ForwardSolver:
    """Per-trial equilibrium solver for one model; the rootfinder is built once."""

    def __init__(self, model: KneeModel, tol: float = EQUILIBRIUM_TOL, max_iter: int = 60):
        self.model = model
        #: the knee's reference pose: where cold starts begin and the envelope is centred (rad, m)
        self.reference = np.asarray(model.knee.reference_pose[1], float)
        self.tol = tol
        self.max_iter = max_iter
        self.newton = EquilibriumNewton(model)
        self._contact_columns = [o.column for e, o in model.outputs
                                 if isinstance(e, StagedElement) and o.name == "force"]
        #: the passive path of :meth:`cold_start` at the last parameters: (theta's bytes, {flexion: pose})
        self._passive: tuple[bytes | None, dict[float, np.ndarray]] = (None, {})
        #: the last :data:`NEWTON_MEMORY` single-trial Newton solves: inputs' bytes -> (pose, residual)
        self._solved: dict[bytes, tuple[np.ndarray, float]] = {}
        self._solved_lock = threading.Lock()

    def cold_start(self, flexion: float, theta: np.ndarray) -> np.ndarray:
        """Where a trial without a warm start begins (rad, m): 0.3 mm proximal of the reference
        pose (slightly penetrated); for a knee imaged at another pose than its frames' coincidence
        ([reference_pose]) the unloaded equilibrium at ``flexion`` reached from the reference pose
        through the flexions ``f_ref +- k`` :data:`PASSIVE_STEP_DEG` before it, one Newton solve
        each (the GS translations of such a knee change by millimetres with flexion), or where that
        walk stopped.  The walk of the last parameters is remembered (a fit's trials at several
        flexions walk it once); every pose on it is computed from the one before on the same grid,
        so the result does not depend on which flexions were asked for before."""
        f_ref, reference = self.model.reference_coordinates(theta)
        q = reference + COLD_START
        if not np.any(reference) and f_ref == 0.0:
            return q
        key = np.asarray(theta, float).tobytes()
        if self._passive[0] != key:
            self._passive = (key, {})
        path = self._passive[1]
        if flexion in path:
            return path[flexion].copy()
        step, side = np.radians(PASSIVE_STEP_DEG), np.sign(flexion - f_ref)
        grid = [f_ref + side * k * step for k in range(1, int(np.ceil(abs(flexion - f_ref) / step)))]
        for f in [*grid, flexion]:
            if f in path:
                q = path[f]
                continue
            q_new, res = self._newton(q, theta, Trial("passive", float(np.degrees(f)), {}))
            if not res <= self.tol:
                return q.copy()
            q = path[f] = q_new
        return q.copy()

    def solve_batch(self, trials, theta: np.ndarray, q0: np.ndarray, threads: int = 2,
                    max_retries: int | None = None, theta0: np.ndarray | None = None,
                    guess: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Newton on all trials at once (one mapped CasADi call per iteration over ``threads``
        threads; the fast path for repeated solves).

        Returns poses (T x 5, SI) and each trial's largest residual; trials above ``tol`` are
        retried before being returned, unless more than ``max_retries`` failed (then they are
        returned as they are: a caller probing a step, such as a trust-region method, learns
        cheaply that it went too far).  The retries, one by one: following the parameters from
        ``theta0`` to ``theta`` (:meth:`continue_parameters`) when ``q0`` are equilibria at
        ``theta0`` (an outer fit's previous iterate: the same branch of equilibria, a few close
        Newton solves), then ramping the load from the cold start.  Without ``theta0`` they are
        first tried all at once from the equilibrium of the converged trial nearest in load at the
        same flexion (the forward solver's own warm start; a measured pose a few tenths of a
        millimetre into stiff cartilage can defeat Newton).  ``guess`` (T x 5, SI): where Newton
        starts instead of ``q0`` (a prediction of the poses at ``theta``); the trials it fails are
        started again from ``q0`` first.
        """
        q0 = np.asarray(q0, dtype=float)
        loads, flexions = np.array([t.load for t in trials]), np.array([t.flexion for t in trials])
        q, res = self._batch(q0 if guess is None else np.asarray(guess, float), theta, loads, flexions, threads)

        def again(failed: np.ndarray, starts: np.ndarray) -> np.ndarray:
            """Newton on the ``failed`` trials from ``starts``, kept where better; those still failing."""
            q_f, res_f = self._batch(starts, theta, loads[failed], flexions[failed], threads)
            better = res_f < res[failed]
            q[failed[better]], res[failed[better]] = q_f[better], res_f[better]
            return np.flatnonzero(~(res <= self.tol))

        failed = np.flatnonzero(~(res <= self.tol))
        if guess is not None and len(failed):
            failed = again(failed, q0[failed])
        retry = max_retries is None or len(failed) <= max_retries
        near = _nearest_converged(loads, flexions, res <= self.tol, failed) if retry and theta0 is None else None
        if near is not None:
            failed = again(failed, q[near])
        for i in failed if retry else ():
            q_i, res_i = q0[i], np.inf
            if theta0 is not None:
                q_i, res_i = self.continue_parameters(trials[i], theta0, theta, q0[i])
            if not res_i <= self.tol:  # Newton from q0[i] is what the batch just did: ramp the load
                q_i, res_i = self._ramp(trials[i], theta, self.cold_start(trials[i].flexion, theta))
            if res_i < res[i]:
                q[i], res[i] = q_i, res_i
        return q, res

    def _batch(self, q0: np.ndarray, theta: np.ndarray, loads: np.ndarray, flexions: np.ndarray,
               threads: int) -> tuple[np.ndarray, np.ndarray]:
        """Newton on the trials of ``loads`` (T x LOAD_SIZE) at ``flexions`` (T, rad) from ``q0``:
        poses and residuals, inf where a contact point their working sets leave out penetrates."""
        out = self.newton.solve(q0, theta, loads, flexions, self.tol, self.max_iter, threads)
        res = out.residual
        if self.model.ws_size:
            res = np.where(self.model.left_out_batch(out.q, theta, flexions, threads) > 0, np.inf, res)
        return out.q, res

    def continue_parameters(self, trial: Trial, theta0: np.ndarray, theta: np.ndarray, q0: np.ndarray,
                            min_step: float = 1 / 16) -> tuple[np.ndarray, float]:
        """Equilibrium of ``trial`` at ``theta`` followed from ``q0``, its equilibrium at ``theta0``
        (SI), through parameters ``theta0 + s (theta - theta0)`` (:meth:`_follow`, steps of at most
        1/2 down to ``min_step``): the pose and its residual at ``theta``."""
        return self._follow(lambda s, q: self._newton(q, theta0 + s * (theta - theta0), trial),
                            np.asarray(q0, float), 0.5, min_step, theta, trial)

    def _follow(self, newton_at, q: np.ndarray, step: float, min_step: float, theta: np.ndarray,
                trial: Trial) -> tuple[np.ndarray, float]:
        """A homotopy from s = 0 (``q`` solves it) to s = 1: ``newton_at(s, q)`` (pose, residual) from
        the last solved pose, the step doubled after a success (at most 1/2), halved after a failure;
        below ``min_step`` it stops with the last try and its residual for ``trial`` at ``theta``."""
        done, res = 0.0, np.inf
        while done < 1.0:
            target = min(1.0, done + step)
            q_try, res = newton_at(target, q)
            if res <= self.tol:
                q, done = q_try, target
                step = min(2 * step, 0.5)
            else:
                step /= 2
                if step < min_step:
                    return q_try, self.residual_norm(q_try, theta, trial)
        return q, res

    def residual_norm(self, q: np.ndarray, theta: np.ndarray, trial: Trial) -> float:
        """Largest equilibrium residual at pose ``q`` (N or N m), with the working sets of ``q``
        itself; inf if a contact point left out of them penetrates (too few working-set slots, or
        contact outside the represented femoral surface)."""
        return float(self.residual_norms(np.asarray(q, float)[None], theta, [trial], threads=1)[0])

    def residual_norms(self, q: np.ndarray, theta: np.ndarray, trials, threads: int = 2) -> np.ndarray:
        """:meth:`residual_norm` of every trial of ``trials`` at its pose ``q`` (T x 5, SI), all at once."""
        q = np.asarray(q, float).reshape(-1, 5)
        flexions = np.array([t.flexion for t in trials])
        finite = np.all(np.isfinite(q), axis=1)
        q_eval = np.where(finite[:, None], q, self.reference)
        r = self.newton.evaluate(q_eval, theta, np.array([t.load for t in trials]), flexions, threads)[0]
        out = np.max(np.abs(r), axis=1)
        if self.model.ws_size:
            out = np.where(self.model.left_out_batch(q_eval, theta, flexions, threads) > 0, np.inf, out)
        return np.where(finite & np.isfinite(out), out, np.inf)

    def _newton(self, q0: np.ndarray, theta: np.ndarray, trial: Trial, scale: float = 1.0):
        """Newton from ``q0``: the pose and its residual (:meth:`residual_norm`).  A deterministic
        function of its inputs, so a solve asked for again (a retry repeating a ramp, a cold start's
        step) or solved ahead in a batch (:meth:`_newton_batch`) is answered from the last
        :data:`NEWTON_MEMORY` solves, to the bit what it would compute."""
        return self._newton_batch(np.asarray(q0, float)[None, :], theta, [trial], scale)[0]

    def _newton_batch(self, q0: np.ndarray, theta: np.ndarray, trials: list[Trial],
                      scale: float = 1.0) -> list[tuple[np.ndarray, float]]:
        """:meth:`_newton` of every trial of ``trials`` from its row of ``q0`` (T x 5, SI): those not
        remembered in one batched Newton (each trial's iteration is its own, so the numbers are those
        of one solve at a time), remembered."""
        theta = np.ascontiguousarray(theta, dtype=float)
        q0 = np.ascontiguousarray(q0, dtype=float).reshape(-1, 5)
        loads = np.array([scale * t.load for t in trials], float).reshape(len(trials), -1)
        flexions = np.array([t.flexion for t in trials], float)
        keys = [b"".join((q.tobytes(), theta.tobytes(), load.tobytes(), f.tobytes()))
                for q, load, f in zip(q0, loads, flexions, strict=True)]
        with self._solved_lock:
            known = [self._solved.get(k) for k in keys]
        todo = [i for i, k in enumerate(known) if k is None]
        if todo:
            out = self.newton.solve(q0[todo], theta, loads[todo], flexions[todo], self.tol, self.max_iter)
            res = out.residual.copy()
            ok = np.flatnonzero(res <= self.tol)
            if self.model.ws_size and len(ok):  # the pose's working sets left a penetrating point out
                res[ok[self.model.left_out_batch(out.q[ok], theta, flexions[todo][ok]) > 0]] = np.inf
            with self._solved_lock:
                for j, i in enumerate(todo):
                    while self._solved and len(self._solved) >= NEWTON_MEMORY:
                        del self._solved[next(iter(self._solved))]  # the oldest
                    known[i] = self._solved[keys[i]] = (out.q[j].copy(), float(res[j]))
        return [(q.copy(), res) for q, res in known]

    def solve_trial(self, trial: Trial, theta: np.ndarray, q0: np.ndarray | None = None,
                    q_unloaded: np.ndarray | None = None) -> TrialSolution:
        """Equilibrium of one trial at parameters ``theta`` (SI), warm-started from ``q0``."""
        start = self.cold_start(trial.flexion, theta) if q0 is None else q0
        q, res = self._newton(start, theta, trial)
        strategy = "newton"
        if not res <= self.tol:
            start = self.cold_start(trial.flexion, theta) if q_unloaded is None else q_unloaded
            q, res = self._ramp(trial, theta, start)
            strategy = "ramp"
        if not res <= self.tol and not np.array_equal(own := self.model.source_theta(), theta):
            # the equilibrium at the knee file's own parameters, followed to theta: a calibrated S192803 knee
            # had equilibria for held-out trials that no load ramp reached (a fold on the load path); read
            # back from its file, the calibrated set replaces the knee's own, hence its source's
            at_own = self.solve_trial(trial, own)
            if at_own.converged:
                q_c, res_c = self.continue_parameters(trial, own, theta, at_own.q, min_step=1 / 64)
                if res_c < res:
                    q, res, strategy = q_c, res_c, "continuation"
        sol = self._solution(trial, theta, q, bool(res <= self.tol), res, strategy)
        if not sol.converged:
            sol.strategy, sol.reason = "failed", f"residual {res:.3g} > tolerance {self.tol:g}"
        elif np.any(np.abs(q - self.reference) > ENVELOPE) or not any(sol.outputs[c] > 0
                                                                        for c in self._contact_columns):
            sol.converged, sol.strategy = False, "failed"
            sol.reason = "equilibrium found only at an implausible (dislocated) pose"
        elif (rim := self.model.rim_share(q, theta, trial.flexion)) > RIM_SHARE:
            sol.converged, sol.strategy = False, "failed"
            sol.reason = rim_reason(rim)
        return sol

    def _ramp(self, trial: Trial, theta: np.ndarray, q_start: np.ndarray, min_step: float = 1 / 64):
        q, res = self._newton(q_start, theta, trial, 0.0)
        if not res <= self.tol:
            return q, res
        return self._follow(lambda s, q: self._newton(q, theta, trial, s), q, 0.25, min_step, theta, trial)

    def _solution(self, trial, theta, q, converged, res, strategy) -> TrialSolution:
        ws = self.model.working_data(q, theta, trial.flexion, order=0)
        values = np.asarray(self.model.details(q, theta, trial.load, trial.flexion, ws)[1]).ravel()
        columns = [o.column for _, o in self.model.outputs]
        return TrialSolution(trial, q, converged, res, strategy, outputs=dict(zip(columns, values, strict=True)))

    def solve(self, trials: list[Trial] | tuple[Trial, ...], theta: np.ndarray,
              q_start: dict[str, np.ndarray] | None = None) -> list[TrialSolution]:
        """Solve all ``trials``; no-load trials first so that loaded ones warm-start from them.

        ``q_start`` optionally maps trial ids to starting poses (e.g. a previous solution).  A trial
        warm-starts from the trials before it at its flexion alone, so the trials go in waves (the
        first of every flexion, then the second, ...), each wave's first Newton solves in one batch
        (:meth:`_newton_batch`); the result is that of solving them one at a time.
        """
        q_start = q_start or {}
        unloaded: dict[float, np.ndarray] = {}
        last: dict[float, np.ndarray] = {}
        order = sorted(range(len(trials)), key=lambda i: (not _is_unloaded(trials[i]), i))
        out: dict[int, TrialSolution] = {}
        for wave in _waves(order, [round(t.flexion_deg, 9) for t in trials]):
            keys = {i: round(trials[i].flexion_deg, 9) for i in wave}
            starts = {i: q_start.get(trials[i].id, last.get(keys[i], unloaded.get(keys[i]))) for i in wave}
            first = [i for i in wave if keys[i] not in unloaded and not _is_unloaded(trials[i])]
            self._prime([_unloaded(trials[i]) for i in first], theta, [starts[i] for i in first])
            for i in first:
                sol0 = self.solve_trial(_unloaded(trials[i]), theta, starts[i])
                if sol0.converged:
                    unloaded[keys[i]] = sol0.q
                    starts[i] = q_start.get(trials[i].id, sol0.q)
            self._prime([trials[i] for i in wave], theta, [starts[i] for i in wave])
            for i in wave:
                t = trials[i]
                sol = self.solve_trial(t, theta, starts[i], unloaded.get(keys[i]))
                if sol.converged:
                    last[keys[i]] = sol.q
                    if _is_unloaded(t):
                        unloaded[keys[i]] = sol.q
                out[i] = sol
        solutions = [out[i] for i in range(len(trials))]
        done = [s for s in solutions if s.converged]
        if done:  # every equilibrium's stability, in one batch
            flags = unstable_equilibria(self.model, np.array([s.q for s in done]), theta,
                                        np.array([s.trial.load for s in done]),
                                        np.array([s.trial.flexion for s in done]), threads=2)
            for s, unstable in zip(done, flags, strict=True):
                s.stable = not unstable
        return solutions

    def _prime(self, trials: list[Trial], theta: np.ndarray, starts: list[np.ndarray | None]) -> None:
        """The first Newton solve :meth:`solve_trial` makes for each of ``trials`` from ``starts``
        (its cold start where None), solved ahead in one batch and remembered."""
        if len(trials) > 1:
            q0 = [self.cold_start(t.flexion, theta) if q is None else q for t, q in zip(trials, starts, strict=True)]
            self._newton_batch(np.array(q0, float), theta, trials)


def _waves(order: list[int], keys: list) -> list[list[int]]:
    """``order`` split into waves: the k-th wave holds the k-th of ``order``'s items of every key."""
    seen: dict = {}
    waves: list[list[int]] = []
    for i in order:
        k = seen[keys[i]] = seen.get(keys[i], -1) + 1
        if k == len(waves):
            waves.append([])
        waves[k].append(i)
    return waves


@dataclass
class EquilibriumStart:
    """Start poses of an identification: ``q`` (T x 5, SI) and ``q_user`` (mm and deg, the measured
    values themselves where ``ok`` is false), and per trial whether it is an equilibrium inside the
    pose envelope (``ok``)."""

    q: np.ndarray
    q_user: np.ndarray
    ok: np.ndarray


def equilibrium_start(problem: IdentificationProblem, theta: np.ndarray, threads: int = 2) -> EquilibriumStart:
    """Start poses of an identification at parameters ``theta`` (SI).  Newton on all trials at once from the measured
    poses, per-trial ramping for the few that fail, then the forward solver's own start (unloaded
    pose first; measured poses far from the start's equilibrium, e.g. cartilage much softer than
    the model's, defeat Newton from them).  A trial that still fails, or whose equilibrium lies
    outside the NLP's pose envelope (IPOPT would move it onto its bound, far from equilibrium: a
    slack scattered start reached 36 deg varus), starts at its data."""
    data = problem.data
    solver = forward_solver(problem.model, problem.equilibrium_tol)
    q0, res0 = solver.solve_batch(data.trials, theta, data.q, threads)
    ok = res0 <= problem.equilibrium_tol
    if not ok.all():
        failed = np.flatnonzero(~ok)
        for i, sol in zip(failed, solver.solve([data.trials[i] for i in failed], theta), strict=True):
            if sol.converged:
                q0[i], ok[i] = sol.q, True
    ok &= problem.inside_pose_bounds(q0)
    return EquilibriumStart(np.where(ok[:, None], q0, data.q),
                            np.where(ok[:, None], coords_to_user(q0), problem.measured), ok)


def unstable_equilibria(model: KneeModel, q: np.ndarray, theta: np.ndarray, loads: np.ndarray,
                        flexions: np.ndarray, threads: int = 1) -> np.ndarray:
    """Per pose of ``q`` (T x 5, SI, equilibria under ``loads`` T x 6 at ``flexions`` T, rad): it is
    unstable, ``det(-dr/dq) <= 0``: an odd number of directions in which the tibia moves away under
    its loads (a pose no loading ends at, though Newton converges to it as to any root).  The
    determinant's sign does not depend on the units of the coordinates."""
    jacobians = model.trial_derivatives(np.asarray(q, float), theta, np.asarray(loads, float),
                                        np.asarray(flexions, float), threads)[1]
    return np.linalg.det(-np.asarray(jacobians)) <= 0


def rim_reason(share: float) -> str:
    """Why a pose with contact at the femoral mesh's open edge is refused (``share`` of a
    compartment's contact force from beyond the edge, above :data:`~kneenlp.model.mesh_contact.RIM_SHARE`)."""
    return (f"contact beyond the femoral surface's open edge: {100 * share:.1f} % of a compartment's contact force "
            f"would come from where the femoral mesh ends (more than {100 * RIM_SHARE:g} %; a cropped or partial "
            "surface, the knee report says where it is open)")


def _nearest_converged(loads: np.ndarray, flexions: np.ndarray, converged: np.ndarray,
                       failed: np.ndarray) -> np.ndarray | None:
    """For each ``failed`` trial, the converged trial at the nearest flexion, nearest in load among
    those (each load component scaled by its largest magnitude over the trials); None when no
    trial converged."""
    done = np.flatnonzero(converged)
    if not len(done) or not len(failed):
        return None
    scale = np.max(np.abs(loads), axis=0)
    scaled = np.divide(loads, scale, out=np.zeros_like(loads), where=scale > 0)
    near = np.empty(len(failed), dtype=np.intp)
    for k, i in enumerate(failed):
        flex_gap = np.abs(flexions[done] - flexions[i])
        same = done[flex_gap <= flex_gap.min() + 1e-9]
        near[k] = same[np.argmin(np.linalg.norm(scaled[same] - scaled[i], axis=1))]
    return near


def _is_unloaded(t: Trial) -> bool:
    return not any(v != 0 for v in t.loads.values())


def _unloaded(t: Trial) -> Trial:
    return Trial(f"none_flex{t.flexion_deg:g}", t.flexion_deg, {}, "none", 0.0)


def forward_solver(model: KneeModel, tol: float = EQUILIBRIUM_TOL) -> ForwardSolver:
    """The model's forward solver for ``tol`` (N or N m), built once per model (``model.solvers``)."""
    return model.solvers.get(("forward", tol), lambda: ForwardSolver(model, tol=tol))
