"""Built-in structures a knee file declares by a table of its own (``[menisci]``): one module each.

Every module of this package defines ``TABLE``, a :class:`StructureTable`: the table's name and
schema, how its values become the knee's (user units to SI, checked), the force elements a knee
that declares it carries, the neutral candidates a knee that does not declare it carries (model
adequacy may free them), and its line in the knee's report.  The knee file's schema
(:mod:`kneenlp.model.knee_schema`), :class:`~kneenlp.model.knee.Knee` and the model find them with
:func:`structure_tables`, so a new structure is one new module here and nothing else (the meniscus,
:mod:`.meniscus`, is the worked example).  A user's own elements need no table: ``--element``
(:mod:`kneenlp.model.plugins`).
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


@dataclass(frozen=True)
class StructureTable:
    """A knee-file table that declares a built-in structure (see module docstring)."""

    #: the table's name in a knee file (``[menisci]``)
    name: str
    #: its schema (keys, types, units in the descriptions)
    schema: type[Table]
    #: (the validated table, the knee file's path) -> the knee's value of it (SI), checked
    read: Callable[[Any, str], Any]
    #: (the knee, its value) -> the force elements of a knee that declares the table
    declared: Callable[[KneeGeometry, Any], list[ForceElement]]
    #: the knee -> the neutral candidates of a knee that does not declare it
    candidates: Callable[[KneeGeometry], list[ForceElement]]
    #: the knee's value -> its line in the knee's report
    describe: Callable[[Any], str]


@functools.cache
def structure_tables() -> tuple[StructureTable, ...]:
    """Every module's :class:`StructureTable`, by module name."""
    return tuple(importlib.import_module(f"{__name__}.{m.name}").TABLE
                 for m in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name))
