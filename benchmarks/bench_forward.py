"""Benchmark: forward simulation of all Set 4 trials, real default knee beside the synthetic one.

Prints the knee load and model build times, the cold solve of all 60 trials (best of 3), a warm
re-solve (every trial started from its previous solution, k +1 %) and the contact points per trial
(mean and largest number of penetrating tibial points, both compartments; the synthetic knee's
sphere contact evaluates every point).  Target: forward Set 4 <= 1 s on 2 cores.
Run: python benchmarks/bench_forward.py
"""

import time

import numpy as np

from kneenlp import Knee, Protocol
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.solvers.forward import ForwardSolver


def contact_points(model: KneeModel, sols, theta: np.ndarray) -> tuple[float, int]:
    """Mean and largest number of penetrating tibial points per trial."""
    values = dict(zip(model.parameter_names, theta, strict=True))
    counts = []
    for s in sols:
        R, p = (np.asarray(v) for v in model.pose(s.q, s.trial.flexion, theta))
        counts.append(sum(int(np.sum(e.clearance(R, p, values) < 0)) for e in model.staged))
    return float(np.mean(counts)), int(np.max(counts))


def bench(name: str) -> None:
    t0 = time.perf_counter()
    knee = Knee.named(name)
    field = knee.femur.field if knee.femur is not None else None  # built or read from the cache
    t1 = time.perf_counter()
    model = KneeModel(knee)
    solver = ForwardSolver(model)
    t2 = time.perf_counter()
    protocol = Protocol.load("set4")
    theta = model.theta()
    cold = []
    for _ in range(3):
        model.solvers.clear()  # nothing kept from the previous solve: its built functions
        solver = ForwardSolver(model)  # and a new workspace: no Newton memory
        s = time.perf_counter()
        sols = solver.solve(protocol.trials, theta)
        cold.append(time.perf_counter() - s)
    warm_start = {s.trial.id: s.q for s in sols}
    s = time.perf_counter()
    solver.solve(protocol.trials, theta * np.where(np.arange(len(theta)) % 3 == 0, 1.01, 1.0), warm_start)
    warm = time.perf_counter() - s
    mean_pts, max_pts = contact_points(model, sols, theta)
    print(f"{name} knee ({'mesh contact, distance field' if field else 'explicit spheres'})")
    print(f"  knee load (meshes, fits{', field' if field else ''}): {t1 - t0:.3f} s")
    print(f"  model + solver build:             {t2 - t1:.3f} s")
    runs = ", ".join(f"{c:.2f}" for c in cold)
    print(f"  Set 4 cold solve, 60 trials:      {min(cold):.3f} s (best of 3; all {runs})")
    print(f"  Set 4 warm re-solve (k +1 %):     {warm:.3f} s")
    print(f"  penetrating points per trial:     {mean_pts:.0f} mean, {max_pts} max")
    print(f"  converged {sum(x.converged for x in sols)}/{len(sols)}, max residual "
          f"{max(x.max_residual for x in sols):.2e} N or N m, ramped {sum(x.strategy == 'ramp' for x in sols)}")


if __name__ == "__main__":
    for knee_name in ("default", "synthetic"):
        bench(knee_name)
