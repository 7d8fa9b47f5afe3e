"""Ctrl-C and SIGTERM that a running solver cannot swallow.

CasADi checks for Ctrl-C while IPOPT runs; when the Python signal handler raises there, CasADi
prints a ``KeyboardInterruptException`` warning, drops the exception and lets the solve go on to
its end, so an interrupted study would store the sample and carry on.  The handler of
:func:`catching_signals` (installed by the command-line interface) therefore remembers the signal;
inside :func:`deferred` (around a solver call) it raises nothing, and :func:`check` raises it when
the solve has returned; elsewhere it raises at once.  So Ctrl-C during an IPOPT solve takes effect
when that solve ends (seconds on the synthetic knee, up to minutes on a mesh knee), and the
interrupted result is never used.  Without that handler (a script, a notebook) :func:`deferred`
and :func:`check` do nothing.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

#: The signals handled: Ctrl-C and SIGTERM (a batch system's "stop").
SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (``signum`` SIGINT) or SIGTERM; a KeyboardInterrupt, so ``except Exception`` in the
    work does not swallow it."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class _Handler:
    """Remembers the first signal received and raises :class:`Interrupted`."""

    def __init__(self) -> None:
        self.received: int | None = None
        self.deferring = 0  # depth of deferred() blocks

    def __call__(self, signum: int, frame) -> None:
        if self.received is None:
            self.received = signum
        if not self.deferring:
            raise Interrupted(self.received)


@contextlib.contextmanager
def catching_signals() -> Iterator[None]:
    """While the block runs, SIGINT and SIGTERM raise :class:`Interrupted` (and :func:`check`
    raises it again); the previous handlers are restored after.  Main thread only (elsewhere a
    no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handler = _Handler()
    old = {s: signal.signal(s, handler) for s in SIGNALS}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def pending() -> int | None:
    """The signal received under :func:`catching_signals`, if any (``None`` otherwise).  An
    exception raised while it is pending is the interrupt's doing: a signal handler that raises
    inside a compiled (numba) function surfaces as ``SystemError``, not as :class:`Interrupted`."""
    for s in SIGNALS:
        handler = signal.getsignal(s)
        if isinstance(handler, _Handler) and handler.received is not None:
            return handler.received
    return None


def check() -> None:
    """Raise :class:`Interrupted` if a signal arrived under :func:`catching_signals` (even if a
    solver swallowed the exception)."""
    signum = pending()
    if signum is not None:
        raise Interrupted(signum)


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Around a solver call that swallows exceptions: a signal is only remembered, and raised by
    :func:`check` when the block ends."""
    with held():
        yield
    check()


@contextlib.contextmanager
def held() -> Iterator[None]:
    """Inside a Python callback that compiled code calls (CasADi's working sets): a signal is only
    remembered, never raised there (CasADi would print the exception's traceback and go on); the
    caller's next :func:`check`, the end of a :func:`deferred` block (the NLP's solve) or the
    command line's end raises it."""
    handler = signal.getsignal(signal.SIGINT)
    if not isinstance(handler, _Handler):
        yield
        return
    handler.deferring += 1
    try:
        yield
    finally:
        handler.deferring -= 1


def as_worker() -> None:
    """In a worker process: leave Ctrl-C and SIGTERM to the parent, SIGINT ignored (the parent stops
    its workers), SIGTERM back to its default (a handler inherited by fork would keep them alive)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
