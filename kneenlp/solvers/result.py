"""The one result every identification solver returns: :class:`SolverResult`.

The simultaneous NLP (:func:`~kneenlp.solvers.nlp.solve_nlp`), the reduced-space Gauss-Newton fit
(:func:`~kneenlp.solvers.reduced.reduced_least_squares`) and the nested Complex method
(:func:`~kneenlp.solvers.nested.nested_fit`) all report a solve as the solver left it, in these
fields; :mod:`kneenlp.estimation` judges it (equilibrium, contact, bounds) and builds the
:class:`~kneenlp.estimation.fit.Fit`.  Fields one solver alone fills have a neutral default.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class SolverResult:
    """One solve, as the solver left it.

    ``objective`` is what the solver minimised at its end: the weighted sum of squared coordinate
    differences (mm^2 + deg^2 times the weights) plus the priors' share, and for the nested method
    its penalties (none when every trial is in equilibrium).  ``iterations`` are the solver's own
    (IPOPT iterations, the Complex method's iterations; the reduced-space fit counts its residual
    evaluations, trf has no other count); ``evaluations`` its objective (or residual) evaluations.
    """

    solver: str  # the solver's name: an nlpsol plugin, "reduced" or "complex"
    values: dict[str, float]  # free parameters, SI
    q: np.ndarray  # equilibrium poses at the end, T x 5, SI
    objective: float  # mm^2 + deg^2 (weighted), see the class docstring
    success: bool  # the solver's own verdict
    status: str  # the solver's return status or message
    iterations: int
    evaluations: int
    seconds: float  # the solve itself
    max_residual: float  # largest equilibrium residual at the end, N or N m
    #: the equilibrium start and the NLP's build (simultaneous NLP), s
    start_seconds: float = 0.0
    #: building the solver (simultaneous NLP; 0 when it was built before), s
    build_seconds: float = 0.0
    #: deepest penetration (m) of a contact point outside the working sets; -inf: none or not checked
    left_out: float = -np.inf
    #: largest share of a compartment's contact force from beyond the femoral surface's open edge
    #: (above :data:`~kneenlp.model.mesh_contact.RIM_SHARE`: noted); 0: none or not checked
    rim: float = 0.0
    #: trials with no equilibrium inside the pose envelope at the start (simultaneous NLP)
    started_at_data: int = 0
    #: trial equilibria solved (nested method: each objective evaluation solves every trial)
    equilibrium_solves: int = 0
    #: largest equilibrium residual per trial at the end (nested method), N or N m
    residuals: np.ndarray | None = None
    #: (evaluations, best objective so far) after each iteration (nested method), k x 2
    history: np.ndarray | None = None
