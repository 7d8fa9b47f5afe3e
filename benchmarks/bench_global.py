"""Benchmark: the global calibration of ``problems/s192803`` is one answer, whatever the path.

Runs the problem's calibration (the global search, ``kneenlp.estimation.search``) in fresh
processes under each setting: BLAS threads 1 and 2, search workers 1 and 2, compiled residuals on
and off, the data and the knee's values perturbed by 1e-12 relative, and the solves on a local Dask
cluster.  Prints, per setting, the
kept MAP objective, how many solves reached it, the distinct minima and the wall time; then the
largest spread of the kept objective (relative) and of the kept parameters (prior sd) over the
settings.  The target: the same kept minimum (1e-6 relative, 1e-4 prior sd), reached by at least 3
solves, the one docs/real-experiment.md quotes (tests/test_search.py checks one setting).

Run: python benchmarks/bench_global.py [--problem DIR] [--starts N] [--settings NAME,...]   (about 1 min per setting)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

PROBLEM = Path(__file__).resolve().parents[1] / "problems" / "s192803"
SETTINGS = {
    "blas2-workers2": ({"OPENBLAS_NUM_THREADS": "2"}, {"workers": 2}),
    "blas1-workers2": ({"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}, {"workers": 2}),
    "blas2-workers1": ({"OPENBLAS_NUM_THREADS": "2"}, {"workers": 1}),
    "interpreted": ({"KNEENLP_COMPILE": "off"}, {"workers": 2}),
    "data+1e-12": ({}, {"workers": 2, "perturb_data": 1e-12}),
    "start+1e-12": ({}, {"workers": 2, "perturb_start": 1e-12}),
    "dask": ({}, {"workers": "dask"}),
}


def one(options: dict) -> dict:
    """The calibration under ``options`` in this process: its kept minimum and search, as a record."""
    import kneenlp
    from kneenlp.estimation.calibrate import calibrate
    from kneenlp.estimation.minima import standardised
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.experiment.measured import MeasuredData, read_measured
    from kneenlp.experiment.problem_file import ProblemFile

    problem = ProblemFile.load(options.get("problem", PROBLEM))
    base = kneenlp.Knee.named(problem.knee)
    if options.get("perturb_start"):  # the knee's values: the first start and the priors' centres
        model = KneeModel.of(base)
        theta = model.theta() * (1 + options["perturb_start"])
        values = {n: float(theta[model.index(n)]) for n in base.parameters.names()}
        base = base.with_parameters(base.parameters.with_values(values))
    knee = problem.knee_with_parameters(base)
    data = read_measured(problem.data)
    if options.get("perturb_data"):
        data = MeasuredData.from_user(data.trials, data.q_user * (1 + options["perturb_data"]), data.protocol,
                                      data.source, side=data.side, experiment=data.experiment)
    model = KneeModel.of(knee)
    workers = options.get("workers", 2)
    if workers == "dask":  # a local Dask cluster of two single-threaded worker processes
        from kneenlp.base.dask_cluster import DaskWorkers

        workers = DaskWorkers(processes=2)
    calibration_options = problem.calibrate_options() | {"workers": workers}
    if options.get("starts"):
        calibration_options["starts"] = options["starts"]
    t0 = time.perf_counter()
    cal = calibrate(model, data, **calibration_options)
    seconds = time.perf_counter() - t0
    fit, found = cal.fit, cal.search
    return {"objective": fit.map_objective, "hits": found.best.hits, "minima": len(found.minima),
            "solves": len(found.ends), "seconds": seconds, "set_aside": list(found.set_aside),
            "z": standardised(fit.problem, fit.params).tolist(), "free": fit.free,
            "lowest": [m.objective for m in found.minima[:5]]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=None, help="starts (default: the problem's)")
    parser.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated, of: " + ", ".join(SETTINGS))
    parser.add_argument("--problem", default=str(PROBLEM), help="the problem folder (default: problems/s192803)")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(one(json.loads(args.one))))
        return
    records = {}
    for name in args.settings.split(","):
        env, options = SETTINGS[name]
        options = options | {"problem": args.problem} | ({"starts": args.starts} if args.starts else {})
        out = subprocess.run([sys.executable, __file__, "--one", json.dumps(options)], env=os.environ | env,
                             capture_output=True, text=True, check=True)
        r = records[name] = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{name:16s} MAP objective {r['objective']:.6f}, reached by {r['hits']} of {r['solves']} solves, "
              f"{r['minima']} minima (lowest {', '.join(f'{v:.3f}' for v in r['lowest'])}), set aside "
              f"{','.join(r['set_aside']) or 'none'}, {r['seconds']:.1f} s", flush=True)
    objectives = np.array([r["objective"] for r in records.values()])
    z = np.array([r["z"] for r in records.values()])
    print(f"spread over {len(records)} settings: objective {np.ptp(objectives) / objectives.min():.2e} relative, "
          f"parameters {np.ptp(z, axis=0).max():.2e} prior sd")


if __name__ == "__main__":
    main()
