"""Benchmark: with wide priors the MAP is the paper's least squares.  Sets 1-4 on the
synthetic knee (uniform +-0.5 noise, seeds 1-4): the data-only fit and the MAP with a normal prior
of sd 1000 times each value on every free parameter, from the same start.  Target: every estimate
within 1 % of its standard error of the data-only one, so the paper's results stand.
Run: python benchmarks/bench_wide_priors.py
"""

import tempfile
import time
from pathlib import Path

import kneenlp
from kneenlp.experiment.measured import read_measured
from kneenlp.model.priors import Prior

NOISE = "uniform:0.5"


def main() -> None:
    knee = kneenlp.Knee.named("synthetic")
    tmp = Path(tempfile.mkdtemp())
    worst_all = 0.0
    for n in range(1, 5):
        path = tmp / f"set{n}.csv"
        kneenlp.simulate(knee, f"set{n}").measured(NOISE, n).to_csv(path, index=False)
        data = read_measured(path)
        t0 = time.perf_counter()
        data_only = kneenlp.identify(knee, data, seed=n, noise=NOISE)
        wide = kneenlp.identify(knee, data, seed=n, noise=NOISE,
                                priors={p: Prior("normal", knee.parameters[p], 1e3 * abs(knee.parameters[p]))
                                        for p in data_only.free})
        worst = max(abs(wide.params[p] - data_only.params[p]) / data_only.stderr[p] for p in data_only.free)
        worst_all = max(worst_all, worst)
        print(f"set{n}: {len(data)} trials, both converged {data_only.success and wide.success}; largest "
              f"|MAP - least squares| / standard error {worst:.2e} ({time.perf_counter() - t0:.1f} s)")
    print(f"largest over Sets 1-4: {worst_all:.2e} (target <= 1e-2): {'met' if worst_all <= 1e-2 else 'MISSED'}")


if __name__ == "__main__":
    main()
