"""The parameter file declared as a schema: its tables, their keys and types
(:meth:`~kneenlp.model.parameters.ParameterSet.load` converts the values to SI and checks them
against the kinds' bounds).  The units accepted per kind and the ligament properties come from
the one table of kinds (:data:`~kneenlp.model.parameters.KINDS`), passed to
:func:`parameter_file_schema`, so they are declared there only."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, StrictBool, create_model

from kneenlp.base.schema import Number, Table, fail, to_number


def to_bounds(value: object) -> tuple[float, float]:
    """``[LOWER, UPPER]``, two finite numbers in the entry's unit."""
    if not isinstance(value, list) or len(value) != 2:
        raise fail(f"expected [LOWER, UPPER], got {value!r}")
    lo, hi = (to_number(v) for v in value)
    return lo, hi


class PriorTable(Table):
    """A prior: ``{distribution = "normal", mean = M, sd = S}`` or ``{distribution = "lognormal",
    median = M, sd_log = S}`` (``mean``, ``sd`` and ``median`` in the entry's unit, ``sd_log``
    dimensionless)."""

    distribution: Literal["normal", "lognormal"] = Field(description='distribution ("normal" or "lognormal")')
    mean: Number | None = None
    sd: Number | None = None
    median: Number | None = None
    sd_log: Number | None = None


class Entry(Table):
    """A row of a parameter table: ``"NAME" = {value = V, unit = "U"}`` with optionally a prior,
    ``bounds = [LOWER, UPPER]`` (same unit), ``free = true|false`` and ``expr``, a tie to other
    parameters (SI; :mod:`kneenlp.model.ties`)."""

    value: Number | None = None
    unit: str = Field(description='unit (e.g. unit = "N")')
    prior: PriorTable | None = None
    bounds: Annotated[tuple[float, float], BeforeValidator(to_bounds)] | None = None
    free: StrictBool | None = None
    expr: str | None = None


#: A parameter table (``[values]`` of a parameter file, ``[parameters]`` of a problem file).
Entries = dict[str, Entry]


class ContactValues(Table):
    """``[contact]``: the elastic-foundation modulus (in ``units.modulus``)."""

    modulus: Number = Field(description="value")


def to_variance(value: object) -> float:
    """A covariance entry: a number, ``inf`` allowed (a direction nothing determined), NaN not."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise fail(f"expected a number, got {value!r}")
    if value != value:
        raise fail("NaN in the covariance")
    return float(value)


def to_distinct_names(value: object) -> list[str]:
    """A list of distinct parameter names."""
    if not isinstance(value, list) or not all(isinstance(n, str) for n in value) or len(set(value)) != len(value):
        raise fail("must be a list of distinct parameter names")
    return value


class PosteriorTable(Table):
    """``[posterior]``: a calibration's Laplace posterior in display units
    (:class:`~kneenlp.model.posterior.Posterior` checks the matrix and the names against the file)."""

    method: Literal["laplace"] = Field(description='method ("laplace")')
    parameters: Annotated[list[str], BeforeValidator(to_distinct_names)] = Field(description="parameter names")
    units: list[str] = Field(description="one unit per parameter")
    covariance: list[list[Annotated[float, BeforeValidator(to_variance)]]] = Field(
        description="covariance matrix (one row per parameter)")
    noise_sd: list[Number] = Field(description="five noise sds")


class ParameterFile(Table):
    """A parameter file.  :func:`parameter_file_schema` adds ``units`` and the ligament tables'
    keys (one value per property of the paper's law)."""

    name: str | None = None
    description: str = ""
    ligaments: dict[str, Any] = Field(default_factory=dict)
    contact: ContactValues = Field(default_factory=dict, validate_default=True)
    values: Entries = Field(default_factory=dict)
    posterior: PosteriorTable | None = None


def accepted_unit(units: Iterable[str]) -> BeforeValidator:
    """A unit among ``units``: else ``unit 'x' not accepted; use one of a, b``."""
    names = tuple(units)

    def check(value: object) -> object:
        if not isinstance(value, str) or value not in names:
            raise fail(f"unit {value!r} not accepted; use one of {', '.join(names)}")
        return value
    return BeforeValidator(check)


def parameter_file_schema(units: Mapping[str, Iterable[str]], ligament_kinds: Iterable[str]) -> type[ParameterFile]:
    """The parameter file's schema: ``[units]`` with one optional unit per kind of ``units`` (kind
    -> accepted units), ``[ligaments.<NAME>]`` with one value per kind of ``ligament_kinds``."""
    unit_fields: dict[str, Any] = {kind: (Annotated[str, accepted_unit(accepted)] | None, None)
                                   for kind, accepted in units.items()}
    value_fields: dict[str, Any] = {kind: (Number, Field(description="value")) for kind in ligament_kinds}
    units_table = create_model("Units", __base__=Table, __doc__="``[units]``: a unit per kind.", **unit_fields)
    ligament_table = create_model("LigamentValues", __base__=Table,
                                  __doc__="``[ligaments.<NAME>]``: the law's values.", **value_fields)
    return create_model("ParameterFileSchema", __base__=ParameterFile,
                        units=(units_table, Field(default_factory=dict, validate_default=True)),
                        ligaments=(dict[str, ligament_table], Field(default_factory=dict)))
