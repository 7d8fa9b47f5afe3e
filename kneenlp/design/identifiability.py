"""Identifiability before fitting: which parameters a protocol can determine, said in words.

:func:`identifiability` simulates the protocol at the knee's parameter values, takes the
sensitivities of the measured coordinates to the free parameters through every trial's equilibrium
(:meth:`IdentificationProblem.sensitivities`), and decomposes them (SVD of the sensitivity matrix
in the parameters' scaled units, each coordinate weighted by its inverse noise variance).  The
numerical rank says how many parameter directions the protocol determines at all; the linearised
standard errors say how well, for the given noise.  Directions with a singular value below
``1e-6`` of the largest cannot be identified; they are reported as the combination of parameters
the data do not see ("MCLd.k_scale and MCLp.k_scale: only +0.71 MCLd.k_scale + 0.70
MCLp.k_scale is determined" style).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kneenlp.estimation.statistics import gauss_newton_covariance, svd_rank, weighted_svd
from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.protocol import Protocol
from kneenlp.model.params import default_free


@dataclass
class Identifiability:
    """What a protocol can identify (see module docstring); SI values."""

    free: list[str]
    values: dict[str, float]  # the parameter values it was assessed at
    singular_values: np.ndarray
    vt: np.ndarray
    stderr: dict[str, float]  # linearised standard errors for the noise (inf: not identifiable)
    units: dict[str, tuple[str, float]]  # display unit and factor per parameter
    noise: str
    protocol: str = ""
    failed: list[str] = field(default_factory=list)  # trials that did not converge (left out)

    @property
    def rank(self) -> int:
        return svd_rank(self.singular_values)

    @property
    def identifiable(self) -> bool:
        return self.rank == len(self.free)

    def directions(self, tol: float = 0.05) -> list[dict[str, float]]:
        """The parameter combinations (scaled units) the protocol cannot determine."""
        return [{n: float(c) for n, c in zip(self.free, self.vt[i], strict=True) if abs(c) > tol}
                for i in range(self.rank, len(self.free))]

    def relative_stderr(self) -> dict[str, float]:
        return {n: self.stderr[n] / abs(self.values[n]) if self.values[n] else float("inf") for n in self.free}

    def report(self) -> str:
        sv = self.singular_values
        condition = f"; condition number {sv[0] / sv[-1]:.3g}" if sv[-1] > 0 else ""
        verdict = ", all identifiable" if self.identifiable else f", {len(self.free) - self.rank} not identifiable"
        lines = [f"identifiability of {len(self.free)} parameters from {self.protocol} (noise {self.noise}): "
                 f"rank {self.rank}{verdict}{condition}"]
        for i, d in enumerate(self.directions(), 1):
            names = sorted(d, key=lambda n: -abs(d[n]))
            combo = " ".join(f"{d[n]:+.2f} {n}" for n in names)
            lines.append(f"  direction {i} the data do not see: {combo}: "
                         + ("the protocol cannot tell these apart; fix all but one of them to identify it"
                            if len(names) > 1 else f"{names[0]} does not change any measured coordinate"))
        rel = self.relative_stderr()
        for n in self.free:
            unit, f = self.units[n]
            se = self.stderr[n]
            share = f" ({100 * rel[n]:.1f} %)" if np.isfinite(rel[n]) else ""
            txt = f"+/- {se * f:.3g} {unit}{share}" if np.isfinite(se) else "not identifiable"
            lines.append(f"  {n:28s} {self.values[n] * f:10.4g} {unit:6s} {txt}")
        if self.failed:
            lines.append(f"  left out (did not converge): {', '.join(self.failed)}")
        return "\n".join(lines)


def identifiability(knee, protocol: Protocol | str, free: list[str] | None = None, noise: str = "uniform:0.5",
                    values: dict[str, float] | None = None) -> Identifiability:
    """Identifiability of ``free`` (default: each ligament's stiffness and reference strain, or
    each bundle group's scale and offset) from ``protocol`` at the knee's parameter values (or
    ``values``, SI), for measurement ``noise``."""
    from kneenlp.experiment.kneemodel import KneeModel
    from kneenlp.simulation import simulate

    model = KneeModel.of(knee)
    proto = protocol if isinstance(protocol, Protocol) else Protocol.load(protocol)
    result = simulate(model, proto, parameters=values)
    ok = [s for s in result.solutions if s.converged]
    free = list(free or default_free(model))
    problem = IdentificationProblem(model, tuple(s.trial for s in ok), free, noise=NoiseModel.parse(noise),
                                    fixed=dict(values or {}))
    theta = problem.theta()
    q = np.array([s.q for s in ok])
    sens = problem.sensitivities(q, theta)
    nm = problem.noise
    variance = nm.std**2
    w = np.full(sens.shape[0], 1.0 / max(variance, 1e-300))
    _, sv, vt = weighted_svd(sens, w, problem.scales)
    cov = gauss_newton_covariance(sens, w, np.full(sens.shape[0], variance), problem.scales, free)
    stderr = {n: float(np.sqrt(c)) for n, c in zip(free, np.diag(cov), strict=True)}
    units = {p.name: (p.unit, p.to_user) for p in problem.parameters}
    return Identifiability(free, problem.values(theta), sv, vt, stderr, units, noise, proto.name,
                           [s.trial.id for s in result.failed])
