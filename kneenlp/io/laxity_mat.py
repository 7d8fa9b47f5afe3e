"""Robotic laxity measurements from MATLAB files: ``kneenlp import-laxity FILE.mat --out data.csv``.

Reads any MATLAB file holding a ``processed_laxity_trial`` struct array (as the S192803 deposit
writes it) whose entries have ``tf_kin_step2_GS`` (the pose at the end of the load) and
``tf_loads_step2`` (the load then); every other field is optional.  One trial per entry, in the
file's order, in kneenlp's measured-data format (:mod:`kneenlp.experiment.measured`) with the
robot's loads as joint loads (``load_axes = "jcs"``) and the measured flexion.

The file's conventions (six numbers ``[flexion, varus-valgus, internal-external, medial-lateral,
anterior-posterior, superior-inferior]``, deg and mm; loads ``[flexion moment, varus-valgus and
internal-external moments (N m), medial-lateral, anterior-posterior, superior-inferior forces (N)]``
in the same axes and signs), checked against the S192803 model's own frames
(tests/test_real_knee_s192803.py):

* signs are anatomical for either side (the deposit's processing negates varus-valgus,
  internal-external and medial-lateral for a left knee): varus (-), internal (-), lateral (+),
  anterior (+), superior (+); kneenlp's varus and internal are therefore the negated file values;
* the ``_GS`` translations are the orthogonal projections of the femoral-to-tibial origin vector on
  the Grood-Suntay axes ``e1``, ``e2``, ``e3``; kneenlp's coordinates are its components along them
  (``p = lateral e1 + anterior e2 + proximal e3``, as the file's ``_cylindrical`` poses give them):
  :func:`gs_projections_to_coordinates` converts exactly;
* the loads are the generalised forces of those coordinates (the robot's joint loads); the flexion
  moment is kept as a column and reported (the prescribed flexion carries it).

The ``direction`` labels of the internal/external entries contradict their numbers in the deposit:
trial ids are made from the numbers (the dominant load), the source's labels are kept in the
``source_label`` column.

Checks (one-line errors naming the file, the entry and the field): the struct and both fields
present; six finite numbers each; loads within laxity magnitudes (moments beyond 100 N m: N mm?);
poses within what a knee reaches; and every pair of opposite loads at one flexion moves the knee
the way the loads push (a sign slip otherwise).  A note says when the tibia rotates externally with
flexion in the unloaded or anterior trials (the opposite of the screw-home: a mirrored side?).
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from kneenlp.base.errors import InputError
from kneenlp.experiment.kind import LABORATORY
from kneenlp.experiment.measured import check_plausible, measured_frame
from kneenlp.experiment.protocol import DIRECTION_WORDS, MAX_FORCE, MAX_MOMENT, Trial, dominant_direction
from kneenlp.model.kinematics import tibial_pose

log = logging.getLogger("kneenlp")

STRUCT = "processed_laxity_trial"
POSE_FIELD = "tf_kin_step2_GS"
LOAD_FIELD = "tf_loads_step2"
#: Largest plausible |measured translation| (mm) and |rotation| other than flexion (deg).
MAX_TRANSLATION_MM = 60.0
MAX_ROTATION_DEG = 60.0
#: Coordinate each direction moves (column, sign).
MOVES = {"anterior_force": "anterior_translation_mm", "varus_moment": "varus_rotation_deg",
         "internal_moment": "internal_rotation_deg", "lateral_force": "lateral_translation_mm"}


def gs_projections_to_coordinates(flexion_deg: float, varus_deg: float, internal_deg: float,
                                  projections_mm: np.ndarray) -> np.ndarray:
    """kneenlp's translations (lateral, anterior, proximal; mm) from the orthogonal projections of
    the origin vector on ``e1``, ``e2``, ``e3`` at a pose (kneenlp's signs and units)."""
    _, _, (e1, e2, e3) = tibial_pose(np.radians(flexion_deg), np.radians([varus_deg, internal_deg, 0, 0, 0]))
    E = np.column_stack([np.asarray(e, float).ravel() for e in (e1, e2, e3)])
    return np.linalg.solve(E.T @ E, np.asarray(projections_mm, float))


@dataclass
class LaxityEntry:
    """One entry of the struct: the source's labels, the pose and the load (file conventions)."""

    index: int
    label: str
    nominal_flexion: float | None
    pose: np.ndarray  # flexion, VV, IE, ML, AP, SI (deg, mm)
    load: np.ndarray  # FE, VV, IE (N m), ML, AP, SI (N)


def read_laxity_mat(path: str | Path) -> list[LaxityEntry]:
    """The entries of ``processed_laxity_trial`` in ``path`` (checks: module docstring)."""
    import scipy.io

    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise InputError("file not found", source=src)
    try:
        mat = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except NotImplementedError:
        raise InputError("a MATLAB v7.3 (HDF5) file: save it with -v7 (scipy reads up to v7)", source=src) from None
    except Exception as exc:  # scipy raises many kinds for files that are not MATLAB files
        raise InputError(f"not a MATLAB file scipy can read ({type(exc).__name__}: {exc})", source=src) from None
    if STRUCT not in mat:
        known = ", ".join(k for k in mat if not k.startswith("__")) or "none"
        raise InputError(f"no struct array {STRUCT!r} (variables: {known})", source=src, field=STRUCT)
    entries = np.atleast_1d(mat[STRUCT])
    if entries.size == 0:
        raise InputError("the struct array is empty", source=src, field=STRUCT)
    out = []
    for i, e in enumerate(entries):
        fields = getattr(e, "_fieldnames", None)
        if fields is None:
            raise InputError(f"entry {i + 1} is not a struct", source=src, field=STRUCT)
        values = {}
        for name in (POSE_FIELD, LOAD_FIELD):
            if name not in fields:
                raise InputError(f"entry {i + 1} has no field {name}", source=src, field=f"{STRUCT}({i + 1}).{name}")
            v = np.atleast_1d(np.asarray(getattr(e, name), dtype=float)).ravel() \
                if _numeric(getattr(e, name)) else None
            if v is None or v.size != 6:
                what = "a missing load component" if name == LOAD_FIELD else "a missing coordinate"
                raise InputError(f"entry {i + 1}: expected six numbers, got {0 if v is None else v.size} ({what}?)",
                                 source=src, field=f"{STRUCT}({i + 1}).{name}")
            bad = ~np.isfinite(v)
            if bad.any():
                raise InputError(f"entry {i + 1}: value {int(np.argmax(bad)) + 1} is {v[bad][0]} (not a finite number)",
                                 source=src, field=f"{STRUCT}({i + 1}).{name}")
            values[name] = v
        label = " ".join(str(getattr(e, f)) for f in ("type", "direction") if f in fields).strip()
        nominal = float(e.FEAngle) if "FEAngle" in fields and _numeric(e.FEAngle) else None
        out.append(LaxityEntry(i, label, nominal, values[POSE_FIELD], values[LOAD_FIELD]))
    _check_magnitudes(out, src)
    return out


def _numeric(value: object) -> bool:
    try:
        np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return True


def _check_magnitudes(entries: list[LaxityEntry], src: str) -> None:
    for e in entries:
        fld = f"{STRUCT}({e.index + 1})"
        moments, forces = np.abs(e.load[:3]), np.abs(e.load[3:])
        if moments.max() > MAX_MOMENT:
            raise InputError(f"entry {e.index + 1}: moment {e.load[int(np.argmax(moments))]:g} beyond "
                             f"{MAX_MOMENT:g} N m: moments in N mm? (give N m)", source=src,
                             field=f"{fld}.{LOAD_FIELD}")
        if forces.max() > MAX_FORCE:
            raise InputError(f"entry {e.index + 1}: force {e.load[3 + int(np.argmax(forces))]:g} beyond "
                             f"{MAX_FORCE:g} N: a unit slip?", source=src, field=f"{fld}.{LOAD_FIELD}")
        if np.abs(e.pose[3:]).max() > MAX_TRANSLATION_MM or np.abs(e.pose[1:3]).max() > MAX_ROTATION_DEG \
                or not -30 <= e.pose[0] <= 150:
            raise InputError(f"entry {e.index + 1}: pose {np.round(e.pose, 2).tolist()} is beyond any knee's reach "
                             f"(|translation| <= {MAX_TRANSLATION_MM:g} mm, |rotation| <= {MAX_ROTATION_DEG:g} deg): "
                             "another unit?", source=src, field=f"{fld}.{POSE_FIELD}")


def entry_trial(e: LaxityEntry) -> tuple[Trial, np.ndarray]:
    """kneenlp's trial (joint loads, measured flexion) and measured coordinates (5, deg and mm) of
    one entry (conventions: module docstring)."""
    flexion, vv, ie, ml, ap, si = e.pose
    varus, internal = -vv, -ie
    lateral, anterior, proximal = gs_projections_to_coordinates(flexion, varus, internal, np.array([ml, ap, si]))
    fe, m_vv, m_ie, f_ml, f_ap, f_si = e.load
    loads = {"flexion_moment": fe, "varus_moment": -m_vv, "internal_moment": -m_ie, "lateral_force": f_ml,
             "anterior_force": f_ap, "proximal_force": f_si}
    word = dominant_direction(loads)
    nominal = f"{e.nominal_flexion:g}" if e.nominal_flexion is not None else f"{round(flexion):d}"
    trial = Trial(f"{word}_flex{nominal}", float(flexion), {k: float(v) for k, v in loads.items() if v != 0.0},
                  "combined", 0.0, "jcs")
    return trial, np.array([varus, internal, lateral, anterior, proximal])


def laxity_frame(path: str | Path, side: str) -> pd.DataFrame:
    """The measured-data table (kneenlp's CSV format) of a MATLAB laxity file; ``side`` is the
    knee's (``left``/``right``)."""
    if side not in ("left", "right"):
        raise InputError(f"side must be 'left' or 'right', got {side!r}", field="side")
    entries = read_laxity_mat(path)
    trials, poses = [], []
    for e in entries:
        t, q = entry_trial(e)
        trials.append(t)
        poses.append(q)
    total, seen = Counter(t.id for t in trials), Counter()
    for i, t in enumerate(trials):  # ids unique: a repeated load case gets _1, _2, ...
        if total[t.id] > 1:
            seen[t.id] += 1
            trials[i] = dataclasses.replace(t, id=f"{t.id}_{seen[t.id]}")
    df = measured_frame(trials, np.array(poses), protocol="", side=side, experiment=LABORATORY)
    df["source_label"] = [e.label for e in entries]
    df["source_entry"] = [e.index + 1 for e in entries]
    words = np.array([t.dominant for t in trials])
    nominal = np.array([e.nominal_flexion if e.nominal_flexion is not None else 10 * round(t.flexion_deg / 10)
                        for e, t in zip(entries, trials, strict=True)])
    check_plausible(df, str(path))  # what the CSV reader checks, before anything is written
    _check_directions(df, words, nominal, str(path))
    _screw_home_note(df, words, str(path))
    return df


def _check_directions(df: pd.DataFrame, words: np.ndarray, nominal: np.ndarray, src: str) -> None:
    """Opposite loads at one nominal flexion must move the knee apart the way they push."""
    for comp, col in MOVES.items():
        pos, neg = DIRECTION_WORDS[(comp, 1)], DIRECTION_WORDS[(comp, -1)]
        for f in sorted(set(nominal)):
            a = df[(words == pos) & (nominal == f)][col]
            b = df[(words == neg) & (nominal == f)][col]
            if len(a) and len(b) and a.mean() <= b.mean():
                raise InputError(f"the {pos} trial at {f:g} deg sits at {a.mean():.3g}, the {neg} one at "
                                 f"{b.mean():.3g}: the loads push the other way (a sign slip in the poses or the "
                                 "loads?)", source=src, field=col)


#: Flexions closer than this (deg) are one flexion for the side check; its slope's significance level.
SCREW_HOME_SPACING = 10.0
SCREW_HOME_P = 0.01


def _screw_home_note(df: pd.DataFrame, words: np.ndarray, src: str) -> None:
    flexion = df["flexion_deg"].to_numpy()
    near = np.isin(words, ["none", "anterior", "posterior"])
    # only on evidence: at least three flexions apart and a slope the scatter cannot make (a slope
    # fitted through two flexions' blocks is their difference, whatever its cause)
    if len(np.unique(np.round(flexion[near] / SCREW_HOME_SPACING))) >= 3 and np.ptp(flexion[near]) > 30:
        fit = stats.linregress(flexion[near], df["internal_rotation_deg"].to_numpy()[near])
        slope = fit.slope
        if slope < -0.02 and fit.pvalue < SCREW_HOME_P:
            log.warning(f"{src}: the tibia rotates externally by {-slope * 60:.1f} deg per 60 deg of flexion in the "
                        "unloaded and drawer trials, the opposite of the screw-home: is the knee's side right (a left "
                        "knee processed as a right one flips internal-external rotation)?")


def import_laxity(path: str | Path, out: str | Path, side: str) -> pd.DataFrame:
    """Write the measured-data CSV of a MATLAB laxity file (atomically); returns the table."""
    from kneenlp.base.atomic import write_csv_atomic

    if Path(out).resolve() == Path(path).resolve():
        raise InputError("is the MATLAB file itself: give another path for the CSV", source=str(out), field="--out")
    df = laxity_frame(path, side)
    write_csv_atomic(df, out, index=False, float_format="%.6g")
    return df

