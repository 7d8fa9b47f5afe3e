r"""Box's Complex method with the Complex-RF refinements (bound constrained, derivative free).

A standalone minimiser for expensive black-box objectives on a box-shaped design domain. The
objective may be non-smooth, may return large penalty values and may be undefined (NaN) in
parts of the domain. The only dependency is numpy.

Notation
--------
``n`` design variables, a *complex* of ``k >= n + 1`` points (default ``k = 2 n + 1``, e.g. 17
for 8 variables), bounds ``lo <= x <= hi``. Each variable has a *scale* ``s_j``, used to
compare spreads between variables: ``s_j = hi_j - lo_j`` when this is finite and positive,
otherwise ``max(1, |x_ref_j|)``, where ``x_ref`` is ``x0`` or the mean of the initial cloud. For a
set of points, ``spread_j = max_i x_ij - min_i x_ij`` and the *relative spread* is
``d = max_j spread_j / s_j``.

Algorithm
---------
1. **Initial complex.** ``k`` points, all randomness taken from ``seed``:

   * ``initial``: this ``(k, n)`` cloud is used as given (it must lie within the bounds);
   * ``x0`` with ``spread``: ``x0`` is point 0, and the other ``k - 1`` points are
     ``x0 + U(-spread, +spread)`` per variable, clipped to the bounds;
   * ``x0`` alone: ``x0`` plus ``k - 1`` points drawn uniformly over the bounds;
   * nothing: ``k`` points drawn uniformly over the bounds (the bounds must be finite).

   Every point is evaluated. A NaN or +-inf value is stored as ``+inf`` (the worst possible).

2. **Iterations.** One iteration is one reflection followed by its retractions.

   a. *Forgetting* (Complex-RF). Every point has its raw value ``f_i`` and an *effective* value
      ``g_i``, and every comparison uses ``g``. A newly evaluated point starts with
      ``g = f``. At the start of each iteration all effective values are aged (Krus &
      Andersson 2003, as in Andersson's reference ``complexrf.m``)::

          g_i <- g_i + (max_j g_j - min_j g_j) * K_f,   K_f = 1 - (alpha / 2) ** (gamma / k)

      The max and min are taken over the finite ``g_j``. ``K_f`` is clamped at 0, so there is
      no forgetting when ``alpha >= 2``. A point that has survived ``a`` iterations therefore
      compares as ``f_i`` plus ``K_f`` times the sum of the ``a`` ranges seen since it entered.
      Old points, possibly lucky ones, slowly look worse than fresh points, and the complex
      cannot settle on one old point. With the defaults (alpha 1.3, gamma 0.3, k 17),
      ``K_f = 0.0076``.

   b. *Reflection* (Box 1965). ``x_w`` is the point with the largest ``g``. ``x_c`` is the
      centroid of the other ``k - 1`` points, and ``x_b`` the point with the smallest ``g``::

          x_new = x_c + alpha * (x_c - x_w)                                   (alpha = 1.3)

      ``x_new`` is brought inside the bounds (see *Bounds* below), evaluated, and replaces
      ``x_w``, with raw and effective value ``f_new``.

   c. *Retraction.* While the new point is still the worst, i.e. ``f_new >= max g`` over the
      other points, it is moved again. ``k_r = 1, 2, ...`` counts the retries and
      ``n_r = 4``::

          eps   = (n_r / (n_r + k_r - 1)) ** ((n_r + k_r - 1) / n_r)      # 1, .76, .54, .39
          x_new = (x_new + eps * x_c + (1 - eps) * x_b) / 2  +  r

      The first retraction is Box's "halfway towards the centroid". After each further
      failure the target moves from the centroid towards the best point (Krus & Andersson
      2003). ``r`` is the Complex-RF random term. It is scaled by the spread of the complex,
      shaped like it, and decays with the retries::

          r = rfak * eps / sqrt(k - 1) * sum_i xi_i * (x_i - x_c),   xi_i ~ U(-1, 1)

      The sum runs over the ``k - 1`` other points, so ``cov(r) = (rfak * eps)**2 / 3``
      times the covariance matrix of those points. The noise follows the shape of the complex,
      e.g. it stays along a narrow valley. An axis-aligned term sized by the largest spread
      (the ``complexrf.m`` form) needed 10-15 times more evaluations on an 8-D Rosenbrock.
      The retracted point is brought inside the bounds, evaluated, and replaces the previous
      one.

   d. *Re-initialisation.* If the point is still the worst after ``max_retries`` (default 4)
      retractions, it is replaced by a random point ``x_c + w * (U(0, 1) - 1/2)`` per variable,
      where ``w_j = max(spread_j, d * s_j)`` is computed from the other points. The point is
      drawn around the current complex, in a box at least as wide, relative to ``s``, as its
      widest variable. A variable whose spread has collapsed is therefore re-expanded. The
      point is evaluated and accepted whatever its value, and the next iteration starts.

   *Bounds.* Clipping a reflected point onto a bound makes the complex collapse onto that
   face: on the 2-D Rosenbrock function in ``[-5, 5]^2``, one seed in ten converged to
   ``(-2.234, 5)`` with ``f = 10.5``. The refined method therefore places each violating
   coordinate uniformly between the centroid and the violated bound::

       x_j <- x_c,j + U(0, 1) * (bound_j - x_c,j)

   A point still converges onto a bound when the optimum lies there, because ``x_c`` then
   approaches the bound.

   ``refinements=False`` runs the textbook method (Box 1965) instead: no forgetting, no random
   terms, points are clipped to the bounds, and each retraction only moves halfway towards
   the centroid (``x_new = (x_new + x_c) / 2``). After ``max_retries`` retractions the last
   point is kept, without re-initialisation. This variant tends to collapse onto the centroid
   and stall. It is provided for comparison.

3. **Stopping.** The tests are made before each iteration, and the budgets before each
   evaluation:

   * converged (``success=True``, status 0): ``d <= xtol`` for the whole complex **and**
     ``max_i f_i - min_i f_i <= ftol * (1 + |min_i f_i|)`` on the raw values of the complex;
   * ``max_evals`` evaluations reached (status 1). This limit is never exceeded:
     ``nfev <= max_evals``;
   * ``max_seconds`` of wall time elapsed (status 2);
   * ``callback`` returned ``True`` (status 3).

   The result is the best point ever evaluated (by raw value). Because of forgetting, that
   point may no longer be in the complex.

All randomness comes from a single ``numpy.random.Generator`` built from ``seed``. For a
deterministic objective, the sequence of evaluated points is fully reproducible.

References
----------
M. J. Box, "A new method of constrained optimization and a comparison with other methods",
The Computer Journal 8(1):42-52, 1965.

P. Krus and J. Andersson, "Optimizing optimization for design optimization", Proc. ASME Design
Engineering Technical Conferences (DETC 2003), Chicago, 2003.

J. Andersson, ``complexrf.m``, reference MATLAB implementation of Complex-RF, Linkoping
University, 2003.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import OptimizeResult

from kneenlp.base.keywords import keyword_options
from kneenlp.solvers.boxcomplex_inputs import ComplexOptions, Options, Start, as_float, as_int, parse_bounds

__all__ = [
    "RESULT_FIELDS",
    "STATUS_CALLBACK",
    "STATUS_CONVERGED",
    "STATUS_MAX_EVALS",
    "STATUS_MAX_SECONDS",
    "forgetting_factor",
    "minimize_complex",
    "retraction_eps",
]

FloatArray = NDArray[np.float64]

#: Constant ``n_r`` of the Complex-RF retraction schedule (Krus & Andersson 2003).
N_R = 4

STATUS_CONVERGED = 0
STATUS_MAX_EVALS = 1
STATUS_MAX_SECONDS = 2
STATUS_CALLBACK = 3

_MESSAGES = {
    STATUS_CONVERGED: "converged: spread of the complex in x <= xtol and in f <= ftol",
    STATUS_MAX_EVALS: "maximum number of function evaluations (max_evals) reached",
    STATUS_MAX_SECONDS: "wall-time budget (max_seconds) exhausted",
    STATUS_CALLBACK: "stopped by callback",
}


#: Fields of the :class:`scipy.optimize.OptimizeResult` that :func:`minimize_complex` returns.
RESULT_FIELDS = ("x", "fun", "nfev", "nit", "success", "status", "message", "history", "population",
                 "population_f", "x_spread", "f_spread")


class _Stop(Exception):
    """Internal signal that a budget is exhausted."""

    def __init__(self, status: int) -> None:
        super().__init__(status)
        self.status = status


class _Evaluator:
    """Call the objective, enforce the budgets, sanitise values and record the history."""

    def __init__(
        self,
        fun: Callable[..., Any],
        args: tuple[Any, ...],
        max_evals: int,
        max_seconds: float | None,
    ) -> None:
        self.fun = fun
        self.args = args
        self.max_evals = max_evals
        self.deadline = None if max_seconds is None else time.monotonic() + max_seconds
        self.nfev = 0
        self.best_f = math.inf
        self.best_x: FloatArray | None = None
        self.history: list[tuple[float, float]] = []

    def __call__(self, x: FloatArray) -> float:
        if self.nfev >= self.max_evals:
            raise _Stop(STATUS_MAX_EVALS)
        if self.deadline is not None and time.monotonic() >= self.deadline:
            raise _Stop(STATUS_MAX_SECONDS)
        value = self.fun(x.copy(), *self.args)
        self.nfev += 1
        f = as_float(value)
        if self.best_x is None or f < self.best_f:
            self.best_f = f
            self.best_x = x.copy()
        self.history.append((float(self.nfev), self.best_f))
        return f

    def result(self, population: _Population, nit: int, status: int, scale: FloatArray) -> OptimizeResult:
        """The result of a run (fields :data:`RESULT_FIELDS`) ending with ``population`` after ``nit``
        iterations."""
        pop, pop_f = population.points, population.values
        n_done = pop.shape[0]
        best_x = self.best_x.copy() if self.best_x is not None else pop[0].copy()
        history = np.asarray(self.history, dtype=float).reshape(-1, 2)
        return OptimizeResult(
            x=best_x,
            fun=self.best_f,
            nfev=self.nfev,
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


@dataclass(frozen=True)
class _Population:
    """The complex: its ``(k, n)`` points and their ``(k,)`` raw values (non-finite ones ``inf``),
    updated in place by the iterations."""

    points: FloatArray
    values: FloatArray

    def first(self, n: int) -> _Population:
        """A copy of the first ``n`` points and values."""
        return _Population(self.points[:n].copy(), self.values[:n].copy())


@dataclass(frozen=True)
class _Box:
    """The design domain ``lo <= x <= hi`` and the per-variable scales ``s_j`` that compare spreads
    (module docstring, *Notation*)."""

    lo: FloatArray
    hi: FloatArray
    scale: FloatArray


def forgetting_factor(alpha: float, gamma: float, k: int) -> float:
    """Return ``K_f = max(0, 1 - (alpha / 2) ** (gamma / k))`` (Krus & Andersson 2003)."""
    return max(0.0, 1.0 - (alpha / 2.0) ** (gamma / k))


def retraction_eps(k_r: int, n_r: int = N_R) -> float:
    """Return the centroid weight ``eps = (n_r / (n_r + k_r - 1)) ** ((n_r + k_r - 1) / n_r)``."""
    m = n_r + k_r - 1
    return (n_r / m) ** (m / n_r)


def _relative_spread(points: FloatArray, scale: FloatArray) -> float:
    """Return ``max_j (max_i x_ij - min_i x_ij) / s_j``."""
    return float(np.max(np.ptp(points, axis=0) / scale))


def _f_spread(values: FloatArray) -> float:
    hi = float(values.max())
    return hi - float(values.min()) if math.isfinite(hi) else math.inf


def minimize_complex(fun: Callable[..., Any], bounds: Sequence[tuple[float | None, float | None]] | Any,
                     **options: Any) -> OptimizeResult:
    """Minimise ``fun`` over a box with Box's Complex method and the Complex-RF refinements.

    The exact algorithm is described in the module docstring. The keyword options (``args`` to
    ``refinements``) are checked in one place (:class:`ComplexOptions`); an unknown name raises ``TypeError``.

    Parameters
    ----------
    fun : ``fun(x, *args) -> float``, ``x`` a copy of a float array of shape ``(n,)``. NaN or
        infinite values are treated as ``+inf``; exceptions propagate to the caller.
    bounds : sequence of (lo, hi) pairs or scipy.optimize.Bounds. A ``None`` or infinite entry means
        unbounded (``x0`` with ``spread``, or ``initial``, is then required); ``lo == hi`` fixes a variable.
    args : extra positional arguments passed to ``fun``.
    x0 : start point, shape (n,), within the bounds: point 0 of the initial complex.
    spread : half-width of the uniform cloud around ``x0``, per variable (float or shape (n,)), in
        the units of ``x``; requires ``x0``. Without it the other points are uniform over the bounds.
    initial : explicit initial complex, shape (k, n), within the bounds; not combined with ``x0``.
    n_points : number of points ``k >= n + 1`` (default ``2 n + 1``, or the rows of ``initial``).
    alpha : reflection coefficient (> 0).
    max_retries : retractions before a point that is still the worst is re-initialised (>= 0).
    rfak : randomisation factor of the Complex-RF random term (>= 0; 0 disables it).
    gamma : forgetting factor (>= 0; 0 disables forgetting).
    xtol : tolerance on the relative spread of the complex in x.
    ftol : tolerance on ``max f - min f``, relative and absolute: ``<= ftol * (1 + |f_min|)``.
    max_evals : hard evaluation budget (>= ``k``); ``nfev <= max_evals`` always holds.
    max_seconds : wall-time budget (s), checked before every evaluation.
    seed : int or numpy.random.Generator, the source of all randomness.
    callback : ``callback(x_best, f_best, nfev)``, called after the initial complex and after each
        iteration; returning ``True`` stops the optimisation.
    refinements : ``False`` runs the textbook Box method: halfway towards the centroid only, clipping
        to the bounds, no forgetting, no randomisation and no re-initialisation.

    Returns
    -------
    scipy.optimize.OptimizeResult with the fields :data:`RESULT_FIELDS`: ``x`` (n,), the best point
    ever evaluated, and ``fun``, its value (``inf`` if no finite value was ever obtained); ``nfev``
    (always ``<= max_evals``) and ``nit`` (iterations, i.e. reflections); ``success``, the
    convergence criterion (``xtol`` and ``ftol``) met; ``status`` 0 converged, 1 ``max_evals``
    reached, 2 ``max_seconds`` elapsed, 3 stopped by callback, and ``message``, the reason in words;
    ``history`` (nfev, 2), one row ``(evaluation number, best f so far)`` per evaluation;
    ``population`` (k, n), the final complex (only the evaluated points if a budget ran out during
    initialisation), and ``population_f`` (k,), its raw values (non-finite ones stored as ``inf``);
    ``x_spread``, its relative spread ``max_j (max_i x_ij - min_i x_ij) / s_j``, and ``f_spread``,
    ``max f - min f`` (``inf`` if any value is infinite).

    Raises
    ------
    ValueError
        For inconsistent shapes, ``lo > hi``, points outside the bounds, ``n_points < n + 1``,
        ``max_evals < n_points``, invalid coefficients or a non-scalar objective value.
    """
    given = keyword_options(ComplexOptions, "minimize_complex", options)
    if not callable(fun):
        raise ValueError("fun must be callable")
    lo, hi = parse_bounds(bounds)
    checked = Options.checked(given)
    start = Start.checked(lo, hi, given)
    max_evals = as_int("max_evals", given.max_evals, start.k)
    rng = np.random.default_rng(given.seed)
    points = start.points(lo, hi, rng)
    x_ref = start.x0 if start.x0 is not None else points.mean(axis=0)
    width = hi - lo
    box = _Box(lo, hi, np.where(np.isfinite(width) & (width > 0), width, np.maximum(1.0, np.abs(x_ref))))
    evaluate = _Evaluator(fun, tuple(given.args), max_evals, checked.max_seconds)
    population = _Population(points, np.full(start.k, math.inf))
    n_done, status = _evaluate_initial(evaluate, population)
    nit = 0
    if status is None:
        optimizer = _ComplexIterations(evaluate, population, box, checked, rng)
        status = optimizer.run()
        nit = optimizer.nit
    return evaluate.result(population.first(n_done), nit, status, box.scale)


def _evaluate_initial(evaluate: _Evaluator, population: _Population) -> tuple[int, int | None]:
    """Evaluate the initial complex in order into its ``values``; return how many points were
    evaluated and the status if a budget ran out (None otherwise)."""
    points, values = population.points, population.values
    n_done = 0
    try:
        for i in range(points.shape[0]):
            values[i] = evaluate(points[i])
            n_done = i + 1
    except _Stop as stop:
        return n_done, stop.status
    return n_done, None


class _ComplexIterations:
    """State and main loop of the iterations; updates ``points`` and ``values`` in place."""

    def __init__(self, evaluate: _Evaluator, population: _Population, box: _Box, options: Options,
                 rng: np.random.Generator) -> None:
        refinements = options.refinements
        points = population.points
        self.evaluate = evaluate
        self.points = points
        self.values = population.values
        self.eff = population.values.copy()  # effective (aged) values, used for every comparison
        self.lo = box.lo
        self.hi = box.hi
        self.scale = box.scale
        self.alpha = options.alpha
        self.max_retries = options.max_retries
        self.rfak = options.rfak if refinements else 0.0
        k_f = forgetting_factor(options.alpha, options.gamma, points.shape[0])
        self.k_f = k_f if refinements else 0.0
        self.refinements = refinements
        self.xtol = options.xtol
        self.ftol = options.ftol
        self.rng = rng
        self.callback = options.callback
        self.nit = 0

    # -- helpers -------------------------------------------------------------------------
    def _converged(self) -> bool:
        values = self.values
        f_min = float(values.min())
        if not _f_spread(values) <= self.ftol * (1.0 + abs(f_min)):
            return False
        return _relative_spread(self.points, self.scale) <= self.xtol

    def _age(self) -> None:
        eff = self.eff
        finite = eff[np.isfinite(eff)]
        if finite.size >= 2:
            eff += (float(finite.max()) - float(finite.min())) * self.k_f

    def _into_bounds(self, x: FloatArray, x_c: FloatArray) -> FloatArray:
        lo, hi = self.lo, self.hi
        if not self.refinements:
            return np.clip(x, lo, hi)
        below = x < lo
        above = x > hi
        bad = below | above
        if bad.any():
            x = x.copy()
            target = np.where(below, lo, hi)[bad]
            x[bad] = x_c[bad] + self.rng.random(int(bad.sum())) * (target - x_c[bad])
            x = np.clip(x, lo, hi)  # guards against rounding
        return x

    def _replace(self, w: int, x: FloatArray) -> float:
        f = self.evaluate(x)
        self.points[w] = x
        self.values[w] = f
        self.eff[w] = f
        return f

    def _notify(self) -> bool:
        if self.callback is None:
            return False
        ev = self.evaluate
        x_best = ev.best_x if ev.best_x is not None else self.points[0]
        return bool(self.callback(x_best.copy(), ev.best_f, ev.nfev))

    # -- main loop -----------------------------------------------------------------------
    def run(self) -> int:
        """Iterate until a stopping criterion holds; return the status code."""
        if self._notify():
            return STATUS_CALLBACK
        try:
            while True:
                if self._converged():
                    return STATUS_CONVERGED
                self._iteration()
                if self._notify():
                    return STATUS_CALLBACK
        except _Stop as stop:
            return stop.status

    def _iteration(self) -> None:
        points, eff = self.points, self.eff
        k, n = points.shape
        if self.k_f > 0.0:
            self._age()

        # (b) reflect the worst point through the centroid of the others.
        w = int(np.argmax(eff))
        rest = np.delete(points, w, axis=0)
        rest_eff = np.delete(eff, w)
        x_c = rest.sum(axis=0) / (k - 1)
        x_b = rest[int(np.argmin(rest_eff))]
        rest_eff_max = float(rest_eff.max())

        x_new = self._into_bounds(x_c + self.alpha * (x_c - points[w]), x_c)
        f_new = self._replace(w, x_new)
        self.nit += 1

        # (c) retract while still the worst; (d) re-initialise after max_retries failures.
        k_r = 0
        while f_new >= rest_eff_max:
            k_r += 1
            if k_r > self.max_retries:
                if self.refinements:
                    spread = np.ptp(rest, axis=0)
                    width = np.maximum(spread, float(np.max(spread / self.scale)) * self.scale)
                    x_new = self._into_bounds(x_c + width * (self.rng.random(n) - 0.5), x_c)
                    self._replace(w, x_new)
                return
            if self.refinements:
                eps = retraction_eps(k_r)
                x_new = 0.5 * (x_new + eps * x_c + (1.0 - eps) * x_b)
                if self.rfak > 0.0:
                    xi = self.rng.uniform(-1.0, 1.0, size=k - 1)
                    x_new = x_new + (self.rfak * eps / math.sqrt(k - 1)) * (xi @ (rest - x_c))
            else:
                x_new = 0.5 * (x_new + x_c)
            x_new = self._into_bounds(x_new, x_c)
            f_new = self._replace(w, x_new)
