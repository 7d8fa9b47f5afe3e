"""Laxity per flexion and load pair (``kneenlp.prediction.laxity``), against hand-made poses."""

from __future__ import annotations

import numpy as np
import pytest

from kneenlp.experiment.protocol import Trial
from kneenlp.prediction.laxity import laxity_lines, laxity_records, laxity_table


def _trial(direction: str, size: float, flexion: float) -> Trial:
    component, sign = {"anterior": ("anterior_force", 1), "posterior": ("anterior_force", -1),
                       "internal": ("internal_moment", 1), "external": ("internal_moment", -1),
                       "none": ("anterior_force", 0)}[direction]
    return Trial(f"{direction}_{size:g}_flex{flexion:g}", flexion, {component: sign * size}, "combined", 0.0, "jcs")


def test_laxity_is_the_largest_loads_difference_per_flexion():
    trials = [_trial("anterior", 50, 30.4), _trial("anterior", 200, 29.1), _trial("posterior", 190, 31.0),
              _trial("internal", 5, 30.0), _trial("external", 5, 29.5), _trial("none", 0, 30.2),
              _trial("anterior", 200, 90.0), _trial("posterior", 200, 88.0),   # no internal-external pair at 89 deg
              _trial("internal", 7, 60.0)]                                       # a direction alone: no row
    rng = np.random.default_rng(3)
    measured = rng.normal(size=(len(trials), 5))
    predicted = rng.normal(size=(len(trials), 5))
    predicted[7] = np.nan  # posterior at 88 deg without equilibrium
    table = laxity_table(trials, measured, predicted)
    assert list(table["laxity"]) == ["anterior-posterior", "internal-external", "anterior-posterior"]
    assert list(table["flexion_deg"]) == pytest.approx([30.04, 30.04, 89.0], abs=0.06)  # groups' mean flexion
    ap30, ie30, ap89 = (table.iloc[k] for k in range(3))
    # the 200 N anterior trial (index 1), not the 50 N one; anterior translation is column 3, internal 1
    assert ap30["measured"] == measured[1, 3] - measured[2, 3]
    assert ap30["predicted"] == predicted[1, 3] - predicted[2, 3]
    assert ap30["measured_minus_predicted"] == pytest.approx(ap30["measured"] - ap30["predicted"])
    assert (ap30["unit"], ap30["trials"]) == ("mm", "anterior_200_flex29.1 / posterior_190_flex31")
    assert ie30["measured"] == measured[3, 1] - measured[4, 1] and ie30["unit"] == "deg"
    assert np.isnan(ap89["predicted"]) and ap89["measured"] == measured[6, 3] - measured[7, 3]
    records = laxity_records(table)
    assert records[2]["predicted"] is None and records[0]["measured"] == ap30["measured"]
    lines = laxity_lines(table, "Laxity:")
    assert lines[0] == "Laxity:" and len(lines) == 5 and "anterior-posterior [mm]" in lines[2]


def test_laxity_without_pairs_is_empty_and_shapes_are_checked():
    trials = [_trial("none", 0, 0.0), _trial("anterior", 100, 0.0)]
    table = laxity_table(trials, np.zeros((2, 5)), np.zeros((2, 5)))
    assert table.empty and laxity_lines(table, "Laxity:") == []
    with pytest.raises(ValueError, match="2 x 5"):
        laxity_table(trials, np.zeros((3, 5)), np.zeros((3, 5)))
