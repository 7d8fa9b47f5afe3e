"""Benchmark: the first calibration of ``problems/s192803`` on a fresh machine, then the second.

Runs ``kneenlp identify --problem problems/s192803`` in a fresh process with ``$KNEENLP_CACHE`` an
empty directory (so the femoral distance field, numba's contact kernels and the compiled residuals
are all built), then again with that cache filled (the problem's global search; ``--starts N``
another number of starts).  Prints
the wall time of each and what the cache holds after the first.  Target (issue): the first run
<= 2 min on 2 cores.  Run: python benchmarks/bench_first_run.py [--starts N]
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PROBLEM = Path(__file__).resolve().parents[1] / "problems" / "s192803"


def run(cache: Path, out: Path, starts: int) -> float:
    env = os.environ | {"KNEENLP_CACHE": str(cache), "NUMBA_CACHE_DIR": str(cache / "numba")}
    argv = [sys.executable, "-m", "kneenlp.cli", "identify", "--problem", str(PROBLEM), "--out", str(out)]
    if starts > 1:
        argv += ["--starts", str(starts)]
    t0 = time.perf_counter()
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=1, help="the global search's starts (default: the problem's)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp) / "cache"
        first = run(cache, Path(tmp) / "first", args.starts)
        held = sorted(p.relative_to(cache).parts[0] for p in cache.glob("*"))
        second = run(cache, Path(tmp) / "second", args.starts)
    label = f"starts {args.starts}" if args.starts > 1 else "the problem's starts"
    print(f"{label}: first run (empty cache) {first:.1f} s, second {second:.1f} s; "
          f"the cache held: {', '.join(held)}")


if __name__ == "__main__":
    main()
