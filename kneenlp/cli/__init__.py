"""The command line: ``kneenlp <command> ...`` (:func:`~kneenlp.cli.main.main`; the parser in
:mod:`~kneenlp.cli.parser`, the commands in :mod:`~kneenlp.cli.commands`, their input checks in
:mod:`~kneenlp.cli.inputs`)."""

from kneenlp.cli.main import main

__all__ = ["main"]
