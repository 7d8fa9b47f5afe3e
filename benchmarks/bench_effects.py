"""Benchmark: each candidate effect of S192803 judged by what it predicts, beside its twin.

The table of docs/real-experiment.md ("Which effects the held-out error accepts").  Per variant
(the MAP calibration and what it frees beside it, ``also_free``): the free parameters, the MAP
objective, the fitted RMS (deg; mm), the seven hold-outs of ``kneenlp cross-validate`` (met within
5 deg and 2 mm, the mean normalised error and the spread the global search leaves: the mean over
the hold-outs of each fold's range over its lowest minima) and the same hold-outs of ``--twins N``
twins of the experiment as that variant calibrates it (the calibrated knee, noise at its misfit):
the range of met and of the mean an exactly right model of that kind reaches, and how many
hold-outs the knee predicts no worse than the worst twin (the target: all).  Every calibration,
every fold's and every twin's is the global search of problems/s192803 (16 starts).

A structure the shipped knee does not declare (the popliteus, the oblique popliteal ligament, a
meniscal rim) is added to a copy of the knee as its knee-file table with ``candidate = true``:
default attachments and priors, neutral until freed.

Run: python benchmarks/bench_effects.py [--only NAME,...] [--twins N] [--fitted-only | --held-out-only]
[--store DIR]
(``--store``: each variant's searches' finished solves and its twin draws kept under DIR/<variant>,
so a rerun resumes where an interrupted one stopped).  A variant on 2 cores: its calibration 1-2 min, the hold-outs
5-9 min, each twin 15-25 min; with the superficial MCL over the tibia (paths solved at every pose)
far longer.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.estimation.calibrate import calibrate
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem_file import ProblemFile
from kneenlp.validation import crossval

PROBLEM = Path(__file__).resolve().parents[1] / "problems" / "s192803"
PROBLEM_FILE = ProblemFile.load(PROBLEM)
#: The effects problems/s192803 frees beside the MAP calibration (the six the held-out error accepts).
SIX = list(PROBLEM_FILE.also_free)
#: Every group's femoral attachment (the generic geometry variant).
FEMORAL = [f"{g}_femoral_attachment" for g in kneenlp.Knee.named("s192803").ligaments]
#: name: (the calibration's options beside the problem's, the structure added to the knee file or None)
VARIANTS = {
    "none": ({"also_free": []}, None),
    "six": ({"also_free": SIX}, None),
    "six+neutral_zone": ({"also_free": [*SIX, "neutral_zone"]}, None),
    "six+PFL_tibial_attachment": ({"also_free": [*SIX, "PFL_tibial_attachment"]}, None),
    "six+neutral_zone+PFL_tibial_attachment": ({"also_free": [*SIX, "neutral_zone", "PFL_tibial_attachment"]}, None),
    "six+popliteus": ({"also_free": [*SIX, "popliteus"]}, "popliteus"),
    "six+oblique_popliteal": ({"also_free": [*SIX, "oblique_popliteal"]}, "oblique_popliteal"),
    "six+meniscal_rim": ({"also_free": [*SIX, "meniscal_rim"]}, "meniscal_rim"),
    "six+sMCL_over_tibia": ({"also_free": SIX}, "sMCL_over_tibia"),
    "weight 0.3": ({"also_free": [], "prior_weight": 0.3}, None),
    "weight estimated": ({"also_free": [], "prior_weight": "estimate"}, None),
    "least squares": ({"also_free": [], "priors": "none"}, None),
    "frames and femoral attachments": ({"also_free": ["tibial_origin", "femoral_origin", "tibial_axes", *FEMORAL]},
                                       None),
}


#: The superficial MCL's groups over the tibia's own surface (``shape = "bone"``).
OVER_THE_TIBIA = "".join(f'\n[ligaments.{g}.wrap]\nshape = "bone"\nbody = "tibia"\n' for g in ("MCLa", "MCLm", "MCLp"))


def knee_with(structure: str | None, folder: Path) -> kneenlp.Knee:
    """The S192803 knee, with ``structure``'s table declared as a candidate in a copy of its file
    (``sMCL_over_tibia``: the superficial MCL's paths over the tibia, :data:`OVER_THE_TIBIA`)."""
    if structure is None:
        return kneenlp.Knee.named("s192803")
    copy = folder / structure
    shutil.copytree(resource("knees", "s192803"), copy)
    with open(copy / "knee.toml", "a") as f:
        f.write(OVER_THE_TIBIA if structure == "sMCL_over_tibia" else f"\n[{structure}]\ncandidate = true\n")
    return kneenlp.Knee.load(copy / "knee.toml")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=",".join(VARIANTS), help="variants, comma-separated")
    parser.add_argument("--twins", type=int, default=2, help="twins per variant")
    parser.add_argument("--fitted-only", action="store_true", help="the calibrations only (no hold-out, no twin)")
    parser.add_argument("--held-out-only", action="store_true", help="the hold-outs only (the calibration's row: "
                        "--fitted-only)")
    parser.add_argument("--store", type=Path, help="keep finished solves and twin draws here (a rerun resumes)")
    args = parser.parse_args()
    problem = PROBLEM_FILE
    data = read_measured(problem.data)
    base = {k: v for k, v in problem.calibrate_options().items() if k != "also_free"}
    print(f"problems/s192803 frees {', '.join(problem.also_free)} beside the MAP calibration; options {base}")
    print("| variant | free | MAP objective | fitted RMS varus / internal (deg) \\| lateral / anterior / proximal "
          "(mm) | held out: met, mean +- spread | per hold-out | twins: met, mean | hold-outs within the twins' "
          "worst | seconds |")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.only.split(","):
            options, structure = VARIANTS[name]
            options = base | options
            model = KneeModel.of(knee_with(structure, Path(tmp)))
            kept = None if args.store is None else args.store / name.replace(" ", "_")
            t0 = time.perf_counter()
            fitted = f"| {name} | - | - | - | "
            if not args.held_out_only:
                cal = calibrate(model, data, **options, workers=2, store=kept and kept / crossval.SOLVES)
                rms = list(cal.rms_after.values())
                fitted = (f"| {name} | {len(cal.fit.free)} | {cal.fit.map_objective:.4f} | "
                          f"{rms[0]:.2f} / {rms[1]:.2f} \\| {rms[2]:.2f} / {rms[3]:.2f} / {rms[4]:.2f} | ")
            if args.fitted_only:
                print(f"{fitted}{time.perf_counter() - t0:.0f} |", flush=True)
                continue
            results = crossval.cross_validate(model, data, **options, workers=2, reference_draws=args.twins,
                                              store=kept)
            scores = [r.normalised() for r in results]
            spread = float(np.nanmean([r.spread() for r in results]))
            twins = np.array([r.reference_normalised() for r in results]).reshape(len(results), -1)  # hold-outs x draws
            twin_met = (twins <= 1).sum(axis=0)
            twin_mean = twins.mean(axis=0)
            outside = [f"{r.name} {s:.2f} > {np.nanmax(t):.2f}" for r, s, t in zip(results, scores, twins, strict=True)
                       if s > np.nanmax(t)]
            named = f" ({', '.join(outside)})" if outside else ""
            inside = f"{len(results) - len(outside)} of {len(results)}{named}" if args.twins else "-"
            twin = (f"{twin_met.min()}-{twin_met.max()} of 7, {twin_mean.min():.2f}-{twin_mean.max():.2f}"
                    if args.twins else "-")
            print(f"{fitted}{sum(s <= 1 for s in scores)} of 7, {np.mean(scores):.2f} +- {spread:.2f} | "
                  f"{' '.join(f'{r.name}:{s:.2f}' for r, s in zip(results, scores, strict=True))} | {twin} | "
                  f"{inside} | {time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
