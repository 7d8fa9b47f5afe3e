"""Priors of model parameters: what is known of a parameter before the data (normal or log-normal).

A :class:`Prior` is centred on a value in SI (the mean of a normal, the median of a log-normal)
with a width (a normal's standard deviation in SI; a log-normal's standard deviation of the
natural logarithm, dimensionless).  Its one job is the standardised residual :meth:`Prior.z`,
``(value - mean) / sd`` or ``(ln value - ln median) / sd``: minus twice the log prior density is
``z^2`` plus a constant, so a maximum a-posteriori (MAP) fit adds ``noise variance x z^2`` per
parameter to the weighted sum of squares it minimises (:mod:`kneenlp.experiment.problem`).  The
same :meth:`Prior.z` serves NumPy values and CasADi symbols, so the NLP's prior term and the
reduced-space fit's are one function.

Defaults come from the parameter's kind or element (:attr:`kneenlp.model.parameters.Kind.prior`,
:attr:`kneenlp.model.parameters.Parameter.prior`) centred on the knee's own value: an imported
knee's source values are its prior means (docs/priors.md names each width's literature source).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

SHAPES = ("normal", "lognormal")
#: A log-normal prior keeps its parameter above ``median * exp(-LOGNORMAL_FLOOR * sd)``: the log
#: needs a positive value, and below that the prior's density is < 1e-15 of its peak.
LOGNORMAL_FLOOR = 8.0
#: Probability inside :meth:`Prior.interval` by default: the normal's +-3 sd.
RANGE_LEVEL = 0.9973


@dataclass(frozen=True)
class Prior:
    """A normal (``mean``, ``sd`` in SI) or log-normal (``mean`` the median in SI, ``sd`` that of
    ``ln value``) prior of one parameter; ``source`` says where it came from (``default``,
    a file's path, ``api``)."""

    shape: str
    mean: float
    sd: float
    source: str = "default"

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f"unknown prior shape {self.shape!r}; known: {', '.join(SHAPES)}")
        if not (math.isfinite(self.sd) and self.sd > 0):
            raise ValueError(f"prior sd must be > 0, got {self.sd!r}")
        if self.shape == "lognormal" and not self.mean > 0:
            raise ValueError(f"a log-normal prior needs a positive median, got {self.mean!r}")

    @property
    def log(self) -> bool:
        return self.shape == "lognormal"

    @property
    def centre(self) -> float:
        """The centre of :meth:`z`'s transform: the mean, or the log of the median."""
        return math.log(self.mean) if self.log else self.mean

    def transform(self, value):
        """``ln value`` (log-normal) or ``value`` (normal), for floats, arrays and CasADi symbols."""
        if not self.log:
            return value
        return ca.log(value) if isinstance(value, ca.SX | ca.MX | ca.DM) else np.log(value)

    def untransform(self, x):
        """The value (SI) whose :meth:`transform` is ``x`` (floats and arrays)."""
        return np.exp(x) if self.log else x

    def z(self, value):
        """The standardised residual of ``value`` (SI): ``(transform(value) - centre) / sd``."""
        return (self.transform(value) - self.centre) / self.sd

    def sample(self, rng: np.random.Generator, size: int | None = None):
        """Draws (SI) from the prior: ``mean + sd N(0, 1)``, or ``exp(ln median + sd N(0, 1))``."""
        return self.untransform(self.centre + self.sd * rng.standard_normal(size))

    def interval(self, level: float = RANGE_LEVEL) -> tuple[float, float]:
        """The central interval (SI) holding ``level`` of the prior (default +-3 sd)."""
        from scipy import stats

        half = float(stats.norm.ppf(0.5 + level / 2)) * self.sd
        lo, hi = self.centre - half, self.centre + half
        return (math.exp(lo), math.exp(hi)) if self.log else (lo, hi)

    def floor(self) -> float:
        """The smallest value a log-normal prior allows a fit (:data:`LOGNORMAL_FLOOR`); -inf for a normal."""
        return self.mean * math.exp(-LOGNORMAL_FLOOR * self.sd) if self.log else -math.inf

    def describe(self, to_user: float, unit: str) -> str:
        """The prior in words, in the display unit (``to_user`` times SI)."""
        if self.log:
            return f"log-normal, median {self.mean * to_user:.4g} {unit}, sd of ln {self.sd:.3g}"
        return f"normal, mean {self.mean * to_user:.4g} {unit}, sd {self.sd * to_user:.4g} {unit}"

    def record(self, to_user: float, unit: str) -> dict:
        """The prior in the display unit, for JSON and parameter files."""
        if self.log:
            return {"distribution": "lognormal", "median": self.mean * to_user, "sd_log": self.sd, "unit": unit}
        return {"distribution": "normal", "mean": self.mean * to_user, "sd": self.sd * to_user, "unit": unit}
