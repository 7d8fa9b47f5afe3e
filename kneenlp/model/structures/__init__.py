"""Built-in structures a knee file declares by a table of its own (``[contact]``, ``[menisci]``): one
module each.

Every module of this package defines ``TABLE``, a :class:`StructureTable`: the table's name and
schema, how its values become the knee's (user units to SI, checked), the force elements a knee
that declares it carries, the neutral candidates a knee that does not declare it carries (model
adequacy may free them), and its line in the knee's report.  The knee file's schema
(:mod:`kneenlp.model.knee_schema`), :class:`~kneenlp.model.knee.Knee` and the model find them with
:func:`structure_tables`, so a new structure is one new module here and nothing else (the meniscus,
:mod:`.meniscus`, is the worked example).  The contact (:mod:`.contact`) registers its elements the
same way; its table alone is read by the knee file's reader (its meshes, fields and fits need the
whole file), so its ``schema`` and ``read`` are None and every knee carries it.  The elements'
order is the modules' (by name), which is the order of the parameters.  A user's own elements
need no table: ``--element`` (:mod:`kneenlp.model.plugins`).
"""

from __future__ import annotations

import functools
import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from kneenlp.base.schema import Table
from kneenlp.model.elements import ForceElement


class KneeGeometry(Protocol):
    """What a structure may read of the knee it is built into (:class:`~kneenlp.model.knee.Knee`)."""

    def condyle_centres(self) -> list[np.ndarray]: ...

    def condyle_rest(self) -> list[np.ndarray]: ...

    compartments: dict[str, Any]  # the contact compartments the knee file's reader built
    gate: float  # the contact's working-set gate, m
    working_set: int  # the sphere contact's working-set size
    femur: Any  # the femoral surface of the mesh compartments (None: spheres only)


@dataclass(frozen=True)
class StructureTable:
    """A knee-file table that declares a built-in structure (see module docstring)."""

    #: the table's name in a knee file (``[menisci]``)
    name: str
    #: its schema (keys, types, units in the descriptions); None: the knee file's own (the contact)
    schema: type[Table] | None
    #: (the validated table, the knee file's path) -> the knee's value of it (SI), checked; None:
    #: the knee file's reader reads it and every knee carries the structure (the contact)
    read: Callable[[Any, str], Any] | None
    #: (the knee, its value) -> the force elements of a knee that declares the table
    declared: Callable[[KneeGeometry, Any], list[ForceElement]]
    #: the knee -> the neutral candidates of a knee that does not declare it
    candidates: Callable[[KneeGeometry], list[ForceElement]]
    #: the knee's value -> its line in the knee's report (None: the knee's report has its own)
    describe: Callable[[Any], str] | None


@functools.cache
def structure_tables() -> tuple[StructureTable, ...]:
    """Every module's :class:`StructureTable`, by module name."""
    return tuple(importlib.import_module(f"{__name__}.{m.name}").TABLE
                 for m in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name))
