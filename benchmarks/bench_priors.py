"""Benchmark (issue 38): which calibration of S192803 predicts what it did not see.

Cross-validates (the seven hold-outs of ``kneenlp cross-validate``: the highest flexion, and each
load direction) four calibrations of the robot data and prints, per hold-out, the RMS of measured
minus predicted on the held-out trials (deg, mm) and whether it meets 5 deg and 2 mm:

- ``source``: the knee's source values (the FE authors' calibration); only the experiment's
  registration and the robot's load point fitted (no ligament parameter moves);
- ``data-only``: least squares, the ligament parameters the trials determine (``--priors none``);
- ``MAP``: the default, every ligament parameter with its prior, weighed against a 1 mm / 1 deg misfit;
- ``MAP, weight estimated``: the same with the prior weight estimated from the fit's own residuals.

Also the calibration's time, its fitted RMS, and the parameters outside their prior's 99.7 % range.
Run: python benchmarks/bench_priors.py [--only NAME,...]   (about 4 min on 2 cores)
"""

from __future__ import annotations

import sys
import time

import numpy as np

import kneenlp
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import resolve_priors
from kneenlp.inference import crossval
from kneenlp.inference.calibrate import LOAD_POINT, REGISTRATION, calibrate
from kneenlp.io.resources import resource
from kneenlp.model.kneemodel import KneeModel

VARIANTS = {
    "source": {"free": [*REGISTRATION, LOAD_POINT], "priors": "none"},
    "data-only": {"priors": "none"},
    "MAP": {},
    "MAP, weight estimated": {"prior_weight": "estimate"},
}
ROTATION, TRANSLATION = 5.0, 2.0


def outside_prior(fit) -> list[str]:
    """The fitted parameters outside the 99.7 % range of their priors (the default ones for a fit without)."""
    return fit.outside_prior(fit.problem.priors or resolve_priors(fit.model, fit.free, "default"))


def main() -> None:
    only = sys.argv[sys.argv.index("--only") + 1].split(",") if "--only" in sys.argv else list(VARIANTS)
    model = KneeModel.of(kneenlp.Knee.named("s192803"))
    data = read_measured(resource("datasets", "s192803_laxity.csv"))
    errors = {}
    for name in only:
        options = VARIANTS[name]
        t0 = time.perf_counter()
        cal = calibrate(model, data, **options)
        seconds = time.perf_counter() - t0
        rms = ", ".join(f"{v:.2f}" for v in cal.rms_after.values())
        print(f"{name}: calibration {seconds:.1f} s, success {cal.fit.success}, {len(cal.fit.free)} free, "
              f"prior weight {cal.fit.problem.prior_weight:.3g}; fitted RMS (deg, deg, mm, mm, mm) {rms}; "
              f"outside the prior's 99.7 %: {', '.join(outside_prior(cal.fit)) or 'none'}")
        t0 = time.perf_counter()
        results = crossval.cross_validate(model, data, **options)
        print(f"  cross-validation, 7 hold-outs: {time.perf_counter() - t0:.1f} s")
        errors[name] = {r.name: (r.rms(), int(r.prediction.converged.sum()), len(r.prediction.solutions))
                        for r in results}
    holdouts = list(next(iter(errors.values())))
    print("\nHeld-out RMS: rotations (varus, internal; deg) | translations (lateral, anterior, proximal; mm); "
          "* = meets 5 deg and 2 mm")
    for h in holdouts:
        print(f"{h}")
        for name in errors:
            rms, ok, n = errors[name][h]
            v = list(rms.values())
            met = max(v[:2]) <= ROTATION and max(v[2:]) <= TRANSLATION
            print(f"  {name:24s} {ok}/{n}  {v[0]:5.2f} {v[1]:5.2f} | {v[2]:5.2f} {v[3]:5.2f} {v[4]:5.2f} "
                  + ("*" if met else ""))
    print("\nsummary: hold-outs meeting both targets; mean over hold-outs of the largest rotation / 5 deg and "
          "translation / 2 mm; hold-outs no worse than source (largest normalised error)")
    for name in errors:
        met, score, no_worse = 0, [], 0
        for h in holdouts:
            v = list(errors[name][h][0].values())
            s = max(max(v[:2]) / ROTATION, max(v[2:]) / TRANSLATION)
            score.append(s)
            met += s <= 1
            if "source" in errors:
                w = list(errors["source"][h][0].values())
                no_worse += s <= max(max(w[:2]) / ROTATION, max(w[2:]) / TRANSLATION) + 1e-9
        print(f"  {name:24s} {met}/7 met, mean normalised {np.mean(score):.2f}"
              + (f", no worse than source in {no_worse}/7" if "source" in errors else ""))


if __name__ == "__main__":
    main()
