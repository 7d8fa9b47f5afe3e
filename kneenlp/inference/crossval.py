"""Predict what was not fitted: a calibration's errors on trials it did not see.

A calibration's RMS on its own trials says how well the model can be bent to them; the errors on
held-out trials say how far its predictions can be trusted.  :func:`hold_out` calibrates
(:func:`~kneenlp.inference.calibrate.calibrate`) on the trials a mask keeps and predicts the others
with the calibrated parameters, registration included (:func:`~kneenlp.inference.predict.predict`).
:func:`folds` names the two hold-outs of a laxity experiment:

* ``flexion <F> deg``: the trials at the highest nominal flexion (measured flexions grouped by
  :func:`~kneenlp.experiment.protocol.flexion_groups`; ``F`` their mean), calibrated on the others;
* ``<direction>``: every trial whose dominant load is that direction (anterior, valgus, ...),
  calibrated on the others.

Errors are measured minus predicted, RMS per coordinate (mm, deg), over the held-out trials that
reach equilibrium (the others are counted and reported, never dropped silently).  Beside each
error, what the calibration itself expects it to be: the RMS over the held-out trials of the
standard deviation of measured minus predicted, the noise the calibration estimated plus its
parameters' covariance carried to the held-out trials
(:func:`~kneenlp.inference.calibrate.prediction_variances`, linearised).  An error well above it is
a model that cannot be bent to what was held out; an expected error as large as the error is a
calibration that says itself it cannot predict that (the held-out loads were the only ones to
determine some of its parameters).  :func:`consistency` turns the comparison into a p-value: small,
the held-out errors are larger than the calibration's own uncertainty allows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from kneenlp.conventions import coordinate_columns
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.protocol import flexion_groups
from kneenlp.inference.calibrate import Calibration, calibrate, noise_per_observation, prediction_variances
from kneenlp.inference.predict import Prediction, predict, rms_by_coordinate
from kneenlp.model.kneemodel import KneeModel


def folds(data: MeasuredData) -> list[tuple[str, np.ndarray]]:
    """(name, held-out mask) of the highest-flexion hold-out and of every loaded direction."""
    nominal = flexion_groups(data.trials)
    top = nominal == nominal.max()
    out = [(f"flexion {nominal.max():.0f} deg", top)]
    words = np.array([t.dominant for t in data.trials])
    for word in dict.fromkeys(words):
        if word != "none":
            out.append((word, words == word))
    return out


@dataclass
class HeldOut:
    """One hold-out: the calibration on the kept trials and its prediction of the held-out ones."""

    name: str
    held: np.ndarray  # boolean mask over the full data's trials
    calibration: Calibration
    prediction: Prediction  # of the held-out trials
    #: what the calibration expects measured minus predicted to be, a standard deviation per held-out
    #: trial and coordinate (T x 5, mm and deg; NaN without equilibrium; module docstring)
    expected: np.ndarray

    def rms(self) -> dict[str, float]:
        """RMS of measured minus predicted per coordinate column (mm, deg), held-out trials."""
        return self.prediction.rms()

    def expected_rms(self) -> dict[str, float]:
        """RMS of :attr:`expected` per coordinate column (mm, deg), over the held-out trials at
        equilibrium: what :meth:`rms` should be if the calibration's own uncertainty is right."""
        return rms_by_coordinate(self.expected[self.prediction.converged])

    def p_value(self) -> float:
        """:func:`consistency` of the held-out trials at equilibrium (NaN if none)."""
        ok = self.prediction.converged
        return consistency(self.prediction.errors_user[ok], self.expected[ok])

    def row(self) -> dict:
        return {"held_out": self.name, "trials_fitted": int((~self.held).sum()),
                "trials_predicted": int(self.held.sum()),
                "converged": int(self.prediction.converged.sum()),
                **{f"fit_rms_{c}": v for c, v in self.calibration.rms_after.items()},
                **{f"rms_{c}": v for c, v in self.rms().items()},
                **{f"expected_rms_{c}": v for c, v in self.expected_rms().items()},
                "p_within_expected": self.p_value()}


def consistency(errors: np.ndarray, expected: np.ndarray) -> float:
    """p-value of held-out errors (T x 5, mm and deg) against the calibration's expected standard
    deviations (T x 5): the chi-square ``sum (error / expected)^2`` on as many degrees of freedom as
    finite cells, the errors taken as independent and normal (the prediction's correlations between
    a trial's coordinates are left out).  NaN with no finite cell."""
    z2 = (np.asarray(errors, float) / np.asarray(expected, float)) ** 2
    z2 = z2[np.isfinite(z2)]
    return float(stats.chi2.sf(z2.sum(), z2.size)) if z2.size else float("nan")


def hold_out(model: KneeModel, data: MeasuredData, held: np.ndarray, name: str = "held out",
             **calibrate_options) -> HeldOut:
    """Calibrate ``model`` on the trials ``held`` leaves and predict those it holds out."""
    held = np.asarray(held, bool)
    if held.all() or not held.any():
        raise ValueError(f"hold-out {name!r} must keep some trials and hold out some")
    cal = calibrate(model, data.subset(~held), **calibrate_options)
    predicted = data.subset(held)
    pred = predict(model, predicted, cal.fit.params)
    expected = np.full((len(predicted), 5), np.nan)
    ok = pred.converged
    if ok.any():
        fit = cal.fit
        variance = prediction_variances(fit, predicted.subset(ok), np.array([s.q for s in pred.solutions])[ok])
        expected[ok] = np.sqrt(variance + noise_per_observation(fit)[0])
    return HeldOut(name, held, cal, pred, expected)


def cross_validate(model: KneeModel, data: MeasuredData, which: list[str] | None = None,
                   **calibrate_options) -> list[HeldOut]:
    """Every hold-out of :func:`folds` (or those named in ``which``), in order."""
    chosen = folds(data)
    if which is not None:
        names = [n for n, _ in chosen]
        unknown = [w for w in which if w not in names]
        if unknown:
            from kneenlp.errors import unknown_name

            raise unknown_name("hold-out", unknown[0], names)
        chosen = [(n, m) for n, m in chosen if n in which]
    return [hold_out(model, data, mask, name, **calibrate_options) for name, mask in chosen]


def table(results: list[HeldOut]) -> pd.DataFrame:
    """One row per hold-out: trial counts, the calibration's RMS on its own trials and the
    held-out RMS per coordinate (columns ``fit_rms_<coordinate>``, ``rms_<coordinate>``: mm, deg)."""
    return pd.DataFrame([r.row() for r in results])


def report(results: list[HeldOut]) -> str:
    """The hold-outs as a text table (mm, deg): each error and, in brackets, the calibration's
    expected error (module docstring)."""
    cols = coordinate_columns()
    head = "  ".join(f"{c.rsplit('_', 1)[0].replace('_translation', '').replace('_rotation', ''):>13}"
                     for c in cols)
    units = "  ".join(f"{c.rsplit('_', 1)[1]:>13}" for c in cols)
    width = max(12, *(len(r.name) for r in results))
    lines = ["Held-out prediction: RMS of measured minus predicted on trials the calibration did not see",
             "(in brackets: what the calibration expects it to be, its noise and its parameters' uncertainty;",
             " p: how likely errors this large are if that expectation is right)",
             f"{'held out':<{width}}  trials  {head}  {'p':>7}", f"{'':<{width}}          {units}"]
    for r in results:
        cells = "  ".join(f"{v:5.2f} ({e:5.2f})" for v, e in zip(r.rms().values(), r.expected_rms().values(),
                                                                  strict=True))
        n = f"{int(r.prediction.converged.sum())}/{int(r.held.sum())}"
        lines.append(f"{r.name:<{width}}  {n:>6}  {cells}  {r.p_value():7.2g}")
    return "\n".join(lines)
