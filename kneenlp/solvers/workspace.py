"""A solver's workspace: what a solver remembers between solves, owned and passed by its caller.

Solvers keep no memory of their own that other callers could see.  A solver built without a
workspace gets a new one and keeps it for its life: a fit's reduced-space solver or the nested
method's keeps its Newton memory over all its retries (S192803's calibration took 47.0 s with the
memory shared by every caller of a model, 47.1 s with one per solver).  A caller that wants several
solvers to share one passes it (:func:`~kneenlp.solvers.forward.forward_solver`).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ForwardMemory:
    """A forward solver's workspace: what it remembers between solves.  Every entry is a
    deterministic function of its inputs, so a memory changes how long a solve takes, never its
    result (module docstring)."""

    #: the passive path of :meth:`~kneenlp.solvers.forward.ForwardSolver.cold_start` at the last
    #: parameters: (theta's bytes, {flexion: pose})
    passive: tuple[bytes | None, dict[float, np.ndarray]] = (None, {})
    #: the last :data:`~kneenlp.solvers.forward.NEWTON_MEMORY` single-trial Newton solves: inputs'
    #: bytes -> (pose, residual)
    solved: dict[bytes, tuple[np.ndarray, float]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
