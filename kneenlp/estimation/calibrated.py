"""A calibration's result: its fit, what it found besides (:class:`CalibrationRecord`), and what a
calibrated fit says of trials (the prediction variances, the misfit per observation, the Laplace
posterior written to ``calibrated.toml``).  :mod:`kneenlp.estimation.calibrate` makes it."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from kneenlp.estimation.fit import Fit
from kneenlp.estimation.minima import Search
from kneenlp.estimation.outliers import Outlier, prediction_variance
from kneenlp.estimation.statistics import gauss_newton_covariance
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.protocol import Loading
from kneenlp.model.parameters import ParameterSet
from kneenlp.model.posterior import Posterior
from kneenlp.prediction.laxity import laxity_lines, laxity_records, laxity_table
from kneenlp.prediction.predict import Prediction, predict, rms_by_coordinate
from kneenlp.solvers.forward import unstable_equilibria

#: Largest difference (mm or deg) between the fit's pose of a trial and predict's for the same one.
SAME_POSE = 0.05


@dataclass(frozen=True)
class CalibrationRecord:
    """What a calibration found besides its fit: the prediction with the knee's own parameters, what
    was left fixed, the groups engaged, predict's check, the outliers.  A calibrated
    :class:`~kneenlp.estimation.fit.Fit` carries it (:class:`Calibration` holds the two)."""

    before: Prediction | None  # None: an identification without the prediction before it
    fixed: list[str]
    #: ligament groups slack in every trial at the knee's values, engaged at the fit's start
    engaged: list[str] = field(default_factory=list)
    #: ``predict`` at the calibrated values: each trial solved from the knee's unloaded state, as a
    #: user's ``predict --parameters calibrated.toml`` solves it (None: not checked)
    check: Prediction | None = None
    #: trials the outlier test set aside (:mod:`~kneenlp.estimation.outliers`), in the order found
    outliers: list[Outlier] = field(default_factory=list)
    #: ``predict`` of the set-aside trials at the calibrated values (None: none set aside)
    set_aside: Prediction | None = None
    #: the global search that found the fit, its competing minima (None: a local calibration)
    search: Search | None = None


#: The record of a fit that is no calibration (an identification): nothing found besides the fit.
NO_RECORD = CalibrationRecord(None, [])


@dataclass(frozen=True)
class Calibration:
    """A calibration: its fit and what it found besides (:class:`CalibrationRecord`; an
    identification's fit has :data:`NO_RECORD`).  The record's fields read through."""

    fit: Fit
    record: CalibrationRecord = NO_RECORD

    before = property(lambda self: self.record.before, doc=":attr:`CalibrationRecord.before`")
    fixed = property(lambda self: self.record.fixed, doc=":attr:`CalibrationRecord.fixed`")
    engaged = property(lambda self: self.record.engaged, doc=":attr:`CalibrationRecord.engaged`")
    check = property(lambda self: self.record.check, doc=":attr:`CalibrationRecord.check`")
    outliers = property(lambda self: self.record.outliers, doc=":attr:`CalibrationRecord.outliers`")
    set_aside = property(lambda self: self.record.set_aside, doc=":attr:`CalibrationRecord.set_aside`")
    search = property(lambda self: self.record.search, doc=":attr:`CalibrationRecord.search`")

    @property
    def elsewhere(self) -> list[str]:
        """Trials whose calibrated equilibrium ``predict`` does not reach from the unloaded state (it
        finds none, or another one more than :data:`SAME_POSE` away): the fit found them by
        continuation in the parameters, on a branch a loading from neutral need not follow."""
        if self.check is None:
            return []
        return [t.id for t, off in zip(self.fit.data.trials, off_loading_path(self.fit, self.check), strict=True)
                if off]

    @property
    def rms_before(self) -> dict[str, float] | None:
        return None if self.before is None else self.before.rms()

    @property
    def rms_after(self) -> dict[str, float]:
        """RMS of measured minus fitted per coordinate column (mm, deg) over the fitted trials."""
        return rms_by_coordinate(self.fit.data.q_user - self.fit.predicted_user)

    @property
    def rms_with_outliers(self) -> dict[str, float] | None:
        """:attr:`rms_after` with the set-aside trials' predictions at the calibrated values (None:
        none set aside)."""
        if self.set_aside is None:
            return None
        return rms_by_coordinate(np.vstack([self.fit.data.q_user - self.fit.predicted_user,
                                            self.set_aside.errors_user[self.set_aside.converged]]))

    def parameter_set(self) -> ParameterSet:
        """The knee's parameter set with the fitted values: ``--parameters`` of later commands."""
        knee = self.fit.problem.model.knee
        values = {n: self.fit.params[n] for n in self.fit.problem.free}
        out = knee.parameters.with_values(values, name=f"{knee.name}-calibrated",
                                          description=f"{knee.name} calibrated to {self.fit.data.source}")
        return dataclasses.replace(out, posterior=posterior(self.fit))

    def to_toml(self) -> str:
        info = {p.name: p for p in self.fit.problem.model.parameters}
        rms = ", ".join(f"{c} {v:.2f}" for c, v in self.rms_after.items())
        return self.parameter_set().to_toml(info, [
            f"Calibrated by kneenlp identify on {self.fit.data.source} ({len(self.fit.data)} trials).",
            f"RMS of measured minus fitted after calibration: {rms} (mm, deg).",
            "Values in [values] carry their units; the rest are the knee's own parameter set."])

    def laxity(self) -> pd.DataFrame:
        """Measured and fitted laxity per flexion and load pair (mm, deg; :mod:`~kneenlp.prediction.laxity`)."""
        return laxity_table(self.fit.data.trials, self.fit.data.q_user, self.fit.predicted_user)

    def summary(self) -> dict:
        out = {"rms_after": self.rms_after, "laxity_after": laxity_records(self.laxity())}
        if self.check is not None:
            out |= {"rms_predicted": self.check.rms(), "predicted_converged": int(self.check.converged.sum()),
                    "equilibrium_elsewhere": self.elsewhere}
        if self.set_aside is not None:
            out |= {"outliers": [o.record() for o in self.outliers], "rms_with_outliers": self.rms_with_outliers,
                    "outliers_converged": int(self.set_aside.converged.sum())}
        if self.before is not None:
            out |= {"rms_before": self.rms_before, "fixed": self.fixed, "engaged": self.engaged,
                    "converged_before": int(self.before.converged.sum())}
        if self.search is not None:
            out["search"] = self.search.summary()
        return out

    def report(self) -> str:
        """The fit's report and what the calibration found besides (:func:`calibration_report`)."""
        return calibration_report(self)


def on_loading_path(fit: Fit) -> Fit:
    """``fit`` with the trials whose fitted equilibrium is not the one ``predict`` reaches by loading
    from the unloaded state (:func:`off_loading_path`) named in its ``off_path``.

    A laxity trial has several equilibria where the knee is bistable; the simultaneous NLP, whose
    poses are free, may put a trial on any of them, and may fit its data better there.  Each choice
    of branches is a minimum of its own: on S192803 the global search found 21 distinct minima in
    28 solves, and the lowest four had 2-4 trials each on equilibria no loading from neutral
    reaches (so that ``predict`` of the very trials fitted differs from the fit).  The trial was
    loaded from neutral: the search ranks the minima with every trial on the loading path first
    (:mod:`~kneenlp.estimation.search`).  Solving again from the loading path's poses did not help:
    the NLP went back to another branch in every case tried, and bounding every pose to 2 mm / 2 deg
    about the loading path's (16 starts, 25 trials) left 1 of 11 converged ends on it (MAP
    objectives 370-428; free poses 362-395): as the parameters move, the loading path's branch moves
    with them.  The equilibria in question lie 0.1-1.5 mm or deg apart (the knee's neutral zone)."""
    check = predict(fit.problem.model, fit.data, fit.params)
    ids = [t.id for t in fit.data.trials]
    return dataclasses.replace(fit, off_path=tuple(i for i, o in zip(ids, off_loading_path(fit, check), strict=True)
                                                   if o),
                               unstable=tuple(i for i, u in zip(ids, unstable(fit), strict=True) if u))


def unstable(fit: Fit) -> np.ndarray:
    """Per trial of ``fit``: its fitted equilibrium is unstable
    (:func:`~kneenlp.solvers.forward.unstable_equilibria`).  On S192803 most of the global search's
    minima put varus_flex0 on one."""
    problem = fit.problem
    return unstable_equilibria(problem.model, fit.q_pred, fit.theta, Loading.of(problem.trials))


def off_loading_path(fit: Fit, check: Prediction) -> np.ndarray:
    """Per trial of ``fit``: its fitted equilibrium is not what ``check`` (``predict`` at the fit's
    values) reaches from the unloaded state (none, or one more than :data:`SAME_POSE` away)."""
    gap = np.abs(check.observed_user - fit.predicted_user).max(axis=1)
    return ~check.converged | ~(gap <= SAME_POSE)


def prediction_variances(fit: Fit, data: MeasuredData, q: np.ndarray) -> np.ndarray:
    """Variance (T x 5, mm^2 or deg^2) of ``fit``'s prediction of the trials ``data`` at their
    predicted poses ``q`` (T x 5, SI): the fitted parameters' covariance (the fit's weights, noise
    from its residuals, :func:`noise_per_observation`) carried through each trial's sensitivities
    (:func:`~kneenlp.estimation.outliers.prediction_variance`); the trials' own noise not included."""
    problem = IdentificationProblem.from_data(fit.problem.model, data, fit.free)
    sens = problem.sensitivities(np.asarray(q, float).reshape(-1, 5), fit.theta)
    rows = fit.with_prior_rows(noise_per_observation(fit))
    return np.array([prediction_variance(sens[5 * t:5 * t + 5], *rows) for t in range(len(data))])


def posterior(fit: Fit) -> Posterior:
    """The Laplace posterior of ``fit``'s free parameters (:mod:`~kneenlp.model.posterior`): the
    Gauss-Newton covariance of its MAP problem, priors included (:meth:`Fit.with_prior_rows`), the
    data's rows with the declared noise or, without one, each coordinate's from the residuals
    (:func:`noise_per_observation`, as :func:`prediction_variances`); that noise's sd beside it."""
    variance = fit.noise_variance if fit.problem.noise is not None else noise_per_observation(fit)
    covariance = gauss_newton_covariance(*fit.with_prior_rows(variance), fit.scales, fit.free)
    return Posterior(tuple(fit.free), covariance, np.sqrt(variance[0]))


def noise_per_observation(fit: Fit) -> np.ndarray:
    """The noise variance of each observation of ``fit`` (T x 5, mm^2 or deg^2), per coordinate
    from the fit's residuals (sum of squares over ``T - p / 5``); NaN, not determined, when the
    trials are too few for that (``T - p / 5 < 1``: the residuals of a fit with as many parameters
    as observations say nothing of the misfit, and a zero would promise exact predictions)."""
    residuals = fit.data.q_user - fit.predicted_user
    dof = len(residuals) - len(fit.free) / 5
    if dof < 1:
        return np.full(residuals.shape, np.nan)
    return np.broadcast_to(np.sum(residuals**2, axis=0) / dof, residuals.shape).copy()


def calibration_report(calibration: Calibration) -> str:
    """The report of ``calibration``: its fit's (:func:`~kneenlp.estimation.fit.fit_report`), then
    the prediction before it, the outliers, the check and the search (mm and deg)."""
    if calibration.before is None:
        return calibration.fit.report()

    def row(rms):
        return ", ".join(f"{c.rsplit('_', 1)[0]} {v:.2f} {c.rsplit('_', 1)[1]}" for c, v in rms.items())

    lines = [calibration.fit.report(), "[[Calibration]]",
             f"    RMS before (the knee's parameters, {int(calibration.before.converged.sum())}/"
             f"{len(calibration.before.solutions)} trials at equilibrium): {row(calibration.rms_before)}",
             f"    RMS after ({len(calibration.fit.data)} trials fitted): {row(calibration.rms_after)}",
             *_outlier_lines(calibration, row),
             *_check_lines(calibration, row),
             *laxity_lines(calibration.laxity(), "    laxity after calibration (mm, deg):"),
             "    left at the knee's values (the trials do not determine them): "
             f"{', '.join(calibration.fixed) or 'none'}",
             "    slack in every trial at the knee's values, engaged at the start: "
             f"{', '.join(calibration.engaged) or 'none'}",
             *(calibration.search.lines() if calibration.search is not None else [])]
    return "\n".join(lines)

def _outlier_lines(calibration: Calibration, row: Callable) -> list[str]:
    if calibration.set_aside is None:
        return []
    lines = ["    set aside by the outlier test (fitted without them; --keep-outliers fits every trial):",
             *(f"      {o.line()}" for o in calibration.outliers)]
    failed = [s.trial.id for s in calibration.set_aside.solutions if not s.converged]
    if failed:
        lines.append(f"      no equilibrium at the calibrated values: {', '.join(failed)}")
    lines.append(f"    RMS after, with them predicted at the calibrated values: {row(calibration.rms_with_outliers)}")
    return lines

def _check_lines(calibration: Calibration, row: Callable) -> list[str]:
    if calibration.check is None:
        return []
    n, ok = len(calibration.check.solutions), int(calibration.check.converged.sum())
    lines = [f"    RMS as predict solves the calibrated knee (each trial from the unloaded state; {ok}/{n} at "
             f"equilibrium): {row(calibration.check.rms())}"]
    if calibration.elsewhere:
        lines.append("    equilibrium found only by the fit's continuation (from the unloaded state predict "
                     f"reaches none or another): {', '.join(calibration.elsewhere)}")
    return lines
