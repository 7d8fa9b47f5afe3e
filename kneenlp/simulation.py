"""Simulate a laxity protocol on a knee: the forward problem, as a table in user units."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from kneenlp.base.atomic import write_csv_atomic
from kneenlp.base.conventions import EQUILIBRIUM_TOL, coords_to_user
from kneenlp.experiment.kind import SIMULATED, Experiment
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import measured_frame
from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.protocol import Protocol
from kneenlp.model.knee import Knee
from kneenlp.solvers.forward import TrialSolution, forward_solver


@dataclass
class SimulationResult:
    """Equilibria of every trial of a protocol (``solutions`` in SI; tables in user units)."""

    knee: Knee
    protocol: Protocol
    solutions: list[TrialSolution]
    seconds: float
    parameters: dict[str, float]
    model: KneeModel | None = None
    #: the experiment simulated: what its data observe, where its force acts
    experiment: Experiment = SIMULATED

    @property
    def converged(self) -> int:
        return sum(s.converged for s in self.solutions)

    @property
    def failed(self) -> list[TrialSolution]:
        return [s for s in self.solutions if not s.converged]

    @property
    def max_residual(self) -> float:
        return max(s.max_residual for s in self.solutions)

    @property
    def q(self) -> np.ndarray:
        """Poses (n x 5, SI)."""
        return np.array([s.q for s in self.solutions])

    def table(self) -> pd.DataFrame:
        """One row per trial: loads, coordinates (mm, deg), every force element's outputs (ligament
        strain in % and force in N, contact force per compartment in N and penetration in mm; the
        unit is in each column name), convergence."""
        trials = [s.trial for s in self.solutions]
        df = measured_frame(trials, coords_to_user(self.q), self.protocol.name, experiment=self.experiment)
        model = self.model or KneeModel.of(self.knee)
        theta = model.theta(self.parameters)
        for element, out in model.outputs:
            if element.candidate and all(theta[model.index(n)] == model.parameter(n).neutral
                                         for n in element.frees()):
                continue  # a candidate element that is switched off adds nothing to report
            df[out.column] = [out.to_user * s.outputs[out.column] for s in self.solutions]
        df["converged"] = [s.converged for s in self.solutions]
        df["max_residual"] = [s.max_residual for s in self.solutions]
        df["strategy"] = [s.strategy for s in self.solutions]
        df["note"] = [s.note for s in self.solutions]
        return df

    def recruitment(self) -> pd.DataFrame:
        """Each ligament's force change from the unloaded pose at the same flexion (N), one row per
        trial, and ``dominant``: the ligament whose force rises most in that trial ("" if none
        rises; NaN rows where the protocol has no unloaded trial at that flexion).

        This is the reading of the paper's Fig. 2 ("a load case where the specific ligament is
        loaded relatively more than other ligaments"): a trial dominated by one ligament is the
        trial that isolates it."""
        names = list(self.knee.ligaments)
        forces = np.array([[s.outputs[f"{n}_force_N"] for n in names] for s in self.solutions])
        flex = [s.trial.flexion_deg for s in self.solutions]
        base = {f: forces[j] for j, (s, f) in enumerate(zip(self.solutions, flex, strict=True))
                if s.trial.direction == "none"}
        change = np.array([forces[j] - base.get(f, np.nan) for j, f in enumerate(flex)])
        df = pd.DataFrame(change, columns=[f"{n}_force_change_N" for n in names])
        df.insert(0, "trial", [s.trial.id for s in self.solutions])
        df.insert(1, "flexion_deg", flex)
        df["dominant"] = ["" if not np.isfinite(row).all() or row.max() <= 0 else names[int(np.argmax(row))]
                          for row in change]
        return df

    def measured(self, noise: str | NoiseModel = "none", seed: int | None = 0) -> pd.DataFrame:
        """Measured-data table: the converged poses plus seeded noise (mm, deg)."""
        noise = NoiseModel.parse(noise)
        if self.failed:
            from kneenlp.base.errors import ConvergenceError

            raise ConvergenceError("cannot write measured data: trials did not converge: "
                                   + ", ".join(s.trial.id for s in self.failed), self)
        rng = np.random.default_rng(seed)
        model = self.model or KneeModel.of(self.knee)
        # what the instrument reads, biases included
        y = model.observe(self.q, model.theta(self.parameters), [s.trial.load for s in self.solutions],
                          [s.trial.flexion for s in self.solutions])
        return measured_frame([s.trial for s in self.solutions], y + noise.sample(rng, self.q.shape),
                              self.protocol.name, experiment=self.experiment)

    def to_csv(self, path: str | Path) -> Path:
        return write_csv_atomic(self.table(), path, index=False, float_format="%.10g")

    def summary(self) -> dict:
        return {
            "protocol": self.protocol.name,
            "knee": self.knee.name,
            "trials": len(self.solutions),
            "converged": self.converged,
            "failed": [{"trial": s.trial.id, "max_residual": s.max_residual, "reason": s.reason}
                       for s in self.failed],
            "notes": {s.trial.id: s.note for s in self.solutions if s.note},
            "max_residual": self.max_residual,
            "seconds": round(self.seconds, 4),
        }

    def to_json(self) -> str:
        return json.dumps(self.summary(), indent=2)


def simulate(knee: Knee | KneeModel | None = None, protocol: Protocol | str = "set3",
             parameters: dict[str, float] | None = None, tol: float = EQUILIBRIUM_TOL, *,
             experiment: Experiment = SIMULATED) -> SimulationResult:
    """Solve every trial of ``protocol`` on ``knee`` (default: the embedded knee), loaded as
    ``experiment`` loads it (its load point; its data observe its coordinates).

    ``parameters`` overrides values of the knee's parameter set (SI, by name, e.g.
    ``{"ACL.k": 12000.0}``).  Returns a :class:`SimulationResult`; trials that do not converge are
    listed in ``result.failed`` (with their residual), never silently kept.
    """
    model = KneeModel.of(knee or Knee.default())
    knee = model.knee
    protocol = protocol if isinstance(protocol, Protocol) else Protocol.load(protocol)
    knee.check_flexions(protocol.trials, protocol.source)
    theta = model.theta(parameters)
    solver = forward_solver(model, tol)
    t0 = time.perf_counter()
    sols = solver.solve(experiment.applied_to(list(protocol.trials)), theta)
    seconds = time.perf_counter() - t0
    return SimulationResult(knee, protocol, sols, seconds, dict(zip(model.parameter_names, theta, strict=True)),
                            model, experiment)
