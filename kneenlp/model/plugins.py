"""User force elements named by import path, so that the CLI, studies and worker processes can
build the same model: ``"package.module:factory"`` names a callable returning a
:class:`~kneenlp.model.elements.ForceElement` or an experiment part
(:class:`kneenlp.experiment.parts.ExperimentPart`), or a list of them (called without arguments).
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence

from kneenlp.base.errors import InputError
from kneenlp.model.elements import Part


def load_elements(specs: Sequence[str]) -> list[Part]:
    """The user elements named by ``specs`` (``"module:factory"`` each), in order."""
    out: list[Part] = []
    for spec in specs:
        module, sep, attr = spec.partition(":")
        if not sep or not module or not attr:
            raise InputError(f"expected MODULE:FACTORY, got {spec!r}", field="--element")
        try:
            factory = getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:
            raise InputError(f"cannot import {spec!r} ({type(exc).__name__}: {exc})", field="--element") from None
        made = factory()
        made = made if isinstance(made, list | tuple) else [made]
        for e in made:
            if not isinstance(e, Part):
                raise InputError(f"{spec} returned {type(e).__name__}, not a ForceElement or an ExperimentPart",
                                 field="--element")
        out += list(made)
    return out
