r"""Box's Complex method with the Complex-RF refinements (bound-constrained, derivative free).

This module is a standalone minimiser for expensive, possibly noisy or partly undefined black-box
objectives on a box-shaped design domain. Its only dependency is numpy.

Algorithm
---------
Notation: ``n`` design variables, a *complex* of ``k`` points (``k >= n + 1``, default
``2 n + 1``), bounds ``lo <= x <= hi``. For every variable a *scale* ``s_j`` is used to
make spreads comparable: ``s_j = hi_j - lo_j`` when that is finite and positive, otherwise
``max(1, |x_ref_j|)`` (``x_ref`` = ``x0`` or the mean of the initial cloud).

1. **Initial complex.** ``k`` points are drawn with the random generator built from ``seed``:

   * ``initial`` given: that ``(k, n)`` cloud is used as is (it must lie within the bounds);
   * ``x0`` and ``spread`` given: ``x0`` itself is point 0; the other ``k - 1`` points are
     ``x0 + U(-spread, +spread)`` per variable, clipped to the bounds;
   * ``x0`` only: ``x0`` plus ``k - 1`` points uniform over the bounds;
   * nothing: ``k`` points uniform over the bounds (the bounds must then be finite).

   Every point is evaluated. Values that are NaN or +-inf are replaced by ``+inf`` (worst).

2. **Iteration** (one iteration = one reflection plus its retractions):

   a. *Forgetting* (Complex-RF only). The complex keeps, besides the raw values ``f_i``, an
      *effective* value ``g_i`` used for every comparison. At the start of each iteration every
      effective value is aged (Krus & Andersson 2003; Andersson's reference ``complexrf.m``)::

          g_i <- g_i + (max_j g_j - min_j g_j) * K_f,     K_f = 1 - (alpha / 2) ** (gamma / k)

      (max/min over the finite ``g_j``; ``K_f`` is clamped at 0, i.e. no forgetting when
      ``alpha >= 2``). A newly evaluated point enters with ``g = f``. Hence a point that has
      survived ``a`` iterations compares as ``f_i + K_f * sum over those a iterations of the
      then-current range``: old, possibly lucky, points slowly become worse than fresh ones, so
      the complex cannot get stuck around a single old point. With the defaults
      (alpha = 1.3, gamma = 0.3, k = 17) ``K_f = 0.0076``.

   b. *Reflection.* ``w`` = the point with the largest ``g`` (the worst); ``x_c`` = centroid of
      the other ``k - 1`` points; ``x_b`` = the point with the smallest ``g`` (the best)::

          x_new = x_c + alpha * (x_c - x_w)  [+ r]                         (alpha = 1.3, Box)

      Complex-RF adds the random term ``r_j = rfak * d * s_j * (R_j - 1/2)``, ``R_j ~ U(0, 1)``,
      where ``d = max_j (max_i x_ij - min_i x_ij) / s_j`` is the relative spread of the complex
      without ``x_w`` (the randomisation of Andersson's ``complexrf.m``). The point is clipped
      to the bounds, evaluated and replaces ``x_w`` (raw and effective value ``f_new``).

   c. *Retraction.* While the new point is still the worst, i.e. ``f_new >= max g`` of the other
      points, it is retracted. With retry counter ``k_r = 1, 2, ...`` and ``n_r = 4``::

          eps   = (n_r / (n_r + k_r - 1)) ** ((n_r + k_r - 1) / n_r)   # 1, .757, .544, .393, ...
          x_new = 1/2 * (x_new + eps * x_c + (1 - eps) * x_b)  [+ r * n_r / (n_r + k_r - 1)]

      The first retraction is Box's "halfway towards the centroid"; every further failure
      steers the point increasingly towards the best point (Krus & Andersson 2003), and the
      random term ``r`` (same form as in b., freshly drawn, scaled by the relative spread ``d``
      of the complex) decays as ``n_r / (n_r + k_r - 1)`` = 1, 0.8, 0.67, 0.57, ...
      The retracted point is clipped, evaluated and replaces the previous one.

   d. *Re-initialisation.* If the point is still the worst after ``max_retries`` (default 4)
      retractions, it is replaced by a random point drawn uniformly inside the bounding box
      of the other ``k - 1`` points (clipped to the bounds). That point is evaluated and
      accepted whatever its value, and the next iteration starts.

   With ``refinements=False`` the textbook method (Box 1965) is run instead: no forgetting,
   no random terms, every retraction moves halfway towards the centroid only
   (``x_new = (x_new + x_c) / 2``), and after ``max_retries`` retractions the last retracted
   point is simply kept (no re-initialisation). This is the variant that tends to collapse
   onto the centroid; it is kept for comparison.

3. **Stopping.** Checked before every iteration, and the budgets before every evaluation:

   * converged (``success=True``): ``max_j (max_i x_ij - min_i x_ij) / s_j <= xtol`` **and**
     ``max_i f_i - min_i f_i <= ftol * (1 + |min_i f_i|)`` (raw values of the complex);
   * ``max_evals`` evaluations spent (never exceeded: ``nfev <= max_evals``);
   * ``max_seconds`` of wall time elapsed (checked before each evaluation);
   * ``callback`` returned ``True``.

   The result always holds the best point ever evaluated (raw value), which may have left the
   complex because of forgetting.

All randomness comes from one ``numpy.random.Generator`` built from ``seed``; the evaluation
sequence is therefore fully reproducible for a deterministic objective.

References
----------
M. J. Box, "A new method of constrained optimization and a comparison with other methods",
The Computer Journal 8(1):42-52, 1965.

P. Krus and J. Andersson, "Optimizing optimization for design optimization", Proceedings of
ASME DETC 2003 (Design Automation Conference), Chicago, 2003.

J. Andersson, "complexrf.m" (reference MATLAB implementation of Complex-RF), Linkoping
University, 2003.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ComplexResult", "minimize_complex"]

FloatArray = NDArray[np.float64]

#: Constant ``n_r`` of the Complex-RF retraction schedule (Krus & Andersson 2003).
N_R = 4

STATUS_CONVERGED = 0
STATUS_MAX_EVALS = 1
STATUS_MAX_SECONDS = 2
STATUS_CALLBACK = 3

_MESSAGES = {
    STATUS_CONVERGED: "converged: spread in x <= xtol and spread in f <= ftol",
    STATUS_MAX_EVALS: "maximum number of function evaluations (max_evals) reached",
    STATUS_MAX_SECONDS: "wall-time budget (max_seconds) exhausted",
    STATUS_CALLBACK: "stopped by callback",
}


@dataclass(frozen=True)
class ComplexResult:
    """Result of :func:`minimize_complex`.

    Attributes
    ----------
    x : ndarray, shape (n,)
        Best point ever evaluated.
    fun : float
        Objective value at ``x`` (``inf`` if no finite value was ever found).
    nfev : int
        Number of objective evaluations.
    nit : int
        Number of iterations (reflections).
    success : bool
        True when the convergence criterion (``xtol`` and ``ftol``) was met.
    status : int
        0 converged, 1 ``max_evals`` reached, 2 ``max_seconds`` elapsed, 3 stopped by callback.
    message : str
        Human-readable stopping reason.
    history : ndarray, shape (nfev, 2)
        One row ``(nfev, best f so far)`` per evaluation.
    population : ndarray, shape (k, n)
        Final complex (only the evaluated points if the budget ran out during initialisation).
    population_f : ndarray, shape (k,)
        Raw objective values of ``population`` (non-finite values stored as ``inf``).
    x_spread : float
        Final relative spread ``max_j (max x_j - min x_j) / s_j`` of the complex.
    f_spread : float
        Final spread ``max f - min f`` of the complex.
    """

    x: FloatArray
    fun: float
    nfev: int
    nit: int
    success: bool
    status: int
    message: str
    history: FloatArray = field(repr=False)
    population: FloatArray = field(repr=False)
    population_f: FloatArray = field(repr=False)
    x_spread: float = math.inf
    f_spread: float = math.inf


class _Stop(Exception):
    """Internal signal: a budget is exhausted."""

    def __init__(self, status: int) -> None:
        super().__init__(status)
        self.status = status


class _Evaluator:
    """Counts evaluations, enforces the budgets, sanitises values and records history."""

    def __init__(
        self,
        fun: Callable[..., Any],
        args: tuple[Any, ...],
        max_evals: int,
        max_seconds: float | None,
        n: int,
    ) -> None:
        self.fun = fun
        self.args = args
        self.max_evals = max_evals
        self.deadline = None if max_seconds is None else time.monotonic() + max_seconds
        self.nfev = 0
        self.best_f = math.inf
        self.best_x: FloatArray | None = None
        self.first_x: FloatArray = np.zeros(n)
        self.history: list[tuple[float, float]] = []

    def __call__(self, x: FloatArray) -> float:
        if self.nfev >= self.max_evals:
            raise _Stop(STATUS_MAX_EVALS)
        if self.deadline is not None and time.monotonic() >= self.deadline:
            raise _Stop(STATUS_MAX_SECONDS)
        value = self.fun(x.copy(), *self.args)
        self.nfev += 1
        f = _as_float(value)
        if self.nfev == 1:
            self.first_x = x.copy()
        if f < self.best_f:
            self.best_f = f
            self.best_x = x.copy()
        self.history.append((float(self.nfev), self.best_f))
        return f


def _as_float(value: Any) -> float:
    """Convert an objective value to float; NaN and +-inf become ``+inf``."""
    arr = np.asarray(value)
    if arr.size != 1:
        raise ValueError(f"fun must return a scalar, got an array of shape {arr.shape}")
    try:
        f = float(arr.reshape(()))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"fun must return a real scalar, got {value!r}") from exc
    return f if math.isfinite(f) else math.inf


def _parse_bounds(bounds: Any) -> tuple[FloatArray, FloatArray]:
    """Return ``(lo, hi)`` from a sequence of pairs or a ``scipy.optimize.Bounds``-like object."""
    if hasattr(bounds, "lb") and hasattr(bounds, "ub"):
        lo = np.atleast_1d(np.asarray(bounds.lb, dtype=float)).copy()
        hi = np.atleast_1d(np.asarray(bounds.ub, dtype=float)).copy()
        if lo.ndim != 1 or hi.ndim != 1:
            raise ValueError("Bounds.lb and Bounds.ub must be one-dimensional")
        if lo.shape != hi.shape:
            lo, hi = np.broadcast_arrays(lo, hi)
            lo, hi = lo.copy(), hi.copy()
    else:
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
            except (TypeError, ValueError) as exc:
                raise ValueError(f"bounds[{i}] must be a (lo, hi) pair, got {pair!r}") from exc
            lo_list.append(-math.inf if a is None else float(a))
            hi_list.append(math.inf if b is None else float(b))
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
    return lo, hi


def _check_positive(name: str, value: float, *, allow_zero: bool) -> float:
    v = float(value)
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        rel = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {rel}, got {value!r}")
    return v


def _forgetting_factor(alpha: float, gamma: float, k: int) -> float:
    """``K_f = 1 - (alpha / 2) ** (gamma / k)``, clamped at 0 (Krus & Andersson 2003)."""
    return max(0.0, 1.0 - (alpha / 2.0) ** (gamma / k))


def _retraction_eps(k_r: int, n_r: int = N_R) -> float:
    """Centroid weight ``eps = (n_r / (n_r + k_r - 1)) ** ((n_r + k_r - 1) / n_r)``."""
    m = n_r + k_r - 1
    return (n_r / m) ** (m / n_r)


def _relative_spread(points: FloatArray, scale: FloatArray) -> float:
    """``max_j (max_i x_ij - min_i x_ij) / s_j``."""
    return float(np.max((points.max(axis=0) - points.min(axis=0)) / scale))


def _f_spread(values: FloatArray) -> float:
    if not np.all(np.isfinite(values)):
        return math.inf
    return float(values.max() - values.min())


def minimize_complex(
    fun: Callable[..., Any],
    bounds: Sequence[tuple[float | None, float | None]] | Any,
    *,
    args: tuple[Any, ...] = (),
    x0: ArrayLike | None = None,
    spread: ArrayLike | None = None,
    initial: ArrayLike | None = None,
    n_points: int | None = None,
    alpha: float = 1.3,
    max_retries: int = 4,
    rfak: float = 0.3,
    gamma: float = 0.3,
    xtol: float = 1e-6,
    ftol: float = 1e-9,
    max_evals: int = 10000,
    max_seconds: float | None = None,
    seed: int | np.random.Generator | None = None,
    callback: Callable[[FloatArray, float, int], Any] | None = None,
    refinements: bool = True,
) -> ComplexResult:
    """Minimise ``fun`` over a box with Box's Complex method and the Complex-RF refinements.

    See the module docstring for the exact algorithm.

    Parameters
    ----------
    fun : callable
        ``fun(x, *args) -> float`` with ``x`` a float array of shape ``(n,)`` (a copy).
        NaN or infinite return values are treated as ``+inf``. Exceptions propagate.
    bounds : sequence of (lo, hi) pairs or scipy.optimize.Bounds
        Design domain; ``None`` or ``+-inf`` entries mean unbounded (then ``x0`` + ``spread``
        or ``initial`` must be given). ``lo == hi`` fixes a variable.
    args : tuple, optional
        Extra positional arguments for ``fun``.
    x0 : array_like, shape (n,), optional
        Start point (must lie within the bounds); it is point 0 of the initial complex.
    spread : float or array_like, shape (n,), optional
        Half-width of the uniform cloud around ``x0`` (absolute units, per variable).
        Requires ``x0``. Without it the other points are uniform over the bounds.
    initial : array_like, shape (k, n), optional
        Explicit initial complex (within the bounds). Mutually exclusive with ``x0``.
    n_points : int, optional
        Number of points ``k`` in the complex, ``k >= n + 1``. Default ``2 n + 1``
        (or the number of rows of ``initial``).
    alpha : float, default 1.3
        Reflection coefficient (> 0).
    max_retries : int, default 4
        Retractions before a still-worst point is re-initialised (>= 0).
    rfak : float, default 0.3
        Randomisation factor of the Complex-RF random terms (>= 0; 0 disables them).
    gamma : float, default 0.3
        Forgetting factor (>= 0; 0 disables forgetting).
    xtol : float, default 1e-6
        Tolerance on the relative spread of the complex in x.
    ftol : float, default 1e-9
        Tolerance on ``max f - min f``, relative and absolute: ``<= ftol * (1 + |f_min|)``.
    max_evals : int, default 10000
        Hard budget of evaluations (>= ``k``); ``nfev <= max_evals`` always.
    max_seconds : float, optional
        Wall-time budget, checked before every evaluation.
    seed : int or numpy.random.Generator, optional
        Source of all randomness.
    callback : callable, optional
        ``callback(x_best, f_best, nfev)``, called after the initial complex and after every
        iteration; returning ``True`` stops the optimisation.
    refinements : bool, default True
        ``False`` runs the textbook Box method (halfway towards the centroid only, no
        forgetting, no randomisation, no re-initialisation).

    Returns
    -------
    ComplexResult
        Best point and value, counters, stopping reason, history and final complex.

    Raises
    ------
    ValueError
        For inconsistent shapes, ``lo > hi``, points outside the bounds, ``n_points < n + 1``,
        ``max_evals < n_points``, invalid coefficients or a non-scalar objective value.
    """
    if not callable(fun):
        raise ValueError("fun must be callable")
    lo, hi = _parse_bounds(bounds)
    n = lo.size
    finite_box = bool(np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)))

    alpha = _check_positive("alpha", alpha, allow_zero=False)
    rfak = _check_positive("rfak", rfak, allow_zero=True)
    gamma = _check_positive("gamma", gamma, allow_zero=True)
    xtol = _check_positive("xtol", xtol, allow_zero=True)
    ftol = _check_positive("ftol", ftol, allow_zero=True)
    if max_seconds is not None:
        max_seconds = _check_positive("max_seconds", max_seconds, allow_zero=False)
    if isinstance(max_retries, bool) or int(max_retries) != max_retries or max_retries < 0:
        raise ValueError(f"max_retries must be an integer >= 0, got {max_retries!r}")
    max_retries = int(max_retries)

    rng = np.random.default_rng(seed)

    # ---------------------------------------------------------------- initial complex setup
    x0_arr: FloatArray | None = None
    init_arr: FloatArray | None = None
    if initial is not None:
        if x0 is not None or spread is not None:
            raise ValueError("give either initial or x0 (+ spread), not both")
        init_arr = np.array(initial, dtype=float)
        if init_arr.ndim != 2 or init_arr.shape[1] != n:
            raise ValueError(
                f"initial must have shape (n_points, {n}), got {np.shape(init_arr)}"
            )
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
        x0_arr = np.array(x0, dtype=float).reshape(-1) if np.ndim(x0) <= 1 else None
        if x0_arr is None or x0_arr.shape != (n,):
            raise ValueError(f"x0 must have shape ({n},), got {np.shape(x0)}")
        if not np.all(np.isfinite(x0_arr)):
            raise ValueError("x0 must be finite")
        if np.any(x0_arr < lo) or np.any(x0_arr > hi):
            raise ValueError("x0 lies outside the bounds")
    spread_arr: FloatArray | None = None
    if spread is not None:
        if x0_arr is None:
            raise ValueError("spread requires x0")
        spread_arr = np.broadcast_to(np.asarray(spread, dtype=float), (n,)).copy() \
            if np.ndim(spread) == 0 or np.shape(spread) == (n,) else None
        if spread_arr is None:
            raise ValueError(f"spread must be a scalar or have shape ({n},), got {np.shape(spread)}")
        if not np.all(np.isfinite(spread_arr)) or np.any(spread_arr < 0):
            raise ValueError("spread must be finite and >= 0")
    if init_arr is None and spread_arr is None and not finite_box:
        raise ValueError(
            "infinite bounds require an explicit initial complex or x0 together with spread"
        )

    if n_points is None:
        n_points = 2 * n + 1
    if isinstance(n_points, bool) or int(n_points) != n_points:
        raise ValueError(f"n_points must be an integer, got {n_points!r}")
    k = int(n_points)
    if k < n + 1:
        raise ValueError(f"n_points must be >= n + 1 = {n + 1}, got {k}")
    if isinstance(max_evals, bool) or int(max_evals) != max_evals or max_evals < k:
        raise ValueError(
            f"max_evals must be an integer >= n_points = {k}, got {max_evals!r}"
        )
    max_evals = int(max_evals)

    if init_arr is not None:
        points = init_arr.copy()
    else:
        points = np.empty((k, n))
        start = 0
        if x0_arr is not None:
            points[0] = x0_arr
            start = 1
        if spread_arr is not None and x0_arr is not None:
            u = rng.uniform(-1.0, 1.0, size=(k - start, n))
            points[start:] = np.clip(x0_arr + u * spread_arr, lo, hi)
        else:
            u = rng.uniform(0.0, 1.0, size=(k - start, n))
            points[start:] = lo + u * (hi - lo)

    # Per-variable scale used for spreads and random terms.
    x_ref = x0_arr if x0_arr is not None else points.mean(axis=0)
    width = hi - lo
    scale = np.where(
        np.isfinite(width) & (width > 0), width, np.maximum(1.0, np.abs(x_ref))
    )

    evaluate = _Evaluator(fun, tuple(args), max_evals, max_seconds, n)
    values = np.full(k, math.inf)
    nit = 0
    status: int | None = None
    n_done = 0
    try:
        for i in range(k):
            values[i] = evaluate(points[i])
            n_done = i + 1
    except _Stop as stop:
        status = stop.status

    if status is None:
        status = _iterate(
            evaluate=evaluate,
            points=points,
            values=values,
            lo=lo,
            hi=hi,
            scale=scale,
            alpha=alpha,
            max_retries=max_retries,
            rfak=rfak if refinements else 0.0,
            k_f=_forgetting_factor(alpha, gamma, k) if refinements else 0.0,
            refinements=refinements,
            xtol=xtol,
            ftol=ftol,
            rng=rng,
            callback=callback,
        )
        nit = status[1]
        status = status[0]
        n_done = k

    pop = points[:n_done].copy()
    pop_f = values[:n_done].copy()
    best_x = evaluate.best_x if evaluate.best_x is not None else evaluate.first_x.copy()
    history = np.asarray(evaluate.history, dtype=float).reshape(-1, 2)
    return ComplexResult(
        x=best_x,
        fun=evaluate.best_f,
        nfev=evaluate.nfev,
        nit=nit,
        success=status == STATUS_CONVERGED,
        status=status,
        message=_MESSAGES[status],
        history=history,
        population=pop,
        population_f=pop_f,
        x_spread=_relative_spread(pop, scale) if n_done else math.inf,
        f_spread=_f_spread(pop_f) if n_done else math.inf,
    )


def _iterate(
    *,
    evaluate: _Evaluator,
    points: FloatArray,
    values: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    scale: FloatArray,
    alpha: float,
    max_retries: int,
    rfak: float,
    k_f: float,
    refinements: bool,
    xtol: float,
    ftol: float,
    rng: np.random.Generator,
    callback: Callable[[FloatArray, float, int], Any] | None,
) -> tuple[int, int]:
    """Run the Complex iterations in place; return ``(status, nit)``."""
    k, n = points.shape
    eff = values.copy()  # effective (aged) values used for every comparison
    others = np.ones(k, dtype=bool)
    nit = 0

    def report() -> bool:
        if callback is None:
            return False
        x_best = evaluate.best_x if evaluate.best_x is not None else evaluate.first_x
        return bool(callback(x_best.copy(), evaluate.best_f, evaluate.nfev))

    if report():
        return STATUS_CALLBACK, nit
    try:
        while True:
            # Convergence on the raw complex.
            f_lo = float(values.min())
            if (
                _relative_spread(points, scale) <= xtol
                and _f_spread(values) <= ftol * (1.0 + abs(f_lo))
            ):
                return STATUS_CONVERGED, nit

            # (a) forgetting: age every effective value.
            if k_f > 0.0:
                finite = eff[np.isfinite(eff)]
                if finite.size >= 2:
                    eff += (finite.max() - finite.min()) * k_f

            # (b) reflection of the worst point through the centroid of the others.
            w = int(np.argmax(eff))
            others[:] = True
            others[w] = False
            rest = points[others]
            x_c = rest.mean(axis=0)
            b_local = int(np.argmin(eff[others]))
            x_b = rest[b_local]
            d = _relative_spread(rest, scale) if rfak > 0.0 else 0.0
            rest_eff_max = float(eff[others].max())

            x_new = x_c + alpha * (x_c - points[w])
            if rfak > 0.0:
                x_new = x_new + rfak * d * scale * (rng.random(n) - 0.5)
            x_new = np.clip(x_new, lo, hi)
            f_new = evaluate(x_new)
            points[w], values[w], eff[w] = x_new, f_new, f_new
            nit += 1

            # (c) retraction while the new point is still the worst; (d) re-initialisation.
            k_r = 0
            while f_new >= rest_eff_max:
                k_r += 1
                if k_r > max_retries:
                    if refinements:
                        x_new = rng.uniform(rest.min(axis=0), rest.max(axis=0))
                        x_new = np.clip(x_new, lo, hi)
                        f_new = evaluate(x_new)
                        points[w], values[w], eff[w] = x_new, f_new, f_new
                    break
                if refinements:
                    eps = _retraction_eps(k_r)
                    x_new = 0.5 * (x_new + eps * x_c + (1.0 - eps) * x_b)
                    if rfak > 0.0:
                        decay = N_R / (N_R + k_r - 1)
                        x_new = x_new + rfak * decay * d * scale * (rng.random(n) - 0.5)
                else:
                    x_new = 0.5 * (x_new + x_c)
                x_new = np.clip(x_new, lo, hi)
                f_new = evaluate(x_new)
                points[w], values[w], eff[w] = x_new, f_new, f_new

            if report():
                return STATUS_CALLBACK, nit
    except _Stop as stop:
        return stop.status, nit
