"""Parameter sets: named model parameters with values in SI, read from TOML data files.

Parameter names are ``<LIGAMENT>.k`` (N per unit strain), ``<LIGAMENT>.ref_strain`` and
``<LIGAMENT>.lin_strain`` (fractions inside, percent at the user boundary) and
``contact.modulus`` (N/m^3 inside, GN/m^3 at the user boundary).  Model extensions add their own
names (``<effect>.<parameter>``) with their own units.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kneenlp.errors import InputError, unknown_name

#: Per parameter kind: accepted file units with their factor to SI, and the display unit.
UNIT_FACTORS: dict[str, dict[str, float]] = {
    "k": {"N": 1.0, "kN": 1e3},
    "ref_strain": {"%": 1e-2, "1": 1.0},
    "lin_strain": {"%": 1e-2, "1": 1.0},
    "modulus": {"GN/m^3": 1e9, "N/mm^3": 1e9, "N/m^3": 1.0},
}
DISPLAY_UNITS: dict[str, str] = {"k": "N", "ref_strain": "%", "lin_strain": "%", "modulus": "GN/m^3"}
LIGAMENT_KINDS: tuple[str, ...] = ("k", "ref_strain", "lin_strain")


@dataclass(frozen=True)
class ParameterInfo:
    """Metadata of one model parameter: display unit and the factor SI -> display."""

    name: str
    unit: str
    to_user: float
    description: str = ""
    lower: float = -np.inf  # SI bounds used by the identification NLP
    upper: float = np.inf
    scale: float = 1.0  # the NLP works with value / scale
    neutral: float | None = None  # value at which an effect parameter switches the effect off


def ligament_parameter_info(ligament: str, kind: str) -> ParameterInfo:
    """Metadata of a ligament parameter ``kind`` (k, ref_strain, lin_strain)."""
    unit = DISPLAY_UNITS[kind]
    factor = 1.0 / UNIT_FACTORS[kind][unit]
    lower, upper, scale = {"k": (0.0, 1e5, 1e4), "ref_strain": (-0.3, 0.3, 1e-2),
                           "lin_strain": (0.005, 0.1, 1e-2)}[kind]
    text = {
        "k": "stiffness, N per unit strain",
        "ref_strain": "reference strain at the reference pose",
        "lin_strain": "linear strain limit of the toe region",
    }[kind]
    return ParameterInfo(f"{ligament}.{kind}", unit, factor, f"{ligament} {text}", lower, upper, scale)


MODULUS_INFO = ParameterInfo("contact.modulus", "GN/m^3", 1e-9, "elastic-foundation pressure modulus",
                             1e8, 1e12, 1e10)


@dataclass
class ParameterSet:
    """Values (SI) of named model parameters; ``name`` says where they came from."""

    values: dict[str, float]
    name: str = "unnamed"
    source: str | None = None
    description: str = ""
    meta: dict[str, str] = field(default_factory=dict)

    def __getitem__(self, key: str) -> float:
        try:
            return self.values[key]
        except KeyError:
            raise unknown_name("parameter", key, self.values) from None

    def __contains__(self, key: str) -> bool:
        return key in self.values

    def names(self) -> list[str]:
        return list(self.values)

    def updated(self, values: Mapping[str, float]) -> ParameterSet:
        """A copy with some values replaced (SI); unknown names are an error."""
        for k in values:
            if k not in self.values:
                raise unknown_name("parameter", k, self.values)
        return ParameterSet({**self.values, **{k: float(v) for k, v in values.items()}},
                            name=self.name, source=self.source, description=self.description)

    def vector(self, names: Iterable[str]) -> list[float]:
        return [self[n] for n in names]

    @classmethod
    def load(cls, path: str | Path) -> ParameterSet:
        """Read a parameter-set TOML file (see ``kneenlp/resources/parameters/table1.toml``)."""
        path = Path(path)
        doc = read_toml(path)
        src = str(path)
        units = doc.get("units", {})
        if not isinstance(units, dict):
            raise InputError("must be a table of units", source=src, field="units")
        factors = {}
        for kind, accepted in UNIT_FACTORS.items():
            unit = units.get(kind, DISPLAY_UNITS[kind])
            if unit not in accepted:
                raise InputError(f"unit {unit!r} not accepted; use one of {', '.join(accepted)}",
                                 source=src, field=f"units.{kind}")
            factors[kind] = accepted[unit]
        for kind in units:
            if kind not in UNIT_FACTORS:
                raise unknown_name("unit kind", kind, UNIT_FACTORS, source=src)
        values: dict[str, float] = {}
        ligs = doc.get("ligaments", {})
        if not isinstance(ligs, dict) or not ligs:
            raise InputError("missing table [ligaments.<NAME>]", source=src, field="ligaments")
        for lig, props in ligs.items():
            if not isinstance(props, dict):
                raise InputError("must be a table", source=src, field=f"ligaments.{lig}")
            for key in props:
                if key not in LIGAMENT_KINDS:
                    raise unknown_name(f"property of ligament {lig}", key, LIGAMENT_KINDS, source=src)
            for kind in LIGAMENT_KINDS:
                if kind not in props:
                    raise InputError("missing value", source=src, field=f"ligaments.{lig}.{kind}")
                values[f"{lig}.{kind}"] = number(props[kind], src, f"ligaments.{lig}.{kind}") * factors[kind]
            if values[f"{lig}.k"] < 0:
                raise InputError("stiffness must be >= 0", source=src, field=f"ligaments.{lig}.k")
            if values[f"{lig}.lin_strain"] <= 0:
                raise InputError("linear strain limit must be > 0", source=src, field=f"ligaments.{lig}.lin_strain")
        contact = doc.get("contact", {})
        if "modulus" not in contact:
            raise InputError("missing value", source=src, field="contact.modulus")
        values["contact.modulus"] = number(contact["modulus"], src, "contact.modulus") * factors["modulus"]
        if values["contact.modulus"] <= 0:
            raise InputError("must be > 0", source=src, field="contact.modulus")
        return cls(values, name=str(doc.get("name", path.stem)), source=src,
                   description=str(doc.get("description", "")))


def read_toml(path: Path) -> dict:
    """Read a TOML file, turning every failure into a one-line :class:`InputError`."""
    if not path.is_file():
        raise InputError("file not found", source=str(path))
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"malformed TOML ({exc})", source=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read ({exc})", source=str(path)) from None


def number(value: object, source: str, field: str) -> float:
    """A finite float from a TOML value, or a one-line error naming the field."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(f"expected a number, got {value!r}", source=source, field=field)
    if not math.isfinite(value):
        raise InputError(f"must be finite, got {value!r}", source=source, field=field)
    return float(value)
