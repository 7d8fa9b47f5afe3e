"""Benchmark: how fast the command line starts (issue target: ``kneenlp --help`` and an argument
error <= 0.5 s on 2 cores).  Prints the best and median wall time (s) of 7 runs of each, as a new
process (interpreter start included), and the heavy modules the start loaded (none expected).
Run: python benchmarks/bench_startup.py
"""

import statistics
import subprocess
import sys
import time

RUNS = 7
CASES = {"kneenlp --help": ["--help"], "argument error (--starts 0)": ["identify", "--starts", "0"]}


def wall(argv: list[str]) -> list[float]:
    times = []
    for _ in range(RUNS):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "kneenlp.cli", *argv], capture_output=True, check=False)
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    print(f"{'case':<30} {'best (s)':>9} {'median (s)':>11}")
    for name, argv in CASES.items():
        t = wall(argv)
        print(f"{name:<30} {min(t):9.3f} {statistics.median(t):11.3f}")
    probe = ("import sys; from kneenlp.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
             "print([m for m in ('casadi', 'scipy', 'pandas', 'numba', 'matplotlib') if m in sys.modules])")
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=False)
    print("heavy modules loaded by --help:", run.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    main()
