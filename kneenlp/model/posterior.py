"""A parameter set's posterior: what a calibration knows about the values it fitted.

A calibration writes it into ``calibrated.toml`` beside the values (``[posterior]``), so that
``kneenlp predict --parameters calibrated.toml`` can say how far to trust a prediction
(:func:`~kneenlp.prediction.predict.predict`: the covariance carried through each trial's
equilibrium, plus the measurement noise).  It is the Laplace approximation: a normal about the
fitted values with the Gauss-Newton covariance of the MAP problem, priors included
(:meth:`~kneenlp.estimation.fit.Fit.with_prior_rows`).

In the file, display units (those of ``[values]``)::

    [posterior]
    method = "laplace"
    parameters = ["ACLam.k_scale", "registration.varus_rotation", ...]
    units = ["1", "deg", ...]
    covariance = [[...], ...]          # units[i] * units[j]
    noise_sd = [0.9, 1.1, 1.2, 1.3, 0.8]   # deg, deg, mm, mm, mm: varus, internal, lateral, anterior, proximal

A direction nothing determined has an infinite variance (``inf``): its predictions have no band.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from kneenlp.base.conventions import coordinate_columns
from kneenlp.base.errors import InputError

if TYPE_CHECKING:
    from kneenlp.model.parameter_schema import PosteriorTable

#: Largest relative asymmetry, and most negative eigenvalue relative to the largest, of a
#: covariance read from a file.
SYMMETRY_TOL = 1e-6


@dataclass(frozen=True)
class Posterior:
    """Normal posterior of named parameters (SI) about a parameter set's values, with the noise sd
    (deg, deg, mm, mm, mm) of the measurements the fit saw."""

    names: tuple[str, ...]
    covariance: np.ndarray  # (n, n), SI units
    noise_sd: np.ndarray  # (5,), deg and mm
    method: str = "laplace"

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "covariance", np.asarray(self.covariance, float))
        object.__setattr__(self, "noise_sd", np.asarray(self.noise_sd, float))

    def sd(self) -> dict[str, float]:
        """Posterior standard deviation (SI) per parameter."""
        return {n: float(np.sqrt(v)) for n, v in zip(self.names, np.diag(self.covariance), strict=True)}

    def table(self, units: Mapping[str, str], unit_to_si: Mapping[str, float]) -> dict:
        """The ``[posterior]`` table, each parameter in the unit ``units`` gives it (``unit_to_si``:
        a unit's factor to SI)."""
        f = np.array([1.0 / unit_to_si[units[n]] for n in self.names])
        return {"method": self.method, "parameters": list(self.names), "units": [units[n] for n in self.names],
                "covariance": (self.covariance * np.outer(f, f)).tolist(), "noise_sd": self.noise_sd.tolist()}

    @classmethod
    def read(cls, table: PosteriorTable, unit_to_si: Mapping[str, float], valued: set[str], src: str) -> Posterior:
        """The ``[posterior]`` table of the file ``src`` (validated by its schema; units and
        ``unit_to_si`` as :meth:`table`; ``valued``: the names the file gives values), checked against
        the file: every name valued, one known unit each, a square symmetric positive semi-definite
        covariance, five noise sds >= 0; anything else a one-line :class:`InputError` naming the field."""
        names = table.parameters
        unknown = [n for n in names if n not in valued]
        if unknown:
            raise InputError(f"{unknown[0]!r} has no value in the file: a posterior describes the fitted values",
                             source=src, field="posterior.parameters")
        cov = _covariance(table.covariance, len(names), src)
        sd = np.array(table.noise_sd)
        if len(sd) != 5 or np.any(sd < 0):
            raise InputError(f"must be five sds >= 0 ({', '.join(coordinate_columns())})", source=src,
                             field="posterior.noise_sd")
        if len(table.units) != len(names) or not all(u in unit_to_si for u in table.units):
            raise InputError(f"must be one unit per parameter, each one of {', '.join(unit_to_si)}", source=src,
                             field="posterior.units")
        f = np.array([unit_to_si[u] for u in table.units])
        return cls(tuple(names), cov * np.outer(f, f), sd)


def _covariance(rows: list[list[float]], n: int, src: str) -> np.ndarray:
    """The ``n`` x ``n`` covariance, symmetric and positive semi-definite over its finite rows."""
    fld = "posterior.covariance"
    if len(rows) != n or any(len(row) != n for row in rows):
        raise InputError(f"must be a {n} x {n} matrix (one row per parameter)", source=src, field=fld)
    m = np.array(rows, float).reshape(n, n)
    finite = np.all(np.isfinite(m), axis=1)
    core = m[np.ix_(finite, finite)]
    scale = max(float(np.max(np.abs(np.diag(core)), initial=0.0)), 1e-300)
    if not np.allclose(core, core.T, rtol=SYMMETRY_TOL, atol=SYMMETRY_TOL * scale):
        raise InputError("the covariance is not symmetric", source=src, field=fld)
    if core.size and float(np.min(np.linalg.eigvalsh(core))) < -SYMMETRY_TOL * scale:
        raise InputError("the covariance is not positive semi-definite", source=src, field=fld)
    return m
