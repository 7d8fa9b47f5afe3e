"""Errors that speak the user's language.

Every problem with user input (a file, a field, a name, a unit) raises :class:`InputError`, whose
message is one line naming the file and the field.  The command-line interface prints that line
and exits with status 2; it never shows a traceback for bad input.
"""

from __future__ import annotations

from collections.abc import Iterable


class InputError(ValueError):
    """Bad user input: a one-line message naming the file/field and what was expected."""

    def __init__(self, message: str, *, source: str | None = None, field: str | None = None):
        where = ": ".join(s for s in (source, field) if s)
        text = f"{where}: {message}" if where else message
        super().__init__(" ".join(str(text).split()))  # always one line
        self.source = source
        self.field = field


class ConvergenceError(RuntimeError):
    """A numerical solve failed; carries whatever partial result exists in ``result``."""

    def __init__(self, message: str, result: object | None = None):
        super().__init__(" ".join(str(message).split()))
        self.result = result


def unknown_name(kind: str, name: str, known: Iterable[str], *, source: str | None = None) -> InputError:
    """Build the standard "unknown X 'name'; known: a, b, c" error."""
    known_list = ", ".join(sorted(known, key=str))
    return InputError(f"unknown {kind} {name!r}; known: {known_list}", source=source)
