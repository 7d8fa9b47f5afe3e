"""The checked inputs of :func:`~kneenlp.solvers.boxcomplex.minimize_complex`: bounds, options and
the initial complex, each refused with a ``ValueError`` naming the argument (the minimiser's own
conventions, module docstring of :mod:`kneenlp.solvers.boxcomplex`)."""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def as_float(value: Any) -> float:
    """Convert an objective value to float; NaN and +-inf become ``+inf``."""
    if isinstance(value, float):
        f = value
    else:
        arr = np.asarray(value)
        if arr.size != 1:
            raise ValueError(f"fun must return a scalar, got an array of shape {arr.shape}")
        try:
            f = float(arr.reshape(()))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"fun must return a real scalar, got {value!r}") from exc
    return f if math.isfinite(f) else math.inf


def parse_bounds(bounds: Any) -> tuple[FloatArray, FloatArray]:
    """Return ``(lo, hi)`` from a sequence of pairs or a ``scipy.optimize.Bounds``-like object."""
    if hasattr(bounds, "lb") and hasattr(bounds, "ub"):
        lo_raw = np.atleast_1d(np.asarray(bounds.lb, dtype=float))
        hi_raw = np.atleast_1d(np.asarray(bounds.ub, dtype=float))
        if lo_raw.ndim != 1 or hi_raw.ndim != 1:
            raise ValueError("Bounds.lb and Bounds.ub must be one-dimensional")
        try:
            lo_b, hi_b = np.broadcast_arrays(lo_raw, hi_raw)
        except ValueError as exc:
            raise ValueError("Bounds.lb and Bounds.ub have incompatible shapes") from exc
        lo, hi = lo_b.astype(float), hi_b.astype(float)
    else:
        if isinstance(bounds, (str, bytes)):
            raise ValueError("bounds must be a sequence of (lo, hi) pairs")
        try:
            pairs = list(bounds)
        except TypeError as exc:
            raise ValueError(
                "bounds must be a sequence of (lo, hi) pairs or a scipy.optimize.Bounds"
            ) from exc
        lo_list: list[float] = []
        hi_list: list[float] = []
        for i, pair in enumerate(pairs):
            try:
                a, b = pair
                lo_list.append(-math.inf if a is None else float(a))
                hi_list.append(math.inf if b is None else float(b))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"bounds[{i}] must be a (lo, hi) pair, got {pair!r}") from exc
        lo = np.asarray(lo_list, dtype=float)
        hi = np.asarray(hi_list, dtype=float)
    if lo.size == 0:
        raise ValueError("bounds must describe at least one variable")
    if np.isnan(lo).any() or np.isnan(hi).any():
        raise ValueError("bounds must not contain NaN")
    bad = np.flatnonzero(lo > hi)
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"lower bound > upper bound for variable {i}: {lo[i]} > {hi[i]}")
    if np.any(lo == math.inf) or np.any(hi == -math.inf):
        raise ValueError("lower bounds must be < +inf and upper bounds > -inf")
    return lo, hi


def as_nonneg_float(name: str, value: Any, *, allow_zero: bool = True) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number, got {value!r}") from exc
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        rel = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {rel}, got {value!r}")
    return v


def as_int(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value}")
    return int(value)


def as_vector(name: str, value: ArrayLike, n: int) -> FloatArray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr.copy()


@dataclass(frozen=True)
class ComplexOptions:
    """The keyword options of :func:`~kneenlp.solvers.boxcomplex.minimize_complex` as given, with
    their defaults (their meanings and units: that function's docstring); :class:`Options` and
    :class:`Start` check their values."""

    args: tuple[Any, ...] = ()
    x0: ArrayLike | None = None
    spread: ArrayLike | None = None
    initial: ArrayLike | None = None
    n_points: int | None = None
    alpha: float = 1.3
    max_retries: int = 4
    rfak: float = 0.3
    gamma: float = 0.3
    xtol: float = 1e-6
    ftol: float = 1e-9
    max_evals: int = 10000
    max_seconds: float | None = None
    seed: int | np.random.Generator | None = None
    callback: Callable[[FloatArray, float, int], Any] | None = None
    refinements: bool = True



@dataclass(frozen=True)
class Options:
    """The checked coefficients, tolerances, time budget (s) and callback of a run (see
    :func:`minimize_complex`)."""

    alpha: float
    max_retries: int
    rfak: float
    gamma: float
    xtol: float
    ftol: float
    max_seconds: float | None
    callback: Callable[[FloatArray, float, int], Any] | None
    refinements: bool

    @classmethod
    def checked(cls, given: ComplexOptions) -> Options:
        """The options of ``given`` after their checks; ``ValueError`` names the first invalid one."""
        alpha = as_nonneg_float("alpha", given.alpha, allow_zero=False)
        rfak = as_nonneg_float("rfak", given.rfak)
        gamma = as_nonneg_float("gamma", given.gamma)
        xtol = as_nonneg_float("xtol", given.xtol)
        ftol = as_nonneg_float("ftol", given.ftol)
        max_seconds = given.max_seconds
        if max_seconds is not None:
            max_seconds = as_nonneg_float("max_seconds", max_seconds, allow_zero=False)
        max_retries = as_int("max_retries", given.max_retries, 0)
        callback = given.callback
        if callback is not None and not callable(callback):
            raise ValueError("callback must be callable or None")
        return cls(alpha, max_retries, rfak, gamma, xtol, ftol, max_seconds, callback, given.refinements)


@dataclass(frozen=True)
class Start:
    """How the initial complex of ``k`` points is made: the explicit cloud ``initial``, or ``x0``
    and ``k - 1`` points uniform within ``+-spread`` of it (or over the bounds without ``spread``),
    or ``k`` points uniform over the bounds."""

    k: int
    initial: FloatArray | None
    x0: FloatArray | None
    spread: FloatArray | None

    @classmethod
    def checked(cls, lo: FloatArray, hi: FloatArray, given: ComplexOptions) -> Start:
        """The start of ``given`` (its ``initial``, ``x0``, ``spread`` and ``n_points``) after its checks
        against the bounds ``lo``, ``hi``; ``ValueError`` names the first inconsistency."""
        initial, x0, spread, n_points = given.initial, given.x0, given.spread, given.n_points
        n = lo.size
        x0_arr: FloatArray | None = None
        init_arr: FloatArray | None = None
        spread_arr: FloatArray | None = None
        if initial is not None:
            if x0 is not None or spread is not None:
                raise ValueError("give either initial or x0 (with optional spread), not both")
            init_arr = np.array(initial, dtype=float)
            if init_arr.ndim != 2 or init_arr.shape[1] != n:
                raise ValueError(f"initial must have shape (n_points, {n}), got {init_arr.shape}")
            if not np.all(np.isfinite(init_arr)):
                raise ValueError("initial must contain only finite values")
            if np.any(init_arr < lo) or np.any(init_arr > hi):
                raise ValueError("all points of initial must lie within the bounds")
            if n_points is None:
                n_points = init_arr.shape[0]
            elif n_points != init_arr.shape[0]:
                raise ValueError(
                    f"n_points={n_points} does not match the {init_arr.shape[0]} rows of initial"
                )
        if x0 is not None:
            x0_arr = as_vector("x0", x0, n)
            if np.any(x0_arr < lo) or np.any(x0_arr > hi):
                raise ValueError("x0 lies outside the bounds")
        if spread is not None:
            if x0_arr is None:
                raise ValueError("spread requires x0")
            spread_in = np.asarray(spread, dtype=float)
            spread_arr = as_vector(
                "spread", np.full(n, float(spread_in)) if spread_in.ndim == 0 else spread_in, n
            )
            if np.any(spread_arr < 0):
                raise ValueError("spread must be >= 0")
        finite_box = bool(np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)))
        if init_arr is None and spread_arr is None and not finite_box:
            raise ValueError(
                "infinite bounds require an explicit initial complex or x0 together with spread"
            )
        k = as_int("n_points", 2 * n + 1 if n_points is None else n_points, n + 1)
        return cls(k, init_arr, x0_arr, spread_arr)

    def points(self, lo: FloatArray, hi: FloatArray, rng: np.random.Generator) -> FloatArray:
        """The ``(k, n)`` initial complex; the random points are drawn from ``rng`` in one call."""
        if self.initial is not None:
            return self.initial
        points = np.empty((self.k, lo.size))
        start = 0
        if self.x0 is not None:
            points[0] = self.x0
            start = 1
        if self.x0 is not None and self.spread is not None:
            u = rng.uniform(-1.0, 1.0, size=(self.k - start, lo.size))
            points[start:] = np.clip(self.x0 + u * self.spread, lo, hi)
        else:
            u = rng.uniform(0.0, 1.0, size=(self.k - start, lo.size))
            points[start:] = lo + u * (hi - lo)
        return points
