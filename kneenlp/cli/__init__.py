"""The command line: ``kneenlp <command> ...`` (:func:`~kneenlp.cli.main.main`; the parser in
:mod:`~kneenlp.cli.parser`, the commands in :mod:`~kneenlp.cli.commands`, their input checks in
:mod:`~kneenlp.cli.inputs`).

Before it imports ``main`` the process ends a SIGINT or SIGTERM in one line (:func:`own_signals`):
the command line's imports take a while on a loaded machine, and a signal during them must not
print a traceback.  :func:`~kneenlp.cli.main.main` takes the signals over for the command itself."""

from __future__ import annotations

import signal
import sys

__all__ = ["main"]

#: Exit status and line of a signal that arrives while the command line is still importing.
_EARLY = {signal.SIGINT: (130, "interrupted (Ctrl-C)"), signal.SIGTERM: (143, "terminated (SIGTERM)")}


def _early_exit(signum: int, frame) -> None:
    status, what = _EARLY[signum]
    print(f"kneenlp: {what} while starting", file=sys.stderr)
    raise SystemExit(status)


def own_signals() -> None:
    """SIGINT and SIGTERM end the process in one line until :func:`~kneenlp.cli.main.main` takes them."""
    for signum in _EARLY:
        signal.signal(signum, _early_exit)


own_signals()

from kneenlp.cli.main import main  # noqa: E402
