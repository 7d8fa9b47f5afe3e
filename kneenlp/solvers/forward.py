"""Forward laxity simulation: solve each trial's static equilibrium.

The loading path a laxity test describes, the same for every way of writing the knee's parameters
(the answer is a function of the forces alone):

1. the unloaded equilibrium at each flexion: Newton from the cold start (the knee's reference pose,
   0.3 mm proximal so that contact has stiffness from the first iteration; for a knee imaged at
   another pose, the passive path walked from its imaged flexion, :meth:`ForwardSolver.cold_start`);
   where Newton fails, the knee settles into a stable equilibrium by pseudo-transient continuation
   (:meth:`~kneenlp.solvers.newton.EquilibriumNewton.settle`; strategy ``settle``);
2. each loaded trial's load applied from there in fractions (1/4, 3/4, 1, steps halved on failure;
   strategy ``ramp``); where a fraction cannot be reached (a fold of the equilibrium path), the knee
   snaps: it settles at that load and the ramp goes on (strategy ``settle``).  A trial never starts
   from another trial's pose, so the protocol's order does not choose its branch.  A caller's start
   (``q_start``: a fit's poses) is tried first, by Newton (strategy ``newton``);
3. Newton (:mod:`kneenlp.solvers.newton`: damped, affine-invariant step control, the contact
   working sets retaken at every iterate) solves every step;
4. a trial is *converged* only if the largest generalised force at the returned pose is below
   ``tol`` (default :data:`~kneenlp.base.conventions.EQUILIBRIUM_TOL`, 1e-6 N / N m; the paper's 1e-3 is
   the ceiling) AND the pose lies in the
   physiological envelope (:data:`ENVELOPE`: |varus| <= 30 deg, |internal| <= 60 deg,
   |translation| <= 25 mm, some cartilage contact).  An "equilibrium" outside it (e.g. a 100 kN
   drawer force "balanced" by a dislocated tibia) is reported as not converged.  Trials that fail
   are reported with their residual and the reason, never silently kept as converged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kneenlp.base.conventions import (
    EQUILIBRIUM_TOL,
    POSE_ENVELOPE_USER,
    coords_from_user,
    coords_to_user,
    scaled_load,
)
from kneenlp.base.modes import SolveStrategy
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.path_checks import path_jumps
from kneenlp.experiment.protocol import Loading, Trial
from kneenlp.model.elements import StagedElement
from kneenlp.model.mesh_contact import RIM_SHARE
from kneenlp.solvers.newton import EquilibriumNewton
from kneenlp.solvers.workspace import ForwardMemory

COLD_START = np.array([0.0, 0.0, 0.0, 0.0, 0.3e-3])  # rad, m from the reference pose: slightly penetrated
#: Flexion step (deg) of the passive path from a knee's reference pose (:meth:`ForwardSolver.cold_start`).
PASSIVE_STEP_DEG = 10.0
#: Times a load ramp may settle where Newton cannot follow it (:meth:`ForwardSolver._ramps`).
SNAPS = 4
#: A settling that moves the knee by more than this (mm or deg) from the ramp's last equilibrium is a
#: snap through a fold; a shorter one crossed a stretch Newton could not (the same branch).
SNAP_JUMP = 0.5
#: Single-trial Newton solves a forward solver remembers (:meth:`ForwardSolver._newton`): a fit's
#: retries ask for the same solve again (S192803 calibration: 2211 solves, 1478 distinct, 3.5 s of 9.8 s).
NEWTON_MEMORY = 4096
#: Largest |coordinate| of a plausible knee pose from the knee's reference pose (rad, rad, m, m, m).
ENVELOPE = coords_from_user(POSE_ENVELOPE_USER)


#: An unloaded equilibrium: pose (rad, m), residual (N or N m), how it was reached.
Unloaded = tuple[np.ndarray, float, SolveStrategy]


@dataclass(frozen=True, eq=False)
class BatchStart:
    """Where :meth:`ForwardSolver.solve_batch` starts its trials (T x 5, SI): ``q0``, equilibria at the
    parameters ``theta0`` when these are given (an outer fit's previous iterate: its retries follow the
    parameters from there), and the ``guess`` Newton tries first (a prediction of the poses)."""

    q0: np.ndarray
    theta0: np.ndarray | None = None
    guess: np.ndarray | None = None


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
    #: a warning on a converged trial (:func:`rim_note`: contact where a cropped femoral surface ends)
    note: str = ""

    @property
    def snapped(self) -> bool:
        """Its loading path passed a fold (several equilibria there): the knee settled into this one."""
        return self.converged and self.strategy == "settle" and not _is_unloaded(self.trial)


class ForwardSolver:
    """Per-trial equilibrium solver for one model (its CasADi functions are the model's, built once)
    with a workspace, ``memory`` (a new one by default)."""

    def __init__(self, model: KneeModel, tol: float = EQUILIBRIUM_TOL, max_iter: int = 60,
                 memory: ForwardMemory | None = None):
        self.model = model
        #: the knee's reference pose: where cold starts begin and the envelope is centred (rad, m)
        self.reference = np.asarray(model.knee.reference_pose[1], float)
        self.tol, self.max_iter, self.newton = tol, max_iter, EquilibriumNewton(model, tol)
        self._contact_columns = [o.column for e, o in model.outputs
                                 if isinstance(e, StagedElement) and o.name == "force"]
        self.memory = ForwardMemory() if memory is None else memory

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
        if self.memory.passive[0] != key:
            self.memory.passive = (key, {})
        path = self.memory.passive[1]
        if flexion in path:
            return path[flexion].copy()
        step, side = np.radians(PASSIVE_STEP_DEG), np.sign(flexion - f_ref)
        grid = [f_ref + side * k * step for k in range(1, int(np.ceil(abs(flexion - f_ref) / step)))]
        f_last = f_ref
        for f in [*grid, flexion]:
            if f not in path:
                q_new, res = self._newton(q, theta, _passive(f))
                if not res <= self.tol:  # flexed in smaller steps from the equilibrium at the last flexion
                    if f_last == f_ref and f_ref not in path:
                        q_ref, res_ref = self._newton(q, theta, _passive(f_ref))
                        if not res_ref <= self.tol:
                            return q.copy()
                        q = path[f_ref] = q_ref
                    def passive_at(s, q, a=f_last, b=f):
                        return self._newton(q, theta, _passive(a + s * (b - a)))
                    q_new, res = self._follow(passive_at, q, 1 / 64, theta, _passive(f))
                if not res <= self.tol:
                    return q.copy()
                path[f] = q_new
            q, f_last = path[f], f
        return q.copy()

    def solve_batch(self, trials, theta: np.ndarray, start: BatchStart, threads: int = 2,
                    max_retries: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Newton on all trials at once (one mapped CasADi call per iteration over ``threads``
        threads; the fast path for repeated solves).

        Returns poses (T x 5, SI) and each trial's largest residual; trials above ``tol`` are
        retried before being returned, unless more than ``max_retries`` failed (then they are
        returned as they are: a caller probing a step, such as a trust-region method, learns
        cheaply that it went too far).  The retries, one by one: following the parameters from
        ``start.theta0`` to ``theta`` (:meth:`continue_parameters`) when ``start.q0`` are equilibria
        at ``theta0`` (an outer fit's previous iterate: the same branch of equilibria, a few close
        Newton solves), then ramping the load from the cold start.  Without ``theta0`` they are
        first tried all at once from the equilibrium of the converged trial nearest in load at the
        same flexion (the forward solver's own warm start; a measured pose a few tenths of a
        millimetre into stiff cartilage can defeat Newton).  With ``start.guess`` (T x 5, SI), Newton
        starts there instead of ``q0`` (a prediction of the poses at ``theta``); the trials it fails
        are started again from ``q0`` first.
        """
        q0, theta0, guess = np.asarray(start.q0, dtype=float), start.theta0, start.guess
        loading = Loading.of(trials)
        q, res = self._batch(q0 if guess is None else np.asarray(guess, float), theta, loading, threads)

        def again(failed: np.ndarray, starts: np.ndarray) -> np.ndarray:
            """Newton on the ``failed`` trials from ``starts``, kept where better; those still failing."""
            q_f, res_f = self._batch(starts, theta, loading[failed], threads)
            better = res_f < res[failed]
            q[failed[better]], res[failed[better]] = q_f[better], res_f[better]
            return np.flatnonzero(~(res <= self.tol))

        failed = np.flatnonzero(~(res <= self.tol))
        if guess is not None and len(failed):
            failed = again(failed, q0[failed])
        retry = max_retries is None or len(failed) <= max_retries
        near = _nearest_converged(loading, res <= self.tol, failed) if retry and theta0 is None else None
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

    def _batch(self, q0: np.ndarray, theta: np.ndarray, loading: Loading,
               threads: int) -> tuple[np.ndarray, np.ndarray]:
        """Newton on the trials of ``loading`` from ``q0``: poses and residuals, inf where a contact
        point their working sets leave out penetrates."""
        out = self.newton.solve(q0, theta, loading, self.max_iter, threads)
        res = out.residual
        if self.model.ws_size:
            res = np.where(self.model.left_out_batch(out.q, theta, loading.flexions, threads) > 0, np.inf, res)
        return out.q, res

    def continue_parameters(self, trial: Trial, theta0: np.ndarray, theta: np.ndarray, q0: np.ndarray,
                            min_step: float = 1 / 16) -> tuple[np.ndarray, float]:
        """Equilibrium of ``trial`` at ``theta`` followed from ``q0``, its equilibrium at ``theta0``
        (SI), through parameters ``theta0 + s (theta - theta0)`` (:meth:`_follow`, steps of at most
        1/2 down to ``min_step``): the pose and its residual at ``theta``."""
        return self._follow(lambda s, q: self._newton(q, theta0 + s * (theta - theta0), trial),
                            np.asarray(q0, float), min_step, theta, trial)

    def _follow(self, newton_at, q: np.ndarray, min_step: float, theta: np.ndarray,
                trial: Trial) -> tuple[np.ndarray, float]:
        """A homotopy from s = 0 (``q`` solves it) to s = 1: ``newton_at(s, q)`` (pose, residual) from
        the last solved pose, the step 1/2 first, doubled after a success (at most 1/2), halved after a
        failure; below ``min_step`` it stops with the last try and its residual for ``trial`` at ``theta``."""
        done, res, step = 0.0, np.inf, 0.5
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
        loading = Loading.of(trials)
        finite = np.all(np.isfinite(q), axis=1)
        q_eval = np.where(finite[:, None], q, self.reference)
        r = self.newton.evaluate(q_eval, theta, loading, threads)[0]
        out = np.max(np.abs(r), axis=1)
        if self.model.ws_size:
            out = np.where(self.model.left_out_batch(q_eval, theta, loading.flexions, threads) > 0, np.inf, out)
        return np.where(finite & np.isfinite(out), out, np.inf)

    def _newton(self, q0: np.ndarray, theta: np.ndarray, trial: Trial, scale: float = 1.0):
        """Newton from ``q0``: the pose and its residual (:meth:`residual_norm`).  A deterministic
        function of its inputs, so a solve asked for again (a retry repeating a ramp, a cold start's
        step) or solved ahead in a batch (:meth:`_newton_batch`) is answered from the last
        :data:`NEWTON_MEMORY` solves, to the bit what it would compute."""
        return self._newton_batch(np.asarray(q0, float)[None, :], theta, [trial], scale)[0]

    def _newton_batch(self, q0: np.ndarray, theta: np.ndarray, trials: list[Trial],
                      scale: float | np.ndarray = 1.0) -> list[tuple[np.ndarray, float]]:
        """:meth:`_newton` of every trial of ``trials`` from its row of ``q0`` (T x 5, SI) under
        ``scale`` (one, or one per trial) times its load: those not remembered in one batched Newton
        (each trial's iteration is its own, so the numbers are those of one solve at a time),
        remembered."""
        theta = np.ascontiguousarray(theta, dtype=float)
        q0 = np.ascontiguousarray(q0, dtype=float).reshape(-1, 5)
        scales = np.broadcast_to(np.asarray(scale, float), (len(trials),))
        loads = np.array([scaled_load(t.load, c) for c, t in zip(scales, trials, strict=True)], float)
        flexions = np.array([t.flexion for t in trials], float)
        keys = [b"".join((q.tobytes(), theta.tobytes(), load.tobytes(), f.tobytes()))
                for q, load, f in zip(q0, loads, flexions, strict=True)]
        memory = self.memory
        with memory.lock:
            known = [memory.solved.get(k) for k in keys]
        todo = [i for i, k in enumerate(known) if k is None]
        if todo:
            out = self.newton.solve(q0[todo], theta, Loading(loads, flexions)[todo], self.max_iter)
            res = out.residual.copy()
            ok = np.flatnonzero(res <= self.tol)
            if self.model.ws_size and len(ok):  # the pose's working sets left a penetrating point out
                res[ok[self.model.left_out_batch(out.q[ok], theta, flexions[todo][ok]) > 0]] = np.inf
            with memory.lock:
                for j, i in enumerate(todo):
                    while memory.solved and len(memory.solved) >= NEWTON_MEMORY:
                        del memory.solved[next(iter(memory.solved))]  # the oldest
                    known[i] = memory.solved[keys[i]] = (out.q[j].copy(), float(res[j]))
        return [(q.copy(), res) for q, res in known]

    def solve_trial(self, trial: Trial, theta: np.ndarray, q0: np.ndarray | None = None) -> TrialSolution:
        """Equilibrium of one trial at parameters ``theta`` (SI): :meth:`solve` of it alone."""
        return self.solve([trial], theta, None if q0 is None else {trial.id: q0})[0]

    def _ramp(self, trial: Trial, theta: np.ndarray, q_start: np.ndarray) -> tuple[np.ndarray, float]:
        """The load ramp of :meth:`_ramps` from the unloaded equilibrium Newton finds from ``q_start``."""
        q, res = self._newton(q_start, theta, trial, 0.0)
        if not res <= self.tol:
            return q, res
        q_end, res_end, _ = self._ramps([trial], theta, q[None])
        return q_end[0], float(res_end[0])

    def _ramps(self, trials: list[Trial], theta: np.ndarray, q_unloaded: np.ndarray,
               min_step: float = 1 / 64, snaps: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every trial's load applied from its unloaded equilibrium (row of ``q_unloaded``, T x 5, SI)
        in fractions, each from the last one's equilibrium: 1/4 first, the step doubled after a
        success (at most 1/2) and halved after a failure; the trials' fractions of each round are
        solved in one batch (:meth:`_newton_batch`, the numbers of one trial at a time).  Where the
        step falls below ``min_step`` the path has reached a fold: the knee snaps, settling at the
        fraction it could not reach (:meth:`EquilibriumNewton.settle`), and the ramp goes on from
        there (at most ``snaps`` times; none: the ramp stops at the fold).  Returns the poses,
        residuals and whether a trial snapped (settled more than :data:`SNAP_JUMP` away)."""
        n = len(trials)
        q = np.array(q_unloaded, float).reshape(n, 5)
        res = np.full(n, np.inf)
        done, step = np.zeros(n), np.full(n, 0.25)
        settled, snapped = np.zeros(n, int), np.zeros(n, bool)
        active = np.ones(n, bool)
        while np.any(active):
            idx = np.flatnonzero(active)
            target = np.minimum(1.0, done[idx] + step[idx])
            tried = self._newton_batch(q[idx], theta, [trials[i] for i in idx], target)
            for i, s, (q_try, r) in zip(idx, target, tried, strict=True):
                if r <= self.tol:
                    q[i], done[i], step[i] = q_try, s, min(2 * step[i], 0.5)
                    if s == 1.0:
                        res[i], active[i] = r, False
                    continue
                step[i] /= 2
                if step[i] >= min_step:
                    continue
                q_s, r_s = self._settle(q[i], theta, trials[i], s) if settled[i] < snaps else (q_try, np.inf)
                if r_s <= self.tol:
                    snapped[i] |= np.max(np.abs(coords_to_user(q_s - q[i]))) > SNAP_JUMP
                    q[i], done[i], step[i], settled[i] = q_s, s, 0.25, settled[i] + 1
                    if s == 1.0:
                        res[i], active[i] = r_s, False
                else:
                    q[i], res[i], active[i] = q_try, self.residual_norm(q_try, theta, trials[i]), False
        return q, res, snapped

    def _settle(self, q0: np.ndarray, theta: np.ndarray, trial: Trial, scale: float = 1.0) -> tuple[np.ndarray, float]:
        """Where the knee comes to rest from ``q0`` under ``scale`` times the trial's load
        (:meth:`EquilibriumNewton.settle`): the pose and its residual (inf where a contact point the
        working sets leave out penetrates)."""
        loading = Loading(scaled_load(trial.load, scale)[None], np.array([trial.flexion]))
        out = self.newton.settle(np.asarray(q0, float)[None], theta, loading, threads=1)
        res = float(out.residual[0])
        if res <= self.tol and self.model.ws_size and self.model.left_out_batch(out.q, theta, [trial.flexion])[0] > 0:
            res = np.inf
        return out.q[0], res

    def _solution(self, trial, theta, q, res, strategy) -> TrialSolution:
        """The trial's solution at ``q``: its element outputs, and converged only if the residual is
        within ``tol`` and the pose plausible (inside :data:`ENVELOPE`, some contact, not beyond the
        femoral surface's rim); otherwise ``failed`` with the reason."""
        ws = self.model.working_data(q, theta, trial.flexion, order=0)
        values = np.asarray(self.model.details(q, theta, trial.load, trial.flexion, ws)[1]).ravel()
        columns = [o.column for _, o in self.model.outputs]
        sol = TrialSolution(trial, q, bool(res <= self.tol), res, strategy,
                            outputs=dict(zip(columns, values, strict=True)))
        if not sol.converged:
            sol.strategy, sol.reason = "failed", f"residual {res:.3g} > tolerance {self.tol:g}"
        elif np.any(np.abs(q - self.reference) > ENVELOPE) or not any(sol.outputs[c] > 0
                                                                        for c in self._contact_columns):
            sol.converged, sol.strategy = False, "failed"
            sol.reason = "equilibrium found only at an implausible (dislocated) pose"
        else:
            rim = self.model.rim_share(q, theta, trial.flexion)
            jumps = path_jumps(self.model, q[None], theta, [trial.flexion])[0]
            sol.note = "; ".join(filter(None, [rim_note(rim) if rim > RIM_SHARE else "", jumps]))
        return sol

    def unloaded_states(self, flexions: list[float], theta: np.ndarray,
                        q_start: dict[float, np.ndarray] | None = None) -> dict[float, Unloaded]:
        """The unloaded equilibrium at each of ``flexions`` (rad): Newton from ``q_start`` of that
        flexion (a caller's start) or else from the :meth:`cold_start` (the passive path from the
        knee's imaged pose), all in one batch; where Newton fails, the knee settles from the cold
        start (:meth:`_settle`).  Returns flexion -> (pose, residual, strategy)."""
        q_start = q_start or {}
        flexions = list(dict.fromkeys(flexions))
        starts = np.array([q_start[f] if f in q_start else self.cold_start(f, theta) for f in flexions], float)
        tried = self._newton_batch(starts.reshape(-1, 5), theta, [_passive(f) for f in flexions])
        out: dict[float, Unloaded] = {}
        for f, (q, res) in zip(flexions, tried, strict=True):
            strategy: SolveStrategy = "newton"
            if not res <= self.tol:
                q_s, res_s = self._settle(self.cold_start(f, theta), theta, _passive(f))
                if res_s < res:
                    q, res, strategy = q_s, res_s, "settle"
            out[f] = (q, res, strategy)
        return out

    def solve(self, trials: list[Trial] | tuple[Trial, ...], theta: np.ndarray,
              q_start: dict[str, np.ndarray] | None = None, snap: bool = True) -> list[TrialSolution]:
        """Solve all ``trials`` along the loading path a laxity test describes: the unloaded
        equilibrium at each flexion (:meth:`unloaded_states`), then each trial's load applied from
        it (:meth:`_ramps`, all trials at once).  The answer is a function of the knee's forces
        alone, not of how its parameters are written, the order of the trials or what was solved
        before: where a load has several equilibria, the one the loading path reaches.

        ``q_start`` optionally maps trial ids to starting poses (e.g. a fit's poses, whose branch the
        caller asks for): Newton from there first, the loading path where it fails (an unloaded
        trial's start serves its flexion's unloaded state).  ``snap=False``: a ramp that reaches a
        fold stops there (the trial fails) instead of settling past it: an outer fit's residuals
        stay continuous in the parameters (a snap is a jump to another branch).
        """
        q_start = q_start or {}
        keys = [round(t.flexion_deg, 9) for t in trials]
        flexion_of = {k: t.flexion for k, t in zip(keys, trials, strict=True)}
        given = {flexion_of[k]: q_start[t.id] for k, t in zip(keys, trials, strict=True)
                 if _is_unloaded(t) and t.id in q_start}
        unloaded = self.unloaded_states([flexion_of[k] for k in keys], theta, given)
        out: dict[int, TrialSolution] = {}
        loaded = []
        for i, (k, t) in enumerate(zip(keys, trials, strict=True)):
            if _is_unloaded(t):
                q, res, strategy = unloaded[flexion_of[k]]
                out[i] = self._solution(t, theta, q, res, strategy)
            else:
                loaded.append(i)
        started = [i for i in loaded if trials[i].id in q_start]
        if started:
            tried = self._newton_batch(np.array([q_start[trials[i].id] for i in started], float), theta,
                                       [trials[i] for i in started])
            for i, (q, res) in zip(started, tried, strict=True):
                if res <= self.tol:
                    out[i] = self._solution(trials[i], theta, q, res, "newton")
        rest = [i for i in loaded if i not in out and unloaded[flexion_of[keys[i]]][1] <= self.tol]
        if rest:
            q, res, snapped = self._ramps([trials[i] for i in rest], theta,
                                          np.array([unloaded[flexion_of[keys[i]]][0] for i in rest]),
                                          snaps=SNAPS if snap else 0)
            for j, i in enumerate(rest):
                out[i] = self._solution(trials[i], theta, q[j], res[j], "settle" if snapped[j] else "ramp")
        for i in loaded:
            if i not in out:  # no unloaded state at its flexion: Newton from the cold start, for the record
                q, res = self._newton(self.cold_start(trials[i].flexion, theta), theta, trials[i])
                out[i] = self._solution(trials[i], theta, q, res, "newton")
        solutions = [out[i] for i in range(len(trials))]
        done = [s for s in solutions if s.converged]
        if done:  # every equilibrium's stability, in one batch
            flags = unstable_equilibria(self.model, np.array([s.q for s in done]), theta,
                                        Loading.of([s.trial for s in done]), threads=2)
            for s, unstable in zip(done, flags, strict=True):
                s.stable = not unstable
        return solutions


def unstable_equilibria(model: KneeModel, q: np.ndarray, theta: np.ndarray, loading: Loading,
                        threads: int = 1) -> np.ndarray:
    """Per pose of ``q`` (T x 5, SI, equilibria under ``loading``, the loads and flexions of T trials): it is
    unstable, ``det(-dr/dq) <= 0``: an odd number of directions in which the tibia moves away under
    its loads (a pose no loading ends at, though Newton converges to it as to any root).  The
    determinant's sign does not depend on the units of the coordinates."""
    jacobians = model.trial_derivatives(np.asarray(q, float), theta, loading, threads)[1]
    return np.linalg.det(-np.asarray(jacobians)) <= 0


def rim_note(share: float) -> str:
    """The warning of an equilibrium with contact at the femoral mesh's open edge (``share`` of a
    compartment's contact force from beyond the edge, above :data:`~kneenlp.model.mesh_contact.RIM_SHARE`):
    the cropped surface's equilibrium, which an intact surface would move."""
    return (f"contact at the femoral surface's open edge: {100 * share:.1f} % of a compartment's contact force "
            f"would come from where the femoral mesh ends (more than {100 * RIM_SHARE:g} %): the equilibrium of "
            "the cropped surface; a whole one would carry more there (the knee report says where it is open)")


def _nearest_converged(loading: Loading, converged: np.ndarray, failed: np.ndarray) -> np.ndarray | None:
    """For each ``failed`` trial, the converged trial at the nearest flexion, nearest in load among
    those (each load component scaled by its largest magnitude over the trials); None when no
    trial converged."""
    loads, flexions = loading.loads, loading.flexions
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


def _passive(flexion: float) -> Trial:
    """The unloaded trial at ``flexion`` (rad) of the passive path."""
    return Trial("passive", float(np.degrees(flexion)), {})


def _is_unloaded(t: Trial) -> bool:
    """No load and nothing held: the passive equilibrium at its flexion (a held trial is reached
    from it, as a loaded one)."""
    return not t.held and not any(v != 0 for v in t.loads.values())


def forward_solver(model: KneeModel, tol: float = EQUILIBRIUM_TOL,
                   memory: ForwardMemory | None = None) -> ForwardSolver:
    """A forward solver of ``model`` for ``tol`` (N or N m) working in ``memory`` (the caller's
    workspace; a new one by default: see :class:`ForwardMemory`)."""
    return ForwardSolver(model, tol=tol, memory=memory)
