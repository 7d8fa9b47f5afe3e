"""Laxity protocols: what was done to the knee (load cases at prescribed flexion angles).

A protocol is a TOML file (``kneenlp/resources/protocols/set1.toml`` ... ``set4.toml`` hold the paper's
Table 2).  Each ``[[cases]]`` entry gives a ``direction`` (none, anterior, posterior, varus,
valgus, internal, external) with ``magnitude`` values (N for anterior/posterior forces, N m for
moments; positive numbers, the direction gives the sign) and ``flexion`` angles (deg); every
magnitude x flexion combination is one trial, except those listed in ``exclude``.  A combined load
is written ``loads = {anterior_force = 50.0, internal_moment = 1.0}`` (signed, N and N m) with
``flexion`` and an optional ``name``.

Load axes (top-level ``load_axes``):

* ``"femoral"`` (default, the paper's choice): forces and moments along the femoral axes, so at
  30 deg flexion a varus moment about femoral X carries ``sin(30 deg) = 50 %`` of its magnitude
  as an internal moment about the tibial long axis;
* ``"joint"``: along the Grood & Suntay axes at the prescribed flexion (drawer force and varus
  moment along the floating axis ``e2``, internal moment about the tibial axis at zero varus), as a
  clinical laxity device applies them.  These directions depend only on the flexion angle, so the
  loads stay fixed in the femoral frame during a trial in both cases;
* ``"jcs"``: generalised forces of the joint coordinate system, as a robotic knee simulator
  applies them (:mod:`kneenlp.base.conventions`).

A combined load may also name ``lateral_force``, ``proximal_force`` (N) and ``flexion_moment`` (N m,
reported only).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kneenlp.base.conventions import COORDINATES, DIRECTIONS, LOAD_SIZE, load_vector
from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.modes import LoadAxes
from kneenlp.base.resources import resource
from kneenlp.base.schema import validated
from kneenlp.base.tomlfile import read_toml
from kneenlp.experiment.protocol_schema import Case, ProtocolFile

PROTOCOL_DIR = resource("protocols")


@dataclass(frozen=True)
class Trial:
    """One load case at one flexion angle (user units: deg, N, N m)."""

    id: str
    flexion_deg: float
    loads: dict[str, float]  # component -> signed value (N or N m)
    direction: str = "none"
    magnitude: float = 0.0
    axes: LoadAxes = "femoral"  # see module docstring
    #: where the applied force acts (tibial frame, m; None: the knee's tuberosity), the experiment's
    #: load point (:class:`~kneenlp.experiment.kind.Experiment`)
    point: tuple[float, float, float] | None = None
    #: the coordinates the apparatus holds and where (index in COORDINATES, rad or m): the
    #: experiment's (:class:`~kneenlp.experiment.kind.Experiment`); they are prescribed, not solved
    held: tuple[tuple[int, float], ...] = ()
    #: where a compressive preload (the proximal force) acts, when elsewhere than the other loads:
    #: the experiment's preload point (a tibial point, m, and the tuberosity's weight)
    preload_point: tuple[float, float, float, float] | None = None

    @property
    def flexion(self) -> float:
        """Flexion in rad."""
        return float(np.deg2rad(self.flexion_deg))

    @property
    def load(self) -> np.ndarray:
        """Internal load vector (N, N m; :func:`~kneenlp.base.conventions.load_vector`)."""
        return load_vector(self.loads, flexion=self.flexion, axes=self.axes, point=self.point, held=self.held,
                           preload_point=self.preload_point, loaded=self.loaded)

    @property
    def loaded(self) -> tuple[int, float] | None:
        """The coordinate the dominant load drives (index in ``COORDINATES``) and the load's sign;
        None without a load."""
        word = self.dominant
        if word == "none":
            return None
        comp, sign = next(key for key, w in DIRECTION_WORDS.items() if w == word)
        return COORDINATES.index(LOADED_COORDINATE[comp]), float(sign)

    @property
    def dominant(self) -> str:
        """The direction of the trial's largest load (:func:`dominant_direction`), e.g. ``anterior``."""
        return self.direction if self.direction != "combined" else dominant_direction(self.loads)

    @property
    def dominant_component(self) -> str | None:
        """The load component of :attr:`dominant` (e.g. ``anterior_force``); None without a load."""
        word = self.dominant
        return None if word == "none" else next(c for (c, _), w in DIRECTION_WORDS.items() if w == word)

    @property
    def dominant_size(self) -> float:
        """The size of the trial's dominant load component (N or N m; 0 without a load)."""
        comp = self.dominant_component
        return 0.0 if comp is None else abs(float(self.loads.get(comp, 0.0)))

    def describe(self) -> str:
        """Words for reports, e.g. 'anterior 134 N at 30 deg flexion'."""
        if self.direction == "none":
            what = "no load"
        elif self.direction == "combined":  # a measured load: name its dominant component
            word = self.dominant
            if word == "none":
                what = "measured near-zero load"
            else:
                unit = "N" if self.dominant_component.endswith("force") else "N m"
                what = f"{word} {self.dominant_size:.3g} {unit} (measured load)"
        else:
            unit = "N" if self.direction in ("anterior", "posterior") else "N m"
            what = f"{self.direction} {self.magnitude:g} {unit}"
        return f"{what} at {self.flexion_deg:g} deg flexion"



@dataclass(frozen=True, eq=False)
class Loading:
    """What a batch of T trials' equilibria depend on besides the poses and the parameters: the load
    vectors (T x :data:`~kneenlp.base.conventions.LOAD_SIZE`, N and N m) and the flexions (T, rad)."""

    loads: np.ndarray
    flexions: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "loads", np.asarray(self.loads, dtype=float).reshape(-1, LOAD_SIZE))
        object.__setattr__(self, "flexions", np.asarray(self.flexions, dtype=float).ravel())

    @classmethod
    def of(cls, trials) -> Loading:
        """The loading of ``trials`` (:attr:`Trial.load`, :attr:`Trial.flexion`)."""
        return cls(np.array([t.load for t in trials]), np.array([t.flexion for t in trials]))

    def __len__(self) -> int:
        return len(self.flexions)

    def __getitem__(self, index) -> Loading:
        """The loading of the trials ``index`` selects (an index array or a boolean mask)."""
        return Loading(self.loads[index], self.flexions[index])


#: Names of the dominant load of a trial (component, sign) -> direction word.
DIRECTION_WORDS = {("anterior_force", 1): "anterior", ("anterior_force", -1): "posterior",
                   ("varus_moment", 1): "varus", ("varus_moment", -1): "valgus",
                   ("internal_moment", 1): "internal", ("internal_moment", -1): "external",
                   ("lateral_force", 1): "lateral", ("lateral_force", -1): "medial"}
#: The coordinate each dominant load component drives.
LOADED_COORDINATE = {"anterior_force": "anterior_translation", "varus_moment": "varus_rotation",
                     "internal_moment": "internal_rotation", "lateral_force": "lateral_translation"}
#: The laxity a pair of opposite loads measures: the coordinate column (mm or deg) and the two
#: direction words, positive first (anterior-posterior laxity is the anterior translation under the
#: anterior load minus that under the posterior load).
LAXITY_PAIRS = {"anterior_translation_mm": ("anterior", "posterior"),
                "internal_rotation_deg": ("internal", "external"),
                "varus_rotation_deg": ("varus", "valgus")}
#: Typical magnitude of each load component of a laxity test (N, N m): a trial's direction is its
#: largest component relative to these.
TYPICAL = {"anterior_force": 100.0, "varus_moment": 5.0, "internal_moment": 5.0, "lateral_force": 100.0}


def dominant_direction(loads: dict[str, float]) -> str:
    """The direction word of a trial's largest load relative to :data:`TYPICAL` (``none`` below a
    tenth of it)."""
    rel = {c: loads.get(c, 0.0) / s for c, s in TYPICAL.items()}
    comp = max(rel, key=lambda c: abs(rel[c]))
    if abs(rel[comp]) < 0.1:
        return "none"
    return DIRECTION_WORDS[(comp, 1 if rel[comp] > 0 else -1)]


#: Measured flexions (deg) closer than this to the next one belong to one nominal flexion: a robot
#: scatters a few degrees about its target (S192803: 84.1-88.7 deg for 90, consecutive gaps under
#: 2.5 deg), while designed protocols space their flexions by 5 deg or more.
FLEXION_GAP_DEG = 3.0


def flexion_groups(trials) -> np.ndarray:
    """Each trial's nominal flexion (deg): :func:`nominal_flexions` of their measured flexions."""
    return nominal_flexions(np.array([t.flexion_deg for t in trials], float))


def nominal_flexions(flexion: np.ndarray) -> np.ndarray:
    """Each measured flexion's nominal one (deg): the mean of its group, the flexions sorted and split
    where consecutive ones differ by more than :data:`FLEXION_GAP_DEG`.  A protocol's exact
    flexions are their own groups."""
    flexion = np.asarray(flexion, float)
    order = np.argsort(flexion, kind="stable")
    out = np.empty_like(flexion)
    start = 0
    for k in range(1, len(order) + 1):
        if k == len(order) or flexion[order[k]] - flexion[order[k - 1]] > FLEXION_GAP_DEG:
            group = order[start:k]
            out[group] = flexion[group].mean()
            start = k
    return out


def trial_id(direction: str, magnitude: float, flexion_deg: float) -> str:
    """Canonical trial id, e.g. ``anterior_134N_flex30`` or ``none_flex0``."""
    if direction == "none":
        return f"none_flex{flexion_deg:g}"
    unit = "N" if direction in ("anterior", "posterior") else "Nm"
    return f"{direction}_{magnitude:g}{unit}_flex{flexion_deg:g}"


@dataclass(frozen=True)
class Protocol:
    """An ordered list of trials with a name."""

    name: str
    trials: tuple[Trial, ...]
    title: str = ""
    description: str = ""
    source: str | None = None

    def __len__(self) -> int:
        return len(self.trials)

    def to_dict(self) -> dict:
        """The protocol as a protocol-file document (one case per trial); ``from_dict`` of it gives
        the same trials."""
        axes = {t.axes for t in self.trials}
        if len(axes) > 1:
            raise InputError("trials with different load axes cannot be written to one protocol file",
                             source=self.source, field="load_axes")
        cases = []
        for t in self.trials:
            if t.direction == "combined":
                cases.append({"name": t.id.rsplit("_flex", 1)[0], "loads": dict(t.loads), "flexion": [t.flexion_deg]})
            elif t.direction == "none":
                cases.append({"direction": "none", "flexion": [t.flexion_deg]})
            else:
                cases.append({"direction": t.direction, "magnitude": [t.magnitude], "flexion": [t.flexion_deg]})
        return {"name": self.name, "title": self.title, "description": self.description,
                "load_axes": axes.pop() if axes else "femoral", "cases": cases}

    def to_toml(self, header: list[str] | None = None) -> str:
        """Protocol-file text (TOML written by tomli-w) with ``header`` lines as comments."""
        import tomli_w

        lines = [*(header or []), "magnitude: N for anterior/posterior, N m for moments; flexion: deg."]
        return "".join(f"# {line}\n" for line in lines) + tomli_w.dumps(self.to_dict())

    def trial(self, tid: str) -> Trial:
        for t in self.trials:
            if t.id == tid:
                return t
        raise unknown_name("trial", tid, [t.id for t in self.trials], source=self.source)

    @classmethod
    def load(cls, name_or_path: str | Path) -> Protocol:
        """Load a protocol by name (``set1`` ... ``set4``, or any file in ``kneenlp/resources/protocols``)
        or by path to a TOML file."""
        path = Path(name_or_path)
        if not path.suffix:
            candidate = PROTOCOL_DIR / f"{name_or_path}.toml"
            if not candidate.is_file():
                known = sorted(p.stem for p in PROTOCOL_DIR.glob("*.toml"))
                raise unknown_name("protocol", str(name_or_path), known)
            path = candidate
        return cls.from_dict(read_toml(path), source=str(path), default_name=path.stem)

    @classmethod
    def from_dict(cls, doc: dict, *, source: str = "<protocol>", default_name: str = "protocol") -> Protocol:
        """Build and validate a protocol from a protocol-file document (see module docstring): the
        document against :class:`~kneenlp.experiment.protocol_schema.ProtocolFile`, then the loads
        and angles; an error names ``source`` and the field."""
        if not isinstance(doc, dict):
            raise InputError("expected a table", source=source)
        spec = validated(ProtocolFile, doc, source)
        trials: list[Trial] = []
        for i, case in enumerate(spec.cases):
            trials += _case_trials(case, f"cases[{i}]", i, spec.load_axes, source)
        ids = [t.id for t in trials]
        dup = sorted({t for t in ids if ids.count(t) > 1})
        if dup:
            raise InputError(f"duplicate trials: {', '.join(dup)}", source=source, field="cases")
        return cls(spec.name if spec.name is not None else default_name, tuple(trials), spec.title,
                   spec.description, source)


#: Largest load a protocol or a measured-data file may give: 1000 N and 100 N m, about ten times
#: the largest loads of laxity tests (the paper's Table 2: 134 N, 10 N m).  Larger values are
#: unit slips (N m as N mm, kN as N) or typing errors, and would be fitted as garbage.
MAX_FORCE = 1000.0
MAX_MOMENT = 100.0
#: Flexion angles a protocol or a measured-data file may give (deg).
FLEXION_RANGE = (-10.0, 120.0)


def check_load(component: str, value: float, source: str | None, field: str) -> float:
    """``value`` (N or N m) of a load ``component``, or an error if beyond :data:`MAX_FORCE` /
    :data:`MAX_MOMENT`."""
    limit, unit = (MAX_FORCE, "N") if component.endswith("_force") else (MAX_MOMENT, "N m")
    if abs(value) > limit:
        raise InputError(f"{value:g} {unit} is beyond the largest laxity load ({limit:g} {unit}); a unit slip?",
                         source=source, field=field)
    return value


def _flexions(flexions: list[float], source: str, field: str) -> list[float]:
    """The flexion angles (deg) of a case, each within :data:`FLEXION_RANGE`."""
    lo, hi = FLEXION_RANGE
    for f in flexions:
        if not lo <= f <= hi:
            raise InputError(f"flexion {f:g} deg outside [{lo:g}, {hi:g}]", source=source, field=field)
    return flexions


def _case_trials(case: Case, fld: str, i: int, axes: LoadAxes, source: str) -> list[Trial]:
    """The trials of one ``[[cases]]`` entry (loads in N and N m, flexion in deg)."""
    flexions = _flexions(case.flexion, source, f"{fld}.flexion")
    if case.loads is not None:
        for key in ("direction", "magnitude", "exclude"):
            if getattr(case, key) is not None:
                raise InputError("give either loads or direction/magnitude/exclude", source=source,
                                 field=f"{fld}.{key}")
        if not case.loads:
            raise InputError("must be a table of load components", source=source, field=f"{fld}.loads")
        values = {k: check_load(k, v, source, f"{fld}.loads.{k}") for k, v in case.loads.items()}
        label = case.name if case.name is not None else f"combined{i}"
        return [Trial(f"{label}_flex{f:g}", f, values, "combined", 0.0, axes) for f in flexions]
    direction = case.direction
    if direction is None:
        raise unknown_name("load direction", str(direction), DIRECTIONS, source=source).with_context(
            field=f"{fld}.direction")
    component, sign = DIRECTIONS[direction]
    if direction == "none":
        if case.magnitude is not None:
            raise InputError("no magnitude for direction 'none'", source=source, field=f"{fld}.magnitude")
        magnitudes = [0.0]
    else:
        if case.magnitude is None:
            raise InputError("missing magnitude", source=source, field=f"{fld}.magnitude")
        magnitudes = case.magnitude
        if any(m <= 0 for m in magnitudes):
            raise InputError("magnitudes must be > 0 (the direction gives the sign)",
                             source=source, field=f"{fld}.magnitude")
        for m in magnitudes:
            check_load(component, m, source, f"{fld}.magnitude")
    excluded = _excluded(case, magnitudes, flexions, fld, source)
    trials = []
    for f in flexions:
        for m in magnitudes:
            if (m, f) in excluded:
                continue
            loads = {component: sign * m} if component else {}
            trials.append(Trial(trial_id(direction, m, f), f, loads, direction, m, axes))
    return trials


def _excluded(case: Case, magnitudes: list[float], flexions: list[float], fld: str,
              source: str) -> set[tuple[float, float]]:
    """The (magnitude, flexion) pairs of the case's ``exclude = [{magnitude = M, flexion = F}, ...]`` (the
    case at ``fld``, its trials' ``magnitudes`` and ``flexions``): each entry must name one of the case's
    trials (an entry that excludes nothing is a typo that would silently keep the trial)."""
    out, direction = set(), case.direction
    for j, entry in enumerate(case.exclude or []):
        efld = f"{fld}.exclude[{j}]"
        if entry.magnitude is None and direction != "none":
            raise InputError("missing magnitude", source=source, field=f"{efld}.magnitude")
        m = entry.magnitude if entry.magnitude is not None else 0.0
        f = entry.flexion
        if m not in magnitudes or f not in flexions:
            raise InputError(f"excludes no trial of this case (magnitude {m:g}, flexion {f:g})", source=source,
                             field=efld)
        out.add((m, f))
    return out


def available_protocols() -> list[str]:
    """Names of the protocols shipped in ``kneenlp/resources/protocols``."""
    return sorted(p.stem for p in PROTOCOL_DIR.glob("*.toml"))
