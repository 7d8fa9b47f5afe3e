"""Benchmark: the OpenSim JAM Lenhart 2015 model imported as a multi-bundle knee.

Prints: the time to import the .osim (55 Blankevoort1991Ligament bundles, coarse groups) with the
femoral distance field cold (new cache directory) and warm; the forward solve of Set 4 and of
Set 4 + high flexion; and the simultaneous identification of Set 4 (uniform +-0.5 mm/deg noise,
12 grouped parameters: each group's stiffness scale and reference-strain offset) from the
paper's scatter, median over seeds.  Times in seconds, on this machine (2 cores).
Run: python benchmarks/bench_osim.py [n_seeds]
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.base.resources import resource
from kneenlp.estimation.identify import identify
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.io.import_osim import import_osim

DATA = resource("knees", "lenhart2015", "opensim")


def timed_import(out: Path) -> tuple[float, float, kneenlp.Knee]:
    """Seconds to write the knee files and seconds to load the knee (field built or read from cache)."""
    t0 = time.perf_counter()
    import_osim(DATA / "lenhart2015.osim", out, groups="coarse",
                femur_mesh=DATA / "lenhart2015-R-femur-subchondral-bone.stl", femur_offset=0.002)
    t1 = time.perf_counter()
    knee = kneenlp.Knee.load(out / "knee.toml")
    KneeModel.of(knee)  # builds the model and the distance field
    return t1 - t0, time.perf_counter() - t1, knee


def main(n_seeds: int) -> None:
    tmp = Path(tempfile.mkdtemp())
    os.environ["KNEENLP_CACHE"] = str(tmp / "cache")
    write, load_cold, _ = timed_import(tmp / "cold")
    _, load_warm, knee = timed_import(tmp / "warm")
    n_bundles = sum(len(lig.bundles) for lig in knee.ligaments.values())
    print(f"import-osim ({n_bundles} bundles, {len(knee.ligaments)} groups): write {write:.2f} s; "
          f"load with the distance field cold {load_cold:.2f} s, cached {load_warm:.2f} s")

    for name in ("set4", "set4_high_flexion"):
        for run in ("first", "second"):
            t0 = time.perf_counter()
            res = kneenlp.simulate(knee, name)
            dt = time.perf_counter() - t0
            print(f"forward {name} ({len(res.solutions)} trials), {run} call: {dt:.2f} s, "
                  f"failed {len(res.failed)}, max residual {res.max_residual:.1e}")

    res = kneenlp.simulate(knee, "set4")
    rows = []
    for seed in range(n_seeds):
        path = tmp / f"set4_{seed}.csv"
        res.measured("uniform:0.5", seed).to_csv(path, index=False)
        t0 = time.perf_counter()
        fit = identify(knee, path, seed=seed, noise="uniform:0.5")
        total = time.perf_counter() - t0
        rows.append((fit.success, fit.iterations, fit.seconds, total))
        print(f"  identify Set 4 seed {seed}: success {fit.success}, {len(fit.free)} parameters, "
              f"{fit.iterations} iterations, IPOPT {fit.seconds:.2f} s, total {total:.2f} s", flush=True)
    it, ipopt, total = (float(np.median([r[i] for r in rows])) for i in (1, 2, 3))
    print(f"identification Set 4 on the multi-bundle knee: median of {n_seeds} seeds {it:.0f} iterations, "
          f"IPOPT {ipopt:.2f} s, total {total:.2f} s, converged {sum(r[0] for r in rows)}/{n_seeds}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
