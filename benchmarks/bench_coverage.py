"""Benchmark: coverage of the posterior's 95 % intervals on simulated experiments whose
truth is drawn from the prior (kneenlp.studies.coverage).  Target: 90-99 % over >= 200
experiments.  Prints the coverage per parameter and overall, and the seconds taken.
Run: python benchmarks/bench_coverage.py [EXPERIMENTS] [KNEE:SET ...]   (default 200 synthetic:set1 default:set1)
"""

import sys
import time

import kneenlp
from kneenlp.studies.coverage import coverage


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    cases = sys.argv[2:] or ["synthetic:set1", "default:set1"]
    for case in cases:
        knee, _, protocol = case.partition(":")
        t0 = time.perf_counter()
        result = coverage(kneenlp.Knee.named(knee), protocol, n, seed=0)
        met = 0.90 <= result.overall() <= 0.99
        print(f"{knee} knee, {protocol}, noise gaussian:0.5 (mm, deg), priors the shipped defaults: "
              f"{time.perf_counter() - t0:.0f} s; target 90-99 % {'met' if met else 'MISSED'}")
        print(result.report(), flush=True)


if __name__ == "__main__":
    main()
