"""Command-line interface: ``kneenlp <command> ...``.

Bad input gives a one-line ``kneenlp: error: ...`` on stderr and exit status 2 (never a
traceback); with ``--json`` the error is also printed on stdout as ``{"error": ..., "file": ...,
"field": ...}``.  A run in which some trial or fit did not converge still writes its outputs and
exits with status 1.  Every option and input file is checked before any work starts (option
values by their argparse types, files by :func:`check_inputs`); outputs are written through a
staging directory (:func:`kneenlp.base.atomic.staged_directory`), so a failed or interrupted
command leaves no half-written file.  Ctrl-C (SIGINT) and SIGTERM end a command with one line and
status 130 / 143, keeping finished work (a study's finished samples).  An unexpected exception
(a bug) is one line and status 3 (``KNEENLP_DEBUG=1`` shows the traceback).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys

from kneenlp.base.errors import ConvergenceError, InputError
from kneenlp.cli.commands import COMMANDS
from kneenlp.cli.inputs import check_inputs
from kneenlp.cli.parser import build_parser

#: Exit statuses: 0 done, 1 some trial or fit did not converge, 2 bad input, 3 internal error (a
#: bug), 130 interrupted (Ctrl-C), 143 terminated (SIGTERM).
EXIT_INPUT, EXIT_BUG, EXIT_INTERRUPTED, EXIT_TERMINATED = 2, 3, 130, 143


class _StderrHandler(logging.StreamHandler):
    """A log handler writing to the current ``sys.stderr`` (which tests and notebooks replace)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def _announce_long_steps() -> None:
    """Show kneenlp's progress messages (e.g. a distance field being built once) on stderr."""
    log = logging.getLogger("kneenlp")
    if not any(getattr(h, "kneenlp_cli", False) for h in log.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("kneenlp: %(message)s"))
        handler.kneenlp_cli = True
        log.addHandler(handler)
        log.setLevel(logging.INFO)


def _fail(line: str, status: int, as_json: bool, error: dict | None = None) -> int:
    """End a failed command: ``line`` on stderr and, with ``--json``, the error object on stdout
    (``{"error", "file", "field"}``, ``file``/``field`` null when there is none)."""
    print(f"kneenlp: {line}", file=sys.stderr)
    if as_json:
        print(json.dumps(error or {"error": line, "file": None, "field": None}))
    return status


def _interrupted(signum: int, as_json: bool) -> int:
    if signum == signal.SIGTERM:
        return _fail("terminated (SIGTERM); finished work is kept", EXIT_TERMINATED, as_json)
    return _fail("interrupted (Ctrl-C); finished work is kept", EXIT_INTERRUPTED, as_json)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    as_json = "--json" in argv  # until the options are parsed
    from kneenlp.base.interrupts import Interrupted, catching_signals, pending

    with catching_signals():
        try:
            args = build_parser().parse_args(argv)
            as_json = bool(getattr(args, "json", False))
            _announce_long_steps()
            check_inputs(args)
            code = int(COMMANDS[args.command](args))
            if pending() is not None:  # a signal a callback held past its last check: it still wins
                return _interrupted(pending(), as_json)
            return code
        except InputError as exc:
            return _fail(f"error: {exc}", EXIT_INPUT, as_json, exc.to_dict())
        except ConvergenceError as exc:
            print(f"kneenlp: not converged: {exc}", file=sys.stderr)
            return 1
        except BrokenPipeError:  # output piped into e.g. `head`, which closed early
            sys.stderr.close()
            return 0
        except KeyboardInterrupt as exc:
            return _interrupted(exc.signum if isinstance(exc, Interrupted) else signal.SIGINT, as_json)
        except Exception as exc:  # a bug, not bad input: one line, unless debugging
            if pending() is not None:  # the signal's doing (e.g. raised inside a compiled kernel)
                return _interrupted(pending(), as_json)
            if os.environ.get("KNEENLP_DEBUG"):
                raise
            text = " ".join(f"{type(exc).__name__}: {exc}".split())
            return _fail(f"internal error: {text} (a bug; KNEENLP_DEBUG=1 shows the traceback)", EXIT_BUG, as_json)
