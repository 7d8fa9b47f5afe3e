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

That expectation is linear and counts the parameters a hold-out leaves at the knee's values as
exact.  The *twin* (:func:`twin`, ``cross_validate(reference_draws=N)``) measures instead: the
experiment as the calibrated knee itself would have produced it, every trial at its measured load
and flexion predicted at the all-trial calibration's values, with normal noise at the level that
calibration estimated (per coordinate, seeded).  The same hold-outs on the twin give the errors of
a model that is exactly right, calibrated the same way from the same trials
(:attr:`HeldOut.reference`).  Errors like the twin's are the protocol's: what the held-out trials
alone determine cannot be predicted from the others, whatever the model; errors well above the
twin's are the model's (:func:`against_reference`, a p-value).  S192803 (docs/real-experiment.md
"Session 19"): the twin misses the external hold-out by 8-11 deg too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import stats

from kneenlp.conventions import coordinate_columns
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.noise import NoiseModel
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
    #: the same hold-out on each twin of the experiment (:func:`twin`; empty: none drawn)
    reference: list[HeldOut] = field(default_factory=list)

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

    def reference_errors(self) -> np.ndarray:
        """Measured minus predicted of every twin's held-out trials at equilibrium, stacked (mm, deg)."""
        return np.vstack([r.prediction.errors_user[r.prediction.converged] for r in self.reference]
                         or [np.empty((0, 5))])

    def reference_rms(self) -> dict[str, float]:
        """RMS per coordinate column (mm, deg) of the twins' held-out errors, pooled over the twins:
        the error of a model that is exactly right (module docstring; NaN without twins)."""
        return rms_by_coordinate(self.reference_errors())

    def p_reference(self) -> float:
        """:func:`against_reference` of the held-out errors at equilibrium (NaN without twins)."""
        return against_reference(self.prediction.errors_user[self.prediction.converged], self.reference_errors())

    def row(self) -> dict:
        out = {"held_out": self.name, "trials_fitted": int((~self.held).sum()),
               "trials_predicted": int(self.held.sum()),
               "converged": int(self.prediction.converged.sum()),
               **{f"fit_rms_{c}": v for c, v in self.calibration.rms_after.items()},
               **{f"rms_{c}": v for c, v in self.rms().items()},
               **{f"expected_rms_{c}": v for c, v in self.expected_rms().items()},
               "p_within_expected": self.p_value()}
        if self.reference:
            out |= {"twins": len(self.reference),
                    "twin_converged": sum(int(r.prediction.converged.sum()) for r in self.reference),
                    **{f"twin_rms_{c}": v for c, v in self.reference_rms().items()},
                    "p_against_twin": self.p_reference()}
        return out


def consistency(errors: np.ndarray, expected: np.ndarray) -> float:
    """p-value of held-out errors (T x 5, mm and deg) against the calibration's expected standard
    deviations (T x 5): the chi-square ``sum (error / expected)^2`` on as many degrees of freedom as
    finite cells, the errors taken as independent and normal (the prediction's correlations between
    a trial's coordinates are left out).  NaN with no finite cell."""
    z2 = (np.asarray(errors, float) / np.asarray(expected, float)) ** 2
    z2 = z2[np.isfinite(z2)]
    return float(stats.chi2.sf(z2.sum(), z2.size)) if z2.size else float("nan")


def against_reference(errors: np.ndarray, reference: np.ndarray) -> float:
    """p-value of held-out errors (T x 5, mm and deg) against the twins' (R x 5) at the same
    hold-out: per coordinate, the ratio of the errors' mean square to the twins' is F(n, m) (n, m
    its finite cells), its p-values combined over the coordinates by Fisher's method (exact for
    independent normal cells; a hold-out's errors share its fixed parameters' bias, so this is an
    approximation).  Small, the model misses by more than a model that is exactly right would.
    NaN without a coordinate with finite cells on both sides."""
    errors, reference = np.asarray(errors, float), np.asarray(reference, float)
    p = []
    for e, r in zip(errors.T, reference.T, strict=True):
        e, r = e[np.isfinite(e)], r[np.isfinite(r)]
        if e.size and r.size and np.any(r != 0):
            p.append(stats.f.sf(np.mean(e**2) / np.mean(r**2), e.size, r.size))
    if not p:
        return float("nan")
    return float(stats.chi2.sf(-2.0 * np.sum(np.log(np.maximum(p, 1e-300))), 2 * len(p)))


def twin(model: KneeModel, data: MeasuredData, parameters: dict[str, float], sd: np.ndarray,
         rng: np.random.Generator) -> MeasuredData:
    """The experiment as the knee with ``parameters`` would have produced it: every trial of
    ``data`` at its measured load and flexion predicted (registration included), plus normal noise
    of standard deviation ``sd`` per coordinate (5, mm and deg) drawn from ``rng`` (a (T, 5) draw
    of standard normals, scaled).  A trial without equilibrium is left out."""
    truth = predict(model, data, parameters)
    ok = truth.converged
    q = truth.predicted_user[ok] + NoiseModel("gaussian", 1.0).sample(rng, (int(ok.sum()), 5)) * sd
    trials = [t for t, k in zip(data.trials, ok, strict=True) if k]
    return MeasuredData.from_user(trials, q, data.protocol, f"twin of {data.source}", data.side)


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
                   reference_draws: int = 0, **calibrate_options) -> list[HeldOut]:
    """Every hold-out of :func:`folds` (or those named in ``which``), in order; with
    ``reference_draws`` N, each also on N twins of the experiment (:func:`twin`: from the
    calibration on every trial, noise drawn from ``calibrate_options``' ``seed``, default 0)."""
    results = [hold_out(model, data, mask, name, **calibrate_options) for name, mask in _chosen(data, which)]
    if reference_draws:
        fit = calibrate(model, data, **calibrate_options).fit
        rng = np.random.default_rng(calibrate_options.get("seed", 0))
        for _ in range(reference_draws):
            copy = twin(model, data, fit.params, np.sqrt(noise_per_observation(fit)[0]), rng)
            masks = dict(folds(copy))
            for r in results:
                if r.name in masks:  # (a twin without the trials of a hold-out has none of it)
                    r.reference.append(hold_out(model, copy, masks[r.name], r.name, **calibrate_options))
    return results


def _chosen(data: MeasuredData, which: list[str] | None) -> list[tuple[str, np.ndarray]]:
    """The hold-outs of :func:`folds` named in ``which`` (all if None); an unknown name is an error."""
    chosen = folds(data)
    if which is not None:
        names = [n for n, _ in chosen]
        unknown = [w for w in which if w not in names]
        if unknown:
            from kneenlp.errors import unknown_name

            raise unknown_name("hold-out", unknown[0], names)
        chosen = [(n, m) for n, m in chosen if n in which]
    return chosen


def table(results: list[HeldOut]) -> pd.DataFrame:
    """One row per hold-out: trial counts, the calibration's RMS on its own trials and the
    held-out RMS per coordinate (columns ``fit_rms_<coordinate>``, ``rms_<coordinate>``: mm, deg)."""
    return pd.DataFrame([r.row() for r in results])


def report(results: list[HeldOut]) -> str:
    """The hold-outs as a text table (mm, deg): each error and, in brackets, the calibration's
    expected error (module docstring); with twins, a second table of each error beside the twins'."""
    cols = coordinate_columns()
    head = "  ".join(f"{c.rsplit('_', 1)[0].replace('_translation', '').replace('_rotation', ''):>13}"
                     for c in cols)
    units = "  ".join(f"{c.rsplit('_', 1)[1]:>13}" for c in cols)
    width = max(12, *(len(r.name) for r in results))

    def rows(second, p):
        for r in results:
            cells = "  ".join(f"{v:5.2f} ({e:5.2f})" for v, e in zip(r.rms().values(), second(r).values(),
                                                                      strict=True))
            n = f"{int(r.prediction.converged.sum())}/{int(r.held.sum())}"
            yield f"{r.name:<{width}}  {n:>6}  {cells}  {p(r):7.2g}"

    header = [f"{'held out':<{width}}  trials  {head}  {'p':>7}", f"{'':<{width}}          {units}"]
    lines = ["Held-out prediction: RMS of measured minus predicted on trials the calibration did not see",
             "(in brackets: what the calibration expects it to be, its noise and its parameters' uncertainty;",
             " p: how likely errors this large are if that expectation is right)",
             *header, *rows(HeldOut.expected_rms, HeldOut.p_value)]
    twins = max((len(r.reference) for r in results), default=0)
    if twins:
        lines += ["", f"The same beside, in brackets, the same hold-out of the experiment's twin ({twins} noise draw"
                  f"{'s' if twins > 1 else ''}): the calibrated knee's",
                  "own predictions of every trial plus noise at the calibration's level, i.e. the error of a model",
                  "that is exactly right, calibrated the same way (p: how likely errors this large are for it)",
                  *header, *rows(HeldOut.reference_rms, HeldOut.p_reference)]
    return "\n".join(lines)
