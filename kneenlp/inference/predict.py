"""Compare before fitting: every measured trial simulated at its measured flexion and load.

``kneenlp predict DATA.csv --knee K [--parameters P] --out DIR`` (:func:`predict`) solves each
trial's equilibrium under the load the experiment applied, at the flexion it measured, with the
knee's parameters (or a calibration), and reports measured minus predicted per trial and as the
RMS per coordinate (mm, deg) over the trials that converged.  A trial without equilibrium is
listed with its reason and left out of the RMS, never dropped silently.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from kneenlp.conventions import coordinate_columns
from kneenlp.experiment.measured import MeasuredData, measured_frame
from kneenlp.experiment.protocol import Protocol
from kneenlp.inference.laxity import laxity_lines, laxity_records, laxity_table
from kneenlp.io.atomic import write_csv_atomic
from kneenlp.model.knee import Knee
from kneenlp.model.kneemodel import KneeModel
from kneenlp.solvers.forward import TrialSolution, forward_solver


def rms_by_coordinate(errors_user: np.ndarray) -> dict[str, float]:
    """RMS per coordinate column (mm, deg) of errors (T x 5, deg and mm); NaN with no rows."""
    err = np.asarray(errors_user, float).reshape(-1, 5)
    return {c: float(np.sqrt(np.mean(err[:, j] ** 2))) if len(err) else float("nan")
            for j, c in enumerate(coordinate_columns())}


@dataclass
class Prediction:
    """Predicted poses of measured trials and their errors (SI inside, tables in mm and deg)."""

    data: MeasuredData
    solutions: list[TrialSolution]
    knee_name: str
    #: what the experiment would measure at each solution's pose (T x 5, deg and mm): the model's
    #: observation, registration included (:meth:`KneeModel.observe`)
    observed_user: np.ndarray

    @property
    def converged(self) -> np.ndarray:
        return np.array([s.converged for s in self.solutions])

    @property
    def predicted_user(self) -> np.ndarray:
        """Predicted measured coordinates (T x 5, deg and mm); NaN where a trial did not converge."""
        q = np.array(self.observed_user, float)
        q[~self.converged] = np.nan
        return q

    @property
    def errors_user(self) -> np.ndarray:
        """Measured minus predicted (T x 5, deg and mm); NaN where a trial did not converge."""
        return self.data.q_user - self.predicted_user

    def rms(self, trials: np.ndarray | None = None) -> dict[str, float]:
        """RMS of measured minus predicted per coordinate column (mm, deg) over the converged
        trials (of ``trials``, a boolean mask, if given)."""
        sel = self.converged if trials is None else self.converged & trials
        return rms_by_coordinate(self.errors_user[sel])

    def table(self) -> pd.DataFrame:
        """The data's columns and trial ids with the predicted poses, the errors (``error_<column>``:
        measured minus predicted) and convergence."""
        df = measured_frame(self.data.trials, self.predicted_user, self.data.protocol, self.data.side)
        for j, c in enumerate(coordinate_columns()):
            df[f"measured_{c}"] = self.data.q_user[:, j]
            df[f"error_{c}"] = self.errors_user[:, j]
        df["converged"] = self.converged
        df["reason"] = [s.reason for s in self.solutions]
        return df

    def laxity(self) -> pd.DataFrame:
        """Measured and predicted laxity per flexion and load pair (mm, deg; :mod:`~kneenlp.inference.laxity`)."""
        return laxity_table(self.data.trials, self.data.q_user, self.predicted_user)

    def summary(self) -> dict:
        return {"knee": self.knee_name, "trials": len(self.solutions), "converged": int(self.converged.sum()),
                "rms": self.rms(), "rms_units": {c: c.rsplit("_", 1)[1] for c in coordinate_columns()},
                "failed": [{"trial": s.trial.id, "reason": s.reason} for s in self.solutions if not s.converged],
                "laxity": laxity_records(self.laxity())}

    def to_json(self) -> str:
        return json.dumps(self.summary(), indent=2)

    def report(self) -> str:
        lines = [f"{self.knee_name}: {int(self.converged.sum())}/{len(self.solutions)} trials reach equilibrium "
                 "under their measured loads at their measured flexion",
                 "RMS of measured minus predicted over them: "
                 + ", ".join(f"{c.rsplit('_', 1)[0]} {v:.2f} {c.rsplit('_', 1)[1]}" for c, v in self.rms().items())]
        width = max(len(s.trial.id) for s in self.solutions)
        head = "  ".join(f"{c.replace('_translation', '').replace('_rotation', ''):>14}" for c in coordinate_columns())
        lines.append(f"{'trial':<{width}}  flexion  {head}   (measured minus predicted)")
        for s, e in zip(self.solutions, self.errors_user, strict=True):
            cells = "  ".join(f"{v:14.2f}" for v in e) if s.converged else f"NO EQUILIBRIUM: {s.reason}"
            lines.append(f"{s.trial.id:<{width}}  {s.trial.flexion_deg:7.1f}  {cells}")
        lines += laxity_lines(self.laxity(), "Laxity (positive minus negative load, largest loads; mm and deg):")
        return "\n".join(lines)


def predict(knee: Knee | KneeModel, data: MeasuredData, parameters: dict[str, float] | None = None) -> Prediction:
    """Every trial of ``data`` solved at its measured flexion and load on ``knee`` (its parameter set,
    ``parameters`` overriding by name, SI)."""
    model = KneeModel.of(knee)
    data.check_knee(model.knee)
    protocol = Protocol(data.protocol or "measured", tuple(data.trials), source=data.source)
    theta = model.theta(parameters)
    solutions = forward_solver(model).solve(protocol.trials, theta)
    observed = model.observe(np.array([s.q for s in solutions]), theta, [s.trial.flexion for s in solutions])
    return Prediction(data, solutions, model.knee.name, observed)


def write_prediction(prediction: Prediction, out: Path) -> list[Path]:
    """``predicted.csv``, ``laxity.csv`` and ``predicted_laxity.png`` in ``out``; the paths written."""
    from kneenlp.io.plots import measured_vs_predicted

    table = prediction.table()
    write_csv_atomic(table, out / "predicted.csv", index=False, float_format="%.10g")
    write_csv_atomic(prediction.laxity(), out / "laxity.csv", index=False, float_format="%.10g")
    fig = measured_vs_predicted(table, out / "predicted_laxity.png",
                                f"{prediction.knee_name}: measured (filled) and predicted (open)")
    return [out / "predicted.csv", out / "laxity.csv", fig]
