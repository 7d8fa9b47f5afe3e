"""Benchmark: the global search as an option of the paper's scatter fits (default knee, noisy Set 4).

For each seed: Set 4 measured with uniform +-0.5 noise; the default fit (one NLP from the paper's
scatter), the fit started at the truth (the truth's basin) and the global search
(``identify(starts=N)``: Sobol starts over the default priors, screened, the 2 best solved).  Prints
per seed the three MAP objectives and times, then how often each fit is in the truth's basin (MAP
objective within 1e-6 relative of the truth-started fit's) or lower, and the search's time over
the single NLP's (median).  Targets: the search in the truth's basin (or lower) in 20 of 20 seeds
at <= 3x the single NLP.

Run: python benchmarks/bench_global_scatter.py [--seeds 20] [--starts 4]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.estimation.identify import identify
from kneenlp.experiment.measured import read_measured

SAME = 1e-6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--starts", type=int, default=4)
    args = parser.parse_args()
    knee = kneenlp.Knee.default()
    result = kneenlp.simulate(knee, "set4")
    tmp = Path(tempfile.mkdtemp())
    result.measured("uniform:0.5", 10_000).to_csv(tmp / "warm.csv", index=False)
    identify(knee, read_measured(tmp / "warm.csv"), noise="uniform:0.5")  # builds the NLP once
    rows = []
    for seed in range(args.seeds):
        path = tmp / f"set4_{seed}.csv"
        result.measured("uniform:0.5", seed).to_csv(path, index=False)
        data = read_measured(path)
        t0 = time.perf_counter()
        single = identify(knee, data, seed=seed, noise="uniform:0.5")
        t1 = time.perf_counter()
        found = identify(knee, data, seed=seed, noise="uniform:0.5", starts=args.starts, workers=1)
        t2 = time.perf_counter()
        truth = identify(knee, data, seed=seed, noise="uniform:0.5",
                         start={n: knee.parameters[n] for n in single.free})
        basin = truth.map_objective

        def where(f) -> str:  # the truth's basin, a lower minimum, or a higher one
            if not f.success or f.map_objective > basin * (1 + SAME):  # noqa: B023
                return "higher"
            return "lower" if f.map_objective < basin * (1 - SAME) else "same"  # noqa: B023

        rows.append((where(single), where(found), t1 - t0, t2 - t1))
        print(f"seed {seed:2d}: truth's basin {basin:.6f}; single NLP {single.map_objective:.6f} "
              f"({t1 - t0:.2f} s, {rows[-1][0]}); search {found.map_objective:.6f} ({t2 - t1:.2f} s, {rows[-1][1]})",
              flush=True)
    single_at, search_at = ([r[k] for r in rows] for k in (0, 1))
    t = np.array([r[2:] for r in rows])
    print(f"{args.seeds} seeds, {args.starts} starts: the truth's basin or lower: single NLP "
          f"{sum(w != 'higher' for w in single_at)} ({single_at.count('lower')} lower), search "
          f"{sum(w != 'higher' for w in search_at)} ({search_at.count('lower')} lower); median time single "
          f"{np.median(t[:, 0]):.2f} s, search {np.median(t[:, 1]):.2f} s ({np.median(t[:, 1] / t[:, 0]):.1f}x)")


if __name__ == "__main__":
    main()
