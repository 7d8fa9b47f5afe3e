"""Benchmark: simultaneous identification of Set 1 and Set 4 (uniform +-0.5 noise, one seed each).

Prints NLP build time, solve time, IPOPT iterations and where the time goes (CasADi's per-function
wall times).  Target (issue 3): Set 4 (60 trials, 308 unknowns) solve <= 1 s and <= 30 iterations.
Run: python benchmarks/bench_identify.py [seed]
"""

import sys
import tempfile
import time
from pathlib import Path

import kneenlp
from kneenlp.experiment.measured import read_measured
from kneenlp.inference.identify import get_nlp, identify


def main(seed: int = 1) -> None:
    knee = kneenlp.Knee.default()
    tmp = Path(tempfile.mkdtemp())
    for name in ("set1", "set4"):
        res = kneenlp.simulate(knee, name)
        path = tmp / f"{name}.csv"
        res.measured("uniform:0.5", seed).to_csv(path, index=False)
        data = read_measured(path)
        t0 = time.perf_counter()
        fit = identify(knee, data, seed=seed)
        total = time.perf_counter() - t0
        nlp = get_nlp(fit.problem, "ipopt", None, 2)
        st = nlp.solver.stats()
        n_unknowns = len(fit.free) + 5 * len(data)
        print(f"{name}: {len(data)} trials, {n_unknowns} unknowns, status {fit.status}")
        print(f"  NLP build {fit.build_seconds:.3f} s | start (forward solves) {fit.extra['start_seconds']:.3f} s"
              f" | IPOPT solve {fit.seconds:.3f} s | {fit.iterations} iterations | total {total:.3f} s")
        print(f"  objective {fit.objective:.4f} | max equilibrium residual {fit.max_residual:.2e}")
        parts = []
        for fn in ("nlp_g", "nlp_jac_g", "nlp_hess_l"):
            n = st.get(f"n_call_{fn}", 0)
            parts.append(f"{fn} {1e3 * st.get(f't_wall_{fn}', 0.0) / max(n, 1):.2f} ms x {n}")
        calls = ", ".join(parts)
        print(f"  per call: {calls}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1)
