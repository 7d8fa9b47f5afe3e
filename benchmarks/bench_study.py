"""Benchmark: the paper's full noise study (4 sets x 20 samples, uniform +-0.5) on local processes.

Target: <= 60 s on the 2-core machine.  Also prints the per-set mean time per fit and
the extrapolated time of 1000 samples per set.
Run: python benchmarks/bench_study.py [samples] [workers] [scatter|truth]
"""

import sys
import tempfile
import time
from pathlib import Path

from kneenlp.studies.study import StudySpec, run_study


def main(samples: int = 20, workers: int = 2, start: str = "scatter") -> None:
    out = Path(tempfile.mkdtemp()) / "study"
    t0 = time.perf_counter()
    spec = StudySpec(samples=samples, seed=0, start=start)
    study = run_study(spec, out, workers=workers, progress=False, analyse=False)
    run = time.perf_counter() - t0
    t1 = time.perf_counter()
    from kneenlp.studies.report import analyse_study

    analyse_study(study)
    analysis = time.perf_counter() - t1
    df = study.load_rows()
    print(f"{len(df)} fits ({samples} per set, {workers} workers, {start} starts): run {run:.1f} s, "
          f"analysis {analysis:.1f} s, failed {int((~df['success'].astype(bool)).sum())}")
    per_set = df.groupby("set")["wall_seconds"].mean()
    for s, v in per_set.items():
        print(f"  {s}: {v:.2f} s per fit (one core)")
    extrapolated = 1000 * per_set.sum() / workers
    print(f"  1000 samples per set, extrapolated: {extrapolated / 60:.0f} min on {workers} workers")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]), *sys.argv[3:4])
