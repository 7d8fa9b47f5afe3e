"""The parameter space of a fit: names <-> the full parameter vector <-> the solver's scaled vector.

A fit moves the ``free`` parameters; the model reads the full vector ``theta`` (SI, the model's
order).  :class:`ParameterSpace` is the one place that maps between them: scaled free values
(each divided by its kind's scale, order one for the solvers), the full vector with the fixed
values and every tie evaluated (numerically, or symbolically for the NLP), and ``d theta / d p``,
which carries a sensitivity through the ties.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np

from kneenlp.model import ties as tie_rules


@dataclass(frozen=True, eq=False)
class ParameterSpace:
    """``names``: every parameter in ``theta``'s order; ``free`` the fitted ones with their
    ``scales`` and bounds (SI); ``ties`` the tied parameters' expressions (:mod:`kneenlp.model.ties`)."""

    names: tuple[str, ...]
    free: tuple[str, ...]
    scales: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    ties: Mapping[str, str] = field(default_factory=dict)

    @cached_property
    def order(self) -> list[str]:
        """The tied names, each after the tied names it uses."""
        return tie_rules.ordered(self.ties, self.names)

    @cached_property
    def _index(self) -> dict[str, int]:
        return {n: i for i, n in enumerate(self.names)}

    # ------------------------------------------------------------------ scaled free vectors
    def to_scaled(self, values: Mapping[str, float] | Sequence[float] | np.ndarray) -> np.ndarray:
        """The free parameters (SI, by name or in order) divided by their scales."""
        if isinstance(values, Mapping):
            values = [values[n] for n in self.free]
        return np.asarray(values, dtype=float) / self.scales

    def from_scaled(self, x_scaled: np.ndarray) -> np.ndarray:
        """The free parameters (SI, in order) of scaled values (one point, or one per row)."""
        return np.asarray(x_scaled, dtype=float) * self.scales

    @property
    def scaled_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.lower / self.scales, self.upper / self.scales

    # ------------------------------------------------------------------ the full vector
    def tied(self, theta: np.ndarray) -> np.ndarray:
        """``theta`` (SI) with every tie evaluated from its entries."""
        if not self.ties:
            return theta
        values = tie_rules.tied(dict(zip(self.names, theta, strict=True)), self.ties, self.order)
        return np.array([values[n] for n in self.names], dtype=float)

    def theta_of_scaled(self, x_scaled: ca.MX | ca.SX, theta: ca.MX | ca.SX) -> ca.MX | ca.SX:
        """The full parameter vector (SI, symbolic): scale times ``x_scaled`` for the free
        parameters, each tie of those, ``theta``'s entry for the others.  Element by element, so
        that fixed parameters (e.g. the contact modulus) depend on no decision variable
        structurally: the Hessian then never seeds the contact with parameter directions (a dense
        selection matrix made it ~2x slower)."""
        pos = {n: j for j, n in enumerate(self.free)}
        entries = {n: self.scales[pos[n]] * x_scaled[pos[n]] if n in pos else theta[i]
                   for i, n in enumerate(self.names)}
        for name in self.order:
            entries[name] = tie_rules.evaluate(self.ties[name], entries.__getitem__)
        return ca.vertcat(*entries.values())

    @cached_property
    def _tie_jacobian(self) -> ca.Function:
        x, theta = ca.SX.sym("x", len(self.free)), ca.SX.sym("theta", len(self.names))
        full = self.theta_of_scaled(x / self.scales, theta)
        return ca.Function("dtheta_dp", [x, theta], [ca.jacobian(full, x)])

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        """``d theta / d p`` (n_theta x n_free; SI per SI) at ``theta``: a selection of the free
        entries, plus each tie's derivatives."""
        if not self.ties:
            out = np.zeros((len(self.names), len(self.free)))
            out[[self._index[n] for n in self.free], np.arange(len(self.free))] = 1.0
            return out
        p = np.array([theta[self._index[n]] for n in self.free])
        return np.asarray(self._tie_jacobian(p, theta), dtype=float)
