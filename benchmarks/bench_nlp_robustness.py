"""Benchmark: robustness of the simultaneous NLP on the default (mesh) knee, Set 4 with uniform
+-0.5 noise, one fit per seed: does IPOPT converge from the scattered start without the rescue
(reduced-space Gauss-Newton, then IPOPT again: ``_rescued`` in :mod:`kneenlp.estimation.identify`)
and in how many iterations and seconds.  Targets: every seed converged without rescue,
at most 40 IPOPT iterations, median at most 25; the median time per fit no slower than before
(0.4-0.8 s).  Seeds 40-49 are the development set, 100-119 the held-out one.  The first fit of a
process (it builds the NLP) is timed apart.
Run: python benchmarks/bench_nlp_robustness.py [seed ...]   (default: 40-49 and 100-119)
"""

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.estimation.identify import identify
from kneenlp.experiment.measured import read_measured

NOISE = "uniform:0.5"
DEFAULT_SEEDS = [*range(40, 50), *range(100, 120)]


def fit_seed(knee: kneenlp.Knee, res, seed: int, tmp: Path) -> tuple[bool, bool, int, int, float]:
    """One identification: (success, rescued, starts, IPOPT iterations, seconds of the whole fit)."""
    path = tmp / f"set4_{seed}.csv"
    res.measured(NOISE, seed).to_csv(path, index=False)
    data = read_measured(path)
    t0 = time.perf_counter()
    fit = identify(knee, data, seed=seed, noise=NOISE)
    seconds = time.perf_counter() - t0
    rescued = "rescued" in (fit.message or "")
    return fit.success, rescued, fit.starts, fit.iterations, seconds


def main(seeds: list[int]) -> None:
    knee = kneenlp.Knee.default()
    res = kneenlp.simulate(knee, "set4")
    tmp = Path(tempfile.mkdtemp())
    t0 = time.perf_counter()
    fit_seed(knee, res, 10_000, tmp)
    print(f"first fit of the process (NLP build): {time.perf_counter() - t0:.2f} s", flush=True)
    print(f"{'seed':>5} {'success':>8} {'rescued':>8} {'starts':>7} {'iter':>5} {'seconds':>8}")
    rows = []
    for seed in seeds:
        ok, rescued, starts, it, sec = fit_seed(knee, res, seed, tmp)
        rows.append((seed, ok, rescued, starts, it, sec))
        print(f"{seed:>5} {ok!s:>8} {rescued!s:>8} {starts:>7} {it:>5} {sec:>8.2f}", flush=True)
    clean = [r for r in rows if r[1] and not r[2] and r[3] == 1]
    its = [r[4] for r in rows]
    print(f"converged without rescue or restart: {len(clean)}/{len(rows)}; iterations max {max(its)}, "
          f"median {np.median(its):.0f}; seconds median {np.median([r[5] for r in rows]):.2f}, "
          f"max {max(r[5] for r in rows):.2f}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or DEFAULT_SEEDS)
