"""Ligament force-strain laws: small parts a ligament is built with, named in a knee file.

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
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

import casadi as ca
import numpy as np

from kneenlp.errors import InputError


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


def law_named(spec: str, *, source: object = None, field: str = "law") -> LigamentLaw:
    """The law a knee file names: a built-in name (:data:`LAWS`) or ``"module:name"`` (a class or
    factory, called without arguments)."""
    if not isinstance(spec, str) or not spec:
        raise InputError(f"must name a law; built in: {', '.join(LAWS)}", source=source, field=field)
    if spec in LAWS:
        return LAWS[spec]()
    module, sep, attr = spec.partition(":")
    if not sep or not module or not attr:
        raise InputError(f"unknown law {spec!r}; built in: {', '.join(LAWS)} (or MODULE:NAME of your own)",
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
    if not isinstance(made, LigamentLaw) or not isinstance(getattr(made, "name", None), str):
        raise InputError(f"{spec} made {type(made).__name__}, not a ligament law (a name and tension(strain, k, "
                         "lin_strain, ops))", source=source, field=field)
    return made
