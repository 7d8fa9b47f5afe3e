"""Benchmark: what an exactly right model would predict of S192803's hold-outs.

The twin of the experiment (``crossval.twin``): every trial at its measured load and flexion
predicted by the calibrated knee of ``problems/s192803`` itself, plus normal noise at the
calibration's misfit per coordinate times ``--misfit F``, seeded per draw.  Each twin is
calibrated and cross-validated as the problem says (the seven hold-outs, four starts each).  Prints,
per twin, the hold-outs within 2 mm and 5 deg and the mean normalised error (1 = on target), then
their range: the held-out error these 25 trials allow a model that is right, at that misfit.
(``kneenlp cross-validate --problem problems/s192803 --twins N`` measures the same at F = 1, per
hold-out, beside the real knee's errors.)

Run: python benchmarks/bench_twins.py [--draws N] [--misfit F]   (about 80 s per draw on 2 cores)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.estimation.calibrate import calibrate, noise_per_observation
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem_file import ProblemFile
from kneenlp.validation import crossval

PROBLEM = Path(__file__).resolve().parents[1] / "problems" / "s192803"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=5)
    parser.add_argument("--misfit", type=float, default=1.0, help="noise sd over the calibration's misfit")
    args = parser.parse_args()
    problem = ProblemFile.load(PROBLEM)
    model = KneeModel.of(problem.knee_with_parameters(kneenlp.Knee.named(problem.knee)))
    data = read_measured(problem.data)
    options = dict(also_free=list(problem.also_free), multistart=problem.multistart, priors=problem.priors,
                   prior_weight=problem.prior_weight, workers=2)
    fit = calibrate(model, data, **options).fit
    sd = np.sqrt(noise_per_observation(fit)[0]) * args.misfit
    print(f"noise sd (deg, deg, mm, mm, mm): {' '.join(f'{v:.2f}' for v in sd)} ({args.misfit:g} x the misfit)")
    met, means = [], []
    for draw in range(args.draws):
        t0 = time.perf_counter()
        copy = crossval.twin(model, data, fit.params, sd, np.random.default_rng([0, draw]))
        scores = [crossval.hold_out(model, copy, mask, name, **options).normalised()
                  for name, mask in crossval.folds(copy)]
        met.append(sum(s <= 1 for s in scores))
        means.append(float(np.mean(scores)))
        print(f"twin {draw}: {met[-1]} of {len(scores)} within 2 mm and 5 deg, mean normalised {means[-1]:.2f} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    print(f"{args.draws} twins: met {min(met)}-{max(met)} of 7 (median {np.median(met):g}), mean normalised "
          f"{min(means):.2f}-{max(means):.2f} (mean {np.mean(means):.2f})")


if __name__ == "__main__":
    main()
