"""Batched damped Newton for trial equilibria, with an affine-invariant step control.

A knee's equilibrium couples very stiff directions (contact: ~1e6 N/m proximally) with very soft
ones (axial rotation: ~20 N m/rad near full laxity).  A line search on the residual norm then
takes tiny steps: a 2 deg rotation step leaves a few newtons of contact force behind, which a
residual norm rejects although the remaining correction is microns.  Deuflhard's natural
monotonicity test (NLEQ-ERR) is invariant to that scaling: a damped step ``q + lam dq`` is
accepted when its *simplified Newton correction* ``J(q)^-1 r(q + lam dq)`` is smaller than
``(1 - lam/4) |dq|``, measured in mm and deg.  Damping halves on rejection and doubles (up to
1) after an accepted step; steps are capped at :data:`MAX_STEP` (mm / deg).

Every evaluation takes the contact working sets at the point evaluated (so the iteration is
Newton's method on the contact surfaces themselves, :mod:`kneenlp.model.workingsets`) and all
trials of a batch go through one mapped CasADi call.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kneenlp.base.conventions import EQUILIBRIUM_TOL, TO_USER
from kneenlp.experiment.protocol import Loading

#: Largest Newton step (mm for translations, deg for rotations).
MAX_STEP = 5.0
#: Smallest damping factor before a trial is declared not converged.
MIN_DAMPING = 1.0 / 1024
#: The settling's metric (:meth:`EquilibriumNewton.settle`): 1 N m per deg and 1 N per mm, in SI; a
#: constant of the method, not of the knee, so that the equilibrium it settles into is the same for
#: every parametrisation of the same forces.
SETTLE_METRIC = np.asarray(TO_USER, float)
#: The settling's largest step (mm / deg): a time step follows the flow, not a jump across it.
SETTLE_STEP = 2.0


def newton_steps(jac: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``J^-1 r`` of every trial (``jac`` T x 5 x 5, ``r`` T x 5); where a Jacobian is singular (a
    trial whose pose leaves a coordinate free, e.g. no ligament and no contact engaged), the
    least-squares step of that trial instead, so that one such trial cannot stop the others (whose
    steps are those of a batch without it, bit for bit)."""
    try:
        return np.linalg.solve(jac, r[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        return np.stack([_step(a, b) for a, b in zip(jac, r, strict=True)])


def _step(jac: np.ndarray, r: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.solve(jac[None], r[None, :, None])[0, :, 0]
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(jac, r, rcond=None)[0]


@dataclass
class NewtonResult:
    q: np.ndarray  # (T, 5) SI
    residual: np.ndarray  # (T,) largest |r|, N or N m (inf where not finite)
    iterations: int
    evaluations: int


class EquilibriumNewton:
    """Newton's method on ``KneeModel.residual`` with the working sets of each iterate; a trial is
    solved when its largest residual is at most ``tol`` (N or N m)."""

    def __init__(self, model, tol: float = EQUILIBRIUM_TOL):
        self.model = model
        self.tol = tol

    def evaluate(self, q: np.ndarray, theta: np.ndarray, loading: Loading,
                 threads: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (T x 5) and Jacobians dr/dq (T x 5 x 5) at poses ``q`` (T x 5, SI) under
        ``loading``; the trials are mapped over ``threads`` threads (1 in study workers, which run one
        process per core), each with the working sets of its own pose (:meth:`KneeModel.trial_derivatives`)."""
        return self.model.trial_derivatives(q, theta, loading, threads)

    def solve(self, q0: np.ndarray, theta: np.ndarray, loading: Loading, max_iter: int = 60,
              threads: int = 2) -> NewtonResult:
        """Solve ``r(q) = 0`` for every trial of ``loading`` from ``q0`` (T x 5, SI); ``threads`` as in
        :meth:`evaluate`.  Converged trials have ``residual <= tol``."""
        tol = self.tol
        q = np.array(q0, dtype=float).reshape(-1, 5)
        T = len(q)
        w = np.asarray(TO_USER)
        r, jac = self.evaluate(q, theta, loading, threads)
        evaluations = 1
        lam = np.ones(T)
        active = np.ones(T, dtype=bool)
        failed = ~np.all(np.isfinite(r), axis=1)
        it = 0
        for it in range(1, max_iter + 1):  # noqa: B007 - the count is returned
            active &= ~failed & ~(np.max(np.abs(r), axis=1) <= tol)
            idx = np.flatnonzero(active)
            if not len(idx):
                break
            dq = -newton_steps(jac[idx], r[idx])
            cap = np.minimum(1.0, MAX_STEP / np.maximum(np.max(np.abs(dq * w), axis=1), 1e-300))
            norm = np.linalg.norm(dq * w, axis=1)
            pending = np.arange(len(idx))
            while len(pending):
                j = idx[pending]
                step = np.minimum(lam[j], cap[pending])  # damping, and the step cap as a damping
                qt = q[j] + step[:, None] * dq[pending]
                rt, jt = self.evaluate(qt, theta, loading[j], threads)
                evaluations += 1
                finite = np.all(np.isfinite(rt), axis=1)
                bar = np.full(len(j), np.inf)
                if np.any(finite):
                    bar[finite] = np.linalg.norm(newton_steps(jac[j[finite]], rt[finite]) * w, axis=1)
                ok = finite & ((bar <= (1 - step / 4) * norm[pending]) | (np.max(np.abs(rt), axis=1) <= tol))
                q[j[ok]], r[j[ok]], jac[j[ok]] = qt[ok], rt[ok], jt[ok]
                lam[j[ok]] = np.minimum(1.0, 2 * lam[j[ok]])
                lam[j[~ok]] = step[~ok] / 2
                failed[j[~ok & (lam[j] < MIN_DAMPING)]] = True
                pending = pending[~ok & (lam[j] >= MIN_DAMPING)]
        res = np.max(np.abs(r), axis=1)
        res[~np.isfinite(res)] = np.inf
        return NewtonResult(q, res, it, evaluations)

    def settle(self, q0: np.ndarray, theta: np.ndarray, loading: Loading, max_iter: int = 2000,
               threads: int = 2) -> NewtonResult:
        """Let every trial of ``loading`` settle from ``q0`` (T x 5, SI) into a stable equilibrium, where the knee
        comes to rest (what it does when a load passes a fold of its equilibrium path, or where
        Newton stalls or runs to a saddle): pseudo-transient continuation, implicit Euler steps of
        the flow ``M dq/dt = r(q)`` (``M`` = :data:`SETTLE_METRIC`), ``(M/dt - J) dq = r``.  The
        time step grows as the residual falls (switched evolution relaxation, ``dt *= |r_old| /
        |r_new|`` within [1, 10]: the flow may climb the residual on its way downhill), so that the
        last steps are Newton's; where the stiffness has a direction that runs away (an eigenvalue
        ``l > 0`` of the symmetric part of ``M^-1/2 J M^-1/2``), ``dt <= 1 / (2 l)`` keeps ``M/dt - J``
        positive definite: every step goes downhill, never onto the hump.  Steps are capped at
        :data:`SETTLE_STEP` (mm / deg); a step into a pose that cannot be evaluated is retried with a
        quarter of the time step."""
        tol = self.tol
        q = np.array(q0, dtype=float).reshape(-1, 5)
        w = np.asarray(TO_USER)
        r, jac = self.evaluate(q, theta, loading, threads)
        res = np.max(np.abs(r), axis=1)
        dt = np.ones(len(q))
        evaluations, it = 1, 0
        for it in range(1, max_iter + 1):  # noqa: B007 - the count is returned
            idx = np.flatnonzero(np.isfinite(res) & ~(res <= tol))
            if not len(idx):
                break
            scaled = jac[idx] / np.sqrt(np.outer(SETTLE_METRIC, SETTLE_METRIC))[None]
            rising = np.linalg.eigvalsh(0.5 * (scaled + scaled.transpose(0, 2, 1)))[:, -1]  # 1 / time
            dt[idx] = np.where(rising > 0, np.minimum(dt[idx], 0.5 / np.maximum(rising, 1e-300)), dt[idx])
            lhs = SETTLE_METRIC[None, :, None] * np.eye(5)[None] / dt[idx, None, None] - jac[idx]
            dq = newton_steps(lhs, r[idx])
            dq *= np.minimum(1.0, SETTLE_STEP / np.maximum(np.max(np.abs(dq * w), axis=1), 1e-300))[:, None]
            qt = q[idx] + dq
            rt, jt = self.evaluate(qt, theta, loading[idx], threads)
            evaluations += 1
            rest = np.max(np.abs(rt), axis=1)
            ok = np.isfinite(rest)
            j = idx[ok]
            dt[j] = np.minimum(dt[j] * np.clip(res[j] / np.maximum(rest[ok], 1e-300), 1.0, 10.0), 1e12)
            q[j], r[j], jac[j], res[j] = qt[ok], rt[ok], jt[ok], rest[ok]
            dt[idx[~ok]] /= 4
            res[idx[~ok & (dt[idx] < 1e-6)]] = np.inf  # nowhere to go: not settled
        res[~np.isfinite(res)] = np.inf
        return NewtonResult(q, res, it, evaluations)
