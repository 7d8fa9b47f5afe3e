"""Several starts of one fit: the one loop behind ``identify``'s multistart and restarts and the
base fit of model adequacy.  Each caller says how a start is solved, when enough starts were made
and which fit is best."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from kneenlp.estimation.fit import Fit


def run_starts(solve: Callable[[int], Fit], *, at_least: int, at_most: int,
               done: Callable[[list[Fit]], bool]) -> list[Fit]:
    """The fits of starts ``0, 1, ...`` (``solve(i)`` fits start ``i``): at least ``at_least`` (and
    at least one), then more until ``done(fits)`` or ``at_most`` starts."""
    at_least = max(1, at_least)
    fits: list[Fit] = []
    while len(fits) < max(at_least, at_most):
        fits.append(solve(len(fits)))
        if len(fits) >= at_least and done(fits):
            break
    return fits


def best_fit(fits: list[Fit], key: Callable[[Fit], Any]) -> Fit:
    """The first fit with the largest ``key``."""
    best = fits[0]
    for fit in fits[1:]:
        if key(fit) > key(best):
            best = fit
    return best
