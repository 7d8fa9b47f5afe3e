"""Laxity: the range of motion between two opposite loads at one flexion, measured and predicted.

The number a laxity test is read by: anterior-posterior laxity at 30 deg is the anterior
translation under the anterior load minus that under the posterior load (mm); internal-external
and varus-valgus laxity likewise (deg; :data:`~kneenlp.experiment.protocol.LAXITY_PAIRS`).  Where a
per-trial comparison shows *that* a model misses, the laxities show *how*: too stiff or too lax,
and at which flexion (S192803: the model's anterior-posterior laxity grows from 6 to 14 mm between
5 and 87 deg of flexion where the knee's stays at 8-10 mm; docs/real-experiment.md).

Trials are grouped by flexion (:func:`~kneenlp.experiment.protocol.flexion_groups`); in a group,
each direction of a pair is represented by its trial with the largest load, so a protocol with
several load sizes gives the laxity at its largest loads.  A pair with a direction missing at a
flexion gives no row; a trial without a predicted pose gives a NaN prediction, never a dropped row.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from kneenlp.base.conventions import coordinate_columns
from kneenlp.experiment.protocol import LAXITY_PAIRS, Trial, flexion_groups

#: Columns of :func:`laxity_table` (units in the names; ``laxity`` names the pair, ``unit`` its unit).
COLUMNS = ("flexion_deg", "laxity", "unit", "measured", "predicted", "measured_minus_predicted", "trials")


def laxity_table(trials: Sequence[Trial], measured_user: np.ndarray, predicted_user: np.ndarray) -> pd.DataFrame:
    """One row per flexion group and load pair present in ``trials``: the measured and predicted
    laxity (mm or deg, positive direction minus negative) and their difference.  ``measured_user``
    and ``predicted_user``: T x 5 poses in the coordinate columns' order (deg and mm; NaN where a
    trial has no predicted pose)."""
    measured, predicted = np.asarray(measured_user, float), np.asarray(predicted_user, float)
    if measured.shape != (len(trials), 5) or predicted.shape != measured.shape:
        raise ValueError(f"expected {len(trials)} x 5 poses, got {measured.shape} and {predicted.shape}")
    groups = flexion_groups(trials)
    columns = coordinate_columns()
    rows = []
    for flexion in np.unique(groups):
        members = [i for i in range(len(trials)) if groups[i] == flexion]
        for column, (plus, minus) in LAXITY_PAIRS.items():
            ends = [_largest([i for i in members if trials[i].dominant == word], trials) for word in (plus, minus)]
            if None in ends:
                continue
            j = columns.index(column)
            i_plus, i_minus = ends
            m = measured[i_plus, j] - measured[i_minus, j]
            p = predicted[i_plus, j] - predicted[i_minus, j]
            rows.append((round(float(flexion), 1), f"{plus}-{minus}", column.rsplit("_", 1)[1], m, p, m - p,
                         f"{trials[i_plus].id} / {trials[i_minus].id}"))
    return pd.DataFrame(rows, columns=list(COLUMNS))


def _largest(indices: list[int], trials: Sequence[Trial]) -> int | None:
    return max(indices, key=lambda i: trials[i].dominant_size) if indices else None


def laxity_lines(table: pd.DataFrame, heading: str) -> list[str]:
    """The table as report lines (empty without rows)."""
    if table.empty:
        return []
    lines = [heading, f"  {'flexion [deg]':>13}  {'laxity':<24} {'measured':>9} {'predicted':>9} {'difference':>10}"]
    for r in table.itertuples():
        lines.append(f"  {r.flexion_deg:13.1f}  {r.laxity + ' [' + r.unit + ']':<24} {r.measured:9.2f} "
                     f"{r.predicted:9.2f} {r.measured_minus_predicted:10.2f}")
    return lines


def laxity_records(table: pd.DataFrame) -> list[dict]:
    """The table for JSON (NaN as None)."""
    return [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in row.items()}
            for row in table.to_dict(orient="records")]
