"""Parameter sets: named model parameters with values in SI, read from TOML data files.

Parameter names are ``<LIGAMENT>.k`` (N per unit strain), ``<LIGAMENT>.ref_strain`` and
``<LIGAMENT>.lin_strain`` (fractions inside, percent at the user boundary) and
``contact.modulus`` (N/m^3 inside, GN/m^3 at the user boundary).  Model extensions add their own
names (``<effect>.<parameter>``) with their own units.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.schema import validated
from kneenlp.base.tomlfile import read_toml
from kneenlp.model.parameter_schema import Entries as EntrySchema
from kneenlp.model.parameter_schema import Entry, PriorTable, parameter_file_schema
from kneenlp.model.posterior import Posterior
from kneenlp.model.priors import Prior
from kneenlp.model.ties import names_in


@dataclass(frozen=True)
class Kind:
    """What every parameter of one physical kind shares: units, bounds, NLP scale, start scatter.

    ``file_units`` maps the units accepted in data files to their factor to SI; ``unit`` is the
    display unit (``to_user`` converts SI to it).  ``scatter`` is the half-width of the paper's
    start scatter, in SI (absolute) or as a fraction of the value (``relative``).
    """

    unit: str
    to_user: float
    lower: float
    upper: float
    scale: float
    scatter: float
    relative: bool = False
    file_units: tuple[tuple[str, float], ...] = ()
    text: str = ""
    #: the kind's default prior: ``("lognormal", sd of ln value)`` or ``("normal", sd in SI)``,
    #: centred on the knee's own value (docs/priors.md gives each width's source)
    prior: tuple[str, float] = ("normal", 0.0)


#: The one table of parameter metadata (SI inside; display units at the user boundary).
KINDS: dict[str, Kind] = {
    "k": Kind("N", 1.0, 0.0, 1e5, 1e4, 500.0, False, (("N", 1.0), ("kN", 1e3)), "stiffness, N per unit strain",
              ("lognormal", 0.3)),
    "ref_strain": Kind("%", 100.0, -0.3, 0.3, 1e-2, 0.02, False, (("%", 1e-2), ("1", 1.0)),
                       "reference strain at the reference pose", ("normal", 0.03)),
    "lin_strain": Kind("%", 100.0, 0.005, 0.1, 1e-2, 0.1, True, (("%", 1e-2), ("1", 1.0)),
                       "linear strain limit of the toe region", ("lognormal", 0.3)),
    "modulus": Kind("GN/m^3", 1e-9, 1e8, 1e12, 1e10, 0.1, True,
                    (("GN/m^3", 1e9), ("N/mm^3", 1e9), ("N/m^3", 1.0)), "elastic-foundation pressure modulus",
                    ("lognormal", 0.7)),
    "spring": Kind("N/mm", 1e-3, 0.0, 1e7, 1e5, 1e4, False, (("N/mm", 1e3), ("N/m", 1.0)), "spring stiffness",
                   ("normal", 5e3)),
    "scale": Kind("1", 1.0, 0.0, 20.0, 1.0, 0.05, False, (("1", 1.0),), "stiffness scale of a bundle group",
                  ("lognormal", 0.3)),
    "angle": Kind("deg", 180 / np.pi, -0.2, 0.2, 1e-2, np.deg2rad(1.0), False, (("deg", np.pi / 180),), "angle",
                  ("normal", np.deg2rad(3.0))),
    "length": Kind("mm", 1e3, -0.01, 0.01, 1e-3, 0.5e-3, False, (("mm", 1e-3), ("m", 1.0)), "length",
                   ("normal", 2e-3)),
    "force": Kind("N", 1.0, -1e4, 1e4, 100.0, 50.0, False, (("N", 1.0),), "force", ("normal", 50.0)),
}
#: Parameters every ligament of the paper's law has, in this order.
LIGAMENT_KINDS: tuple[str, ...] = ("k", "ref_strain", "lin_strain")
#: Accepted file units per kind (factor to SI) and display unit per kind (parameter-set files).
UNIT_FACTORS: dict[str, dict[str, float]] = {k: dict(v.file_units) for k, v in KINDS.items()}
DISPLAY_UNITS: dict[str, str] = {k: v.unit for k, v in KINDS.items()}
#: Every unit a parameter file may give in its ``[values]`` table, with its factor to SI (one
#: factor per unit whatever the kind; the model checks the unit suits the parameter's kind).
UNIT_TO_SI: dict[str, float] = {u: f for kind in KINDS.values() for u, f in kind.file_units}
#: The parameter file's schema (:mod:`kneenlp.model.parameter_schema`), its units and ligament
#: values from :data:`KINDS`.
PARAMETER_FILE = parameter_file_schema(UNIT_FACTORS, LIGAMENT_KINDS)


@dataclass(frozen=True)
class Parameter:
    """Metadata of one model parameter (lmfit's Parameter without the value: values live in
    parameter sets and fits).  Everything that depends on a parameter's kind (display unit, bounds,
    NLP scale, start scatter) is taken from :data:`KINDS` here and nowhere else.

    ``default`` is the value used when the knee's parameter set does not give one (``None``: the
    set must give it).  ``neutral`` is the value at which a candidate element contributes nothing
    (e.g. an added bundle's stiffness 0); ``one_sided`` marks a neutral value on a bound, so an
    effect can only act in one direction from it (score tests then count only that side).
    """

    name: str
    kind: str | Kind  # a key of KINDS, or a Kind of the caller's own
    description: str = ""
    default: float | None = None
    neutral: float | None = None
    lower: float | None = None  # SI; None: the kind's bound
    upper: float | None = None
    #: the default prior's shape and width, where the element knows better than the kind (e.g. a
    #: registration offset); None: the kind's (:attr:`Kind.prior`)
    prior: tuple[str, float] | None = None

    @property
    def meta(self) -> Kind:
        return self.kind if isinstance(self.kind, Kind) else KINDS[self.kind]

    @property
    def unit(self) -> str:
        return self.meta.unit

    @property
    def to_user(self) -> float:
        return self.meta.to_user

    @property
    def scale(self) -> float:
        return self.meta.scale

    def from_user(self, value: float) -> float:
        """A value in the display unit (:attr:`unit`) in SI."""
        return float(value) / self.meta.to_user

    @property
    def bounds(self) -> tuple[float, float]:
        """(lower, upper) in SI."""
        return (self.meta.lower if self.lower is None else self.lower,
                self.meta.upper if self.upper is None else self.upper)

    def default_prior(self, value: float) -> Prior:
        """The shipped prior of this parameter centred on ``value`` (SI, the knee's own): the
        element's or the kind's shape and width; a log-normal centred on a value <= 0 (a removed
        ligament) becomes a normal of the same relative width about the kind's scale."""
        shape, width = self.prior or self.meta.prior
        if shape == "lognormal" and not value > 0:
            return Prior("normal", float(value), width * self.meta.scale)
        if shape == "normal" and width <= 0:
            width = self.meta.scatter
        return Prior(shape, float(value), float(width))

    def check_prior(self, prior: Prior, source: str | None = None, field: str | None = None) -> Prior:
        """``prior``, or a one-line :class:`InputError` naming this parameter: a log-normal on a
        parameter that can be negative, or a centre outside the bounds."""
        lo, hi = self.bounds
        where = field or f"priors.{self.name}"
        if prior.log and lo < 0:
            raise InputError(f"a log-normal prior needs a positive parameter; {self.name} may be negative "
                             f"(bounds {lo * self.to_user:g} to {hi * self.to_user:g} {self.unit}): use a normal one",
                             source=source, field=where)
        if not lo <= prior.mean <= hi:
            raise InputError(f"prior {'median' if prior.log else 'mean'} {prior.mean * self.to_user:g} {self.unit} "
                             f"outside the bounds [{lo * self.to_user:g}, {hi * self.to_user:g}] {self.unit}",
                             source=source, field=where)
        return prior

    @property
    def one_sided(self) -> bool:
        return self.neutral is not None and self.neutral in self.bounds

    def scatter(self, value: float, rng: np.random.Generator) -> float:
        """A start drawn uniformly around ``value`` (the paper's scatter: +-500 N on stiffnesses,
        +-0.02 on reference strains, +-10 % on others), clipped to the bounds (SI)."""
        half = self.meta.scatter * (abs(value) if self.meta.relative else 1.0)
        lo, hi = self.bounds
        step = rng.uniform(-half, half)
        if self.one_sided and value == self.neutral:  # from a neutral bound: into the feasible side
            step = abs(step) if self.neutral == lo else -abs(step)
        return float(min(max(value + step, lo), hi))


def ligament_parameters(ligament: str, defaults: Mapping[str, float] | None = None,
                        neutral: Mapping[str, float] | None = None) -> list[Parameter]:
    """The three parameters of a ligament with the paper's law (k, ref_strain, lin_strain)."""
    defaults, neutral = dict(defaults or {}), dict(neutral or {})
    return [Parameter(f"{ligament}.{kind}", kind, f"{ligament} {KINDS[kind].text}", defaults.get(kind),
                      neutral.get(kind)) for kind in LIGAMENT_KINDS]


@dataclass
class ParameterSet:
    """Values (SI) of named model parameters; ``name`` says where they came from."""

    values: dict[str, float]
    name: str = "unnamed"
    source: str | None = None
    description: str = ""
    meta: dict[str, str] = field(default_factory=dict)
    #: priors declared in the file (``[values]``' ``prior``), SI, by name: they replace the shipped defaults
    priors: dict[str, Prior] = field(default_factory=dict)
    #: what a calibration knows about its fitted values (``[posterior]``; None: nothing written)
    posterior: Posterior | None = None
    #: bounds (SI) declared in the file, replacing the kinds' (``[values]``' ``bounds``)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: free flags declared in the file (``[values]``' ``free``): a fit's default free parameters
    free: dict[str, bool] = field(default_factory=dict)
    #: ties declared in the file (``[values]``' ``expr``): the parameter follows the expression (SI)
    ties: dict[str, str] = field(default_factory=dict)
    #: the file's table its declarations came from, named in errors (``parameters`` of a problem file)
    table: str = "values"

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
                            name=self.name, source=self.source, description=self.description, meta=dict(self.meta),
                            priors=dict(self.priors), bounds=dict(self.bounds), free=dict(self.free),
                            ties=dict(self.ties), table=self.table)

    def with_values(self, values: Mapping[str, float], name: str | None = None,
                    description: str | None = None) -> ParameterSet:
        """A copy with ``values`` (SI) set, new names included (e.g. a calibration's fitted group
        scales and registration); the model checks the names when it uses the set."""
        return ParameterSet({**self.values, **{k: float(v) for k, v in values.items()}},
                            name=name or self.name, source=None,
                            description=self.description if description is None else description,
                            priors=dict(self.priors), bounds=dict(self.bounds), free=dict(self.free),
                            ties=dict(self.ties), table=self.table)

    def with_entries(self, entries: Entries, source: str | None = None) -> ParameterSet:
        """A copy with a parameter table's ``entries`` over this set's (values, units, priors,
        bounds, free flags; e.g. a problem file's ``[parameters]``); the model checks the names."""
        return ParameterSet({**self.values, **entries.values}, name=self.name, source=source or self.source,
                            description=self.description, meta=dict(self.meta) | entries.units,
                            priors=dict(self.priors) | entries.priors, posterior=self.posterior,
                            bounds=dict(self.bounds) | entries.bounds, free=dict(self.free) | entries.free,
                            ties=dict(self.ties) | entries.ties, table=entries.section)

    def vector(self, names: Iterable[str]) -> list[float]:
        return [self[n] for n in names]

    def to_toml(self, info: Mapping[str, Parameter], header: Iterable[str] = ()) -> str:
        """Parameter-file text of this set (``ParameterSet.load`` reads it back to the same values):
        single-law ligaments in ``[ligaments]``, the contact modulus in ``[contact]``, every other
        parameter in ``[values]`` with its display unit; ``info`` gives each name's metadata."""
        import tomli_w

        doc: dict = {"name": self.name, "description": self.description,
                     "units": {kind: DISPLAY_UNITS[kind] for kind in (*LIGAMENT_KINDS, "modulus")},
                     "ligaments": {}, "contact": {}, "values": {}}
        ligs = {n.rsplit(".", 1)[0] for n in self.values
                if all(f"{n.rsplit('.', 1)[0]}.{k}" in self.values for k in LIGAMENT_KINDS)}
        for name, value in self.values.items():
            lig, _, key = name.rpartition(".")
            if lig in ligs and key in LIGAMENT_KINDS:
                doc["ligaments"].setdefault(lig, {})[key] = value * KINDS[key].to_user
            elif name == "contact.modulus":
                doc["contact"]["modulus"] = value * KINDS["modulus"].to_user
            else:
                meta = info[name].meta
                doc["values"][name] = {"value": value * meta.to_user, "unit": meta.unit}
        if self.posterior is not None:
            doc["posterior"] = self.posterior.table({n: info[n].meta.unit for n in self.posterior.names}, UNIT_TO_SI)
        return "".join(f"# {h}\n" for h in header) + tomli_w.dumps({k: v for k, v in doc.items() if v != {}})

    @classmethod
    def load(cls, path: str | Path) -> ParameterSet:
        """Read a parameter-set TOML file (see ``kneenlp/resources/parameters/table1.toml``): the
        document against :data:`PARAMETER_FILE`, then every value in SI checked against its kind."""
        path = Path(path)
        src = str(path)
        document = read_toml(path)
        check_quoted(document.get("values") if isinstance(document, dict) else None, src)
        spec = validated(PARAMETER_FILE, document, src)
        factors = {kind: accepted[getattr(spec.units, kind) or DISPLAY_UNITS[kind]]
                   for kind, accepted in UNIT_FACTORS.items()}
        values: dict[str, float] = {}
        for lig, props in spec.ligaments.items():  # may be none: a multi-bundle knee's bundles carry their own
            for kind in LIGAMENT_KINDS:
                values[f"{lig}.{kind}"] = getattr(props, kind) * factors[kind]
            if values[f"{lig}.k"] < 0:
                raise InputError("stiffness must be >= 0", source=src, field=f"ligaments.{lig}.k")
            if values[f"{lig}.lin_strain"] <= 0:
                raise InputError("linear strain limit must be > 0", source=src, field=f"ligaments.{lig}.lin_strain")
            for kind in LIGAMENT_KINDS:
                plausible(values[f"{lig}.{kind}"], kind, src, f"ligaments.{lig}.{kind}")
        entries = entries_in(spec.values, src)
        values |= entries.values
        values["contact.modulus"] = spec.contact.modulus * factors["modulus"]
        if values["contact.modulus"] <= 0:
            raise InputError("must be > 0", source=src, field="contact.modulus")
        plausible(values["contact.modulus"], "modulus", src, "contact.modulus")
        posterior = (Posterior.read(spec.posterior, UNIT_TO_SI, set(values), src) if spec.posterior is not None
                     else None)
        return cls(values, name=spec.name if spec.name is not None else path.stem, source=src,
                   description=spec.description, meta=entries.units, priors=entries.priors,
                   posterior=posterior, bounds=entries.bounds, free=entries.free, ties=entries.ties)


#: The laxity-noise paper's elastic-foundation modulus (N/m^3): the parameter set of an imported knee.
PAPER_MODULUS = 1e10


def imported_parameter_set(program: str, carried: str) -> str:
    """Parameter-file text of a knee imported from ``program`` whose bundles carry ``carried``
    (e.g. "their own stiffness and slack length") in the knee file: the groups' stiffness scales (1)
    and reference-strain offsets (0) are the defaults, the contact modulus the paper's."""
    header = [f"Parameters of a knee imported from {program}: the bundles carry {carried} (knee.toml); the",
              "groups' stiffness scales (1) and reference-strain offsets (0) are the defaults.  The",
              "elastic-foundation modulus is the laxity-noise paper's."]
    return ParameterSet({"contact.modulus": PAPER_MODULUS}, name="imported").to_toml({}, header)


@dataclass
class Entries:
    """The parameter table of a file (``[values]`` of a parameter file, ``[parameters]`` of a
    problem file), SI: values, their declared units, priors, bounds and free flags by name."""

    values: dict[str, float] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    priors: dict[str, Prior] = field(default_factory=dict)
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)
    free: dict[str, bool] = field(default_factory=dict)
    ties: dict[str, str] = field(default_factory=dict)
    #: the table they were read from (errors name it)
    section: str = "values"


def read_entries(table: object, src: str, section: str = "values") -> Entries:
    """``[values]``: any model parameter by its full name, ``"NAME" = {value = V, unit = "U"}``, with
    optionally, in the same unit, a ``prior`` (``{distribution = "normal", mean = M, sd = S}`` or
    ``{distribution = "lognormal", median = M, sd_log = S}``), ``bounds = [LOWER, UPPER]`` (replacing
    the kind's) and ``free = true|false`` (whether a fit frees it; :func:`declared_free`).  Without
    ``value`` the knee's own value stays.  A calibration writes the parameters it fitted so
    (:meth:`ParameterSet.to_toml`).  The table is checked against
    :data:`~kneenlp.model.parameter_schema.Entries`, then converted to SI."""
    check_quoted(table, src, section)
    return entries_in(validated(EntrySchema, table, src, prefix=(section,)), src, section)


def with_unit(value: float, unit: str) -> str:
    """``value`` and its unit for a message (a dimensionless ``1`` left out)."""
    return f"{value:g}" if unit == "1" else f"{value:g} {unit}"


def check_quoted(table: object, src: str, section: str = "values") -> None:
    """Refuse an unquoted dotted name: TOML reads ``ACL.k = {...}`` as a table ``ACL`` holding ``k``."""
    if not isinstance(table, dict):
        return
    for key, item in table.items():
        if isinstance(item, dict) and item and not set(item) & ENTRY_KEYS and all(isinstance(v, dict)
                                                                                 for v in item.values()):
            inner = next(iter(item))
            raise InputError(f'a parameter name with a dot must be quoted: "{key}.{inner}" = {{...}}, not '
                             f"{key}.{inner} = {{...}}", source=src, field=f"{section}.{key}")


#: The keys of one entry of a parameter table.
ENTRY_KEYS = frozenset({"value", "unit", "prior", "bounds", "free", "expr"})


def entries_in(table: dict[str, Entry], src: str, section: str = "values") -> Entries:
    """A validated parameter table in SI (each unit known, bounds ordered, priors complete, no prior
    on a parameter declared not free)."""
    out = Entries(section=section)
    for name, item in table.items():
        fld = f"{section}.{name}"
        if item.free is False and item.prior is not None:
            raise InputError("has a prior but free = false, so the prior would never be used: set free = true or "
                             "drop the prior", source=src, field=fld)
        if not item.model_fields_set - {"unit"}:
            raise InputError(f'expected {{value = V, unit = "U"}} (and optionally prior = {{...}}, bounds = [L, U], '
                             f"free = true), got {item.model_dump(exclude_unset=True)!r}", source=src, field=fld)
        if item.unit not in UNIT_TO_SI:
            raise InputError(f"unknown unit {item.unit!r}; known: {', '.join(UNIT_TO_SI)}", source=src, field=fld)
        factor = UNIT_TO_SI[item.unit]
        if item.value is not None:
            out.values[name] = item.value * factor
        if item.prior is not None:
            out.priors[name] = prior_of(item.prior, factor, src, f"{fld}.prior")
        if item.bounds is not None:
            lo, hi = (v * factor for v in item.bounds)
            if not lo < hi:
                raise InputError(f"lower bound {item.bounds[0]!r} not below upper {item.bounds[1]!r}", source=src,
                                 field=f"{fld}.bounds")
            out.bounds[name] = (lo, hi)
        if item.free is not None:
            out.free[name] = item.free
        if item.expr is not None:
            if item.free or item.prior is not None:
                raise InputError("a tied parameter (expr) follows its tie: it takes neither free = true nor a prior",
                                 source=src, field=fld)
            names_in(item.expr, f"{fld}.expr")
            out.ties[name] = item.expr
        out.units[name] = item.unit
    return out


#: The keys of a prior table per distribution: (centre, width).
PRIOR_KEYS = {"normal": ("mean", "sd"), "lognormal": ("median", "sd_log")}


def prior_of(item: PriorTable, factor: float, src: str | None, fld: str) -> Prior:
    """A validated prior table in SI: the distribution's two keys and no other, a positive width
    (and median, for a log-normal)."""
    shape = item.distribution
    centre, width = PRIOR_KEYS[shape]
    extra = item.model_fields_set - {"distribution", centre, width}
    mean, sd = getattr(item, centre), getattr(item, width)
    if extra or mean is None or sd is None:
        raise InputError(f"a {shape} prior takes {centre} and {width}" + (f"; unknown: {', '.join(sorted(extra))}"
                                                                           if extra else ""), source=src, field=fld)
    mean, sd = mean * factor, sd * (1.0 if shape == "lognormal" else factor)
    if not sd > 0:
        raise InputError(f"{width} must be > 0, got {getattr(item, width)!r}", source=src, field=f"{fld}.{width}")
    if shape == "lognormal" and not mean > 0:
        raise InputError(f"a log-normal prior needs a positive median, got {getattr(item, centre)!r}", source=src,
                         field=f"{fld}.{centre}")
    return Prior(shape, mean, sd, source=src or "file")


#: Smallest plausible nonzero ligament stiffness (N per unit strain): ligaments have 10^3-10^5 N;
#: a smaller nonzero value is a stiffness in kN given without ``units.k = "kN"``.  (0 is allowed:
#: a ligament removed, e.g. an ACL-deficient knee.)
MIN_NONZERO_K = 100.0


def plausible(value: float, kind: str, source: str | None, field: str) -> float:
    """``value`` (SI) of a parameter of ``kind`` in a parameter-set file, or an error if outside the
    kind's bounds (the identification bounds of :data:`KINDS`, in display units in the message) or,
    for a stiffness, below :data:`MIN_NONZERO_K` but not 0."""
    meta = KINDS[kind]
    if not meta.lower <= value <= meta.upper:
        raise InputError(f"{value * meta.to_user:g} {meta.unit} outside [{meta.lower * meta.to_user:g}, "
                         f"{meta.upper * meta.to_user:g}] {meta.unit}; a unit slip? (units are declared in "
                         f"[units], e.g. {kind} = \"{meta.file_units[-1][0]}\")", source=source, field=field)
    if kind == "k" and 0 < value < MIN_NONZERO_K:
        raise InputError(f"{value:g} N per unit strain is implausibly small for a ligament; kN? (declare "
                         "[units] k = \"kN\")", source=source, field=field)
    return value
