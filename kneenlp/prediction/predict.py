"""Compare before fitting: every measured trial simulated at its measured flexion and load.

``kneenlp predict DATA.csv --knee K [--parameters P] --out DIR`` (:func:`predict`) solves each
trial's equilibrium under the load the experiment applied, at the flexion it measured, with the
knee's parameters (or a calibration), and reports measured minus predicted per trial and as the
RMS per coordinate (mm, deg) over the trials that converged.  A trial without equilibrium is
listed with its reason and left out of the RMS, never dropped silently.

With a calibration's posterior (``[posterior]`` of ``calibrated.toml``, :mod:`~kneenlp.model.posterior`)
each prediction has a predictive band: the posterior covariance carried through the trial's
equilibrium (its sensitivities, linearised at the predicted pose) plus the measurement noise the
calibration estimated, ``+-1.96 sd`` (95 %).  The report counts the measurements inside it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from kneenlp.base.atomic import write_csv_atomic
from kneenlp.base.conventions import BAND_LEVEL, BAND_Z, coordinate_columns
from kneenlp.base.errors import InputError
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData, measured_frame
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.protocol import Protocol
from kneenlp.model.knee import Knee
from kneenlp.model.posterior import Posterior
from kneenlp.prediction.laxity import laxity_lines, laxity_records, laxity_table
from kneenlp.solvers.forward import TrialSolution, forward_solver

#: Internal rotation (deg) over the trials' flexion range that the data and the knee must each show
#: before opposite trends are called data mirrored to the other side's signs (screw home: the tibia
#: rotates internally with flexion, by 5-20 deg from 0 to 90 deg in cadaver knees).
SCREW_HOME_DEG = 3.0
#: Internal moment (N m) below which a trial shows the knee's own coupled rotation.
FREE_ROTATION_NM = 0.5


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
    #: predictive sd (T x 5, deg and mm) with the posterior and the noise; None without a posterior
    sd_user: np.ndarray | None = None

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

    def check_side(self) -> None:
        """Refuse data mirrored to the other knee's signs, by the evidence of the trials: over the
        converged trials without an internal moment (:data:`FREE_ROTATION_NM`), the internal rotation's
        linear trend with flexion in the data and in the prediction; both over :data:`SCREW_HOME_DEG`
        across the flexion range and of opposite signs is a mirrored side (+varus, +internal and
        +lateral are anatomical for either knee), not a model error."""
        rows = [i for i, t in enumerate(self.data.trials)
                if abs(t.loads.get("internal_moment", 0.0)) < FREE_ROTATION_NM and self.converged[i]]
        flexion = np.array([self.data.trials[i].flexion_deg for i in rows])
        if len(rows) < 3 or np.ptp(flexion) < 30.0:
            return
        span = np.array([flexion.min(), flexion.max()])
        trend = [np.polyval(np.polyfit(flexion, y[rows, 1], 1), span) @ [-1.0, 1.0]
                 for y in (self.data.q_user, self.observed_user)]
        if min(abs(trend[0]), abs(trend[1])) >= SCREW_HOME_DEG and trend[0] * trend[1] < 0:
            way = {True: "internally", False: "externally"}
            raise InputError(f"the tibia rotates {way[trend[0] > 0]} by {abs(trend[0]):.1f} deg from {span[0]:.0f} to "
                             f"{span[1]:.0f} deg flexion in the data, {way[trend[1] > 0]} by {abs(trend[1]):.1f} deg "
                             f"in knee {self.knee_name!r}: data mirrored to the other knee's signs? Signs are "
                             "anatomical for either side (+varus, +internal, +lateral)", source=self.data.source,
                             field="internal_rotation_deg")

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
        if self.sd_user is not None:
            for j, c in enumerate(coordinate_columns()):
                df[f"sd_{c}"] = self.sd_user[:, j]
        df["converged"] = self.converged
        df["reason"] = [s.reason for s in self.solutions]
        return df

    def inside_band(self) -> dict[str, int] | None:
        """Per coordinate column, how many converged trials' measurements lie inside the 95 % band
        (None without a posterior)."""
        if self.sd_user is None:
            return None
        ok = self.converged
        inside = np.abs(self.errors_user[ok]) <= BAND_Z * self.sd_user[ok]
        return {c: int(inside[:, j].sum()) for j, c in enumerate(coordinate_columns())}

    def laxity(self) -> pd.DataFrame:
        """Measured and predicted laxity per flexion and load pair (mm, deg; :mod:`~kneenlp.prediction.laxity`)."""
        return laxity_table(self.data.trials, self.data.q_user, self.predicted_user)

    def summary(self) -> dict:
        return {"knee": self.knee_name, "trials": len(self.solutions), "converged": int(self.converged.sum()),
                "rms": self.rms(), "rms_units": {c: c.rsplit("_", 1)[1] for c in coordinate_columns()},
                "failed": [{"trial": s.trial.id, "reason": s.reason} for s in self.solutions if not s.converged],
                "unstable": [s.trial.id for s in self.solutions if not s.stable],
                "snapped": [s.trial.id for s in self.solutions if s.snapped],
                "notes": {s.trial.id: s.note for s in self.solutions if s.note},
                "laxity": laxity_records(self.laxity())} | ({} if self.sd_user is None else {
                    "band_level": BAND_LEVEL, "inside_band": self.inside_band(),
                    "sd": {c: [None if not np.isfinite(v) else float(v) for v in self.sd_user[:, j]]
                           for j, c in enumerate(coordinate_columns())}})

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
            note = ("  (an UNSTABLE equilibrium: no loading ends there)" if not s.stable else
                    "  (the loading path passes a fold: several equilibria; the one the knee settles into)"
                    if s.snapped else "") + (f"  ({s.note})" if s.note else "")
            lines.append(f"{s.trial.id:<{width}}  {s.trial.flexion_deg:7.1f}  {cells}{note}")
        if self.sd_user is not None:
            n = int(self.converged.sum())
            lines.append(f"Inside the {100 * BAND_LEVEL:g} % predictive band (posterior and noise, +-{BAND_Z:.2f} sd): "
                         + ", ".join(f"{c.rsplit('_', 1)[0]} {k}/{n}" for c, k in self.inside_band().items()))
            width_sd = np.nanmedian(np.where(np.isfinite(self.sd_user), self.sd_user, np.nan)[self.converged], axis=0)
            lines.append("  median predictive sd: " + ", ".join(
                f"{c.rsplit('_', 1)[0]} {v:.2f} {c.rsplit('_', 1)[1]}"
                for c, v in zip(coordinate_columns(), width_sd, strict=True)))
        lines += laxity_lines(self.laxity(), "Laxity (positive minus negative load, largest loads; mm and deg):")
        return "\n".join(lines)


def predict(knee: Knee | KneeModel, data: MeasuredData, parameters: dict[str, float] | None = None,
            posterior: Posterior | None = None) -> Prediction:
    """Every trial of ``data`` solved at its measured flexion and load on ``knee`` (its parameter set,
    ``parameters`` overriding by name, SI); with a ``posterior`` (default: the parameter set's, when
    no ``parameters`` override it) the predictive band (module docstring)."""
    model = KneeModel.of(knee)
    data.check_knee(model.knee)
    protocol = Protocol(data.protocol or "measured", tuple(data.trials), source=data.source)
    theta = model.theta(parameters)
    solutions = forward_solver(model).solve(protocol.trials, theta)
    q = np.array([s.q for s in solutions])
    observed = model.observe(q, theta, [s.trial.load for s in solutions], [s.trial.flexion for s in solutions])
    if posterior is None and parameters is None:
        posterior = model.knee.parameters.posterior
    sd = None if posterior is None else predictive_sd(model, data, solutions, theta, posterior)
    return Prediction(data, solutions, model.knee.name, observed, sd)


def predictive_sd(model: KneeModel, data: MeasuredData, solutions: list, theta: np.ndarray,
                  posterior: Posterior) -> np.ndarray:
    """Predictive sd (T x 5, deg and mm) of the trials ``data`` at the poses of their forward
    ``solutions`` (each's ``q``, T x 5, SI, and whether it ``converged``) and the parameters
    ``theta``: ``sqrt(diag(S C S') + noise^2)`` with ``S`` the observations'
    sensitivities to the posterior's parameters through each trial's equilibrium and ``C`` its
    covariance; infinite where a direction nothing determined moves the observation, NaN where the
    trial has no equilibrium."""
    for n in posterior.names:
        if n not in model.parameter_names:
            raise InputError(f"{n!r} is not a parameter of knee {model.knee.name}", source=model.knee.parameters.source,
                             field="posterior.parameters")
    q = np.array([s.q for s in solutions])
    converged = np.array([s.converged for s in solutions])
    out = np.full(q.shape, np.nan)
    if not converged.any():
        return out
    problem = IdentificationProblem.from_data(model, data.subset(converged), list(posterior.names))
    S = problem.sensitivities(q[converged], theta)  # (T * 5) x n, mm or deg per SI unit
    C = np.asarray(posterior.covariance, float)
    unknown = ~np.isfinite(np.diag(C))
    var = np.einsum("ij,jk,ik->i", S, np.where(np.isfinite(C), C, 0.0), S).reshape(-1, 5)
    var[np.any(np.abs(S[:, unknown]) > 0, axis=1).reshape(-1, 5)] = np.inf
    out[converged] = np.sqrt(np.maximum(var, 0.0) + posterior.noise_sd**2)
    return out


def write_prediction(prediction: Prediction, out: Path) -> list[Path]:
    """``predicted.csv``, ``laxity.csv`` and ``predicted_laxity.png`` in ``out``; the paths written."""
    from kneenlp.figures.plots import measured_vs_predicted

    table = prediction.table()
    write_csv_atomic(table, out / "predicted.csv", index=False, float_format="%.10g")
    write_csv_atomic(prediction.laxity(), out / "laxity.csv", index=False, float_format="%.10g")
    band = "" if prediction.sd_user is None else f"; shaded: {100 * BAND_LEVEL:g} % predictive band"
    fig = measured_vs_predicted(table, out / "predicted_laxity.png",
                                f"{prediction.knee_name}: measured (filled) and predicted (open){band}")
    return [out / "predicted.csv", out / "laxity.csv", fig]
