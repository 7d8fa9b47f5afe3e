"""TOML input files: reading one with every failure as a one-line :class:`InputError`, and the
numbers in them (finite floats, booleans refused)."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

from kneenlp.base.errors import InputError


def read_toml(path: Path) -> dict:
    """Read a TOML file, turning every failure into a one-line :class:`InputError`."""
    if not path.is_file():
        raise InputError("file not found", source=str(path))
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"malformed TOML ({exc})", source=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read ({exc})", source=str(path)) from None


def not_a_number(value: object) -> str | None:
    """What keeps a TOML value from being a finite number (a boolean is none), or None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return f"expected a number, got {value!r}"
    if not math.isfinite(value):
        return f"must be finite, got {value!r}"
    return None


def number(value: object, source: str, field: str) -> float:
    """A finite float from a TOML value, or a one-line error naming the field."""
    problem = not_a_number(value)
    if problem:
        raise InputError(problem, source=source, field=field)
    return float(value)
