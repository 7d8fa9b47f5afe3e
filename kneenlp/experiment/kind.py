"""The kind of experiment measured data come from: one unit, declared in the data.

A measured-data file names its experiment in an ``experiment`` column (one value for every row);
an :class:`Experiment` says what that experiment is:

* ``laboratory``: a real knee on a real apparatus (a calibration with priors fits it, ``identify``'s
  ``strategy="auto"``), or a simulation (the paper's scatter of starts);
* ``observed``: the coordinates it measures (:data:`~kneenlp.base.conventions.COORDINATES`; the
  others are not in the file, and the fit weighs them zero);
* ``load_point``: the named tibial point its applied force acts at: ``tibial_tuberosity`` (the
  knee's, the paper's), ``tibial_origin``, or a point of its own ``points`` (mm, tibial frame);
* ``held``: the coordinates its apparatus holds (a device that fixes the foot's rotation is not a
  robot in force control), each at a value (deg, mm; ``[held]`` table).  They are prescribed, not
  solved: simulate holds them at those values; measured data that observe a held coordinate hold
  each trial at its measured value (the apparatus set it), and at the declared value where they
  do not observe it.  At least one coordinate stays free;
* ``preload_point``: where its compressive preload (the proximal force) acts when not at the load
  point (a weight hung at the ankle, a pneumatic cylinder along the tibia), named like
  ``load_point``; not for a robot's joint loads (``load_axes = jcs``: generalised forces).

Two kinds are shipped: ``simulated`` (every coordinate, the tuberosity: what ``simulate`` writes)
and ``laboratory`` (the same, on a real knee: what ``import-laxity`` writes).  Any other name is an
experiment file ``NAME.toml`` beside the data::

    name = "strap"
    laboratory = false
    observed = ["varus_rotation", "internal_rotation"]
    load_point = "ankle"
    [points]
    ankle = [0.0, -350.0, 0.0]   # mm, tibial frame (X anterior, Y proximal, Z lateral)

A file without the column was written before it existed: it is ``laboratory`` if it states a
``side`` or has a robot's joint loads (``load_axes = jcs``), else ``simulated``; that is the one
place this is inferred.  The experiment's load point is written into each trial's load vector
(:func:`~kneenlp.base.conventions.load_vector`), so the one model serves every experiment.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated

import numpy as np
import pandas as pd
from pydantic import BeforeValidator, Field

from kneenlp.base.conventions import COORDINATES, POSE_ENVELOPE_USER, TO_USER
from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.schema import Flag, Name, Number, Table, fail, one_of, validated
from kneenlp.base.tomlfile import read_toml
from kneenlp.experiment.protocol import Trial

#: Named tibial points every experiment knows (the tuberosity is the knee's own).
KNOWN_POINTS = ("tibial_tuberosity", "tibial_origin")
#: The farthest a tibial point of an experiment may lie from the tibial origin (mm): a device that
#: straps the foot loads about 400 mm below the knee; farther is a unit slip.
MAX_POINT_MM = 600.0


def _point(value: object) -> list[float]:
    """A tibial point: three finite numbers (mm)."""
    if not isinstance(value, list) or len(value) != 3 or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v) for v in value):
        raise fail(f"expected three finite numbers (mm, tibial frame), got {value!r}")
    return [float(v) for v in value]


Point = Annotated[list[float], BeforeValidator(_point)]


class ExperimentFile(Table):
    """An experiment file: its name, whether it is a real knee's, what it observes, where it loads."""

    name: Name
    description: str = ""
    laboratory: Flag = False
    observed: list[Annotated[str, one_of("coordinate", COORDINATES)]] = Field(
        default_factory=lambda: list(COORDINATES), min_length=1)
    load_point: Name = "tibial_tuberosity"
    points: dict[Name, Point] = Field(default_factory=dict)
    held: dict[Annotated[str, one_of("coordinate", COORDINATES)], Number] = Field(default_factory=dict)
    preload_point: Name | None = None


@dataclass(frozen=True)
class Experiment:
    """What an experiment is (module docstring); ``points`` in the tibial frame, m."""

    name: str
    laboratory: bool = False
    observed: tuple[str, ...] = COORDINATES
    load_point: str = "tibial_tuberosity"
    points: dict[str, tuple[float, float, float]] = field(default_factory=dict, compare=False)
    description: str = ""
    #: the coordinates the apparatus holds and their values (rad, m)
    held: dict[str, float] = field(default_factory=dict, compare=False)
    #: where the compressive preload acts (a point name as ``load_point``; None: at the load point)
    preload_point: str | None = None

    def __post_init__(self) -> None:
        for name, value in self.held.items():
            if name not in COORDINATES:
                raise unknown_name("coordinate", name, COORDINATES).with_context(field=f"held.{name}")
            j = COORDINATES.index(name)
            if abs(value * TO_USER[j]) > POSE_ENVELOPE_USER[j]:
                unit = "deg" if "rotation" in name else "mm"
                raise InputError(f"{value * TO_USER[j]:g} {unit} is beyond what a knee reaches "
                                 f"({POSE_ENVELOPE_USER[j]:g} {unit}); a unit slip?", field=f"held.{name}")
        for name, point in self.points.items():
            if np.linalg.norm(point) * 1e3 > MAX_POINT_MM:
                raise InputError(f"{np.linalg.norm(point) * 1e3:g} mm from the tibial origin, beyond "
                                 f"{MAX_POINT_MM:g} mm (a foot-strap loads about 400 mm below the knee); a unit slip?",
                                 field=f"points.{name}")
        if len(self.held) == len(COORDINATES):
            raise InputError("holds every coordinate: nothing is left for the knee to move (hold at most four)",
                             field="held")
        shadowing = sorted(set(self.points) & set(KNOWN_POINTS))
        if shadowing:
            raise InputError(f"{shadowing[0]!r} is a point every experiment knows; name yours otherwise",
                             field=f"points.{shadowing[0]}")
        known = (*KNOWN_POINTS, *self.points)
        if self.load_point not in known:
            raise unknown_name("load point", self.load_point, known)
        if self.preload_point is not None and self.preload_point not in known:
            raise unknown_name("preload point", self.preload_point, known).with_context(field="preload_point")

    @classmethod
    def load(cls, path: str | Path) -> Experiment:
        """An experiment file (module docstring; points in mm), checked."""
        src = str(path)
        doc = validated(ExperimentFile, read_toml(Path(path)), src)
        try:
            return cls(doc.name, doc.laboratory, tuple(c for c in COORDINATES if c in doc.observed),
                       doc.load_point, {n: tuple(np.asarray(p, float) / 1e3) for n, p in doc.points.items()},
                       doc.description, {n: float(v / TO_USER[COORDINATES.index(n)]) for n, v in doc.held.items()},
                       doc.preload_point)
        except InputError as exc:
            raise exc.with_context(source=src, field=exc.field or "load_point") from None

    @property
    def mask(self) -> np.ndarray:
        """Which of the five coordinates it observes (bool, :data:`COORDINATES` order)."""
        return np.array([c in self.observed for c in COORDINATES])

    def point(self, name: str | None = None) -> np.ndarray | None:
        """Where its applied force acts, or the point ``name`` (tibial frame, m); ``None``: the
        knee's tuberosity."""
        name = self.load_point if name is None else name
        if name == "tibial_tuberosity":
            return None
        return np.zeros(3) if name == "tibial_origin" else np.asarray(self.points[name], float)

    def preload_at(self) -> tuple[float, float, float, float] | None:
        """Where its preload acts, when elsewhere than its load point: a tibial point (m) and the
        weight of the knee's tuberosity added to it (:func:`~kneenlp.base.conventions.load_vector`);
        ``None``: with the other loads."""
        if self.preload_point is None or self.preload_point == self.load_point:
            return None
        at = self.point(self.preload_point)
        return (0.0, 0.0, 0.0, 1.0) if at is None else (*map(float, at), 0.0)

    def applied_to(self, trials: list[Trial], measured: np.ndarray | None = None) -> list[Trial]:
        """``trials`` with their force applied at this experiment's load point (the preload at its
        preload point) and its held coordinates held: at the ``measured`` values (T x 5, SI; NaN
        where not observed) where given, else at the declared ones."""
        at, preload = self.point(), self.preload_at()
        out = [t if at is None and t.point is None and t.preload_point == preload
               else replace(t, point=None if at is None else tuple(at), preload_point=preload) for t in trials]
        if not self.held:
            return out
        index = {c: COORDINATES.index(c) for c in self.held}

        def value(row: int, name: str) -> float:
            if measured is not None and np.isfinite(measured[row, index[name]]):
                return float(measured[row, index[name]])
            return self.held[name]

        return [replace(t, held=tuple((index[n], value(k, n)) for n in self.held)) for k, t in enumerate(out)]


#: The shipped experiments (module docstring).
SIMULATED = Experiment("simulated", description="simulated data: every coordinate, the force at the tuberosity")
LABORATORY = Experiment("laboratory", laboratory=True, description="a real knee on a real apparatus")


def experiment_named(name: str, beside: Path | None = None) -> Experiment:
    """The shipped experiment ``name``, or the experiment file ``NAME.toml`` in ``beside`` (a folder)."""
    shipped = {e.name: e for e in (SIMULATED, LABORATORY)}
    if name in shipped:
        return shipped[name]
    path = None if beside is None else beside / f"{name}.toml"
    if path is None or not path.is_file():
        raise InputError(f"unknown experiment {name!r}: not one of {', '.join(shipped)} and no {name}.toml beside "
                         "the data", field="experiment")
    found = Experiment.load(path)
    if found.name != name:
        raise InputError(f"the file declares experiment {found.name!r}, the data name {name!r}", source=str(path),
                         field="name")
    return found


def experiment_of(df: pd.DataFrame, path: Path) -> Experiment:
    """The experiment a measured-data table declares in its ``experiment`` column (one value for
    every row), files beside it included; without the column, as the module docstring says."""
    if "experiment" not in df.columns:
        side = "side" in df.columns and df["side"].notna().any()
        robot = "load_axes" in df.columns and (df["load_axes"].astype(str).str.strip() == "jcs").any()
        return LABORATORY if side or robot else SIMULATED
    names = {str(v).strip() for v in df["experiment"].dropna()}
    if not len(df):
        return SIMULATED  # no rows: the reader's own check says so
    if df["experiment"].isna().any():
        raise InputError(f"row {int(np.argmax(df['experiment'].isna())) + 2}: no experiment named (one for every "
                         "row)", source=str(path), field="experiment")
    if len(names) != 1:
        raise InputError(f"expected one experiment for every row, got {', '.join(sorted(names)) or 'none'}",
                         source=str(path), field="experiment")
    try:
        return experiment_named(names.pop(), path.parent)
    except InputError as exc:
        raise exc.with_context(source=str(path), field="experiment") from None
