"""Keyword options of a documented entry point, checked in one place: ``f(required..., **options)``
builds a frozen dataclass of its options by :func:`keyword_options`."""

from __future__ import annotations

import dataclasses
from typing import TypeVar

T = TypeVar("T")


def keyword_options(cls: type[T], function: str, options: dict) -> T:
    """``cls(**options)`` (a dataclass of ``function``'s keyword options, each with its default); a
    name it does not have raises TypeError, as Python does for a keyword argument."""
    unknown = sorted(set(options) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise TypeError(f"{function}() got unexpected keyword argument(s): {', '.join(unknown)}")
    return cls(**options)
