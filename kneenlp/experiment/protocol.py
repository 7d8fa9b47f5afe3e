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
  loads stay fixed in the femoral frame during a trial in both cases.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kneenlp.conventions import DIRECTIONS, LOAD_AXES, LOAD_COMPONENTS, load_vector
from kneenlp.errors import InputError, unknown_name
from kneenlp.io.resources import resource
from kneenlp.model.parameters import number, read_toml

PROTOCOL_DIR = resource("protocols")


@dataclass(frozen=True)
class Trial:
    """One load case at one flexion angle (user units: deg, N, N m)."""

    id: str
    flexion_deg: float
    loads: dict[str, float]  # component -> signed value (N or N m)
    direction: str = "none"
    magnitude: float = 0.0
    axes: str = "femoral"  # or "joint", see module docstring

    @property
    def flexion(self) -> float:
        """Flexion in rad."""
        return float(np.deg2rad(self.flexion_deg))

    @property
    def load(self) -> np.ndarray:
        """Internal 6-vector load ``[F, M]`` in the femoral frame (N, N m)."""
        return load_vector(*(self.loads.get(c, 0.0) for c in LOAD_COMPONENTS), flexion=self.flexion,
                           axes=self.axes)

    def describe(self) -> str:
        """Words for reports, e.g. 'anterior 134 N at 30 deg flexion'."""
        if self.direction == "none":
            what = "no load"
        elif self.direction == "combined":
            what = "combined load " + ", ".join(f"{k} {v:g}" for k, v in self.loads.items())
        else:
            unit = "N" if self.direction in ("anterior", "posterior") else "N m"
            what = f"{self.direction} {self.magnitude:g} {unit}"
        return f"{what} at {self.flexion_deg:g} deg flexion"


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
        cases = doc.get("cases")
        if not isinstance(cases, list) or not cases:
            raise InputError("no [[cases]] given", source=source, field="cases")
        axes = doc.get("load_axes", "femoral")
        if axes not in LOAD_AXES:
            raise unknown_name("load_axes", str(axes), LOAD_AXES, source=source)
        trials: list[Trial] = []
        for i, case in enumerate(cases):
            fld = f"cases[{i}]"
            flex = case.get("flexion")
            if flex is None:
                raise InputError("missing flexion angles (deg)", source=source, field=f"{fld}.flexion")
            flexions = [number(f, source, f"{fld}.flexion") for f in (flex if isinstance(flex, list) else [flex])]
            for f in flexions:
                if not -10.0 <= f <= 120.0:
                    raise InputError(f"flexion {f:g} deg outside [-10, 120]", source=source, field=f"{fld}.flexion")
            if "loads" in case:
                loads = case["loads"]
                if not isinstance(loads, dict):
                    raise InputError("must be a table of load components", source=source, field=f"{fld}.loads")
                for k in loads:
                    if k not in LOAD_COMPONENTS:
                        raise unknown_name("load component", k, LOAD_COMPONENTS, source=source)
                values = {k: number(v, source, f"{fld}.loads.{k}") for k, v in loads.items()}
                label = str(case.get("name", f"combined{i}"))
                for f in flexions:
                    trials.append(Trial(f"{label}_flex{f:g}", f, values, "combined", 0.0, axes))
                continue
            direction = case.get("direction")
            if direction not in DIRECTIONS:
                raise unknown_name("load direction", str(direction), DIRECTIONS, source=source)
            component, sign = DIRECTIONS[direction]
            if direction == "none":
                magnitudes = [0.0]
            else:
                mags = case.get("magnitude")
                if mags is None:
                    raise InputError("missing magnitude", source=source, field=f"{fld}.magnitude")
                mags = mags if isinstance(mags, list) else [mags]
                magnitudes = [number(m, source, f"{fld}.magnitude") for m in mags]
                if any(m <= 0 for m in magnitudes):
                    raise InputError("magnitudes must be > 0 (the direction gives the sign)",
                                     source=source, field=f"{fld}.magnitude")
            excluded = {(float(e.get("magnitude", 0.0)), float(e["flexion"])) for e in case.get("exclude", [])}
            for f in flexions:
                for m in magnitudes:
                    if (m, f) in excluded:
                        continue
                    loads = {component: sign * m} if component else {}
                    trials.append(Trial(trial_id(direction, m, f), f, loads, direction, m, axes))
        ids = [t.id for t in trials]
        dup = sorted({t for t in ids if ids.count(t) > 1})
        if dup:
            raise InputError(f"duplicate trials: {', '.join(dup)}", source=source, field="cases")
        return cls(str(doc.get("name", default_name)), tuple(trials), str(doc.get("title", "")),
                   str(doc.get("description", "")), source)


def available_protocols() -> list[str]:
    """Names of the protocols shipped in ``kneenlp/resources/protocols``."""
    return sorted(p.stem for p in PROTOCOL_DIR.glob("*.toml"))
