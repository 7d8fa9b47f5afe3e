"""Benchmark: which calibration of S192803 predicts what it did not see, each at its global MAP.

Cross-validates (the seven hold-outs of ``kneenlp cross-validate``: the highest flexion, and each
load direction) calibrations of the robot data and prints, per hold-out, the RMS of measured minus
predicted on the held-out trials (deg, mm) and whether it meets 5 deg and 2 mm.  Every calibration
(and every fold's) is the global search from 16 starts, the default, unless named "one start":

- ``source``: the knee's source values (the FE authors' calibration); only the experiment's
  registration and the robot's load point fitted (no ligament parameter moves);
- ``data-only``: least squares, the ligament parameters the trials determine (``--priors none``);
- ``MAP``: every ligament parameter with its prior, weighed against a 1 mm / 1 deg misfit (and
  ``MAP (one start)``: the local chain from the knee's values, ``starts=1``);
- ``MAP weight 0.3`` and ``MAP weight estimated``: the priors weighed against a smaller misfit, or
  the one estimated from the fit's own residuals;
- ``MAP + the six effects``: the experiment's frames, the cruciates' femoral attachments and PCLal's
  bundles (problems/s192803's ``also_free``); the six and the apparatus' neutral zone; the seven,
  with the PFL's tibial attachment;
  ``MAP + frames and femoral attachments``: the frames and every group's femoral attachment (2 mm
  priors), the generic version.

Also the calibration's time, its fitted RMS, the parameters outside their prior's 99.7 % range, and
the spread the search leaves: per variant the mean over the hold-outs of the held-out error's range
over each fold's three lowest minima (a difference between variants within it is a tie).
Run: python benchmarks/bench_priors.py [--only NAME,...]   (about 6 min a variant on 2 cores)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.estimation.calibrate import calibrate
from kneenlp.estimation.choice import LOAD_POINT, REGISTRATION
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem import resolve_priors
from kneenlp.experiment.problem_file import ProblemFile
from kneenlp.validation import crossval

#: The effects the held-out error accepts (docs/real-experiment.md): problems/s192803's also_free.
EFFECTS = list(ProblemFile.load(Path(__file__).resolve().parents[1] / "problems" / "s192803").also_free)
#: Every group's femoral attachment (the generic geometry variant).
FEMORAL = [f"{g}_femoral_attachment" for g in kneenlp.Knee.named("s192803").ligaments]
VARIANTS = {
    "source": {"free": [*REGISTRATION, LOAD_POINT], "priors": "none"},
    "data-only": {"priors": "none"},
    "MAP": {},
    "MAP (one start)": {"starts": 1},
    "MAP weight 0.3": {"prior_weight": 0.3},
    "MAP weight estimated": {"prior_weight": "estimate"},
    "MAP + the six effects": {"also_free": EFFECTS},
    "MAP + the six effects and the neutral zone": {"also_free": [*EFFECTS, "neutral_zone"]},
    "MAP + the six effects (one start)": {"also_free": EFFECTS, "starts": 1},
    "MAP + the seven effects (and the PFL's tibial attachment)": {"also_free": [*EFFECTS, "PFL_tibial_attachment"]},
    "MAP + frames and femoral attachments": {"also_free": ["tibial_origin", "femoral_origin", "tibial_axes", *FEMORAL]},
}


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
        cal = calibrate(model, data, **options, workers=2)  # (the search's processes)
        seconds = time.perf_counter() - t0
        rms = ", ".join(f"{v:.2f}" for v in cal.rms_after.values())
        print(f"{name}: calibration {seconds:.1f} s, success {cal.fit.success}, {len(cal.fit.free)} free, "
              f"prior weight {cal.fit.problem.prior_weight:.3g}; fitted RMS (deg, deg, mm, mm, mm) {rms}; "
              f"outside the prior's 99.7 %: {', '.join(outside_prior(cal.fit)) or 'none'}; MAP objective "
              f"{cal.fit.map_objective:.4f}, set aside: {', '.join(o.trial for o in cal.outliers) or 'none'}; "
              f"{cal.search.advice() if cal.search is not None else 'one start'}", flush=True)
        t0 = time.perf_counter()
        results = crossval.cross_validate(model, data, workers=2, **options)
        spreads = [r.spread() for r in results]
        margin = float(np.nanmean(spreads)) if np.isfinite(spreads).any() else float("nan")
        print(f"  cross-validation, 7 hold-outs (2 processes): {time.perf_counter() - t0:.1f} s; held-out error's "
              f"spread over each fold's lowest minima: {', '.join(f'{v:.2f}' for v in spreads)} (mean {margin:.2f})",
              flush=True)
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
            met = crossval.normalised_error(rms) <= 1
            print(f"  {name:38s} {ok}/{n}  {v[0]:5.2f} {v[1]:5.2f} | {v[2]:5.2f} {v[3]:5.2f} {v[4]:5.2f} "
                  + ("*" if met else ""))
    print("\nsummary: hold-outs meeting both targets; mean over hold-outs of the largest rotation / 5 deg and "
          "translation / 2 mm; hold-outs no worse than source (largest normalised error)")
    for name in errors:
        score = [crossval.normalised_error(errors[name][h][0]) for h in holdouts]
        line = f"  {name:38s} {sum(s <= 1 for s in score)}/7 met, mean normalised {np.mean(score):.2f}"
        if "source" in errors:
            source = [crossval.normalised_error(errors["source"][h][0]) for h in holdouts]
            line += f", no worse than source in {sum(s <= w + 1e-9 for s, w in zip(score, source, strict=True))}/7"
        print(line)


if __name__ == "__main__":
    main()
