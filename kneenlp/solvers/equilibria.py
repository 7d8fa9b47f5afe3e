"""An identification's start poses, every trial at once (:func:`equilibrium_start`, identify and
export), on the forward solver (:mod:`kneenlp.solvers.forward`, which also says which equilibria are unstable)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from kneenlp.base.conventions import coords_to_user
from kneenlp.solvers.forward import BatchStart, forward_solver

if TYPE_CHECKING:
    from kneenlp.experiment.problem import IdentificationProblem


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
    measured = problem.measured_q
    q0, res0 = solver.solve_batch(data.trials, theta, BatchStart(measured), threads)
    ok = res0 <= problem.equilibrium_tol
    if not ok.all():
        failed = np.flatnonzero(~ok)
        for i, sol in zip(failed, solver.solve([data.trials[i] for i in failed], theta), strict=True):
            if sol.converged:
                q0[i], ok[i] = sol.q, True
    ok &= problem.inside_pose_bounds(q0)
    return EquilibriumStart(np.where(ok[:, None], q0, measured),
                            np.where(ok[:, None], coords_to_user(q0), problem.measured_start), ok)
