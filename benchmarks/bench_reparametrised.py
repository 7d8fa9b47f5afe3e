"""Benchmark: one knee written two ways solves the same way (issue: a forward solve's answer must not
depend on how the knee's parameters are written).

The S192803 knee at its own values and at a calibration (``identify`` of its data, ligament values
only), each against copies whose group stiffness scales are moved into the bundles' stiffnesses
(:func:`kneenlp.testing.reference.rescaled_knee`, three seeds): every force is the same function of
the pose.  Prints, per protocol (Sets 1-4 and the S192803 trials), the trials solved, and those
whose poses differ by more than 1e-6 mm or deg between the two, with the strategy that reached them.
Target: none.  Run: python benchmarks/bench_reparametrised.py   (about 1 min)
"""

import contextlib
import io
import tempfile
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.base.conventions import coords_to_user
from kneenlp.cli import main
from kneenlp.experiment.measured import read_measured
from kneenlp.prediction.predict import predict
from kneenlp.testing.reference import rescaled_knee

DATA = Path(__file__).resolve().parents[1] / "problems" / "s192803" / "laxity.csv"
TOL = 1e-6  # mm and deg


def differing(a, b) -> list[str]:
    """Trials of two solution lists whose poses differ by more than :data:`TOL` (mm, deg) or that
    one of them solves and the other not, with their strategies."""
    out = []
    for s, t in zip(a, b, strict=True):
        gap = float(np.max(np.abs(coords_to_user(s.q) - coords_to_user(t.q))))
        if s.converged != t.converged or (s.converged and gap > TOL):
            out.append(f"{s.trial.id} ({s.strategy}/{t.strategy}, {gap:.3g})")
    return out


def compare(label: str, knee, seeds=(1, 2, 3)) -> None:
    data = read_measured(DATA)
    for seed in seeds:
        other = rescaled_knee(knee, np.random.default_rng(seed))
        for protocol in ("set1", "set2", "set3", "set4"):
            a, b = kneenlp.simulate(knee, protocol).solutions, kneenlp.simulate(other, protocol).solutions
            bad = differing(a, b)
            print(f"{label:12s} seed {seed} {protocol}: {sum(s.converged for s in a)}/{len(a)} solved, "
                  f"{len(bad)} differ {', '.join(bad)}")
        a, b = predict(knee, data).solutions, predict(other, data).solutions
        bad = differing(a, b)
        print(f"{label:12s} seed {seed} s192803: {sum(s.converged for s in a)}/{len(a)} solved, {len(bad)} differ "
              f"{', '.join(bad)}")


def main_() -> None:
    t0 = time.perf_counter()
    knee = kneenlp.Knee.named("s192803")
    compare("own values", knee)
    with tempfile.TemporaryDirectory() as tmp:
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["identify", str(DATA), "--knee", "s192803", "--out", tmp]) == 0
        fitted = kneenlp.ParameterSet.load(Path(tmp) / "calibrated.toml").values
    ligament_values = {n: v for n, v in fitted.items() if n.split(".")[0] in knee.ligaments}
    compare("calibrated", knee.with_parameters(knee.parameters.with_values(ligament_values)))
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main_()
