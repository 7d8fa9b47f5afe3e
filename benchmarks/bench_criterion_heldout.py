"""Does ``diagnose``'s recommendation (likelihood-ratio tests and BIC) agree with the held-out error
on simulated data?

On a real experiment a candidate effect is recommended only when it lowers the cross-validated
error (:func:`~kneenlp.validation.crossval.judge`).  On data the model produced (noise studies,
hidden-effect tests) ``diagnose`` recommends by its tests; this benchmark measures whether the held
-out error would choose the same, so that the tests may stand in for it there.

Each case simulates the synthetic knee (``--knee`` for another) with one hidden effect (or none),
fits the base model, diagnoses it, then judges the base model and the ``--top`` best-ranked
candidates by what they predict: each fitted (least squares, the paper's) on all trials but one
hold-out of :func:`~kneenlp.validation.crossval.folds` (the highest flexion; each load direction)
and predicting the held-out trials.  The held-out error of a fit is the RMS of measured minus
predicted over every held-out coordinate, in units of the declared noise's sd (1: as good as the
noise allows), averaged over the hold-outs; the held-out choice is the candidate with the lowest,
if lower than the base's (every held-out trial at equilibrium), else none.

Agreement: the recommendation (or none) equals the held-out choice.  Each case is one line of
``<out>/cases.jsonl`` (resumable); the summary is printed from all lines.

    python benchmarks/bench_criterion_heldout.py --out bench-criterion
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.adequacy.basefit import base_fit
from kneenlp.adequacy.diagnosis import diagnose
from kneenlp.estimation.solve import ScatterSettings, scatter_fit
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData, read_measured
from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.prediction.predict import predict
from kneenlp.validation.crossval import folds

NOISE = "uniform:0.5"
#: (name, protocol, hidden parameter values SI, seed): the hidden-effect tests' cases and clean data.
CASES = [
    ("posterior_capsule", "set3", {"posterior_capsule.k": 8000.0}, 7),
    ("registration", "set3", {"registration.anterior_translation": 1.5e-3,
                              "registration.internal_rotation": 0.026}, 11),
    ("flexion_offset", "set4", {"flexion_offset.delta": 0.07}, 3),
    ("contact_modulus", "set4", {"contact.modulus": 2.5e9}, 3000),
    ("MCL_tibial_attachment", "set3", {"MCL.tibia_anterior": 4e-3}, 3),
    ("meniscus", "set3", {"meniscus.k": 4e4}, 5),
    ("clean", "set3", {}, 101),
    ("clean", "set4", {}, 102),
    ("clean", "set3", {}, 103),
]


def held_out_error(model: KneeModel, data: MeasuredData, extra: list[str], sigma: float, seed: int) -> float | None:
    """Mean over the hold-outs of the held-out RMS (in noise sds) of fits with ``extra`` effects
    free beside the base model's parameters; None when a held-out trial has no equilibrium."""
    errors = []
    for _, held in folds(data):
        problem = IdentificationProblem.from_data(model, data.subset(~held), with_effects=extra, noise=NOISE)
        fit = scatter_fit(problem, {}, ScatterSettings(seed=seed))  # the paper's least squares, as diagnose's base fit
        pred = predict(model, data.subset(held), fit.params)
        if not pred.converged.all():
            return None
        errors.append(float(np.sqrt(np.mean(pred.errors_user**2))) / sigma)
    return float(np.mean(errors))


def run_case(knee, name: str, protocol: str, values: dict, seed: int, top: int, tmp: Path) -> dict:
    """Simulate, diagnose, and judge the base and the top candidates by their held-out error."""
    path = tmp / "case.csv"
    kneenlp.simulate(knee, protocol, parameters=values).measured(NOISE, seed).to_csv(path, index=False)
    data = read_measured(path)
    t0 = time.perf_counter()
    d = diagnose(base_fit(knee, data, NOISE, seed=seed), NOISE)
    model = KneeModel.of(knee)
    sigma = NoiseModel.parse(NOISE).std
    candidates = [s.effect for s in d.ranking[:top]]
    held = {"base": held_out_error(model, data, [], sigma, seed)}
    held |= {c: held_out_error(model, data, [c], sigma, seed) for c in candidates}
    whole = {c: v for c, v in held.items() if c != "base" and v is not None}
    best = min(whole, key=whole.get, default=None)
    choice = best if best is not None and held["base"] is not None and whole[best] < held["base"] else None
    recommended = d.recommended.effect if d.recommended else None
    return {"case": name, "protocol": protocol, "seed": seed, "outcome": d.outcome, "recommended": recommended,
            "held_out_choice": choice, "held_out": held, "agree": recommended == choice,
            "seconds": time.perf_counter() - t0}


def summary(rows: list[dict]) -> str:
    lines = [f"{'case':24s} {'protocol':8s} {'recommended (tests)':24s} {'held-out choice':24s} agree  "
             "held-out error (noise sds): base, candidates"]
    for r in rows:
        cells = ", ".join(f"{k} {v:.2f}" if v is not None else f"{k} n.e." for k, v in r["held_out"].items())
        lines.append(f"{r['case']:24s} {r['protocol']:8s} {r['recommended']!s:24s} {r['held_out_choice']!s:24s} "
                     f"{'yes' if r['agree'] else 'NO':5s}  {cells}")
    agree = sum(r["agree"] for r in rows)
    lines.append(f"agreement: {agree} of {len(rows)} cases; {np.mean([r['seconds'] for r in rows]):.0f} s per case "
                 "(n.e.: a held-out trial without equilibrium)")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--knee", default="synthetic")
    parser.add_argument("--top", type=int, default=2, help="candidates judged per case (default 2)")
    parser.add_argument("--out", type=Path, default=Path("bench-criterion"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    log = args.out / "cases.jsonl"
    done = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
    keys = {(r["case"], r["protocol"], r["seed"]) for r in done}
    knee = kneenlp.Knee.named(args.knee)
    for name, protocol, values, seed in CASES:
        if (name, protocol, seed) in keys:
            continue
        row = run_case(knee, name, protocol, values, seed, args.top, args.out)
        with log.open("a") as f:
            f.write(json.dumps(row) + "\n")
        done.append(row)
        print(summary([row]).splitlines()[1], flush=True)
    print(summary(done))


if __name__ == "__main__":
    main()
