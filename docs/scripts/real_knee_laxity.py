"""Laxities of a knee under the paper's largest loads (Set 3), as changes from the unloaded pose at
the same flexion (mm, deg), with loads fixed in the femoral frame (the paper) and along the joint
axes.  Used for docs/real-knee.md.  Run: python docs/scripts/real_knee_laxity.py [KNEE]"""

from __future__ import annotations

import sys
import tomllib

import kneenlp
from kneenlp.base.resources import resource

CASES = [("anterior_134N", "anterior_translation_mm"), ("posterior_67N", "anterior_translation_mm"),
         ("varus_10Nm", "varus_rotation_deg"), ("valgus_10Nm", "varus_rotation_deg"),
         ("internal_2Nm", "internal_rotation_deg"), ("external_2Nm", "internal_rotation_deg")]


def laxities(knee: kneenlp.Knee, axes: str) -> dict[tuple[str, int], float]:
    doc = tomllib.loads(resource("protocols", "set3.toml").read_text())
    doc["load_axes"] = axes
    result = kneenlp.simulate(knee, kneenlp.Protocol.from_dict(doc))
    if result.failed:
        raise SystemExit(f"not converged: {[s.trial.id for s in result.failed]}")
    table = result.table().set_index("trial")
    out = {}
    for flexion in (0, 30):
        rest = table.loc[f"none_flex{flexion}"]
        for case, column in CASES:
            out[case, flexion] = float(table.loc[f"{case}_flex{flexion}", column] - rest[column])
    return out


if __name__ == "__main__":
    knee = kneenlp.Knee.load(sys.argv[1]) if len(sys.argv) > 1 else kneenlp.Knee.default()
    femoral, joint = laxities(knee, "femoral"), laxities(knee, "joint")
    print(f"{knee.name} knee: change from the unloaded pose (mm or deg)")
    print(f"{'load':16s} {'flexion':>7s} {'femoral-frame loads':>20s} {'joint-axis loads':>17s}")
    for (case, flexion), value in femoral.items():
        print(f"{case:16s} {flexion:7d} {value:20.2f} {joint[case, flexion]:17.2f}")
