"""Benchmark: every candidate effect refitted, one at a time, from the S192803 calibration.

For each of the knee's candidate effects (meniscus springs, flexion offset, load point, contact
modulus, ligament-group stiffness and slack, every group's femoral and tibial attachments), the
calibration's free parameters plus the candidate's are fitted by reduced-space Gauss-Newton from
the calibrated values (the candidate at neutral, every trial warm-started from its calibrated
pose).  Prints, per candidate: parameters added, sum of squared residuals (mm^2 + deg^2, 25 trials),
its change against the calibration, the RMS over the loaded trials (deg, deg, mm, mm, mm) and the
seconds taken.  ~15 min on 2 cores.
Run: python benchmarks/bench_real_candidates.py
"""

from __future__ import annotations

import time

import numpy as np

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.estimation.calibrate import calibrate
from kneenlp.estimation.solve import reduced_fit
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.prediction.predict import rms_by_coordinate


def main() -> None:
    model = KneeModel.of(kneenlp.Knee.named("s192803"))
    data = read_measured(resource("datasets", "s192803_laxity.csv"))
    fit = calibrate(model, data, keep_outliers=True).fit
    loaded = np.array([t.dominant != "none" for t in data.trials])
    base = float(np.sum(fit.residuals**2))
    print(f"calibration: {len(fit.free)} free, sum of squares {base:.1f}")
    rows = []
    for effect in model.effects:
        names = [n for n in effect.free_names() if n not in fit.free]
        if not names or effect.name.startswith("registration"):
            continue
        t0 = time.perf_counter()
        problem = IdentificationProblem.from_data(model, data, [*fit.free, *names], with_effects=[effect.name])
        start = fit.params | {n: float(model.theta()[model.index(n)]) for n in names}
        refit = reduced_fit(problem, start, q0=fit.q_pred, max_evaluations=60)
        r = data.q_user - refit.predicted_user
        ss = float(np.sum(r**2))
        rms = ", ".join(f"{v:.2f}" for v in rms_by_coordinate(r[loaded]).values())
        rows.append((ss, effect.name))
        print(f"{effect.name:28s} +{len(names)}  sum of squares {ss:7.1f} ({100 * (ss / base - 1):+5.1f} %)  "
              f"loaded RMS {rms}  {time.perf_counter() - t0:5.1f} s", flush=True)
    print("best:", ", ".join(f"{n} {ss:.1f}" for ss, n in sorted(rows)[:5]))


if __name__ == "__main__":
    main()
