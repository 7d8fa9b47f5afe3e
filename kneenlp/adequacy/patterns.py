"""Where a fit fails, as patterns a researcher acts on ("internal rotation: model above the
measurement in all 6 trials at 0 deg flexion"), not only the worst cells.

Residuals in units of the noise standard deviation, ``z`` (T x 5), are grouped per coordinate by
flexion angle, by load direction, by both, and over all trials.  Under the noise alone the group
sum of ``n`` values over ``sqrt(n)`` is standard normal; a group is a pattern when that exceeds
``threshold`` (default 4, few false patterns over the ~100 groups of a protocol) and at least
80 % of its residuals share the sign.  Patterns are listed strongest first, a group dropped when
a stronger one of the same coordinate and sign already contains it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from kneenlp.base.conventions import COORDINATE_UNITS, COORDINATES
from kneenlp.experiment.protocol import Trial, flexion_groups

#: |sum z| / sqrt(n) above which a group of residuals is a pattern.
THRESHOLD = 4.0
#: Share of a group's residuals that must have the group's sign.
SAME_SIGN = 0.8


@dataclass(frozen=True)
class Pattern:
    """A group of trials in which one coordinate's residuals lean one way."""

    coordinate: str
    where: str  # e.g. "at 0 deg flexion", "under anterior load at 30 deg flexion", "in every trial"
    trials: frozenset[int]
    mean: float  # mean residual, mm or deg (model minus measured)
    same_sign: int
    strength: float  # |sum z| / sqrt(n)

    @property
    def unit(self) -> str:
        """mm or deg."""
        return COORDINATE_UNITS[COORDINATES.index(self.coordinate)]

    def mean_of(self, residuals: np.ndarray) -> float:
        """This pattern's mean in other residuals of the same trials (T x 5, mm and deg): the same
        group at another minimum of the fit."""
        return float(np.mean(np.asarray(residuals)[sorted(self.trials), COORDINATES.index(self.coordinate)]))

    def words(self) -> str:
        n = len(self.trials)
        unit = self.unit
        side = "above" if self.mean > 0 else "below"
        count = f"all {n}" if self.same_sign == n else f"{self.same_sign} of {n}"
        return (f"{self.coordinate.replace('_', ' ')}: model {side} the measurement in {count} trials {self.where} "
                f"(mean {self.mean:+.2f} {unit})")


def _groups(trials: Sequence[Trial]) -> list[tuple[str, list[int]]]:
    """Groups by nominal flexion (measured flexions grouped, :func:`flexion_groups`) and by the
    dominant load direction (a measured load has all six components)."""
    def load(t: Trial) -> str:
        return "unloaded" if t.dominant == "none" else f"under {t.dominant} load"

    def at(f: float) -> str:
        return f"at {f:g} deg flexion" if f == round(f, 6) else f"at {f:.0f} deg flexion"

    out: dict[str, list[int]] = {"in every trial": list(range(len(trials)))}
    for i, (t, f) in enumerate(zip(trials, flexion_groups(trials), strict=True)):
        out.setdefault(at(f), []).append(i)
        out.setdefault(load(t), []).append(i)
        out.setdefault(f"{load(t)} {at(f)}", []).append(i)
    return [(k, v) for k, v in out.items() if len(v) >= 2]


def failure_patterns(trials: Sequence[Trial], residuals: np.ndarray, sigma: float, *,
                     threshold: float = THRESHOLD, limit: int = 4) -> list[Pattern]:
    """The strongest ``limit`` patterns of ``residuals`` (T x 5, mm and deg, model minus
    measured) against noise sd ``sigma`` (see module docstring)."""
    z = np.asarray(residuals, float) / sigma
    found: list[Pattern] = []
    for where, idx in _groups(trials):
        for j, coord in enumerate(COORDINATES):
            zz = z[idx, j]
            strength = abs(zz.sum()) / np.sqrt(len(zz))
            sign = np.sign(zz.sum())
            same = int(np.sum(np.sign(zz) == sign))
            if strength > threshold and same >= SAME_SIGN * len(zz):
                found.append(Pattern(coord, where, frozenset(idx), float(np.mean(residuals[idx, j])), same,
                                     float(strength)))
    found.sort(key=lambda p: -p.strength)
    kept: list[Pattern] = []
    for p in found:
        if any(k.coordinate == p.coordinate and np.sign(k.mean) == np.sign(p.mean) and p.trials <= k.trials
               for k in kept):
            continue
        kept.append(p)
    return kept[:limit]
