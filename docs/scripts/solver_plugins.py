"""CasADi nlpsol plugins on the same identification NLP (docs/solvers.md): Set 1 of a knee, uniform
+-0.5 noise, seed 1, the same start for every plugin.  Prints per plugin: converged, iterations,
seconds, objective and the largest relative parameter difference to IPOPT's estimate.

    python docs/scripts/solver_plugins.py [KNEE]     (default: synthetic)
"""

import sys
import tempfile
from pathlib import Path

import kneenlp
from kneenlp.estimation.identify import identify
from kneenlp.experiment.measured import read_measured

PLUGINS = [("ipopt", {}), ("sqpmethod", {"qpsol": "qrqp"}), ("sqpmethod", {"qpsol": "qpoases"}), ("uno", {})]


def fits(knee_name: str = "synthetic") -> list[tuple[str, object]]:
    """(label, Fit) per plugin of :data:`PLUGINS`, IPOPT's first; a plugin that fails is (label, error)."""
    knee = kneenlp.Knee.named(knee_name)
    path = Path(tempfile.mkdtemp()) / "set1.csv"
    kneenlp.simulate(knee, "set1").measured("uniform:0.5", 1).to_csv(path, index=False)
    data = read_measured(path)
    out = []
    for solver, options in PLUGINS:
        label = f"{solver} {options}" if options else solver
        try:
            out.append((label, identify(knee, data, seed=1, solver=solver, solver_options=options or None)))
        except Exception as exc:  # a plugin not installed or failing is reported, not fatal
            out.append((label, exc))
    return out


def main(knee_name: str = "synthetic") -> None:
    results = fits(knee_name)
    ref = results[0][1]
    print(f"{knee_name} knee, Set 1, uniform +-0.5, seed 1")
    for label, fit in results:
        if isinstance(fit, Exception):
            print(f"  {label:28s} error: {fit}")
            continue
        diff = max(abs(fit.params[n] - ref.params[n]) / abs(ref.params[n]) for n in ref.free)
        print(f"  {label:28s} converged {fit.success}, {fit.iterations} iterations, {fit.seconds:.2f} s, "
              f"objective {fit.objective:.12f}, largest relative parameter difference {diff:.1e}")


if __name__ == "__main__":
    main(*sys.argv[1:2])
