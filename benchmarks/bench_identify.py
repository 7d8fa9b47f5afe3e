"""Benchmark: simultaneous identification of Set 4 (uniform +-0.5 noise), real default knee beside
the synthetic one: median over 5 seeds of IPOPT iterations and seconds, with the start (forward
solves at the scattered parameters) and where IPOPT's time goes.  Targets: Set 4 identification
<= 1.0 s median and <= 30 iterations on 2 cores, on the default knee (the synthetic
knee's was 2 s).  The first fit of a process builds the NLP and compiles nothing else
(numba's passes are cached per machine): it is timed apart, then every seed is timed.
Run: python benchmarks/bench_identify.py [n_seeds]
"""

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.estimation.identify import identify
from kneenlp.experiment.measured import read_measured
from kneenlp.solvers.nlp import get_nlp


def bench(name: str, seeds: range) -> None:
    knee = kneenlp.Knee.named(name)
    tmp = Path(tempfile.mkdtemp())
    res = kneenlp.simulate(knee, "set4")
    path = tmp / "set4_warm.csv"
    res.measured("uniform:0.5", 10_000).to_csv(path, index=False)
    t0 = time.perf_counter()
    fit = identify(knee, read_measured(path), seed=10_000, noise="uniform:0.5")
    print(f"  {name}: first fit of the process {time.perf_counter() - t0:.2f} s "
          f"(NLP build {fit.build_seconds:.2f} s)", flush=True)
    rows = []
    for seed in seeds:
        path = tmp / f"set4_{seed}.csv"
        res.measured("uniform:0.5", seed).to_csv(path, index=False)
        data = read_measured(path)
        t0 = time.perf_counter()
        fit = identify(knee, data, seed=seed, noise="uniform:0.5")
        total = time.perf_counter() - t0
        st = get_nlp(fit.problem, "ipopt", None, 2).solver.stats()
        per_call = {fn: 1e3 * st.get(f"t_wall_{fn}", 0.0) / max(st.get(f"n_call_{fn}", 0), 1)
                    for fn in ("nlp_g", "nlp_jac_g", "nlp_hess_l")}
        rows.append((seed, fit.success, fit.starts, fit.iterations, fit.seconds,
                     fit.result.start_seconds, total, per_call))
        print(f"  {name} seed {seed}: success {fit.success}, starts {rows[-1][2]}, {fit.iterations} iterations, "
              f"IPOPT {fit.seconds:.2f} s, start {fit.result.start_seconds:.2f} s, total {total:.2f} s; "
              + ", ".join(f"{k} {v:.1f} ms" for k, v in per_call.items()), flush=True)
    it = np.median([r[3] for r in rows])
    sec = np.median([r[4] for r in rows])
    tot = np.median([r[6] for r in rows])
    print(f"{name} knee, Set 4 (60 trials, 308 unknowns): median of {len(rows)} seeds: "
          f"{it:.0f} iterations, IPOPT {sec:.2f} s, total {tot:.2f} s, "
          f"converged {sum(r[1] for r in rows)}/{len(rows)}")


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    for knee_name in ("default", "synthetic"):
        bench(knee_name, range(n))
