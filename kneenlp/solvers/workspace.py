"""A solver's workspace: what a solver remembers between solves, owned and passed by its caller.

Solvers keep no memory of their own that other callers could see: a caller that solves one model
again and again (a fit's retries, a calibration's checks) creates a workspace and passes it to each
solver it builds (:func:`~kneenlp.solvers.forward.forward_solver`); a benchmark or a test that wants
a cold solver passes none.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ForwardMemory:
    """A forward solver's workspace: what it remembers between solves.  Every entry is a
    deterministic function of its inputs, so a memory changes how long a solve takes, never its
    result; a caller that solves one model again and again (a fit's retries, a calibration's checks)
    keeps one and passes it (:func:`~kneenlp.solvers.forward.forward_solver`), and nothing is shared behind its back."""

    #: the passive path of :meth:`~kneenlp.solvers.forward.ForwardSolver.cold_start` at the last
    #: parameters: (theta's bytes, {flexion: pose})
    passive: tuple[bytes | None, dict[float, np.ndarray]] = (None, {})
    #: the last :data:`~kneenlp.solvers.forward.NEWTON_MEMORY` single-trial Newton solves: inputs'
    #: bytes -> (pose, residual)
    solved: dict[bytes, tuple[np.ndarray, float]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
