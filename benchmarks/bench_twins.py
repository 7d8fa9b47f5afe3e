"""Benchmark: what an exactly right model would predict of S192803's hold-outs.

The twin of the experiment (``twins.twin``): every trial at its measured load and flexion
predicted by the calibrated knee of ``problems/s192803`` itself, plus normal noise at the
calibration's misfit per coordinate times ``--misfit F``, seeded per draw.  Each twin is
calibrated and cross-validated as the problem says (the seven hold-outs, each by the global search).  Prints,
per twin, the hold-outs within 2 mm and 5 deg and the mean normalised error (1 = on target), then
their range: the held-out error these 25 trials allow a model that is right, at that misfit.
(``kneenlp cross-validate --problem problems/s192803 --twins N`` measures the same at F = 1, per
hold-out, beside the real knee's errors.)

``--half-loads``: a richer protocol, every loaded trial also at half its test load (the same
flexion and preload; 49 trials); the hold-outs are judged on the robot's trials (full load) only,
so that the easier half-load trials do not flatter them.

Run: python benchmarks/bench_twins.py [--draws N] [--misfit F] [--half-loads]
(about 80 s per draw on 2 cores; 4 min with --half-loads)
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.estimation.calibrate import calibrate
from kneenlp.estimation.calibrated import noise_per_observation
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData, read_measured
from kneenlp.experiment.problem_file import ProblemFile
from kneenlp.validation import crossval, twins

PROBLEM = Path(__file__).resolve().parents[1] / "problems" / "s192803"
#: The robot's test loads (halved by --half-loads; the preload and the small components stay).
TEST_LOADS = ("anterior_force", "varus_moment", "internal_moment")
HALF = "_half"


def with_half_loads(data: MeasuredData) -> MeasuredData:
    """``data`` and a copy of each loaded trial at half its test load (id ``<id>_half``; its pose
    is a placeholder: the twin replaces every pose)."""
    loaded = [i for i, t in enumerate(data.trials) if t.dominant != "none"]
    extra = [dataclasses.replace(t, id=t.id + HALF, magnitude=t.magnitude / 2,
                                 loads={k: v / 2 if k in TEST_LOADS else v for k, v in t.loads.items()})
             for t in (data.trials[i] for i in loaded)]
    return MeasuredData.from_user([*data.trials, *extra], np.vstack([data.q_user, data.q_user[loaded]]),
                                  data.protocol, data.source, side=data.side, experiment=data.experiment)


def judged(result: crossval.HeldOut, data: MeasuredData) -> float:
    """The hold-out's normalised error over its held-out trials at equilibrium, half-load ones aside."""
    full_load = np.array([not t.id.endswith(HALF) for t in data.subset(result.held).trials])
    return crossval.normalised_error(result.prediction.rms(full_load))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=5)
    parser.add_argument("--misfit", type=float, default=1.0, help="noise sd over the calibration's misfit")
    parser.add_argument("--half-loads", action="store_true", help="every loaded trial also at half its load")
    args = parser.parse_args()
    problem = ProblemFile.load(PROBLEM)
    model = KneeModel.of(problem.knee_with_parameters(kneenlp.Knee.named(problem.knee)))
    data = read_measured(problem.data)
    options = problem.calibrate_options() | {"workers": 2}
    fit = calibrate(model, data, **options).fit
    sd = np.sqrt(noise_per_observation(fit)[0]) * args.misfit
    protocol = with_half_loads(data) if args.half_loads else data
    print(f"noise sd (deg, deg, mm, mm, mm): {' '.join(f'{v:.2f}' for v in sd)} ({args.misfit:g} x the misfit); "
          f"{len(protocol.trials)} trials")
    met, means = [], []
    for draw in range(args.draws):
        t0 = time.perf_counter()
        copy = twins.twin(model, protocol, fit.params, sd, np.random.default_rng([0, draw]))
        scores = [judged(crossval.hold_out(model, copy, mask, name, **options), copy)
                  for name, mask in crossval.folds(copy)]
        met.append(sum(s <= 1 for s in scores))
        means.append(float(np.mean(scores)))
        print(f"twin {draw}: {met[-1]} of {len(scores)} within 2 mm and 5 deg, mean normalised {means[-1]:.2f} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    print(f"{args.draws} twins: met {min(met)}-{max(met)} of 7 (median {np.median(met):g}), mean normalised "
          f"{min(means):.2f}-{max(means):.2f} (mean {np.mean(means):.2f})")


if __name__ == "__main__":
    main()
