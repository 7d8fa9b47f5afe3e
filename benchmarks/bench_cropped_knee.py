"""Benchmark: a cropped femoral surface against the brute force, at the laxity level.

The default knee with its femoral mesh cropped 10 mm behind the femoral origin (the rim crosses the
30 deg contact patches, :func:`kneenlp.testing.reference.cropped_knee_file`), Set 3.  Every trial the
model solves is solved again with the brute-force contact (exact distances to the cropped mesh, a
point pressing only where its nearest mesh point is inside the surface:
:func:`~kneenlp.testing.reference.reference_equilibrium`).  Prints the rim's share of the force per
trial, the largest pose difference (mm, deg) and the laxities of both (anterior-posterior mm,
internal-external and varus-valgus deg per flexion) with their relative difference.  Target: laxity
within 2 % of the brute force.  Run: python benchmarks/bench_cropped_knee.py
"""

import tempfile
import time
from pathlib import Path

import numpy as np

import kneenlp
from kneenlp.base.conventions import coords_to_user
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.prediction.laxity import laxity_table
from kneenlp.testing.reference import cropped_knee_file, reference_equilibrium


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        knee = kneenlp.Knee.load(cropped_knee_file("default", 10e-3, Path(tmp)))
        sim = kneenlp.simulate(knee, "set3")
        noted = [s.trial.id for s in sim.solutions if s.note]
        print(f"cropped knee and Set 3: {time.perf_counter() - t0:.1f} s, {sim.converged} of {len(sim.solutions)} "
              f"trials at equilibrium; noted (more than 5 % of a compartment's force beyond the rim): "
              f"{', '.join(noted) or 'none'}")
        model = KneeModel.of(knee)
        theta = model.theta()
        trials, q_model, q_ref = [], [], []
        t1 = time.perf_counter()
        for s in sim.solutions:
            share = model.rim_share(s.q, theta, s.trial.flexion)
            q, res = reference_equilibrium(model, s, theta)
            diff = np.abs(coords_to_user(q) - coords_to_user(s.q))
            print(f"  {s.trial.id:24s} rim share {100 * share:5.2f} %  brute force residual {res:.1e}  "
                  f"|pose difference| {diff[:2].max():.3f} deg, {diff[2:].max():.3f} mm")
            trials.append(s.trial)
            q_model.append(coords_to_user(s.q))
            q_ref.append(coords_to_user(q))
        print(f"brute-force equilibria: {time.perf_counter() - t1:.0f} s")
        table = laxity_table(trials, np.array(q_ref), np.array(q_model))
        table["relative"] = (table["predicted"] - table["measured"]) / table["measured"].abs()
        print("laxities (mm, deg): 'measured' = brute force, 'predicted' = the model with its rim weight")
        print(table.to_string(index=False))
        print(f"largest relative laxity difference: {100 * table['relative'].abs().max():.2f} % (target <= 2 %)")


if __name__ == "__main__":
    main()
