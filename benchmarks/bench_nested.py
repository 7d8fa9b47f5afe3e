"""Benchmark: nested Complex method vs simultaneous NLP on the same data (Set 1 and Set 3).

Prints wall-time ratio, evaluation counts and the largest relative parameter difference, for
one noise seed per set.  Run: python benchmarks/bench_nested.py [seed] [max_evals]
"""

import sys
import tempfile
from pathlib import Path

import kneenlp
from kneenlp.estimation.identify import identify
from kneenlp.experiment.measured import read_measured


def main(seed: int = 1, max_evals: int = 6000) -> None:
    knee = kneenlp.Knee.default()
    tmp = Path(tempfile.mkdtemp())
    for name in ("set1", "set3"):
        path = tmp / f"{name}.csv"
        kneenlp.simulate(knee, name).measured("uniform:0.5", seed).to_csv(path, index=False)
        data = read_measured(path)
        sim = identify(knee, data, seed=seed)
        nest = identify(knee, data, method="nested", seed=seed, nested_options={"max_evals": max_evals})
        worst = max(abs(nest.params[n] - sim.params[n]) / abs(sim.params[n]) for n in sim.free)
        print(f"{name} ({len(data)} trials), seed {seed}:")
        print(f"  simultaneous: {sim.seconds:.2f} s, {sim.iterations} IPOPT iterations, objective {sim.objective:.6f}")
        print(f"  nested:       {nest.seconds:.2f} s, {nest.result.evaluations} objective evaluations "
              f"({nest.equilibrium_solves} trial equilibrium solves), objective {nest.objective:.6f}, {nest.status}")
        print(f"  time ratio nested/simultaneous: {nest.seconds / sim.seconds:.0f}x; "
              f"largest relative parameter difference {100 * worst:.4f} %")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
