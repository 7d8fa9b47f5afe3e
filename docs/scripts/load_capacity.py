"""The largest load of each direction a knee can carry, found by ramping the load in small steps
(0.1 N m or 0.5 N m) from the unloaded pose until Newton finds no equilibrium.  Used for the
menisci decision in docs/real-knee.md.

    python docs/scripts/load_capacity.py [KNEE] [PARAMETER=VALUE ...]   (SI values)
    python docs/scripts/load_capacity.py default meniscus.k=0          # the four ligaments alone
"""

from __future__ import annotations

import sys

import numpy as np

import kneenlp
from kneenlp.base.conventions import LOAD_SIZE, TO_USER
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.protocol import Loading
from kneenlp.solvers.forward import COLD_START, forward_solver

#: (name, load component, sign, steps): internal/external moment is component 4 (N m about Y),
#: varus/valgus component 3 (N m about X), loads fixed in the femoral frame as in the paper.
DIRECTIONS = [("internal", 4, 1.0, np.arange(0.1, 10.01, 0.1)), ("external", 4, -1.0, np.arange(0.1, 10.01, 0.1)),
              ("varus", 3, 1.0, np.arange(0.5, 15.0, 0.5)), ("valgus", 3, -1.0, np.arange(0.5, 15.0, 0.5))]


def capacity(knee: kneenlp.Knee, theta: np.ndarray, flexion_deg: float, component: int, sign: float,
             steps: np.ndarray) -> tuple[float, np.ndarray]:
    """Largest magnitude carried (N m) and the pose there (mm, deg)."""
    newton = forward_solver(KneeModel.of(knee)).newton
    flexion = np.array([np.radians(flexion_deg)])
    q = newton.solve(COLD_START[None, :], theta, Loading(np.zeros((1, LOAD_SIZE)), flexion)).q
    carried, pose = 0.0, q[0] * TO_USER
    for magnitude in steps:
        load = np.zeros((1, LOAD_SIZE))
        load[0, component] = sign * magnitude
        out = newton.solve(q, theta, Loading(load, flexion))
        if not out.residual[0] <= 1e-6:
            break
        q, carried, pose = out.q, float(magnitude), out.q[0] * TO_USER
    return carried, pose


if __name__ == "__main__":
    knee = kneenlp.Knee.load(sys.argv[1]) if len(sys.argv) > 1 else kneenlp.Knee.default()
    values = dict((k, float(v)) for k, v in (a.split("=") for a in sys.argv[2:]))
    theta = KneeModel.of(knee).theta(values)
    print(f"{knee.name} knee {values or ''}: largest load carried (N m) and the internal rotation there (deg)")
    for flexion in (0.0, 30.0):
        for name, component, sign, steps in DIRECTIONS:
            carried, pose = capacity(knee, theta, flexion, component, sign, steps)
            limit = "" if carried < steps[-1] else " (no limit up to here)"
            print(f"  {flexion:4.0f} deg  {name:9s} {carried:5.1f}{limit}  internal rotation {pose[1]:6.1f}")
