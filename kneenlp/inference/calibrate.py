"""Calibrate a knee to a real experiment: what ``kneenlp identify`` does with measured data.

A real experiment (data with a declared side or a robot's joint loads, as ``import-laxity``
writes them) differs from data the model produced in two ways the fit must take up:

* the experiment's frames are not the model's: the registration (a constant offset of the five
  measured coordinates, :class:`~kneenlp.model.effects.Registration`) is fitted with the ligaments;
* nobody declares the noise: its level is estimated from the fit (the residual variance).

Which ligament parameters the trials can determine is decided before the fit
(:func:`calibration_free`): the sensitivities of the measured coordinates to every ligament
parameter at the knee's own values (through each trial's equilibrium), with the registration's
columns, are ranked by a pivoted QR; a parameter is kept while its pivot is at least
:data:`PIVOT_TOLERANCE` of the largest, i.e. while it changes the coordinates in a direction the
parameters kept before it do not.  The rest stay at the knee's values (the report names them).

:func:`calibrate` returns the fit with the RMS per coordinate before (the knee's parameters) and
after; :meth:`Calibration.parameter_set` is the calibrated parameter file's content.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from kneenlp.conventions import COORDINATES
from kneenlp.experiment.measured import MeasuredData
from kneenlp.inference.fit import Fit
from kneenlp.inference.predict import Prediction, predict, rms_by_coordinate
from kneenlp.inference.problem import IdentificationProblem, default_free
from kneenlp.model.kneemodel import KneeModel
from kneenlp.model.parameters import ParameterSet
from kneenlp.solvers.forward import forward_solver

#: Smallest pivot (relative to the largest) of a parameter the calibration frees.
PIVOT_TOLERANCE = 0.02
REGISTRATION = [f"registration.{c}" for c in COORDINATES]


def real_experiment(data: MeasuredData) -> bool:
    """Data from an experiment rather than from the model: a declared side or joint loads."""
    return data.side is not None or any(t.axes == "jcs" for t in data.trials)


def calibration_free(model: KneeModel, data: MeasuredData) -> tuple[list[str], list[str]]:
    """(parameters to fit, ligament parameters left at the knee's values): the registration and the
    ligament parameters the trials determine (module docstring)."""
    candidates = default_free(model)
    names = [*REGISTRATION, *candidates]
    problem = IdentificationProblem.from_data(model, data, names)
    theta = model.theta()
    solutions = forward_solver(model).solve(data.trials, theta)
    ok = np.array([s.converged for s in solutions])
    q = np.array([s.q for s in solutions])
    S = problem.sensitivities(q, theta, names)  # (T * 5) x n, mm or deg per SI unit
    rows = np.repeat(ok, 5)
    scaled = S[rows] * np.array([model.parameter(n).scale for n in names])
    _, R, piv = scipy.linalg.qr(scaled, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    keep = {names[piv[i]] for i in range(len(diag)) if diag[i] >= PIVOT_TOLERANCE * diag[0]}
    free = [*REGISTRATION, *[n for n in candidates if n in keep]]
    return free, [n for n in candidates if n not in keep]


@dataclass
class Calibration:
    """A calibration: the fit, the prediction with the knee's own parameters, what was left fixed."""

    fit: Fit
    before: Prediction | None  # None: an identification without the prediction before it
    fixed: list[str]

    @property
    def rms_before(self) -> dict[str, float] | None:
        return None if self.before is None else self.before.rms()

    @property
    def rms_after(self) -> dict[str, float]:
        return rms_by_coordinate(self.fit.data.q_user - self.fit.predicted_user)

    def parameter_set(self) -> ParameterSet:
        """The knee's parameter set with the fitted values: ``--parameters`` of later commands."""
        knee = self.fit.problem.model.knee
        values = {n: self.fit.params[n] for n in self.fit.problem.free}
        return knee.parameters.with_values(values, name=f"{knee.name}-calibrated",
                                           description=f"{knee.name} calibrated to {self.fit.data.source}")

    def to_toml(self) -> str:
        info = {p.name: p for p in self.fit.problem.model.parameters}
        rms = ", ".join(f"{c} {v:.2f}" for c, v in self.rms_after.items())
        return self.parameter_set().to_toml(info, [
            f"Calibrated by kneenlp identify on {self.fit.data.source} ({len(self.fit.data)} trials).",
            f"RMS of measured minus fitted after calibration: {rms} (mm, deg).",
            "Values in [values] carry their units; the rest are the knee's own parameter set."])

    def summary(self) -> dict:
        out = {"rms_after": self.rms_after}
        if self.before is not None:
            out |= {"rms_before": self.rms_before, "fixed": self.fixed,
                    "converged_before": int(self.before.converged.sum())}
        return out

    def report(self) -> str:
        if self.before is None:
            return self.fit.report()

        def row(rms):
            return ", ".join(f"{c.rsplit('_', 1)[0]} {v:.2f} {c.rsplit('_', 1)[1]}" for c, v in rms.items())

        lines = [self.fit.report(), "[[Calibration]]",
                 f"    RMS before (the knee's parameters, {int(self.before.converged.sum())}/"
                 f"{len(self.before.solutions)} trials at equilibrium): {row(self.rms_before)}",
                 f"    RMS after: {row(self.rms_after)}",
                 f"    left at the knee's values (the trials do not determine them): {', '.join(self.fixed) or 'none'}"]
        return "\n".join(lines)


def calibrate(model: KneeModel, data: MeasuredData, free: list[str] | None = None, *, seed: int = 0,
              noise=None, **identify_options) -> Calibration:
    """Fit ``free`` (default :func:`calibration_free`) to the real experiment ``data``."""
    from kneenlp.inference.identify import identify

    before = predict(model, data)
    fixed: list[str] = []
    if free is None:
        free, fixed = calibration_free(model, data)
    theta = model.theta()
    start = {n: float(theta[model.index(n)]) for n in free} | identify_options.pop("start", {})
    fit = identify(model, data, free=free, seed=seed, noise=noise, start=start, **identify_options)
    return Calibration(fit, before, fixed)
