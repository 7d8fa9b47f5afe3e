"""Does the paper's Fig. 2 pattern depend on the load axes or on our attachment coordinates?

Moves every ligament attachment of a knee (the default knee unless named; both ends, each
coordinate) by a uniform random offset of +-SPREAD mm, simulates Set 3 with the loads fixed in the
femoral frame (the paper's choice) and along the joint axes, and counts the knees in which each of
the paper's three isolating load cases holds (:meth:`kneenlp.simulation.SimulationResult.recruitment`): anterior
134 N at 0 deg -> ACL, valgus 10 N m at 0 deg -> MCL, varus 10 N m at 30 deg -> LCL.
Knees with a trial that does not converge are counted separately.

Run: python docs/scripts/fig2_axes_scan.py [KNEES=40] [SPREAD_MM=5] [SEED=0] [KNEE=default]
"""

import dataclasses
import sys
import tomllib

import numpy as np

import kneenlp
import kneenlp.base.resources
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.protocol import Protocol
from kneenlp.model.ligament import Bundle, Ligament

CASES = {"ACL": "anterior_134N_flex0", "MCL": "valgus_10Nm_flex0", "LCL": "varus_10Nm_flex30"}


def set3(axes: str) -> Protocol:
    doc = tomllib.loads((kneenlp.base.resources.resource("protocols", "set3.toml")).read_text())
    doc["load_axes"] = axes
    return Protocol.from_dict(doc)


def main(knees: int = 40, spread_mm: float = 5.0, seed: int = 0, knee: str = "default") -> None:
    base = kneenlp.Knee.named(knee)
    rng = np.random.default_rng(seed)
    protocols = {axes: set3(axes) for axes in ("femoral", "joint")}
    held = {axes: dict.fromkeys([*CASES, "all"], 0) for axes in protocols}
    varus30 = {axes: {} for axes in protocols}
    failed = 0
    for _ in range(knees):
        d = 1e-3 * spread_mm
        ligaments = {n: Ligament(n, [Bundle(lig.femur + rng.uniform(-d, d, 3), lig.tibia + rng.uniform(-d, d, 3))])
                     for n, lig in base.ligaments.items()}
        model = KneeModel(dataclasses.replace(base, ligaments=ligaments))
        results = {axes: kneenlp.simulate(model, p) for axes, p in protocols.items()}
        if any(r.failed for r in results.values()):
            failed += 1
            continue
        for axes, r in results.items():
            dominant = r.recruitment().set_index("trial")["dominant"]
            ok = {lig: dominant[case] == lig for lig, case in CASES.items()}
            for lig, v in ok.items():
                held[axes][lig] += v
            held[axes]["all"] += all(ok.values())
            who = dominant[CASES["LCL"]]
            varus30[axes][who] = varus30[axes].get(who, 0) + 1
    n = knees - failed
    print(f"{knees} knees, attachments moved by up to +-{spread_mm:g} mm (seed {seed}); "
          f"{failed} with a trial that did not converge; counts of the other {n}:")
    print(f"{'load axes':10s} " + " ".join(f"{lig + ' ' + case:>26s}" for lig, case in CASES.items())
          + f" {'all three':>10s}   dominant in varus 10 N m at 30 deg")
    for axes, h in held.items():
        print(f"{axes:10s} " + " ".join(f"{h[lig]:>26d}" for lig in CASES) + f" {h['all']:>10d}   "
              + ", ".join(f"{k} {v}" for k, v in sorted(varus30[axes].items())))


if __name__ == "__main__":
    main(*(float(a) if i == 1 else int(a) for i, a in enumerate(sys.argv[1:4])), *sys.argv[4:5])
