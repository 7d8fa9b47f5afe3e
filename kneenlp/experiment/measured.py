"""Measured laxity data: the CSV format that ``kneenlp simulate`` writes and identification reads.

One row per trial.  Columns (units in the names; signs as in :mod:`kneenlp.conventions`):

=============================  ===============================================================
column                         meaning
=============================  ===============================================================
``trial``                      trial id, unique (e.g. ``anterior_134N_flex30``)
``flexion_deg``                prescribed flexion (deg)
``anterior_force_N``           force at the tibial tuberosity, + anterior (N)
``varus_moment_Nm``            moment, + varus (N m)
``internal_moment_Nm``         moment, + internal (N m)
``varus_rotation_deg``         measured varus (+) / valgus (-) rotation (deg)
``internal_rotation_deg``      measured internal (+) / external (-) rotation (deg)
``lateral_translation_mm``     measured lateral (+) / medial (-) translation (mm)
``anterior_translation_mm``    measured anterior (+) / posterior (-) translation (mm)
``proximal_translation_mm``    measured proximal (+) / distal (-) translation (mm)
``protocol`` (optional)        protocol name the trials come from (e.g. ``set3``)
``load_axes`` (optional)       ``femoral`` (default) or ``joint``, see :mod:`kneenlp.experiment.protocol`
=============================  ===============================================================

Other columns (e.g. ligament forces written by ``simulate``) are ignored; a column that names a
coordinate or load with a different unit (``anterior_translation_m``) is an error.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from kneenlp.conventions import (
    COORDINATES,
    LOAD_AXES,
    LOAD_COMPONENTS,
    coordinate_columns,
    coords_from_user,
    load_columns,
)
from kneenlp.errors import InputError
from kneenlp.experiment.protocol import Protocol, Trial

REQUIRED = ["trial", "flexion_deg", *load_columns(), *coordinate_columns()]


@dataclass
class MeasuredData:
    """Measured poses of a set of trials (``q`` in SI: rad, m; one row per trial)."""

    trials: list[Trial]
    q: np.ndarray  # (n_trials, 5)
    protocol: str | None = None
    source: str | None = None

    def __len__(self) -> int:
        return len(self.trials)

    @property
    def q_user(self) -> np.ndarray:
        from kneenlp.conventions import coords_to_user

        return coords_to_user(self.q)

    def check_protocol(self, protocol: Protocol) -> None:
        """Every trial known to ``protocol`` with the same load, and none of it missing."""
        src = self.source
        known = {t.id: t for t in protocol.trials}
        for t in self.trials:
            if t.id not in known:
                raise InputError(f"trial {t.id!r} is not in protocol {protocol.name!r}", source=src,
                                 field="trial")
            ref = known[t.id]
            if abs(ref.flexion_deg - t.flexion_deg) > 1e-9 or not np.allclose(ref.load, t.load):
                raise InputError(f"trial {t.id!r}: flexion or load differs from protocol {protocol.name!r}",
                                 source=src, field="trial")
        have = {t.id for t in self.trials}
        missing = [t.id for t in protocol.trials if t.id not in have]
        if missing:
            raise InputError(f"missing trials of protocol {protocol.name!r}: {', '.join(missing)}",
                             source=src, field="trial")


def measured_frame(trials: list[Trial], q_user: np.ndarray, protocol: str | None = None) -> pd.DataFrame:
    """Build the measured-data table (user units) from trials and poses (n x 5, mm/deg)."""
    rows = {
        "protocol": [protocol or ""] * len(trials),
        "trial": [t.id for t in trials],
        "flexion_deg": [t.flexion_deg for t in trials],
        "load_axes": [t.axes for t in trials],
    }
    for comp, col in zip(LOAD_COMPONENTS, load_columns(), strict=True):
        rows[col] = [t.loads.get(comp, 0.0) for t in trials]
    for j, col in enumerate(coordinate_columns()):
        rows[col] = np.asarray(q_user)[:, j]
    return pd.DataFrame(rows)


def read_measured(path: str | Path) -> MeasuredData:
    """Read and validate a measured-data CSV; every problem is a one-line :class:`InputError`."""
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise InputError("file not found", source=src)
    try:
        df = pd.read_csv(path, dtype={"trial": str, "protocol": str, "load_axes": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"malformed CSV ({str(exc).splitlines()[0]})", source=src) from None
    df.columns = [str(c).strip() for c in df.columns]
    expected_units = dict(zip([*COORDINATES, *LOAD_COMPONENTS, "flexion"],
                              [*[c.rsplit("_", 1)[1] for c in coordinate_columns()],
                               *[c.rsplit("_", 1)[1] for c in load_columns()], "deg"], strict=True))
    for col in df.columns:
        for name, unit in expected_units.items():
            if col.startswith(name + "_") and col != f"{name}_{unit}" and col[len(name) + 1:].count("_") == 0:
                raise InputError(f"column {col!r} has the wrong unit; expected {name}_{unit}", source=src,
                                 field=col)
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}", source=src)
    if df.empty:
        raise InputError("no data rows", source=src)
    numeric = [c for c in REQUIRED if c != "trial"]
    for col in numeric:
        vals = pd.to_numeric(df[col], errors="coerce")
        bad = ~np.isfinite(vals.to_numpy(dtype=float))
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"row {i + 2} (trial {df['trial'].iloc[i]!r}): value {df[col].iloc[i]!r} is "
                             "not a finite number", source=src, field=col)
        df[col] = vals
    if df["trial"].isna().any():
        raise InputError(f"row {int(np.argmax(df['trial'].isna())) + 2}: empty trial id", source=src, field="trial")
    dup = df["trial"][df["trial"].duplicated()].tolist()
    if dup:
        raise InputError(f"duplicate trial(s) {', '.join(map(str, dup))}", source=src, field="trial")
    axes = df["load_axes"].fillna("femoral") if "load_axes" in df.columns else pd.Series(["femoral"] * len(df))
    for a in axes:
        if a not in LOAD_AXES:
            raise InputError(f"unknown load axes {a!r}; known: {', '.join(LOAD_AXES)}", source=src,
                             field="load_axes")
    trials = []
    for i, row in df.reset_index(drop=True).iterrows():
        loads = {c: float(row[col]) for c, col in zip(LOAD_COMPONENTS, load_columns(), strict=True)
                 if float(row[col]) != 0.0}
        direction, magnitude = _direction(loads)
        trials.append(Trial(str(row["trial"]), float(row["flexion_deg"]), loads, direction, magnitude,
                            str(axes.iloc[i])))
    q = coords_from_user(df[coordinate_columns()].to_numpy(dtype=float))
    protocol = None
    if "protocol" in df.columns:
        names = {str(p) for p in df["protocol"].dropna().unique() if str(p)}
        if len(names) > 1:
            raise InputError(f"several protocols in one file: {', '.join(sorted(names))}", source=src,
                             field="protocol")
        protocol = names.pop() if names else None
    return MeasuredData(trials, q, protocol, src)


def _direction(loads: dict[str, float]) -> tuple[str, float]:
    if not loads:
        return "none", 0.0
    if len(loads) > 1:
        return "combined", 0.0
    (comp, value), = loads.items()
    names = {"anterior_force": ("anterior", "posterior"), "varus_moment": ("varus", "valgus"),
             "internal_moment": ("internal", "external")}[comp]
    return (names[0] if value > 0 else names[1]), abs(value)
