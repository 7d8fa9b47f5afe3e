"""Measured laxity data: the CSV format that ``kneenlp simulate`` writes and identification reads.

One row per trial.  Columns (units in the names; signs as in :mod:`kneenlp.base.conventions`):

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
``load_axes`` (optional)       ``femoral`` (default), ``joint`` or ``jcs`` (a robot's joint
                               loads), see :mod:`kneenlp.base.conventions`
``lateral_force_N`` (optional)   force, + lateral (N)
``proximal_force_N`` (optional)  force, + proximal: compression of the joint (N)
``flexion_moment_Nm`` (optional) moment, + flexion (N m): reported, carried by the prescribed flexion
``side`` (optional)            ``left`` or ``right``: the knee the data come from; a fit refuses
                               a knee of the other side
``experiment`` (optional)      the experiment (:mod:`kneenlp.experiment.kind`): ``simulated``,
                               ``laboratory`` or ``NAME`` of a ``NAME.toml`` beside the data; the
                               coordinate columns are those it observes
=============================  ===============================================================

Real experiments (``kneenlp import-laxity``) give every trial its measured flexion and all six load
components; signs are anatomical whatever the side (+varus, +internal, +lateral for a left knee
too).

Other columns (e.g. ligament forces written by ``simulate``) are ignored; a column that names a
coordinate or load with a different unit (``anterior_translation_m``) is an error.

Checks at reading (every problem is a one-line :class:`~kneenlp.base.errors.InputError` naming the file,
the column and the row):

* every value a finite number; trial ids present and unique; ``load_axes`` known;
* flexion in [-10, 120] deg and loads within 1000 N / 100 N m (as protocol files,
  :mod:`kneenlp.experiment.protocol`);
* plausible units (the thresholds are far from any laxity test, so they only catch unit slips):
  translations beyond :data:`MAX_TRANSLATION_MM` (100 mm: micrometres?), or all within
  :data:`MIN_TRANSLATION_MM` (0.1 mm) although the file has loaded trials (metres?); rotations
  beyond 90 deg, or all within :data:`MIN_ROTATION_DEG` (0.2 deg) although the file has a moment
  of at least 1 N m (radians?), or one rotation within :data:`RADIAN_SLIP_DEG` although its own
  moment reaches 2 N m and the apparatus does not hold it (that column in radians?); a row pushed
  more than 1 mm from the unloaded pose of its flexion by a force below 1 N and no moment (kN?);
* at most :data:`MAX_TRIALS` rows (1000): the identification NLP has 5 pose variables and 5
  equilibrium constraints per trial, and 1000 trials took 90 s and 0.9 GB on the synthetic knee
  (a loaded 2-core machine) and take many minutes on a mesh knee (the paper's protocols have 7 to
  60); split larger data sets.  Above :data:`LARGE_TRIALS` rows a note on the ``kneenlp`` logger
  says the fit will take a while;
* the ``protocol`` column: a shipped protocol's name (``set1`` ...; identification then checks the
  trials against it), the name of a protocol file ``NAME.toml`` beside the data (checked here), or
  with ``protocol=`` given (``identify --protocol FILE``) any name.  An unknown name that looks
  like a shipped one (``set9``, ``Set 3``) is an error; any other name (e.g. a designed protocol's,
  as ``simulate --protocol FILE`` writes it) is accepted and noted on the ``kneenlp`` logger: the
  trials are taken from the file's load columns.
"""

from __future__ import annotations

import difflib
import logging
import re
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from kneenlp.base.conventions import (
    ALL_LOAD_COMPONENTS,
    COORDINATES,
    LOAD_AXES,
    LOAD_COMPONENTS,
    POSE_ENVELOPE_USER,
    coordinate_columns,
    coords_from_user,
    coords_to_user,
    load_columns,
)
from kneenlp.base.errors import InputError
from kneenlp.experiment.kind import SIMULATED, Experiment, experiment_of
from kneenlp.experiment.protocol import (
    FLEXION_RANGE,
    TYPICAL,
    Protocol,
    Trial,
    available_protocols,
    check_load,
    nominal_flexions,
)

REQUIRED = ["trial", "flexion_deg", *load_columns(), *coordinate_columns()]
OPTIONAL_LOADS = load_columns(extra=True)[len(LOAD_COMPONENTS):]
#: Most rows a measured-data file may have, and the size above which reading it notes the fit's
#: duration (see module docstring).
MAX_TRIALS = 1000
LARGE_TRIALS = 200
#: Plausibility bounds of the measured coordinates (see module docstring).
MAX_TRANSLATION_MM = 100.0
MIN_TRANSLATION_MM = 0.1
MAX_ROTATION_DEG = 90.0
MIN_ROTATION_DEG = 0.2
#: A rotation that stays below this (deg) in every row although its own moment reaches
#: :data:`RADIAN_MOMENT_NM` was given in radians: a knee under 2 N m turns further (the shipped
#: data's smallest largest varus rotation is 1.4 deg, internal 11 deg; 29 deg in radians is 0.5).
RADIAN_SLIP_DEG = {"varus_rotation_deg": 0.5, "internal_rotation_deg": 1.0}
RADIAN_MOMENT_NM = 2.0
#: A trial with a force of at least this (N) or a moment of at least 1 N m moves the knee.
LOADED_FORCE_N = 20.0

log = logging.getLogger("kneenlp")


@dataclass
class MeasuredData:
    """Measured poses of a set of trials (``q`` in SI: rad, m; one row per trial; NaN in the
    coordinates the experiment does not observe)."""

    trials: list[Trial]
    q: np.ndarray  # (n_trials, 5)
    protocol: str | None = None
    source: str | None = None
    side: str | None = None  # "left" or "right" if the file says so
    experiment: Experiment = SIMULATED

    def __len__(self) -> int:
        return len(self.trials)

    @classmethod
    def from_user(cls, trials: list[Trial], q_user: np.ndarray, protocol: str | None = None,
                  source: str | None = None, **labels: str | Experiment | None) -> MeasuredData:
        """Measured data from poses in user units (T x 5, mm and deg); ``labels``: the fields
        ``side`` and ``experiment``."""
        return cls(list(trials), coords_from_user(q_user), protocol, source, **labels)

    @property
    def q_user(self) -> np.ndarray:
        """The measured poses in user units (T x 5, mm and deg)."""
        return coords_to_user(self.q)

    def subset(self, keep: np.ndarray) -> MeasuredData:
        """The trials where the boolean mask ``keep`` is true, in order."""
        keep = np.asarray(keep, bool)
        return MeasuredData([t for t, k in zip(self.trials, keep, strict=True) if k], self.q[keep],
                            self.protocol, self.source, self.side, self.experiment)

    def check_observed(self, what: str) -> None:
        """Refuse ``what`` (an analysis that needs every coordinate of every trial: a calibration's
        outlier test, cross-validation, diagnose) for data whose experiment observes fewer or holds
        some (a held coordinate is an input, not an observation)."""
        if self.experiment.held:
            raise InputError(f"{what} needs all five coordinates free; experiment {self.experiment.name!r} holds "
                             f"{', '.join(self.experiment.held)} (fit it with --strategy scatter)",
                             source=self.source, field="experiment")
        if len(self.experiment.observed) < len(COORDINATES):
            raise InputError(f"{what} needs all five coordinates; experiment {self.experiment.name!r} observes "
                             f"{', '.join(self.experiment.observed)} (fit it with --strategy scatter)",
                             source=self.source, field="experiment")

    def check_knee(self, knee) -> None:
        """The data fit ``knee`` (a :class:`~kneenlp.model.knee.Knee`): the same side, if the data
        say theirs, and every measured pose within the knee's reach (the physiological envelope
        about its reference pose)."""
        if self.side is not None and self.side != knee.side:
            raise InputError(f"the data come from a {self.side} knee, knee {knee.name!r} is a {knee.side} knee (a "
                             f"{knee.side} knee declared {self.side}? import the data again with --side {knee.side})",
                             source=self.source, field="side")
        knee.check_flexions(self.trials, self.source)
        centre = coords_to_user(knee.reference_pose[1])
        far = np.abs(self.q_user - centre) > POSE_ENVELOPE_USER
        if far.any():
            i, j = np.argwhere(far)[0]
            col = coordinate_columns()[j]
            off = abs(self.q_user[i, j] - centre[j])
            raise InputError(f"trial {self.trials[i].id!r}: {col} = {self.q_user[i, j]:.4g} is {off:.3g} from knee "
                             f"{knee.name!r}'s reference pose, beyond what a knee reaches ({POSE_ENVELOPE_USER[j]:g}):"
                             " another knee, frame or unit?", source=self.source, field=col)

    def check_protocol(self, protocol: Protocol) -> None:
        """Every trial known to ``protocol`` with the same load, and none of it missing."""
        src = self.source
        known = {t.id: t for t in protocol.trials}
        for t in self.trials:
            if t.id not in known:
                raise InputError(f"trial {t.id!r} is not in protocol {protocol.name!r}", source=src,
                                 field="trial")
            ref = known[t.id]
            same_load = np.allclose(ref.load, replace(t, point=ref.point, held=ref.held,  # the experiment's own
                                                      preload_point=ref.preload_point).load)
            if abs(ref.flexion_deg - t.flexion_deg) > 1e-9 or not same_load:
                raise InputError(f"trial {t.id!r}: flexion or load differs from protocol {protocol.name!r}",
                                 source=src, field="trial")
        have = {t.id for t in self.trials}
        missing = [t.id for t in protocol.trials if t.id not in have]
        if missing:
            raise InputError(f"missing trials of protocol {protocol.name!r}: {', '.join(missing)}",
                             source=src, field="trial")


def measured_frame(trials: list[Trial], q_user: np.ndarray, protocol: str | None = None,
                   side: str | None = None, experiment: Experiment | None = None) -> pd.DataFrame:
    """Build the measured-data table (user units) from trials and poses (n x 5, mm/deg); the
    optional load columns only where a trial has such a load, ``side`` and ``experiment`` only if
    given, and the coordinates the experiment observes (all without one)."""
    rows = {
        "protocol": [protocol or ""] * len(trials),
        "trial": [t.id for t in trials],
        "flexion_deg": [t.flexion_deg for t in trials],
        "load_axes": [t.axes for t in trials],
    }
    if side is not None:
        rows["side"] = [side] * len(trials)
    if experiment is not None:
        rows["experiment"] = [experiment.name] * len(trials)
    used = {c for t in trials for c in t.loads}
    for comp, col in zip(ALL_LOAD_COMPONENTS, load_columns(extra=True), strict=True):
        if comp in LOAD_COMPONENTS or comp in used:
            rows[col] = [t.loads.get(comp, 0.0) for t in trials]
    seen = np.ones(5, bool) if experiment is None else experiment.mask
    for j, col in enumerate(coordinate_columns()):
        if seen[j]:
            rows[col] = np.asarray(q_user)[:, j]
    return pd.DataFrame(rows)


def read_measured(path: str | Path, protocol: object = None) -> MeasuredData:
    """Read and validate a measured-data CSV; every problem is a one-line :class:`InputError`.

    ``protocol``: the protocol the data will be checked against, if the caller has one (then the
    file's ``protocol`` column may name any protocol); see the module docstring."""
    path = Path(path)
    src = str(path)
    df = _read_table(path)
    experiment = experiment_of(df, path)
    _check_columns(df, src, experiment)
    df = df.reset_index(drop=True)
    if df["trial"].isna().any():
        raise InputError(f"row {int(np.argmax(df['trial'].isna())) + 2}: empty trial id", source=src, field="trial")
    _to_numbers(df, src)
    dup = df["trial"][df["trial"].duplicated()].tolist()
    if dup:
        raise InputError(f"duplicate trial(s) {', '.join(map(str, dup))}", source=src, field="trial")
    axes = _load_axes(df, src)
    side = _side(df, src)
    check_plausible(df, src, held=tuple(experiment.held))
    q_user = np.column_stack([df[c].to_numpy(dtype=float) if c in df.columns else np.full(len(df), np.nan)
                              for c in coordinate_columns()])
    trials = experiment.applied_to(_trials(df, axes), coords_from_user(q_user))
    name = _protocol_name(df, src)
    data = MeasuredData.from_user(trials, q_user, name, src, side=side, experiment=experiment)
    if name is not None and protocol is None:
        _check_protocol_name(data, path)
    return data


def _read_table(path: Path) -> pd.DataFrame:
    """The CSV file at ``path`` as read, its column names stripped of blanks."""
    src = str(path)
    if path.is_dir():
        raise InputError("is a directory, not a measured-data CSV file", source=src)
    if not path.is_file():
        raise InputError("file not found", source=src)
    try:
        df = pd.read_csv(path, dtype={"trial": str, "protocol": str, "load_axes": str, "side": str, "experiment": str})
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", source=src) from None
    except Exception as exc:  # pandas raises many kinds for garbage (ParserError, UnicodeDecodeError, ...)
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise InputError(f"malformed CSV ({first})", source=src) from None
    df.columns = [str(c).strip() for c in df.columns]
    return df


def _check_columns(df: pd.DataFrame, src: str, experiment: Experiment) -> None:
    """The table's columns have the expected units, none of ours twice, all required ones (the
    coordinates ``experiment`` observes, and no other), and between one and :data:`MAX_TRIALS` rows
    (a note on the logger above :data:`LARGE_TRIALS`)."""
    expected_units = dict(zip([*COORDINATES, *ALL_LOAD_COMPONENTS, "flexion"],
                              [*[c.rsplit("_", 1)[1] for c in coordinate_columns()],
                               *[c.rsplit("_", 1)[1] for c in load_columns(extra=True)], "deg"], strict=True))
    for col in df.columns:
        for name, unit in expected_units.items():
            if col.startswith(name + "_") and col != f"{name}_{unit}" and col[len(name) + 1:].count("_") == 0:
                raise InputError(f"column {col!r} has the wrong unit; expected {name}_{unit}", source=src,
                                 field=col)
    dup_cols = sorted({c for c in df.columns if list(df.columns).count(c) > 1} & set(REQUIRED + OPTIONAL_LOADS))
    if dup_cols:
        raise InputError("column given twice", source=src, field=dup_cols[0])
    unseen = [c for c, seen in zip(coordinate_columns(), experiment.mask, strict=True) if not seen]
    missing = [c for c in REQUIRED if c not in df.columns and c not in unseen]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}", source=src)
    extra = [c for c in unseen if c in df.columns]
    if extra:
        raise InputError(f"experiment {experiment.name!r} does not observe this coordinate (it observes "
                         f"{', '.join(experiment.observed)})", source=src, field=extra[0])
    if df.empty:
        raise InputError("no data rows", source=src)
    if len(df) > MAX_TRIALS:
        raise InputError(f"{len(df)} rows: more than the {MAX_TRIALS} trials one identification takes (its size "
                         "grows with the trials; the paper's protocols have 7 to 60); split the data", source=src)
    if len(df) > LARGE_TRIALS:
        log.info(f"{src}: {len(df)} trials: a large identification (1000 trials took 90 s on the synthetic knee, "
                 "longer on a mesh knee)")


def _to_numbers(df: pd.DataFrame, src: str) -> None:
    """Convert the flexion, load and coordinate columns of ``df`` to floats in place; each value
    must be a finite number."""
    numeric = [c for c in REQUIRED + OPTIONAL_LOADS if c != "trial" and c in df.columns]
    for col in numeric:
        vals = pd.to_numeric(df[col], errors="coerce")
        bad = ~np.isfinite(vals.to_numpy(dtype=float))
        if bad.any():
            i = int(np.argmax(bad))
            value = df[col].iloc[i]
            shown = repr(value) if isinstance(value, str) else "nan (or empty)" if pd.isna(value) else str(value)
            raise InputError(f"row {i + 2} (trial {str(df['trial'].iloc[i])!r}): value {shown} is not a finite number",
                             source=src, field=col)
        df[col] = vals.astype(float)


def _load_axes(df: pd.DataFrame, src: str) -> pd.Series:
    """The load axes of each row (``femoral`` where the file says none), each a known one."""
    axes = df["load_axes"].fillna("femoral") if "load_axes" in df.columns else pd.Series(["femoral"] * len(df))
    for a in axes:
        if a not in LOAD_AXES:
            raise InputError(f"unknown load axes {a!r}; known: {', '.join(LOAD_AXES)}", source=src,
                             field="load_axes")
    return axes


def _side(df: pd.DataFrame, src: str) -> str | None:
    """The knee's side the ``side`` column states (one for every row), or None."""
    if "side" not in df.columns:
        return None
    sides = {str(v).strip() for v in df["side"].dropna()}
    if not sides <= {"left", "right"} or len(sides) > 1:
        raise InputError(f"expected one of left, right for every row, got {', '.join(sorted(sides))}",
                         source=src, field="side")
    return sides.pop() if sides else None


def _trials(df: pd.DataFrame, axes: pd.Series) -> list[Trial]:
    """One trial per row: its id, flexion (deg), nonzero loads (N, N m) and load axes."""
    trials = []
    for i, row in df.iterrows():
        loads = {c: float(row[col]) for c, col in zip(ALL_LOAD_COMPONENTS, load_columns(extra=True), strict=True)
                 if col in df.columns and float(row[col]) != 0.0}
        direction, magnitude = _direction(loads)
        trials.append(Trial(str(row["trial"]), float(row["flexion_deg"]), loads, direction, magnitude,
                            str(axes.iloc[i])))
    return trials


def _protocol_name(df: pd.DataFrame, src: str) -> str | None:
    """The protocol the ``protocol`` column names (one for the whole file), or None."""
    if "protocol" not in df.columns:
        return None
    names = {str(p) for p in df["protocol"].dropna().unique() if str(p).strip()}
    if len(names) > 1:
        raise InputError(f"several protocols in one file: {', '.join(sorted(names))}", source=src,
                         field="protocol")
    return names.pop() if names else None


def check_plausible(df: pd.DataFrame, src: str, held: tuple[str, ...] = ()) -> None:
    """Ranges and unit plausibility of a measured-data table (see module docstring): the one check
    of a table read from CSV and of one made by an importer (``import-laxity``), so an importer never
    writes a file the reader refuses.  ``held``: the coordinates the experiment's apparatus holds
    (they need not turn under their moments)."""
    lo, hi = FLEXION_RANGE
    flex = df["flexion_deg"].to_numpy()
    bad = (flex < lo) | (flex > hi)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"row {i + 2}: flexion {flex[i]:g} deg outside [{lo:g}, {hi:g}]", source=src,
                         field="flexion_deg")
    for comp, col in zip(ALL_LOAD_COMPONENTS, load_columns(extra=True), strict=True):
        if col not in df.columns:
            continue
        for i, v in enumerate(df[col].to_numpy()):
            try:
                check_load(comp, float(v), src, col)
            except InputError as exc:
                raise InputError(f"row {i + 2}: {exc.message}", source=src, field=col) from None
    trans = [c for c in coordinate_columns() if c.endswith("_mm") and c in df.columns]
    rots = [c for c in coordinate_columns() if c.endswith("_deg") and c in df.columns]
    t = np.abs(df[trans].to_numpy()) if trans else np.full((len(df), 1), MIN_TRANSLATION_MM)
    r = np.abs(df[rots].to_numpy()) if rots else np.full((len(df), 1), MIN_ROTATION_DEG)
    force = np.abs(df["anterior_force_N"].to_numpy())
    moment = np.abs(df[["varus_moment_Nm", "internal_moment_Nm"]].to_numpy()).max(axis=1)
    if t.max() > MAX_TRANSLATION_MM:
        i, j = np.unravel_index(np.argmax(t), t.shape)
        raise InputError(f"row {i + 2}: translation {df[trans[j]].iloc[i]:g} mm beyond {MAX_TRANSLATION_MM:g} mm; "
                         "micrometres or another unit in a _mm column?", source=src, field=trans[j])
    if ((force >= LOADED_FORCE_N) | (moment >= 1.0)).any() and t.max() < MIN_TRANSLATION_MM:
        raise InputError(f"every translation is below {MIN_TRANSLATION_MM:g} mm (largest {t.max():.3g}) although "
                         "the knee is loaded: metres in the _mm columns? Give translations in mm", source=src,
                         field=trans[int(np.argmax(t.max(axis=0)))])
    _check_force_unit(df, src, force, moment)
    if r.max() > MAX_ROTATION_DEG:
        i, j = np.unravel_index(np.argmax(r), r.shape)
        raise InputError(f"row {i + 2}: rotation {df[rots[j]].iloc[i]:g} deg beyond {MAX_ROTATION_DEG:g} deg",
                         source=src, field=rots[j])
    if (moment >= 1.0).any() and r.max() < MIN_ROTATION_DEG:
        raise InputError(f"every rotation is below {MIN_ROTATION_DEG:g} deg (largest {r.max():.3g}) although "
                         "moments of 1 N m or more act: radians in the _deg columns? Give rotations in deg",
                         source=src, field=rots[int(np.argmax(r.max(axis=0)))])
    for col, limit in RADIAN_SLIP_DEG.items():
        moment_col = next(m for m, c in PULLS.items() if c == col)
        if col in df.columns and moment_col in df.columns and col.rsplit("_", 1)[0] not in held:
            largest = float(np.abs(df[col].to_numpy(float)).max())
            if (np.abs(df[moment_col].to_numpy(float)) >= RADIAN_MOMENT_NM).any() and largest < limit:
                raise InputError(f"never beyond {limit:g} deg (largest {largest:.3g}) although {moment_col} reaches "
                                 f"{RADIAN_MOMENT_NM:g} N m or more: radians in a _deg column? Give rotations in deg",
                                 source=src, field=col)


#: A row under loads below 1 N and :data:`QUIET_MOMENT_NM` that moved this far (mm or deg) from the
#: quietest row of its flexion, along its own load, was loaded in another unit (kN under ``_N``).
KN_SLIP_MM = 1.0
QUIET_MOMENT_NM = 0.1
#: Each load component and the coordinate it pulls along (the same sign: an anterior force moves
#: the tibia anteriorly, a varus moment into varus).
PULLS = {"anterior_force_N": "anterior_translation_mm", "lateral_force_N": "lateral_translation_mm",
         "varus_moment_Nm": "varus_rotation_deg", "internal_moment_Nm": "internal_rotation_deg"}
#: Rows that must have moved along their loads before the loads are called 1000 times too small.
SLIPPED_ROWS = 3


def _check_force_unit(df: pd.DataFrame, src: str, force: np.ndarray, moment: np.ndarray) -> None:
    """Forces in N and moments in N m, judged by the pull of each load against its displacement.
    At one flexion (a robot's scatter of a few degrees included), rows whose loads are all below
    1 N and :data:`QUIET_MOMENT_NM` are compared with the quietest row: if, with the forces (or
    every load) read as 1000 times larger, at least :data:`SLIPPED_ROWS` of them moved more than
    :data:`KN_SLIP_MM` along their largest load and at most a quarter as many against it, the
    loads were given in kN (or kN m).  A knee's neutral zone moves an unloaded pose too, but not
    along the noise of its load cell."""
    columns = [c for c in PULLS if c in df.columns and PULLS[c] in df.columns]
    loads = df[columns].to_numpy(float)
    typical = np.array([TYPICAL[c.rsplit("_", 1)[0]] for c in columns])
    forces = np.array([c.endswith("_N") for c in columns])
    quiet = (force < 1.0) & (moment < QUIET_MOMENT_NM)
    nominal = nominal_flexions(df["flexion_deg"].to_numpy(float))
    for scaled in (forces, np.ones_like(forces)):  # kN under _N; kN and kN m
        rel = np.abs(loads) * np.where(scaled, 1000.0, 1.0) / typical
        along, against = [], 0
        for flexion in np.unique(nominal):
            rows = np.flatnonzero(nominal == flexion)
            reference = rows[np.argmin(rel[rows].max(axis=1))]
            for i in rows[quiet[rows] & (rows != reference)]:
                c = int(np.argmax(rel[i]))
                moved = df[PULLS[columns[c]]].iloc[i] - df[PULLS[columns[c]]].iloc[reference]
                if abs(moved) > KN_SLIP_MM and loads[i, c] != 0:
                    if np.sign(moved) == np.sign(loads[i, c]):
                        along.append((i, columns[c], float(loads[i, c]), float(moved)))
                    else:
                        against += 1
        if len(along) >= SLIPPED_ROWS and 4 * against <= len(along):
            i, col, load, moved = max(along, key=lambda a: abs(a[3]))
            unit = col.rsplit("_", 1)[1].replace("Nm", "N m")
            raise InputError(f"row {i + 2}: {load:g} {unit} moved the tibia {abs(moved):.3g} "
                             f"{PULLS[col].rsplit('_', 1)[1]} along itself, as {len(along) - 1} more row(s) did: kN in "
                             "the _N columns (kN m in _Nm)? Give forces in N and moments in N m", source=src,
                             field=col)


def _check_protocol_name(data: MeasuredData, path: Path) -> None:
    """The ``protocol`` column of a file read without a protocol to check it against."""
    name, src = data.protocol, data.source
    known = available_protocols()
    if name in known:
        return
    beside = path.parent / f"{name}.toml"
    if re.fullmatch(r"[A-Za-z0-9_.-]+", name) and beside.is_file():
        data.check_protocol(Protocol.load(beside))
        return
    folded = re.sub(r"[\s_-]", "", name.lower())
    if folded in known or re.fullmatch(r"set\d+", folded) or difflib.get_close_matches(folded, known, cutoff=0.75):
        raise InputError(f"unknown protocol {name!r}; known: {', '.join(known)}, or a protocol file {name}.toml "
                         "beside the data (or give the protocol with --protocol)", source=src, field="protocol")
    log.info(f"{src}: protocol {name!r} is not a shipped protocol and no {name}.toml is beside the data: the "
             "trials are taken from the load columns unchecked (--protocol FILE checks them)")


def _direction(loads: dict[str, float]) -> tuple[str, float]:
    if not loads:
        return "none", 0.0
    if len(loads) > 1 or set(loads) - set(LOAD_COMPONENTS):
        return "combined", 0.0
    (comp, value), = loads.items()
    names = {"anterior_force": ("anterior", "posterior"), "varus_moment": ("varus", "valgus"),
             "internal_moment": ("internal", "external")}[comp]
    return (names[0] if value > 0 else names[1]), abs(value)
