"""The one place a model keeps what was built for it: solvers and compiled functions, each built
once and found again by what changes it (its kind, the problem layout, the solver's name and
options, threads).  Nothing else keeps built solvers; nothing outside this class writes the store."""

from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping
from typing import Any, TypeVar

T = TypeVar("T")


def frozen(options: Mapping[str, Any] | None) -> tuple:
    """Solver options as a hashable key: nested mappings as sorted (name, value) tuples, lists as
    tuples (``{"ipopt": {"max_iter": 60}}`` -> ``(("ipopt", (("max_iter", 60),)),)``)."""

    def freeze(v: Any) -> Hashable:
        if isinstance(v, Mapping):
            return tuple(sorted((str(k), freeze(x)) for k, x in v.items()))
        if isinstance(v, list | tuple):
            return tuple(freeze(x) for x in v)
        return v

    return freeze(dict(options or {}))


class SolverCache:
    """Built solvers of one model, keyed by what changes them."""

    def __init__(self) -> None:
        self._built: dict[tuple, Any] = {}

    def get(self, key: tuple, build: Callable[[], T]) -> T:
        """The solver under ``key`` (a tuple naming its kind first, then everything that changes
        it), built by ``build()`` the first time."""
        if key not in self._built:
            self._built[key] = build()
        return self._built[key]

    def clear(self) -> None:
        """Forget every built solver (benchmarks measure cold builds so)."""
        self._built.clear()

    def __len__(self) -> int:
        return len(self._built)

    def __contains__(self, key: tuple) -> bool:
        return key in self._built
