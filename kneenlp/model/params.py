"""``Parameters``: every model parameter as one object (value, unit, bounds, vary, prior, tie).

lmfit's design with a knee's needs: ``params = model.make_params()`` gives every parameter of a
model (:class:`Param`: its value in SI, whether a fit varies it, its bounds, its prior, an optional
tie); the user sets what a fit should do and passes the mapping to
:func:`kneenlp.identify`::

    params = model.make_params(priors="default")
    params["PFL.k_scale"].set(vary=True)
    params["MCLm.k_scale"].set(expr="MCLa.k_scale")        # one scale for two groups
    params["LCL.ref_strain"].set(value=2.0, unit="%", vary=True)
    fit = kneenlp.identify(model, data, params)

Every way of freeing a parameter (effects, a calibration's extras, a file's ``free = true``) is
"set ``vary``": :meth:`Parameters.freed` frees parameters, effects or elements by name.  The values
are SI inside (``set(value, unit=...)`` converts a file unit); :meth:`Parameters.report` shows them
in their display units.  The metadata (kind, unit, description) is the element's declaration,
:class:`~kneenlp.model.parameters.Parameter`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal, Protocol

from kneenlp.base.errors import InputError, unknown_name
from kneenlp.base.keywords import refuse_unknown
from kneenlp.base.modes import checked
from kneenlp.model import ties as tie_rules
from kneenlp.model.parameters import PRIOR_KEYS, UNIT_TO_SI, Parameter
from kneenlp.model.priors import Prior


class ParameterModel(Protocol):
    """What :func:`make_params` and its helpers read of a model
    (:class:`~kneenlp.experiment.kneemodel.KneeModel`)."""

    knee: Any  # its parameter set: values, declared free flags, priors, ties
    parameters: list[Parameter]
    parameter_names: list[str]
    ligament_names: list[str]
    parts: list[Any]  # each with .name and .parameters()
    effects: list[Any]  # each with .name and .free_names()

    def theta(self, values: dict[str, float] | None = None) -> Any: ...

    def element(self, name: str) -> Any: ...

    def index(self, name: str) -> int: ...


#: What :meth:`Param.set` changes beside the value (an absent name leaves it as it is)
SETTABLE = ("unit", "vary", "min", "max", "prior", "expr")


@dataclass
class Param:
    """One parameter of a model: ``value`` (SI), whether a fit varies it, its bounds ``min`` and
    ``max`` (SI), its prior (None: the data alone determine it) and ``expr``, a tie to others
    (:mod:`kneenlp.model.ties`; a tied parameter does not vary)."""

    info: Parameter
    value: float
    vary: bool = False
    min: float = -math.inf
    max: float = math.inf
    prior: Prior | None = None
    expr: str | None = None

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def unit(self) -> str:
        """The display unit (the value times :attr:`to_user` is in it)."""
        return self.info.unit

    @property
    def to_user(self) -> float:
        return self.info.to_user

    def set(self, value: float | None = None, **changes: Any) -> Param:
        """Change what is given (:data:`SETTABLE`; ``value``, ``min``, ``max`` in ``unit`` if
        given, else SI; ``vary``; ``prior``, a :class:`~kneenlp.model.priors.Prior`; ``expr``, a
        tie); returns the parameter.  ``prior=None`` removes the prior, ``expr=None`` the tie; a tie
        stops the parameter varying.  An unknown name is a TypeError, as Python's own."""
        refuse_unknown("set", changes, SETTABLE)
        unit = changes.get("unit")
        factor = 1.0 if unit is None else _factor(unit, self.name)
        if value is not None:
            self.value = float(value) * factor
        if changes.get("min") is not None:
            self.min = float(changes["min"]) * factor
        if changes.get("max") is not None:
            self.max = float(changes["max"]) * factor
        if changes.get("vary") is not None:
            self.vary = bool(changes["vary"])
        if "prior" in changes:
            self.prior = changes["prior"]
        if "expr" in changes:
            self.expr = changes["expr"]
            if self.expr is not None:  # a tie neither varies nor takes a prior
                self.vary = False
                self.prior = changes.get("prior")
        return self

    def check(self, source: str | None = None) -> None:
        """A one-line error naming the parameter: bounds out of order, the value outside them, a
        varied tie, a prior on a tie, a prior the parameter cannot take."""
        field = f"parameters.{self.name}"
        lo, hi = self.min * self.to_user, self.max * self.to_user
        if not self.min < self.max:
            raise InputError(f"lower bound {lo:g} not below upper {hi:g} {self.unit}", source=source, field=field)
        if not self.min <= self.value <= self.max and self.expr is None:
            raise InputError(f"value {self.value * self.to_user:g} {self.unit} outside its bounds [{lo:g}, {hi:g}]",
                             source=source, field=field)
        if self.expr is not None and self.vary:
            raise InputError("a tied parameter (expr) cannot vary: its value follows its tie", source=source,
                             field=field)
        if self.expr is not None and self.prior is not None:
            raise InputError("a tied parameter (expr) takes no prior: put it on a parameter it follows",
                             source=source, field=field)
        if self.prior is not None:
            self.info.check_prior(self.prior, source, f"{field}.prior")

    def entry(self) -> dict:
        """The parameter's row of a file's parameter table, in its display unit: its bounds where
        they are not its kind's (in degrees the kind's would not read back to the same radians, and
        a fit would differ), the prior of a varied parameter only (a file keeps no other)."""
        f = self.to_user
        row: dict[str, Any] = {"value": self.value * f, "unit": self.unit, "free": self.vary}
        if (self.min, self.max) != (self.info.meta.lower, self.info.meta.upper):
            row["bounds"] = [self.min * f, self.max * f]
        if self.prior is not None and self.vary:
            centre, width = PRIOR_KEYS[self.prior.shape]
            row["prior"] = {"distribution": self.prior.shape, centre: self.prior.mean * f,
                            width: self.prior.sd * (1.0 if self.prior.log else f)}
        if self.expr is not None:
            row["expr"] = self.expr
        return row


def _factor(unit: str, name: str) -> float:
    if unit not in UNIT_TO_SI:
        raise InputError(f"unknown unit {unit!r}; known: {', '.join(UNIT_TO_SI)}", field=f"parameters.{name}")
    return UNIT_TO_SI[unit]


class Parameters(Mapping[str, Param]):
    """Every parameter of a model, by name, in the model's order (``theta``'s).  Made by
    :meth:`~kneenlp.experiment.kneemodel.KneeModel.make_params`; a copy is made by :meth:`copy`."""

    def __init__(self, params: Iterable[Param], source: str | None = None,
                 groups: Mapping[str, list[str]] | None = None):
        self._params = {p.name: p for p in params}
        self.source = source
        #: named groups of parameters (an effect's, an element's) that :meth:`freed` frees by name
        self.groups = dict(groups or {})

    def __getitem__(self, name: str) -> Param:
        try:
            return self._params[name]
        except KeyError:
            raise unknown_name("parameter", name, self._params) from None

    def __contains__(self, name: object) -> bool:
        return name in self._params

    def __iter__(self) -> Iterator[str]:
        return iter(self._params)

    def __len__(self) -> int:
        return len(self._params)

    def copy(self) -> Parameters:
        return Parameters([replace(p) for p in self._params.values()], self.source, self.groups)

    # ------------------------------------------------------------------ what a fit reads
    @property
    def free(self) -> list[str]:
        """The varied parameters, in the model's order."""
        return [n for n, p in self._params.items() if p.vary]

    def valuesdict(self) -> dict[str, float]:
        """Every value (SI) by name, each tie evaluated."""
        return tie_rules.tied({n: p.value for n, p in self._params.items()}, self.ties())

    def priors(self) -> dict[str, Prior | None]:
        """The varied parameters' priors (None: the data alone determine it)."""
        return {n: self._params[n].prior for n in self.free}

    def bounds(self) -> dict[str, tuple[float, float]]:
        """(min, max) of every varied parameter (SI)."""
        return {n: (self._params[n].min, self._params[n].max) for n in self.free}

    def ties(self) -> dict[str, str]:
        """The tied parameters' expressions, by name."""
        return {n: p.expr for n, p in self._params.items() if p.expr is not None}

    def check(self) -> Parameters:
        """Every parameter checked (:meth:`Param.check`) and every tie readable, known and acyclic."""
        for p in self._params.values():
            p.check(self.source)
        self.valuesdict()
        return self

    # ------------------------------------------------------------------ changing what varies
    def freed(self, names: Iterable[str]) -> Parameters:
        """A copy with ``names`` varied: parameter names, or the names of :attr:`groups` (an
        effect's or an element's parameters: ``"PCLal_femoral_attachment"``, ``"tibial_origin"``)."""
        out = self.copy()
        for name in names:
            if name not in out and name not in self.groups:
                raise unknown_name("parameter, effect or element", name, [*out, *self.groups])
            for member in [name] if name in out else self.groups[name]:
                out[member].set(vary=True)
        return out

    def only(self, names: Iterable[str]) -> Parameters:
        """A copy in which ``names`` vary and nothing else."""
        names = set(names)
        for name in names:
            self[name]
        out = self.copy()
        for p in out.values():
            p.vary = p.name in names
        return out

    def checked_against(self, model: ParameterModel, given: Mapping[str, object]) -> dict[str, float]:
        """The values (SI, ties evaluated, tied ones left out) that differ from ``model``'s (the knee's),
        after :meth:`check`; a one-line error if any of ``given`` (a fit's other ways of saying what
        it fits: ``free``, ``priors``, ...) is set beside these parameters."""
        for name, value in given.items():
            if value:
                raise InputError(f"params says what is fitted and how: set it there (vary, prior, value), not by "
                                 f"{name}", field=name)
        self.check()
        own, ties = dict(zip(model.parameter_names, model.theta(), strict=True)), self.ties()
        return {n: v for n, v in self.valuesdict().items() if v != own[n] and n not in ties}

    # ------------------------------------------------------------------ showing and writing
    def report(self, names: Iterable[str] | None = None) -> str:
        """A table of ``names`` (default: the varied and tied ones) in display units."""
        names = list(names) if names is not None else [n for n, p in self._params.items() if p.vary or p.expr]
        values = self.valuesdict()
        rows = [f"{'name':28s} {'value':>12s} {'unit':8s} {'vary':5s} {'min':>10s} {'max':>10s}  prior / tie"]
        for n in names:
            p, f = self[n], self[n].to_user
            prior = (f"= {p.expr}" if p.expr else "" if p.prior is None else
                     f"{p.prior.shape} {p.prior.mean * f:.4g} sd {p.prior.sd * (1 if p.prior.log else f):.3g}")
            rows.append(f"{n:28s} {values[n] * f:12.5g} {p.unit:8s} {p.vary!s:5s} {p.min * f:10.4g} "
                        f"{p.max * f:10.4g}  {prior}")
        return "\n".join(rows)

    def to_table(self, names: Iterable[str] | None = None) -> dict[str, dict]:
        """A problem file's ``[parameters]`` table of ``names`` (default: the varied and tied ones),
        each row in its display unit: read back by
        :func:`~kneenlp.model.parameters.read_entries` to the same values, flags, bounds, priors and ties."""
        names = list(names) if names is not None else [n for n, p in self._params.items() if p.vary or p.expr]
        return {n: self[n].entry() for n in names}


def default_free(model: ParameterModel) -> list[str]:
    """Stiffness and reference strain of every ligament (8 values for the four-ligament knee; the
    stiffness scale and reference-strain offset of each bundle group of a multi-bundle knee)."""
    return [n for lig in model.ligament_names for n in model.element(lig).main_parameters()]


def declared_free(model: ParameterModel, default: Sequence[str]) -> list[str]:
    """The free parameters the knee's parameter set declares (``free = true`` entries, in the
    model's order) or, without any, ``default`` less those it declares ``free = false``."""
    flags, ties = model.knee.parameters.free, model.knee.parameters.ties
    chosen = [n for n in model.parameter_names if flags.get(n)]
    return chosen or [n for n in default if flags.get(n, True) and n not in ties]


def make_params(model: ParameterModel, priors: str = "declared") -> Parameters:
    """Every parameter of ``model`` (:class:`~kneenlp.model.params.Parameters`): the knee's value
    (SI, ties evaluated), varied as :func:`declared_free` over :func:`default_free` says, the
    declared bounds and ties and, by ``priors``: ``"declared"`` the knee's parameter file's priors,
    ``"default"`` those or the shipped default of every parameter (centred on its value, as
    :func:`resolve_priors`), ``"none"`` none."""
    checked("priors", priors, Literal["declared", "default", "none"])
    declared, theta = model.knee.parameters, model.theta()
    free = set(declared_free(model, default_free(model)))
    out = []
    for info, value in zip(model.parameters, theta, strict=True):
        name, prior = info.name, None
        if priors != "none" and name not in declared.ties:
            prior = declared.priors.get(name)
            if prior is None and priors == "default":
                prior = info.default_prior(float(value))
        out.append(Param(info, float(value), name in free and name not in declared.ties, *info.bounds, prior,
                         declared.ties.get(name)))
    return Parameters(out, groups=parameter_groups(model))


def parameter_groups(model: ParameterModel) -> dict[str, list[str]]:
    """Every named group of parameters: each part's (``tibial_origin``: its three offsets) and each
    effect's (``PCLal_femoral_attachment``: the attachment's three offsets), those with any."""
    groups = {e.name: [p.name for p in e.parameters()] for e in model.parts} | {
        e.name: e.free_names() for e in model.effects}
    return {n: ps for n, ps in groups.items() if ps}


def named_parameters(model: ParameterModel, names: Sequence[str], field: str | None = None) -> list[str]:
    """The parameters ``names`` name (parameter names, or groups of :func:`parameter_groups`), in the
    model's order; an unknown name is a one-line error listing the groups."""
    groups = parameter_groups(model)
    out: list[str] = []
    for name in names:
        found = [name] if name in model.parameter_names else groups.get(name)
        if not found:
            raise InputError(unknown_name("parameter, effect or element", name, groups).message, field=field)
        out += [n for n in found if n not in out]
    return sorted(out, key=model.index)
