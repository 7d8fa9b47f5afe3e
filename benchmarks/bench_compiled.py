"""Benchmark: CasADi's virtual machine beside the compiled per-trial functions (kneenlp.base.compiled).

Each job runs twice in a fresh process: ``KNEENLP_COMPILE=off`` (the virtual machine) and
``KNEENLP_COMPILE=wait`` after the libraries are in the cache (compiled).  Prints the seconds of
each and the result, which must be the same to the last digit:

- the default knee: forward Set 4 (60 trials, cold) and ``identify`` of noisy Set 4 (seed 0);
- S192803: the calibration of problems/s192803 with one start (MAP and the effects its
  ``also_free`` names).

Also the time one compile of a knee's two functions takes (the libraries removed first, in a
private cache directory; distance fields are copied from the user's cache).
Run: python benchmarks/bench_compiled.py   (about 3 min on 2 cores)
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from kneenlp.base.cache import cache_dir

PROBLEM = str(Path(__file__).resolve().parents[1] / "problems" / "s192803")

JOBS = {
    "default knee, forward Set 4": """
from kneenlp import Knee, Protocol
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.solvers.forward import ForwardSolver
model = KneeModel(Knee.default()); solver = ForwardSolver(model); trials = Protocol.load("set4").trials
model._residual_and_jacobian
t = time.perf_counter(); sols = solver.solve(trials, model.theta()); seconds = time.perf_counter() - t
result = sum(float(abs(s.q).sum()) for s in sols)
""",
    "default knee, identify noisy Set 4": """
import tempfile, kneenlp
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
knee = kneenlp.Knee.default(); KneeModel.of(knee)._residual_and_jacobian
path = tempfile.mktemp(suffix=".csv")
kneenlp.simulate(knee, "set4").measured("uniform:0.5", 0).to_csv(path, index=False)
t = time.perf_counter(); fit = kneenlp.identify(knee, read_measured(path), seed=0, noise="uniform:0.5")
seconds = time.perf_counter() - t; result = fit.objective
""",
    "S192803, problems/s192803 with 1 start": f"""
import kneenlp
from kneenlp.base.resources import resource
from kneenlp.estimation.calibrate import calibrate
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import read_measured
from kneenlp.experiment.problem_file import ProblemFile
EFFECTS = list(ProblemFile.load({PROBLEM!r}).also_free)
model = KneeModel.of(kneenlp.Knee.named("s192803")); model._residual_and_jacobian; model.jacobians
data = read_measured(resource("datasets", "s192803_laxity.csv"))
t = time.perf_counter(); cal = calibrate(model, data, also_free=EFFECTS, starts=1); seconds = time.perf_counter() - t
result = cal.fit.map_objective
""",
}


def run(code: str, env: dict) -> tuple[float, float, float]:
    """(the job's seconds, its result, the process's seconds) of ``code`` in a fresh process."""
    script = (f"import time\nstart = time.perf_counter()\n{code}\n"
              "print(seconds, repr(result), time.perf_counter() - start)")
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
    seconds, result, total = out.stdout.split()[-3:]
    return float(seconds), float(result), float(total)


def main() -> None:
    with tempfile.TemporaryDirectory() as private:
        user = cache_dir()
        if user is not None:  # the distance fields and numba's code, not the libraries
            shutil.copytree(user, private, dirs_exist_ok=True, ignore=shutil.ignore_patterns("compiled"))
        env = os.environ | {"KNEENLP_CACHE": private}
        t = time.perf_counter()
        run(JOBS["S192803, problems/s192803 with 1 start"].split("data =")[0] + "seconds = result = 0",
            env | {"KNEENLP_COMPILE": "wait"})
        print(f"compiling S192803's two functions (and loading the knee): {time.perf_counter() - t:.1f} s")
        for name, code in JOBS.items():
            run(code, env | {"KNEENLP_COMPILE": "wait"})  # the libraries into the cache
            vm = run(code, env | {"KNEENLP_COMPILE": "off"})
            cc = run(code, env | {"KNEENLP_COMPILE": "wait"})
            same = "the same" if vm[1] == cc[1] else f"DIFFERENT ({vm[1]!r} vs {cc[1]!r})"
            print(f"{name}: virtual machine {vm[0]:.2f} s, compiled {cc[0]:.2f} s ({vm[0] / cc[0]:.2f}x); "
                  f"process {vm[2]:.1f} -> {cc[2]:.1f} s; result {same}")


if __name__ == "__main__":
    main()
