"""The distinct minima of a global search and the search's result (:class:`Search`): solves grouped
by MAP objective and standardised parameters, ranked so that the last digits of the arithmetic
never choose, the table, the waterfall's data and the advice on how many starts to try
(:mod:`kneenlp.estimation.search` runs the search)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kneenlp.estimation.fit import Fit
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.problem_file import MAX_STARTS
from kneenlp.prediction.predict import rms_by_coordinate

#: Two ends are one minimum when their MAP objectives differ by at most this share ...
SAME_OBJECTIVE = 1e-6


#: ... and no free parameter differs by more than this many prior sd.
SAME_PARAMETERS = 1e-2


#: Solves that should reach the lowest minimum before it is called found.
ENOUGH_HITS = 3


#: Relative MAP objective within which two ranked solves count as equal (the ranking then goes by
#: start index, so that the last digits of the arithmetic never choose).
TIE = 1e-9
#: Relative MAP objective within which a minimum competes with the lowest (:meth:`Search.competing`):
#: S192803's four lowest minima lie within 0.5 % and differ by 0.1 mm in their residual patterns,
#: and which of them ranks first turns on a borderline stability test of one trial.
COMPETING = 1e-2


@dataclass(frozen=True)
class Minimum:
    """One distinct minimum of a search: its lowest end and the solves that reached it."""

    fit: Fit
    #: labels of the solves that ended here (``start 3``, ``hop 2.1``)
    reached_by: tuple[str, ...]

    @property
    def objective(self) -> float:
        return self.fit.map_objective

    @property
    def hits(self) -> int:
        return len(self.reached_by)


@dataclass(frozen=True)
class Search:
    """What :func:`search` did: every start's screen, the ends, the distinct minima (lowest first)."""

    starts: int
    seed: int
    #: MAP objective of every start after its screen (NaN: its screen failed), in start order
    screened: np.ndarray
    #: every converged or failed end, labelled
    ends: list[tuple[str, Fit]] = field(repr=False)
    minima: list[Minimum] = field(repr=False)
    #: the outlier test's verdicts on the trials set aside inside the search (module docstring)
    outliers: tuple = ()
    #: what the outlier test could not test, in words
    notes: tuple[str, ...] = ()

    @property
    def set_aside(self) -> tuple[str, ...]:
        """The trials the outlier test set aside."""
        return tuple(o.trial for o in self.outliers)

    @property
    def best(self) -> Minimum:
        """The lowest minimum; without any (no solve converged) the best of the failed ends, reached by none."""
        if self.minima:
            return self.minima[0]
        fits = [f for _, f in self.ends]
        return Minimum(fits[ranked(fits)[0]], ())

    @property
    def found(self) -> bool:
        """The lowest minimum reached by at least :data:`ENOUGH_HITS` solves."""
        return self.best.hits >= ENOUGH_HITS

    def advice(self) -> str:
        """One line on whether the search may have missed the global MAP."""
        if not self.minima:
            return (f"none of its {len(self.ends)} solves converged: the fit kept is the best failed one (its "
                    "status says why)")
        if self.found:
            return (f"the lowest minimum was reached by {self.best.hits} solves (of {len(self.ends)}): the search "
                    "finds it repeatedly")
        return (f"the lowest minimum was reached by {self.best.hits} solve(s) only (fewer than {ENOUGH_HITS}): the "
                f"search may not have found the global MAP; try --starts {min(4 * self.starts, MAX_STARTS)}")

    def competing(self, within: float = COMPETING) -> list[Minimum]:
        """The minima whose MAP objective is within ``within`` (relative) of the lowest found, the
        best first: the answers a search on another machine may have ranked first."""
        if not self.minima:
            return [self.best]
        low = min(m.objective for m in self.minima)
        return [self.best] + [m for m in self.minima[1:] if m.objective <= low + within * abs(low)]

    def objectives(self) -> np.ndarray:
        """The MAP objective of every converged end, sorted (the waterfall's points)."""
        return np.sort([f.map_objective for _, f in self.ends if f.success])

    def records(self, held_out: list[float] | None = None) -> list[dict]:
        """The minima table as records (mm, deg): objective, solves that reached it, fitted RMS per
        coordinate, its distance from the lowest (largest, in prior sd) and, given, held-out error."""
        best = self.best.fit
        out = []
        for i, m in enumerate(self.minima):
            row = {"minimum": i + 1, "map_objective": m.objective, "hits": m.hits,
                   "distance_sd": parameter_distance(best, m.fit), "off_loading_path": list(m.fit.off_path),
                   "unstable": list(m.fit.unstable),
                   "rms": rms_by_coordinate(m.fit.data.q_user - m.fit.predicted_user)}
            if held_out is not None and i < len(held_out):
                row["held_out"] = held_out[i]
            out.append(row)
        return out

    def summary(self) -> dict:
        return {"starts": self.starts, "seed": self.seed, "solves": len(self.ends), "found": self.found,
                "advice": self.advice(), "set_aside": list(self.set_aside), "minima": self.records(),
                "objectives": [float(v) for v in self.objectives()]}

    def lines(self, limit: int = 6) -> list[str]:
        """The report's lines: the minima table (lowest first, up to ``limit``) and the advice."""
        header = (f"    {'minimum':>7} {'MAP objective':>14} {'reached by':>10} {'distance':>9} {'off path':>8} "
                  f"{'unstable':>8}   fitted RMS varus, internal (deg) | lateral, anterior, proximal (mm)")
        lines = [f"[[Global search]] {self.starts} starts (seed {self.seed}), {len(self.ends)} solves, "
                 f"{len(self.minima)} distinct minima", header]
        for row in self.records()[:limit]:
            rms = " ".join(f"{v:.2f}" for v in row["rms"].values())
            lines.append(f"    {row['minimum']:>7} {row['map_objective']:>14.4f} {row['hits']:>10} "
                         f"{row['distance_sd']:>6.2f} sd {len(row['off_loading_path']):>8} "
                         f"{len(row['unstable']):>8}   {rms}")
        if len(self.minima) > limit:
            lines.append(f"    ... {len(self.minima) - limit} more (--json lists them all)")
        lines += [f"    {self.advice()}",
                  "    (off path: trials whose fitted equilibrium predict does not reach by loading from the unloaded "
                  "state; unstable: trials at an unstable equilibrium; minima with neither rank first, unstable last)"]
        return lines


def parameter_distance(a: Fit, b: Fit) -> float:
    """Largest difference of a free parameter between two fits of one problem, in prior sd (the
    parameter's scale where it has no prior)."""
    return float(np.max(np.abs(standardised(a.problem, a.params) - standardised(a.problem, b.params)), initial=0.0))


def standardised(problem: IdentificationProblem, values: dict[str, float]) -> np.ndarray:
    """The free parameters of ``values`` in prior sd from the prior's centre (``z``); a parameter
    without a prior in units of its scale."""
    out = []
    for name, scale in zip(problem.free, problem.scales, strict=True):
        prior = problem.priors.get(name)
        out.append(float(prior.z(values[name])) if prior is not None else values[name] / scale)
    return np.array(out)


def from_standardised(problem: IdentificationProblem, z: np.ndarray) -> dict[str, float]:
    """:func:`standardised` inverted, clipped to the problem's bounds."""
    out = {}
    for i, (name, scale) in enumerate(zip(problem.free, problem.scales, strict=True)):
        prior = problem.priors.get(name)
        value = prior.untransform(prior.centre + prior.sd * z[i]) if prior is not None else z[i] * scale
        out[name] = float(np.clip(value, problem.lower[i], problem.upper[i]))
    return out


def ranked(fits: list[Fit], screened: bool = False) -> list[int]:
    """Indices of ``fits`` by MAP objective, lowest first (ties within :data:`TIE` by index): the
    converged ones with every trial at a stable equilibrium, first those with every trial on the
    loading path, then those with trials off it; then those with an unstable trial; then the rest;
    of ``screened`` fits (stopped on purpose) every one at equilibrium counts as converged."""
    def key(i: int) -> tuple[bool, bool, bool, float, int]:
        f = fits[i]
        usable = (f.max_residual <= f.problem.equilibrium_tol) if screened else f.success
        value = f.map_objective if usable and np.isfinite(f.map_objective) else np.inf
        return (*standing(f, usable), rounded(value), i)
    return sorted(range(len(fits)), key=key)


def standing(f: Fit, usable: bool) -> tuple[bool, bool, bool]:
    """What ranks a fit before its objective (:func:`ranked`, :func:`_better`): not usable, a trial
    at an unstable equilibrium, a trial off the loading path (each False first)."""
    return not usable, bool(f.unstable), bool(f.off_path)


def rounded(value: float) -> float:
    """``value`` to :data:`TIE` relative (ranks made on it do not turn on the last digits)."""
    if not np.isfinite(value) or value == 0:
        return value
    digits = int(-np.floor(np.log10(TIE))) - int(np.floor(np.log10(abs(value))))
    return round(value, digits)


def distinct_minima(ends: list[tuple[str, Fit]]) -> list[Minimum]:
    """The converged ends grouped into minima (module docstring), lowest first."""
    converged = [(label, f) for label, f in ends if f.success]
    order = ranked([f for _, f in converged])
    groups: list[list[tuple[str, Fit]]] = []
    for i in order:
        label, f = converged[i]
        for group in groups:
            head = group[0][1]
            if (abs(f.map_objective - head.map_objective) <= SAME_OBJECTIVE * abs(head.map_objective)
                    and parameter_distance(head, f) <= SAME_PARAMETERS):
                group.append((label, f))
                break
        else:
            groups.append([(label, f)])
    return [Minimum(g[0][1], tuple(label for label, _ in g)) for g in groups]
