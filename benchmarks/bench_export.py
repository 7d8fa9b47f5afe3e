"""Benchmark: the C export of a mesh knee.  Exports the default knee's identification
of Set 2 (uniform +-0.5, seed 2) as C, compiles it with gcc at each optimisation level given, and
times one evaluation of every exported function; also the CasADi virtual machine's time for the
same functions in both field layouts (``graph_field.LAYOUTS``).
Run: python benchmarks/bench_export.py [O0 O1 ...]
"""

import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import casadi as ca
import numpy as np

import kneenlp
from kneenlp.io.export import _derivative_functions, export_problem, write_export

NAMES = ("nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l")


def inputs(prob, fn: ca.Function) -> list:
    values = {"x": prob.x0, "p": prob.p_value, "lam_f": 1.0, "lam_g": np.ones(len(prob.con_names))}
    return [values[n] for n in fn.name_in()]


def timed(fn: ca.Function, args: list) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t0


def main(levels: list[str]) -> None:
    knee = kneenlp.Knee.named("default")
    tmp = Path(tempfile.mkdtemp())
    kneenlp.simulate(knee, "set2").measured("uniform:0.5", 2).to_csv(tmp / "m.csv", index=False)
    for layout in ("vector", "loop"):
        prob = export_problem(knee, tmp / "m.csv", seed=2, layout=layout)
        times = {fn.name(): timed(fn, inputs(prob, fn)) for fn in _derivative_functions(prob)}
        print(f"CasADi virtual machine, layout {layout}: " + ", ".join(f"{n} {t:.3f} s" for n, t in times.items()))
    t0 = time.perf_counter()
    write_export(prob, "c", tmp / "c")
    source = tmp / "c" / "kneenlp_nlp.c"
    print(f"export --format c ({len(prob.var_names)} variables, {len(prob.con_names)} constraints): "
          f"{time.perf_counter() - t0:.1f} s, {source.stat().st_size / 1e6:.0f} MB of C")
    if shutil.which("gcc") is None:
        print("no gcc: compilation not measured")
        return
    for level in levels:
        lib = tmp / "c" / f"lib_{level}.so"
        t0 = time.perf_counter()
        subprocess.run(["gcc", "-shared", "-fPIC", f"-{level}", str(source), "-o", str(lib), "-lm"], check=True)
        compile_s = time.perf_counter() - t0
        times = {n: timed(f := ca.external(n, str(lib)), inputs(prob, f)) for n in NAMES}
        print(f"gcc -{level}: compile {compile_s:.1f} s; " + ", ".join(f"{n} {t:.3f} s" for n, t in times.items()))


if __name__ == "__main__":
    main(sys.argv[1:] or ["O0", "O1"])
