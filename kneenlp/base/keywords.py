"""Keyword options of a documented entry point, checked in one place: ``f(required..., **options)``
builds a frozen dataclass of its options by :func:`keyword_options`."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import TypeVar

T = TypeVar("T")


def refuse_unknown(function: str, given: Iterable[str], known: Iterable[str]) -> None:
    """A name of ``given`` not among ``known`` raises TypeError, as Python does for a keyword
    argument of ``function``."""
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise TypeError(f"{function}() got unexpected keyword argument(s): {', '.join(unknown)}")


def keyword_options(cls: type[T], function: str, options: dict) -> T:
    """``cls(**options)`` (a dataclass of ``function``'s keyword options, each with its default); a
    name it does not have raises TypeError (:func:`refuse_unknown`)."""
    refuse_unknown(function, options, [f.name for f in dataclasses.fields(cls)])
    return cls(**options)
