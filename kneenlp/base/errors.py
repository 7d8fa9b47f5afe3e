"""Errors that speak the user's language.

Every problem with user input (a file, a field, a name, a unit, a command-line option) raises
:class:`InputError`, whose message is one line naming the file and the field.  The command-line
interface prints that line and exits with status 2 (with ``--json`` it also prints
:meth:`InputError.to_dict` on stdout); it never shows a traceback for bad input.
"""

from __future__ import annotations

from collections.abc import Iterable


class InputError(ValueError):
    """Bad user input: a one-line message naming the file/field and what was expected.

    ``source`` is the file (or ``None``), ``field`` the field of the file or the command-line
    option (``--seed``); ``message`` is the bare message without them.
    """

    def __init__(self, message: str, *, source: str | None = None, field: str | None = None):
        self.message = " ".join(str(message).split())
        where = ": ".join(s for s in (source, field) if s)
        text = f"{where}: {self.message}" if where else self.message
        super().__init__(" ".join(str(text).split()))  # always one line
        self.source = source
        self.field = field

    def with_context(self, *, source: str | None = None, field: str | None = None) -> InputError:
        """The same error, naming ``source``/``field`` where it named none (e.g. the option that
        gave a protocol name: ``unknown protocol 'set9'`` -> ``--protocol: unknown protocol ...``)."""
        if (source is None or self.source) and (field is None or self.field):
            return self
        return InputError(self.message, source=self.source or source, field=self.field or field)

    def to_dict(self) -> dict:
        """The machine-readable error object of ``--json``: ``{"error", "file", "field"}``."""
        return {"error": str(self), "file": self.source, "field": self.field}


class ConvergenceError(RuntimeError):
    """A numerical solve failed; carries whatever partial result exists in ``result``."""

    def __init__(self, message: str, result: object | None = None):
        super().__init__(" ".join(str(message).split()))
        self.result = result


def unknown_name(kind: str, name: str, known: Iterable[str], *, source: str | None = None,
                 field: str | None = None) -> InputError:
    """Build the standard "unknown X 'name'; known: a, b, c" error."""
    known_list = ", ".join(sorted(known, key=str))
    return InputError(f"unknown {kind} {name!r}; known: {known_list}", source=source, field=field)
