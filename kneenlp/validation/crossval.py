"""Predict what was not fitted: a calibration's errors on trials it did not see.

A calibration's RMS on its own trials says how well the model can be bent to them; the errors on
held-out trials say how far its predictions can be trusted.  :func:`hold_out` calibrates
(:func:`~kneenlp.estimation.calibrate.calibrate`) on the trials a mask keeps and predicts the others
with the calibrated parameters, registration included (:func:`~kneenlp.prediction.predict.predict`).
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
(:func:`~kneenlp.estimation.calibrated.prediction_variances`, linearised).  An error well above it is
a model that cannot be bent to what was held out; an expected error as large as the error is a
calibration that says itself it cannot predict that (the held-out loads were the only ones to
determine some of its parameters).  :func:`consistency` turns the comparison into a p-value: small,
the held-out errors are larger than the calibration's own uncertainty allows.  :func:`lessons` says
which parameters: those the held-out trials move, when they join the calibration, in the direction
that brings their predictions closest to them (``cross_validate(explain=True)``, the CLI's report).

That expectation is linear and counts the parameters a hold-out leaves at the knee's values as
exact.  The *twin* (:func:`twin`, ``cross_validate(reference_draws=N)``) measures instead: the
experiment as the calibrated knee itself would have produced it, every trial at its measured load
and flexion predicted at the all-trial calibration's values, with normal noise at the level that
calibration estimated (per coordinate, seeded).  The same hold-outs on the twin give the errors of
a model that is exactly right, calibrated the same way from the same trials
(:attr:`HeldOut.reference`; each draw written as it finishes and read back on a rerun, so a long
run of many twins resumes).  Errors like the twin's are what these trials and a misfit of this
size allow any model; errors well above the twin's are the model's (:func:`against_reference`, a
p-value).  ``problems/s192803`` (docs/real-experiment.md, benchmarks/bench_twins.py): at the
calibration's misfit (1.1-1.6 mm, 1.6-1.7 deg) the twin meets 2 mm and 5 deg in 2-4 of 7
hold-outs, at half of it in 5-6."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
from scipy import stats

from kneenlp.base.dask_cluster import DaskWorkers
from kneenlp.base.keywords import refuse_unknown
from kneenlp.estimation.calibrate import calibrate
from kneenlp.estimation.calibrated import Calibration, noise_per_observation, prediction_variances
from kneenlp.estimation.calibration_options import CalibrationOptions
from kneenlp.estimation.fit import Fit, forked_fits
from kneenlp.experiment.kneemodel import KneeModel
from kneenlp.experiment.measured import MeasuredData
from kneenlp.experiment.problem import IdentificationProblem
from kneenlp.experiment.protocol import flexion_groups
from kneenlp.prediction.predict import Prediction, predict, rms_by_coordinate
from kneenlp.validation.twins import TwinStore, twin

#: The held-out targets: RMS of measured minus predicted, rotations (deg) and translations (mm).
ROTATION_TARGET = 5.0
TRANSLATION_TARGET = 2.0


def folds(data: MeasuredData) -> list[tuple[str, np.ndarray]]:
    """(name, held-out mask) of the highest-flexion hold-out and of every loaded direction, those
    that leave a loaded trial to calibrate on (:func:`calibrates`)."""
    return [(name, held) for name, held in _default_folds(data) if calibrates(data, held)]


def _default_folds(data: MeasuredData) -> list[tuple[str, np.ndarray]]:
    nominal = flexion_groups(data.trials)
    top = nominal == nominal.max()
    out = [(f"flexion {nominal.max():.0f} deg", top)]
    words = np.array([t.dominant for t in data.trials])
    for word in dict.fromkeys(words):
        if word != "none":
            out.append((word, words == word))
    return out


def calibrates(data: MeasuredData, held: np.ndarray) -> bool:
    """The hold-out ``held`` holds out some trials and leaves some loaded ones to calibrate on."""
    loaded = np.array([t.dominant != "none" for t in data.trials])
    return bool(held.any() and (loaded & ~held).any())


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
    #: the same hold-out's errors on each twin of the experiment (:func:`twin`; T x 5 each, mm and
    #: deg, NaN without equilibrium; empty: none drawn)
    reference: list[np.ndarray] = field(default_factory=list)
    #: what the held-out trials teach the calibration (:func:`lessons`; empty: not asked)
    taught: list[Lesson] = field(default_factory=list)
    #: the normalised held-out error at each of the calibration's :data:`SPREAD_MINIMA` lowest minima
    #: (its global search's; empty: a local calibration): the spread the search leaves
    at_minima: list[float] = field(default_factory=list)

    def spread(self) -> float:
        """Largest minus smallest of :attr:`at_minima` (NaN with fewer than two): a candidate effect
        whose held-out error moves by less is a tie, not an improvement."""
        values = [v for v in self.at_minima if np.isfinite(v)]
        return float(max(values) - min(values)) if len(values) > 1 else float("nan")

    def rms(self) -> dict[str, float]:
        """RMS of measured minus predicted per coordinate column (mm, deg), held-out trials."""
        return self.prediction.rms()

    def expected_rms(self) -> dict[str, float]:
        """RMS of :attr:`expected` per coordinate column (mm, deg), over the held-out trials at
        equilibrium: what :meth:`rms` should be if the calibration's own uncertainty is right."""
        return rms_by_coordinate(self.expected[self.prediction.converged])

    def normalised(self) -> float:
        """The held-out error against the targets: the largest rotation RMS over
        :data:`ROTATION_TARGET` or translation RMS over :data:`TRANSLATION_TARGET` (1: on target;
        NaN when no held-out trial reached equilibrium)."""
        return normalised_error(self.rms())

    def p_value(self) -> float:
        """:func:`consistency` of the held-out trials at equilibrium (NaN if none)."""
        ok = self.prediction.converged
        return consistency(self.prediction.errors_user[ok], self.expected[ok])

    def reference_errors(self) -> np.ndarray:
        """Measured minus predicted of every twin's held-out trials at equilibrium, stacked (mm, deg)."""
        stacked = np.vstack([*self.reference, np.empty((0, 5))])
        return stacked[np.isfinite(stacked).all(axis=1)]

    def reference_rms(self) -> dict[str, float]:
        """RMS per coordinate column (mm, deg) of the twins' held-out errors, pooled over the twins:
        the error of a model that is exactly right (module docstring; NaN without twins)."""
        return rms_by_coordinate(self.reference_errors())

    def p_reference(self) -> float:
        """:func:`against_reference` of the held-out errors at equilibrium (NaN without twins)."""
        return against_reference(self.prediction.errors_user[self.prediction.converged], self.reference_errors())

    def reference_normalised(self) -> list[float]:
        """:meth:`normalised` on each twin (NaN for a twin none of whose held-out trials reached
        equilibrium): whether a model that is exactly right meets the targets here, draw by draw."""
        out = []
        for errors in self.reference:
            finite = errors[np.isfinite(errors).all(axis=1)]
            out.append(normalised_error(rms_by_coordinate(finite)) if len(finite) else float("nan"))
        return out

    def row(self) -> dict:
        out = {"held_out": self.name, "trials_fitted": int((~self.held).sum()),
               "trials_predicted": int(self.held.sum()),
               "converged": int(self.prediction.converged.sum()),
               **{f"fit_rms_{c}": v for c, v in self.calibration.rms_after.items()},
               **{f"rms_{c}": v for c, v in self.rms().items()},
               **{f"expected_rms_{c}": v for c, v in self.expected_rms().items()},
               "p_within_expected": self.p_value()}
        if self.at_minima:
            out |= {"normalised_at_minima": " / ".join(f"{v:.3f}" for v in self.at_minima),
                    "minima_spread": self.spread()}
        if self.taught:
            out["taught"] = "; ".join(f"{x.name} {x.prior_sds:+.1f} prior sd {100 * x.share:.0f} %"
                                      for x in self.taught)
        if self.reference:
            out |= {"twins": len(self.reference),
                    "twin_converged": len(self.reference_errors()),
                    **{f"twin_rms_{c}": v for c, v in self.reference_rms().items()},
                    "p_against_twin": self.p_reference(),
                    "twins_within_target": sum(v <= 1 for v in self.reference_normalised())}
        return out


@dataclass(frozen=True)
class Lesson:
    """A parameter the held-out trials teach (:func:`lessons`): its value calibrated without them and
    with them (SI), that move in its prior's standard deviations (NaN without a prior), and the share
    of the held-out trials' squared error (mm^2 + deg^2) the move alone removes, linearised."""

    name: str
    without: float
    with_them: float
    prior_sds: float
    share: float

    def text(self, model: KneeModel) -> str:
        """E.g. ``PFL.k_scale 0.86 -> 0.32 (-3.2 prior sd): 23 %`` in the parameter's display unit."""
        p = model.parameter(self.name)
        unit = f" {p.unit}" if p.unit not in ("", "1") else ""
        sds = f" ({self.prior_sds:+.1f} prior sd)" if np.isfinite(self.prior_sds) else ""
        return (f"{self.name} {self.without * p.to_user:.3g} -> {self.with_them * p.to_user:.3g}{unit}{sds}: "
                f"{100 * self.share:.0f} %")


#: :func:`lessons` names at most this many parameters per hold-out ...
LESSONS = 3
#: ... each removing at least this share of the held-out squared error.
LESSON_SHARE = 0.05


def lessons(result: HeldOut, full: Fit, data: MeasuredData) -> list[Lesson]:
    """What the trials ``result`` held out teach the calibration: the parameters whose move from the
    hold-out's calibrated value to ``full``'s (the calibration of every trial of ``data``) brings the
    held-out predictions closest to the measurements, linearised (the held-out trials' sensitivities
    at the hold-out's values times the move), each removing at least :data:`LESSON_SHARE` of their
    squared error; at most :data:`LESSONS`, the largest first.  A parameter the other trials leave
    to its prior and these trials move by prior standard deviations is why a hold-out misses:
    S192803's external rotation trials alone move the PFL's stiffness and tibial attachment
    (docs/real-experiment.md)."""
    fit, ok = result.calibration.fit, result.prediction.converged
    names = [n for n in fit.free if n in full.params]
    errors = result.prediction.errors_user[ok]
    total = float(np.sum(errors**2))
    if not names or not ok.any() or total == 0:
        return []
    q = np.array([s.q for s in result.prediction.solutions])[ok]
    held = data.subset(result.held).subset(ok)
    sens = IdentificationProblem.from_data(fit.problem.model, held, names).sensitivities(q, fit.theta)
    out = []
    for i, name in enumerate(names):
        move = (sens[:, i] * (full.params[name] - fit.params[name])).reshape(-1, 5)
        share = (total - float(np.sum((errors - move) ** 2))) / total
        prior = fit.problem.priors.get(name)
        sds = ((prior.transform(full.params[name]) - prior.transform(fit.params[name])) / prior.sd
               if prior is not None else np.nan)
        if share >= LESSON_SHARE:
            out.append(Lesson(name, fit.params[name], full.params[name], float(sds), share))
    return sorted(out, key=lambda lesson: -lesson.share)[:LESSONS]


def normalised_error(rms: dict[str, float]) -> float:
    """``max(rotation RMS / 5 deg, translation RMS / 2 mm)`` of an RMS per coordinate column."""
    rot = [v for c, v in rms.items() if c.endswith("_deg")]
    trans = [v for c, v in rms.items() if c.endswith("_mm")]
    return float(max(max(rot) / ROTATION_TARGET, max(trans) / TRANSLATION_TARGET))


@dataclass(frozen=True)
class Judgement:
    """A calibration judged by what it predicts: its fitted RMS (all trials) and its hold-outs'."""

    name: str  # "base" or the candidate's names
    also_free: tuple[str, ...]
    fitted: dict[str, float]  # RMS per coordinate column over the fitted trials (mm, deg)
    free: int  # parameters fitted
    held_out: dict[str, float]  # normalised held-out error per hold-out (:meth:`HeldOut.normalised`)
    converged: dict[str, tuple[int, int]]  # per hold-out, held-out trials at equilibrium of those held out
    #: per hold-out, :meth:`HeldOut.spread` (NaN: a local calibration, or one minimum)
    spread: dict[str, float] = field(default_factory=dict)

    @property
    def mean(self) -> float:
        return float(np.mean(list(self.held_out.values())))

    @property
    def margin(self) -> float:
        """The mean over the hold-outs of their spreads (0 where there is none): how far the mean
        held-out error may move between the searches' lowest minima, the least difference that is
        not a tie."""
        values = [v for v in self.spread.values() if np.isfinite(v)]
        return float(np.mean(values)) if values else 0.0

    @property
    def met(self) -> int:
        return sum(v <= 1 for v in self.held_out.values())

    def record(self) -> dict:
        return {"name": self.name, "also_free": list(self.also_free), "free": self.free, "fitted_rms": self.fitted,
                "held_out_normalised": self.held_out, "held_out_mean": self.mean, "held_out_met": self.met,
                "held_out_converged": {k: list(v) for k, v in self.converged.items()},
                "held_out_spread": {k: v if np.isfinite(v) else None for k, v in self.spread.items()},
                "held_out_margin": self.margin}


def judge(model: KneeModel, data: MeasuredData, candidates: list[list[str]], which: list[str] | None = None,
          **calibrate_options) -> list[Judgement]:
    """The base calibration and one with each candidate (parameters or effects fitted beside it,
    ``also_free``) judged by what they predict: each calibrated on all trials (the fitted RMS) and
    cross-validated over the hold-outs ``which`` (:func:`cross_validate`; ``calibrate_options``, its
    ``workers`` included, as :func:`~kneenlp.estimation.calibrate.calibrate`'s).  The base first."""
    out = []
    for extra in [[], *candidates]:
        options = dict(calibrate_options)
        if extra:
            options["also_free"] = [*(options.get("also_free") or []), *extra]
        cal = calibrate(model, data, **options)
        results = cross_validate(model, data, which, **options)
        out.append(Judgement(" + ".join(extra) or "base", tuple(extra), cal.rms_after, len(cal.fit.free),
                             {r.name: r.normalised() for r in results},
                             {r.name: (int(r.prediction.converged.sum()), int(r.held.sum())) for r in results},
                             {r.name: r.spread() for r in results}))
    return out


def judged_best(judgements: list[Judgement]) -> Judgement | None:
    """The candidate whose held-out error (mean normalised, every held-out trial at equilibrium) is
    lowest, if lower than the base's by more than either's :attr:`Judgement.margin` (less is a tie:
    the search's neighbouring minima move it as much); None when no candidate lowers it."""
    base, rest = judgements[0], judgements[1:]
    whole = [j for j in rest if all(ok == n for ok, n in j.converged.values())]
    best = min(whole, key=lambda j: j.mean, default=None)
    return best if best is not None and best.mean < base.mean - max(base.margin, best.margin) else None


def tied(judgements: list[Judgement]) -> list[Judgement]:
    """The candidates whose mean held-out error is below the base's by no more than the margin the
    searches leave (:attr:`Judgement.margin`): ties, not improvements."""
    base = judgements[0]
    return [j for j in judgements[1:] if base.mean - max(base.margin, j.margin) <= j.mean < base.mean]


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


#: Minima of a hold-out's global search at which its held-out error is measured (:attr:`HeldOut.at_minima`).
SPREAD_MINIMA = 3
#: The folder of a cross-validation's ``store`` that keeps its searches' finished solves.
SOLVES = "solves"


def hold_out(model: KneeModel, data: MeasuredData, held: np.ndarray, name: str = "held out",
             **calibrate_options) -> HeldOut:
    """Calibrate ``model`` on the trials ``held`` leaves and predict those it holds out."""
    held = np.asarray(held, bool)
    if held.all() or not held.any():
        raise ValueError(f"hold-out {name!r} must keep some trials and hold out some")
    cal = calibrate(model, data.subset(~held), **calibrate_options)
    predicted = data.subset(held)
    pred = predict(model, predicted, cal.fit.params)
    minima = cal.search.minima[:SPREAD_MINIMA] if cal.search is not None else []
    at_minima = [normalised_error(predict(model, predicted, m.fit.params).rms()) for m in minima]
    expected = np.full((len(predicted), 5), np.nan)
    ok = pred.converged
    if ok.any():
        fit = cal.fit
        variance = prediction_variances(fit, predicted.subset(ok), np.array([s.q for s in pred.solutions])[ok])
        expected[ok] = np.sqrt(variance + noise_per_observation(fit)[0])
    return HeldOut(name, held, cal, pred, expected, at_minima=at_minima)


@dataclass(frozen=True)
class CrossValidation:
    """:func:`cross_validate`'s keyword options (its docstring), checked in one place: its own and, in
    ``calibrate``, the calibration's given (:func:`~kneenlp.estimation.calibrate.calibrate`)."""

    reference_draws: int = 0
    store: Path | None = None
    workers: int | DaskWorkers = 1
    explain: bool = False
    calibrate: dict = field(default_factory=dict)

    @classmethod
    def from_kwargs(cls, **options) -> CrossValidation:
        """The options named in ``options``; a name neither :func:`cross_validate` nor
        :func:`~kneenlp.estimation.calibrate.calibrate` takes raises TypeError."""
        own = {f.name for f in fields(cls)} - {"calibrate"}
        refuse_unknown("cross_validate", options, own | {f.name for f in fields(CalibrationOptions)})
        return cls(**{k: v for k, v in options.items() if k in own},
                   calibrate={k: v for k, v in options.items() if k not in own})


def cross_validate(model: KneeModel, data: MeasuredData, which: list[str] | None = None,
                   **options) -> list[HeldOut]:
    """Every hold-out of :func:`folds` (or those named in ``which``), in order; ``options``: those
    below and the calibration's (:func:`~kneenlp.estimation.calibrate.calibrate`).  With
    ``reference_draws`` N, each also on N twins of the experiment (:func:`twin_draw`), each draw
    written to ``store`` as it finishes and read back from there on a rerun (:class:`TwinStore`);
    with a ``store``, every global search's finished solves (the hold-outs', the twins') are kept in
    its :data:`SOLVES` folder too (the search's ``store``), so an interrupted run resumes mid-way.
    ``workers`` > 1 calibrates the hold-outs in that many forked processes (:func:`hold_outs`), those
    left over from whole rounds one at a time with their global searches over the workers (7 hold-outs
    of S192803 on 2: the seventh's search on both, not the 4th round of one process); a
    :class:`~kneenlp.base.dask_cluster.DaskWorkers` calibrates them in turn, each global search
    (``starts``) on Dask.
    ``explain``: each hold-out's :func:`lessons` too (one more calibration, of every trial)."""
    opts = CrossValidation.from_kwargs(**options)
    data.check_observed("cross-validation")
    calibrate_options, workers, store, reference_draws = opts.calibrate, opts.workers, opts.store, opts.reference_draws
    explain = opts.explain
    chosen = chosen_hold_outs(data, which)
    names = [n for n, _ in chosen]
    # the store is checked before the first calibration: a store of another run stops at once
    saved = TwinStore.open(store, model, data, names, calibrate_options) if store and reference_draws else None
    if store and calibrate_options.get("store") is None:  # every search's solves kept: a rerun resumes mid-way
        calibrate_options = calibrate_options | {"store": Path(store) / SOLVES}
    whole = calibrate_options | {"workers": workers}  # a calibration in turn: its search over the workers
    if isinstance(workers, DaskWorkers):  # the hold-outs in turn, each calibration's search on Dask
        calibrate_options = whole
        results = [hold_out(model, data, mask, name, **whole) for name, mask in chosen]
    else:  # whole rounds over the workers; the rest (fewer than the workers) in turn, each search over them all
        split = len(chosen) - len(chosen) % workers
        results = hold_outs(model, data, chosen[:split], workers, **calibrate_options)
        results += [hold_out(model, data, mask, name, **whole) for name, mask in chosen[split:]]
    fit = calibrate(model, data, **whole).fit if explain else None
    for r in results if explain else ():
        r.taught.extend(lessons(r, fit, data))
    for draw in range(reference_draws):
        errors = saved.load(draw) if saved else None
        if errors is None:
            if fit is None:  # (only where a draw is still to run)
                fit = calibrate(model, data, **whole).fit
            errors = twin_draw(fit, data, draw, names, calibrate_options)
            if saved:
                saved.save(draw, errors)
        for r in results:
            if r.name in errors:
                r.reference.append(errors[r.name])
    return results


def hold_outs(model: KneeModel, data: MeasuredData, chosen: list[tuple[str, np.ndarray]], workers: int = 1,
              **calibrate_options) -> list[HeldOut]:
    """:func:`hold_out` of every ``chosen`` (name, mask), in order, shared out over ``workers``
    forked processes (:func:`~kneenlp.estimation.fit.forked_fits`; each calibration is deterministic
    and independent of the others, so the results are the sequential ones)."""
    return forked_fits(lambda item: hold_out(model, data, item[1], item[0], **calibrate_options), chosen, workers,
                       model, fit_of=lambda r: r.calibration.fit)


def twin_draw(fit: Fit, data: MeasuredData, draw: int, names: list[str],
              calibrate_options: dict) -> dict[str, np.ndarray]:
    """The hold-outs ``names`` on twin number ``draw`` of the experiment ``data`` calibrated by ``fit``
    (a :class:`~kneenlp.estimation.fit.Fit` on every trial, of the model the twin is drawn from):
    :func:`twin` at the fit's values with its estimated noise
    (:func:`~kneenlp.estimation.calibrated.noise_per_observation`), drawn from the generator seeded by
    ``(seed, draw)`` (``seed`` of ``calibrate_options``, default 0: any draw alone reproduces), each
    hold-out calibrated with ``calibrate_options``; held-out errors by hold-out name (T x 5, mm and
    deg, NaN without equilibrium; a hold-out whose trials the twin lacks is left out)."""
    model = fit.model
    rng = np.random.default_rng([calibrate_options.get("seed", 0), draw])
    copy = twin(model, data, fit.params, np.sqrt(noise_per_observation(fit)[0]), rng)
    masks = dict(folds(copy))
    return {n: hold_out(model, copy, masks[n], n, **calibrate_options).prediction.errors_user
            for n in names if n in masks}


def flexion_folds(data: MeasuredData) -> list[tuple[str, np.ndarray]]:
    """(name, held-out mask) of every flexion, all its trials held out (the highest is one of
    :func:`folds`; the others are hold-outs a user names: checks the default ones did not choose)."""
    nominal = flexion_groups(data.trials)
    return [(f"flexion {f:.0f} deg", nominal == f) for f in np.unique(nominal)]


def chosen_hold_outs(data: MeasuredData, which: list[str] | None) -> list[tuple[str, np.ndarray]]:
    """The hold-outs of :func:`folds` named in ``which`` (all of them if None), or any flexion of
    :func:`flexion_folds`; an unknown name is an error."""
    from kneenlp.base.errors import InputError, unknown_name

    chosen = folds(data)
    if which is not None:
        known = dict(flexion_folds(data)) | dict(_default_folds(data))
        unknown = [w for w in which if w not in known]
        if unknown:
            raise unknown_name("hold-out", unknown[0], list(known), field="--hold-out")
        chosen = [(n, known[n]) for n in dict.fromkeys(which)]
        for name, held in chosen:
            if not calibrates(data, held):
                raise InputError(f"hold-out {name!r} leaves no loaded trial to calibrate on", field="--hold-out")
    if not chosen:
        raise InputError("no hold-out leaves loaded trials to calibrate on: cross-validation needs trials at two "
                         "flexions or in two load directions", source=data.source, field="data")
    return chosen
