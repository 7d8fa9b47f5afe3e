"""Force laws as parts, named in a knee file: ligament force-strain laws and contact pressure laws.

A law (:class:`LigamentLaw`) gives a line element's tension (N) from its strain (dimensionless,
``(l - l0) / l0``), its stiffness ``k`` (N per unit strain) and its linear strain limit
``lin_strain`` (the strain scale of the toe region): the two law parameters every ligament
carries (:data:`kneenlp.model.parameters.LIGAMENT_KINDS`; the reference strain sets ``l0``).  One
definition serves CasADi symbols and NumPy arrays: a law writes its expression with the
operations of ``ops`` (:data:`CASADI` or :data:`NUMPY`), so the model, the checks and the plots
use the same formula.

Built in (:data:`LAWS`):

* ``toe_linear``: the paper's Eq. (1) (Blankevoort & Huiskes 1991), the default;
* ``blankevoort``: OpenSim's ``Blankevoort1991Ligament`` in its own terms, transition strain
  ``e_t = 2 lin_strain`` (the same function: both are kept so that an imported OpenSim model is
  evaluated by the law it names; a test checks they agree).

A knee file names a law per ligament (``[ligaments.ACL] law = "blankevoort"``); ``"module:name"``
names a user's law (a class or factory returning a :class:`LigamentLaw`), as ``--element`` names a
user's force element.  docs/architecture.md shows a new law in one file.

A contact pressure law (:class:`PressureLaw`) gives the elastic foundation's pressure (Pa) from a
tibial point's penetration depth (m), the modulus ``K`` (N/m^3, the parameter
``contact.modulus``) and the width of the C2 gate that starts contact smoothly (m): its
``pressure`` for CasADi and NumPy, and ``kernel``, what the compiled contact passes evaluate at
every penetrating point: an exponent of the power family the passes know (compiled once per
machine), or a compiled function ``(depth, gate) -> (h, h', h'')``, the pressure per unit modulus
and its first two derivatives in depth (any law; compiled into the passes in every process,
:mod:`kneenlp.geometry.kernels`).  Built in (:data:`PRESSURE_LAWS`):

* ``elastic_foundation``: the paper's, ``p = K g(d)`` with the gate ``g`` of
  :mod:`kneenlp.geometry.ramp` (exactly ``K d`` beyond the gate's width), the default;
* ``power_1.5``: ``p = K d_r (g(d) / d_r)^1.5`` with ``d_r`` = :data:`REFERENCE_DEPTH` (1 mm):
  stiffening with depth like a Hertzian contact, equal to the paper's at ``d_r`` (so ``K`` keeps its
  unit and its scale).

A knee file names one per compartment (``[contact.medial] law = "power_1.5"``) or for all
(``[contact] law``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

import casadi as ca
import numpy as np

from kneenlp.base.errors import InputError
from kneenlp.geometry.kernels import REFERENCE_DEPTH
from kneenlp.geometry.ramp import ramp_inner


@dataclass(frozen=True)
class Ops:
    """The few operations a law's expression needs, for one kind of number."""

    fmin: Callable[[Any, Any], Any]
    fmax: Callable[[Any, Any], Any]
    exp: Callable[[Any], Any]
    log1p: Callable[[Any], Any]


#: CasADi symbols (SX, MX) and DM.
CASADI = Ops(ca.fmin, ca.fmax, ca.exp, ca.log1p)
#: NumPy arrays and floats.
NUMPY = Ops(np.minimum, np.maximum, np.exp, np.log1p)


@runtime_checkable
class LigamentLaw(Protocol):
    """Tension of a line element from its strain (module docstring)."""

    #: the name a knee file gives it
    name: str

    def tension(self, strain: Any, k: Any, lin_strain: Any, ops: Ops = CASADI) -> Any:
        """Tension (N, >= 0) at ``strain`` for stiffness ``k`` (N per unit strain) and linear
        strain limit ``lin_strain``; zero for ``strain <= 0``."""
        ...


class ToeLinearLaw:
    """The paper's Eq. (1): ``0`` for ``eps <= 0``; ``k eps^2 / (4 eps_l)`` up to ``2 eps_l``; then
    ``k (eps - eps_l)``.  C1; written branch-free (``t = min(max(eps, 0), 2 eps_l)``), so every NLP
    exchange format can hold it."""

    name = "toe_linear"

    def tension(self, strain, k, lin_strain, ops: Ops = CASADI):
        t = ops.fmin(ops.fmax(strain, 0), 2 * lin_strain)
        return k * t * t / (4 * lin_strain) + k * ops.fmax(strain - 2 * lin_strain, 0)


class BlankevoortLaw:
    """OpenSim's ``Blankevoort1991Ligament`` (no damping), in its own terms: transition strain
    ``e_t = 2 lin_strain``; ``k e^2 / (2 e_t)`` for ``0 < e < e_t``, ``k (e - e_t / 2)`` beyond."""

    name = "blankevoort"

    def tension(self, strain, k, lin_strain, ops: Ops = CASADI):
        e_t = 2 * lin_strain
        t = ops.fmin(ops.fmax(strain, 0), e_t)
        return 0.5 * k / e_t * t * t + k * ops.fmax(strain - e_t, 0)


#: The built-in laws by name.
LAWS: Mapping[str, type] = MappingProxyType({law.name: law for law in (ToeLinearLaw, BlankevoortLaw)})
#: The law of a ligament whose knee file names none.
DEFAULT_LAW = ToeLinearLaw.name


# ------------------------------------------------------------------ contact pressure laws
def gate(depth, width, ops: Ops = CASADI):
    """C2-smooth ``max(depth, 0)`` (:mod:`kneenlp.geometry.ramp`): zero for ``depth <= 0``, exactly
    ``depth`` beyond ``width`` (m)."""
    t = ops.fmin(ops.fmax(depth, 0), width)
    return ramp_inner(t, width) + (ops.fmax(depth, width) - width)


@runtime_checkable
class PressureLaw(Protocol):
    """The elastic foundation's pressure from penetration depth (module docstring)."""

    name: str
    #: what the compiled contact passes evaluate (:mod:`kneenlp.geometry.kernels`): an exponent ``n``
    #: of the power family ``d_r (g / d_r)^n`` (compiled once per machine), or a compiled function
    #: ``(depth, gate) -> (h, h', h'')``, pressure per unit modulus and its depth derivatives
    #: (any law; compiled in every process)
    kernel: Any

    def pressure(self, depth: Any, modulus: Any, width: float, ops: Ops = CASADI) -> Any:
        """Pressure (Pa) at penetration ``depth`` (m; <= 0: none) for ``modulus`` (N/m^3) and a
        gate of ``width`` (m)."""
        ...


class ElasticFoundation:
    """The paper's law: pressure = modulus x penetration, started by the C2 gate."""

    name = "elastic_foundation"
    kernel = 1.0  # the power family's n = 1: the gate itself

    def pressure(self, depth, modulus, width, ops: Ops = CASADI):
        return modulus * gate(depth, width, ops)


class PowerFoundation:
    """Pressure ``K d_r (g(d) / d_r)^1.5``: stiffening with depth, the paper's at ``d_r`` = 1 mm."""

    name = "power_1.5"
    kernel = 1.5

    def pressure(self, depth, modulus, width, ops: Ops = CASADI):
        g = gate(depth, width, ops)
        return modulus * g * (g / REFERENCE_DEPTH) ** 0.5


#: The built-in pressure laws by name.
PRESSURE_LAWS: Mapping[str, type] = MappingProxyType({law.name: law for law in (ElasticFoundation, PowerFoundation)})
#: The law of a compartment whose knee file names none.
DEFAULT_PRESSURE_LAW = ElasticFoundation.name


def law_named(spec: str, *, source: object = None, field: str = "law", kind: str = "ligament") -> Any:
    """The law a knee file names: a built-in name (:data:`LAWS` for ``kind="ligament"``,
    :data:`PRESSURE_LAWS` for ``kind="pressure"``) or ``"module:name"`` (a class or factory, called
    without arguments)."""
    builtin = LAWS if kind == "ligament" else PRESSURE_LAWS
    protocol = LigamentLaw if kind == "ligament" else PressureLaw
    if not isinstance(spec, str) or not spec:
        raise InputError(f"must name a law; built in: {', '.join(builtin)}", source=source, field=field)
    if spec in builtin:
        return builtin[spec]()
    module, sep, attr = spec.partition(":")
    if not sep or not module or not attr:
        raise InputError(f"unknown law {spec!r}; built in: {', '.join(builtin)} (or MODULE:NAME of your own)",
                         source=source, field=field)
    try:
        factory = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise InputError(f"cannot import law {spec!r} ({type(exc).__name__}: {exc})", source=source,
                         field=field) from None
    try:
        made = factory()
    except Exception as exc:
        raise InputError(f"cannot make law {spec!r}: calling it without arguments failed ({type(exc).__name__}: "
                         f"{exc})", source=source, field=field) from None
    if not isinstance(made, protocol) or not isinstance(getattr(made, "name", None), str):
        what = ("a ligament law (a name and tension(strain, k, lin_strain, ops))" if kind == "ligament" else
                "a pressure law (a name, pressure(depth, modulus, width, ops) and a compiled kernel)")
        raise InputError(f"{spec} made {type(made).__name__}, not {what}", source=source, field=field)
    return made
