"""Benchmark: forward simulation of all Set 4 trials on the default knee.

Prints the knee load / model build time, the cold solve of all 60 trials, and a warm re-solve
(every trial started from its previous solution).  Target (issue 2): < 2 s for Set 4 after build.
Run: python benchmarks/bench_forward.py
"""

import time

import numpy as np

from kneenlp import Knee, Protocol
from kneenlp.model.kneemodel import KneeModel
from kneenlp.solvers.forward import ForwardSolver


def main() -> None:
    t0 = time.perf_counter()
    knee = Knee.default()
    t1 = time.perf_counter()
    model = KneeModel(knee)
    solver = ForwardSolver(model)
    t2 = time.perf_counter()
    protocol = Protocol.load("set4")
    theta = model.theta()
    cold = []
    for _ in range(3):
        s = time.perf_counter()
        sols = solver.solve(protocol.trials, theta)
        cold.append(time.perf_counter() - s)
    warm_start = {s.trial.id: s.q for s in sols}
    s = time.perf_counter()
    solver.solve(protocol.trials, theta * np.where(np.arange(len(theta)) % 3 == 0, 1.01, 1.0), warm_start)
    warm = time.perf_counter() - s
    print(f"knee load (meshes, sphere fits): {t1 - t0:.3f} s")
    print(f"model + rootfinder build:        {t2 - t1:.3f} s")
    print(f"Set 4 cold solve, 60 trials:     {min(cold):.3f} s (best of 3; all {cold})")
    print(f"Set 4 warm re-solve (k +1 %):    {warm:.3f} s")
    print(f"converged: {sum(x.converged for x in sols)}/{len(sols)}, "
          f"max residual {max(x.max_residual for x in sols):.2e} N or N m, "
          f"ramped: {sum(x.strategy == 'ramp' for x in sols)}")


if __name__ == "__main__":
    main()
