"""Model adequacy: where the model fails, which physical effect is missing, and what adding it does.

``diagnose(fit, noise)`` judges a base fit (:func:`kneenlp.adequacy.basefit.base_fit` makes one
with the noise model) against the declared noise (mm, deg):

* **global test**: ``chi2 = sum r^2 / sigma^2`` on ``N - p`` degrees of freedom (for uniform noise
  the statistic is less dispersed than chi-square, so the test is conservative), RMS residual vs
  the noise RMS, every residual beyond the noise bound;
* **where**: a residual map (trials x coordinates, in noise standard deviations), failure patterns
  in words (:mod:`kneenlp.adequacy.patterns`) and the three worst cells;
* **targeted tests** of every candidate effect (:mod:`kneenlp.model.effects`: force elements,
  parameter groups and the position of every ligament attachment): the score test from the base
  fit, a refit of the best ``refit`` of them (:mod:`kneenlp.adequacy.candidates`); each with its
  detection limit for this protocol (:mod:`kneenlp.adequacy.detection`);
* **verdict** (:mod:`kneenlp.adequacy.verdict`): the global and targeted tests as one family,
  Holm-corrected at level ``alpha``; outcome ``adequate``, ``missing_effect`` (with the
  recommended effect and its estimate), ``noise_larger`` (with the noise level the data imply) or
  ``unexplained``.

One quantity says how much of the misfit an effect explains: **excess misfit explained**, the
refit's chi-square drop over the base fit's excess chi-square (``chi2 - dof``), given only when
that excess is significant; otherwise the drop itself (chi-square units) and its p-value.  The
score test's drop is the one-step prediction of the same drop, labelled "score".
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from kneenlp.adequacy.candidates import EffectScore, refit_with, score_effects
from kneenlp.adequacy.detection import DetectionTest, detection_limits, simulated_limits_either_way
from kneenlp.adequacy.patterns import Pattern, failure_patterns
from kneenlp.adequacy.verdict import ALPHA, AMBIGUOUS_BIC, BaseMisfit, Verdict, decide
from kneenlp.base.atomic import write_csv_atomic, write_text_atomic
from kneenlp.base.conventions import COORDINATE_UNITS, COORDINATES
from kneenlp.base.errors import InputError
from kneenlp.base.keywords import keyword_options
from kneenlp.estimation.fit import Fit
from kneenlp.estimation.minima import COMPETING
from kneenlp.estimation.statistics import chi_square_test
from kneenlp.experiment.noise import NoiseModel
from kneenlp.model.ligament import SHIFT_AXES

__all__ = ["Diagnosis", "EffectScore", "diagnose", "rank_effects", "refit_with"]
#: Share of the excess misfit (chi-square over its degrees of freedom) a candidate that leaves the
#: fit still inadequate must remove before the verdict advises adding it: the issue-24 case (data of
#: the multi-bundle knee diagnosed with the single-bundle one) named a candidate removing 20-22 %
#: that changed with the noise seed.
ADVISE_SHARE = 0.5


#: Score-test p-value (unadjusted) below which a candidate is refitted when the global test passes.
REFIT_P = 0.05
#: Words for the signs of the attachment-shift axes (positive, negative).
AXIS_WORDS = {"anterior": ("anterior", "posterior"), "proximal": ("proximal", "distal"),
              "lateral": ("lateral", "medial")}


@dataclass
class Diagnosis:
    """Everything :func:`diagnose` found (residuals mm and deg; see module docstring)."""

    fit: Fit
    noise: NoiseModel
    rms: float
    expected_rms: float
    chi2: float
    dof: int
    p_value: float  # the global chi-square test
    flagged: list[dict]
    residual_map: pd.DataFrame
    worst: list[str]
    patterns: list[Pattern] = field(default_factory=list)
    ranking: list[EffectScore] = field(default_factory=list)
    decision: Verdict | None = None
    verdict: str = ""
    refits: dict[str, Fit] = field(default_factory=dict)  # effect name -> refitted Fit
    seconds: float = 0.0
    limits: str = "linear"  # how the detection limits were computed: "linear", "simulated" or "none"
    #: the figures' range over the competing minima of the fit's search (:func:`minima_spread`)
    spread: dict = field(default_factory=dict)

    @property
    def outcome(self) -> str:
        return self.decision.outcome if self.decision else ("adequate" if self.p_value >= ALPHA else "unexplained")

    @property
    def adequate(self) -> bool:
        return self.outcome == "adequate"

    @property
    def recommended(self) -> EffectScore | None:
        """The effect to add: significant after the multiplicity correction, and its refit brings the
        misfit down to the noise."""
        name = self.decision.recommended if self.decision else None
        return next((s for s in self.ranking if s.effect == name), None) if name else None

    @property
    def named(self) -> EffectScore | None:
        """The significant candidate with the best refit (recommended or not), if any."""
        name = self.decision.best if self.decision else None
        return next((s for s in self.ranking if s.effect == name), None) if name else None

    def summary(self) -> dict:
        rec = self.recommended
        return {"adequate": self.adequate, "outcome": self.outcome, "p_value": self.p_value, "chi2": self.chi2,
                "dof": self.dof, "rms": self.rms, "expected_rms": self.expected_rms, "noise": str(self.noise),
                "flagged": self.flagged, "worst": self.worst, "patterns": [p.words() for p in self.patterns],
                "pattern_means": [{"coordinate": p.coordinate, "where": p.where, "mean": p.mean,
                                   "same_sign": p.same_sign, "trials": len(p.trials)} for p in self.patterns],
                "ranking": [s.to_dict() for s in self.ranking], "tests": self.decision.to_dict() if self.decision
                else None, "recommended": rec.effect if rec else None,
                "estimate": estimate_words(self.fit, rec, self.refits.get(rec.effect)) if rec else None,
                "verdict": self.verdict, "base_starts": self.fit.starts,
                "detection_limits": self.limits, "spread": self.spread,
                "seconds": self.seconds}

    def to_json(self) -> str:
        from kneenlp.base.serialize import dumps

        return dumps(self.summary())

    def report(self) -> str:
        adj = self.decision.adjusted if self.decision else {}
        lines = [f"[[Adequacy]] {self.fit.data.source or 'data'} against noise {self.noise}",
                 f"    RMS residual {self.rms:.3f} (mm, deg); expected from the noise {self.expected_rms:.3f}",
                 f"    global test: chi-square {self.chi2:.1f} on {self.dof} degrees of freedom, p = "
                 f"{self.p_value:.3g} (Holm-adjusted {adj.get('global', self.p_value):.3g})",
                 f"    residuals beyond the noise bound: {len(self.flagged)}"]
        lines.append("[[Where it fails]]")
        lines += [f"    {p.words()}" for p in self.patterns] or ["    no pattern beyond the noise"]
        if self.spread:
            ranges = "; ".join(f"{p.coordinate.replace('_', ' ')} {p.where} {lo:+.2f} to {hi:+.2f} {p.unit}"
                               for p, (lo, hi) in zip(self.patterns, self.spread["pattern_means"], strict=True))
            lo, hi = self.spread["chi2"]
            lines.append(f"    over the {self.spread['minima']} competing minima of the search (within "
                         f"{100 * COMPETING:g} % of its MAP): chi-square {lo:.0f} to {hi:.0f}"
                         + (f"; {ranges}" if ranges else ""))
        lines += ["    worst cells:"] + [f"      {w}" for w in self.worst]
        if self.ranking:
            lines.append(f"[[Candidate effects]] chi-square drop in units of the declared noise variance (score: one "
                         f"step; refit: exact), p Holm-adjusted over {len(adj) or len(self.ranking) + 1} tests; "
                         f"detection limit ({self.limits}): smallest effect flagged in half of repeated "
                         "experiments")
            width = max(len(s.effect) for s in self.ranking)
            for s in self.ranking:
                ref = (" " * 28 if not s.refit else f" refit {'failed':>7s}{'':14s}" if not s.refit["success"]
                       else f" refit {s.refit['chi2_drop']:7.1f} dBIC {s.refit['delta_bic']:+6.1f}")
                limit = _limit_words(s)
                p = adj.get(s.effect, s.p_value)
                lines.append(f"    {s.effect:{width}s} df {s.df} score {s.score_chi2:7.1f}{ref}  p {p:8.2g}"
                             + (f"  limit {limit}" if limit else ""))
        lines.append(f"[[Verdict]] {self.verdict}")
        return "\n".join(lines)

    def write(self, out: str | Path) -> list[Path]:
        """Figures, ``residual_map.csv`` and ``diagnosis.json`` into ``out``; with a recommended
        effect also the refit's figures (``after_<effect>/``) and the parameters before and after
        it (``parameters_before_after_<effect>.csv``, display units)."""
        out = Path(out)
        files = self.figures(out)
        write_csv_atomic(self.residual_map, out / "residual_map.csv", float_format="%.6g")
        files += [out / "residual_map.csv", write_text_atomic(out / "diagnosis.json", self.to_json())]
        rec = self.recommended
        if rec is not None:
            after = self.refits[rec.effect]
            files += diagnose(after, self.noise, refit=0, limits=False).figures(out / f"after_{rec.effect}")
            rows = []
            for n in after.free:
                par = after.model.parameter(n)
                rows.append({"parameter": n, "unit": par.unit,
                             "before": self.fit.params[n] * par.to_user if n in self.fit.params else None,
                             "after": after.params[n] * par.to_user, "after_stderr": after.stderr[n] * par.to_user})
            path = out / f"parameters_before_after_{rec.effect}.csv"
            write_csv_atomic(pd.DataFrame(rows), path, index=False, float_format="%.6g")
            files.append(path)
        return files

    def figures(self, out: str | Path) -> list[Path]:
        """Residual heat map and measured vs predicted laxity curves (mm, deg)."""
        from kneenlp.experiment.measured import measured_frame
        from kneenlp.figures import plots

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        trials = self.fit.data.trials
        pred = measured_frame(trials, self.fit.predicted_user)
        meas = measured_frame(trials, self.fit.data.q_user)
        band = self.noise.bound if self.noise.bound else 2 * self.noise.std
        return [plots.residual_map(self.residual_map, out / "residual_map.png",
                                   f"residual / noise sd (sd {self.noise.std:.3g} mm or deg)"),
                plots.laxity_curves(pred, out / "laxity_fit.png", "model (line, +- noise band) vs measured (x)",
                                    measured=meas, band=band)]


def _short_names(names: list[str]) -> list[str]:
    """Short labels of an effect's parameters: what differs between them."""
    tails = [n.rsplit(".", 1)[-1] for n in names]
    if len(set(tails)) < len(tails):
        return [n.split(".", 1)[0] for n in names]
    return [t.split("_", 1)[1] if t.startswith(("femur_", "tibia_")) else t for t in tails]


def _limit_words(s: EffectScore) -> str:
    if not s.detection_limit:
        return ""
    vals = [f"{v:.2g}" if np.isfinite(v) else "unseen" for v in s.detection_limit.values()]
    units = s.units or [s.unit] * len(vals)
    if len(vals) == 1:
        return f"{vals[0]} {units[0]}"
    if len(set(units)) == 1:
        return ", ".join(f"{k} {v}" for k, v in zip(_short_names(s.parameters), vals, strict=True)) + f" {units[0]}"
    return ", ".join(f"{k} {v} {u}" for k, v, u in zip(_short_names(s.parameters), vals, units, strict=True))


def _words(trial, coord: str, unit: str, r: float) -> str:
    where = "above" if r > 0 else "below"
    what = trial.describe().replace("no load", "unloaded")
    return f"{coord.replace('_', ' ')} in {trial.id} ({what}): model {abs(r):.2f} {unit} {where} the measurement"


@dataclass(frozen=True)
class DiagnoseOptions:
    """:func:`diagnose`'s keyword options (its docstring), checked in one place."""

    effects: list[str] | None = None
    refit: int = 4
    alpha: float = ALPHA
    limits: bool | str = True
    minima: list[Fit] | None = None


def diagnose(fit: Fit, noise: str | NoiseModel = "uniform:0.5", **options) -> Diagnosis:
    """Judge ``fit`` against ``noise`` (see module docstring): score every candidate effect (``effects``,
    default all), refit the best ``refit`` (default 4) of them (only those with score p < :data:`REFIT_P`
    when the global test passes), give each its detection limit and decide at family level ``alpha``
    (default :data:`~kneenlp.adequacy.verdict.ALPHA`).

    ``limits``: ``True`` (default) or ``"linear"`` for the linearised detection limits (instant),
    ``"simulated"`` for limits from simulated noise-free data (:func:`~kneenlp.adequacy.detection.simulated_limits`,
    a few seconds per parameter; exact where the linearisation is optimistic, e.g. the linear strain
    limits), ``False`` for none."""
    opts = keyword_options(DiagnoseOptions, "diagnose", options)
    fit.data.check_observed("diagnose")
    effects, refit, alpha, limits = opts.effects, opts.refit, opts.alpha, opts.limits
    if limits not in (True, False, "linear", "simulated"):
        from kneenlp.base.errors import unknown_name

        raise unknown_name("detection-limit kind", str(limits), ["linear", "simulated"])
    t0 = time.perf_counter()
    noise = NoiseModel.parse(noise)
    sigma = noise.std
    r = fit.residuals
    n_obs = r.size
    if n_obs <= len(fit.free):
        raise InputError(f"{n_obs} observations ({len(fit.data)} trial(s) x 5 coordinates) cannot judge a fit of "
                         f"{len(fit.free)} free parameters: no degree of freedom is left to test; measure more trials",
                         source=fit.data.source)
    if not sigma > 0:
        raise InputError(f"needs a noise level above zero, got {noise}", field="noise")
    chi2, dof, p_value = chi_square_test(r, fit.weights, sigma**2, len(fit.free))
    rms = float(np.sqrt(np.mean(r**2)))
    expected = float(sigma * np.sqrt(dof / n_obs))
    flagged = []
    if noise.bound:
        for i, j in zip(*np.nonzero(np.abs(r) > noise.bound), strict=True):
            flagged.append({"trial": fit.data.trials[i].id, "coordinate": COORDINATES[j], "residual": float(r[i, j]),
                            "unit": COORDINATE_UNITS[j]})
    rmap = pd.DataFrame(r / sigma, index=[t.id for t in fit.data.trials], columns=list(COORDINATES))
    order = np.argsort(-np.abs(r / sigma), axis=None)[:3]
    worst = [_words(fit.data.trials[k // 5], COORDINATES[k % 5], COORDINATE_UNITS[k % 5], r.flat[k]) for k in order]
    diag = Diagnosis(fit, noise, rms, expected, chi2, dof, p_value, flagged, rmap, worst,
                     patterns=failure_patterns(fit.data.trials, r, sigma))
    if opts.minima:
        diag.spread = minima_spread(diag.patterns, opts.minima, sigma)
    diag.ranking = score_effects(fit, sigma, effects)
    # refits cost a solve each: only for candidates with some evidence, unless the global test fails
    # (then the score test may under-score a nonlinear effect such as a slack bundle switched on)
    for s in diag.ranking[:refit]:
        if s.score_p < REFIT_P or p_value < alpha:
            s.refit, diag.refits[s.effect] = refit_with(fit, s, sigma)
    # the score test is linear in the effect, the refit is not: refitted candidates first, by BIC
    done = sorted([s for s in diag.ranking if s.refit], key=lambda s: s.refit["delta_bic"])
    partner = _other_side(done[0].effect) if done and refit else None
    if partner and partner not in diag.refits:
        # the other attachment of the same ligament is the best one's closest mimic (moving the femoral
        # end by d looks like moving the tibial end by -d near the reference pose): it is always refitted
        # too, so that the verdict compares them (a moved ACL femoral attachment was once recommended as
        # the tibial one, its partner left unrefitted at rank 5 of the score test)
        s = next(x for x in diag.ranking if x.effect == partner)
        s.refit, diag.refits[partner] = refit_with(fit, s, sigma)
        done = sorted([s for s in diag.ranking if s.refit], key=lambda s: s.refit["delta_bic"])
    diag.ranking = done + [s for s in diag.ranking if not s.refit]
    diag.limits = "none" if not limits else ("simulated" if limits == "simulated" else "linear")
    if limits:
        level = alpha / (len(diag.ranking) + 1)  # the first (strictest) level of Holm's procedure
        for s in diag.ranking:
            if limits == "simulated":
                s.detection_limit = simulated_limits_either_way(fit, DetectionTest(sigma, s.df, level), s.parameters)
            else:
                s.detection_limit = detection_limits(fit, DetectionTest(sigma, s.df, level), s.parameters)
    weighted = {name: (f.residuals * np.sqrt(f.weights)).ravel() for name, f in diag.refits.items()}
    diag.decision = decide(p_value, diag.ranking, BaseMisfit(fit.data.trials, r, noise, dof), alpha=alpha,
                           refit_residuals=weighted)
    diag.verdict = verdict_words(diag)
    diag.seconds = time.perf_counter() - t0
    return diag


def minima_spread(patterns: list[Pattern], minima: list[Fit], sigma: float) -> dict:
    """The chi-square and each pattern's mean (mm, deg) as ranges ``(low, high)`` over the fits at a
    search's competing minima (same trials): a figure compared across effects or machines means no
    more than this range, as any of these minima could be ranked first."""
    chi2 = [chi_square_test(f.residuals, f.weights, sigma**2, len(f.free))[0] for f in minima]
    means = [[p.mean_of(f.residuals) for f in minima] for p in patterns]
    return {"minima": len(minima), "chi2": (min(chi2), max(chi2)),
            "pattern_means": [(min(m), max(m)) for m in means]}


def _other_side(effect: str) -> str | None:
    """``X_tibial_attachment`` for ``X_femoral_attachment`` and back; ``None`` for other effects."""
    for a, b in (("_femoral_attachment", "_tibial_attachment"), ("_tibial_attachment", "_femoral_attachment")):
        if effect.endswith(a):
            return effect.removesuffix(a) + b
    return None


def rank_effects(fit: Fit, sigma: float, effects: list[str] | None = None) -> list[EffectScore]:
    """Score test of every candidate effect, best first (:func:`~kneenlp.adequacy.candidates.score_effects`)."""
    return score_effects(fit, sigma, effects)


def along_the_ligament(fit: Fit, ligament: str, names: list[str]) -> tuple[float, float, float, np.ndarray]:
    """How well a refitted attachment shift (parameters ``names``) is determined: its component
    (mm) along the direction the data see least (the covariance's largest axis, oriented towards
    the femur; close to the ligament's line, which the reference strain makes nearly invisible),
    that component's standard error (mm), the largest standard error across it (mm) and the
    direction (unit vector, anterior/proximal/lateral)."""
    u = fit.model.knee.ligaments[ligament].direction()
    names = [n for axis in SHIFT_AXES for n in names if n.endswith(f"_{axis}")]
    idx = [fit.free.index(n) for n in names]
    cov = fit.covariance[np.ix_(idx, idx)] * 1e6  # m^2 -> mm^2
    shift = 1e3 * np.array([fit.params[n] for n in names])
    if not np.all(np.isfinite(cov)):
        return float(u @ shift), np.inf, np.inf, u
    var, axes = np.linalg.eigh(cov)
    weak = axes[:, -1] * (1.0 if axes[:, -1] @ u >= 0 else -1.0)
    return float(weak @ shift), float(np.sqrt(max(var[-1], 0.0))), float(np.sqrt(max(var[-2], 0.0))), weak


def _axis_words(shift: np.ndarray) -> str:
    """A shift (mm; anterior, proximal, lateral) in words, largest part first: "4.1 mm anterior,
    0.6 mm distal and 0.2 mm medial"."""
    parts = [f"{abs(v):.1f} mm {AXIS_WORDS[a][0 if v >= 0 else 1]}"
             for v, a in sorted(zip(shift, SHIFT_AXES, strict=True), key=lambda p: -abs(p[0]))]
    return f"{', '.join(parts[:-1])} and {parts[-1]}"


def estimate_words(base: Fit, score: EffectScore, after: Fit | None) -> str:
    """The refitted effect in words, e.g. "the MCL tibial attachment is about 4.1 mm anterior,
    0.6 mm distal and 0.2 mm medial (+- 0.5, 0.9, 0.4 mm) of where the knee file puts it"."""
    if after is None:
        return ""
    model = base.model
    vals = {n: after.params[n] * model.parameter(n).to_user for n in score.parameters}
    errs = {n: after.stderr[n] * model.parameter(n).to_user for n in score.parameters}
    if score.effect.endswith("_attachment"):
        lig, side = score.effect.removesuffix("_attachment").rsplit("_", 1)
        along, sd_along, sd_across, weak = along_the_ligament(after, lig, score.parameters)
        by_axis = {a: next(n for n in score.parameters if n.endswith(f"_{a}")) for a in SHIFT_AXES}
        shift = np.array([vals[by_axis[a]] for a in SHIFT_AXES])
        if sd_along > 2 * sd_across:
            # the point along the line is barely determined: state the line's displacement (the shift
            # across the ligament), then the along-line part with its large uncertainty
            angle = np.degrees(np.arccos(min(1.0, abs(weak @ model.knee.ligaments[lig].direction()))))
            return (f"the {lig} line at its {side} attachment is about {_axis_words(shift - along * weak)} of "
                    f"where the knee file puts it (+- {sd_across:.1f} mm across the ligament); along the ligament "
                    f"(the direction the data see least, {angle:.0f} deg from the line between its attachments) "
                    f"the attachment is {along:+.1f} +- {sd_along:.1f} mm from it: laxity tests fix the ligament's "
                    "line, not the point on it (the reference strain absorbs the length change)")
        unc = ", ".join(f"{errs[by_axis[a]]:.1f}" for a in sorted(SHIFT_AXES, key=lambda a: -abs(vals[by_axis[a]])))
        return f"the {lig} {side} attachment is about {_axis_words(shift)} (+- {unc} mm) of where the knee file puts it"
    units = {n: "" if model.parameter(n).unit == "1" else f" {model.parameter(n).unit}" for n in score.parameters}
    return "; ".join(f"{n} = {vals[n]:.4g} +- {errs[n]:.2g}{units[n]}" for n in score.parameters)


def verdict_words(d: Diagnosis) -> str:
    """The verdict in words a researcher acts on."""
    v = d.decision
    glob = f"chi-square {d.chi2:.1f} on {d.dof} degrees of freedom, p = {d.p_value:.2g}"
    pattern = ("; where: " + "; ".join(p.words() for p in d.patterns[:3])) if d.patterns else ""
    if v.outcome == "adequate":
        best = min(d.ranking, key=lambda s: v.adjusted[s.effect]) if d.ranking else None
        cand = f"; smallest candidate p {v.adjusted[best.effect]:.2g} ({best.effect})" if best else ""
        return (f"ADEQUATE: no test rejects at family level {v.alpha:g} (global {glob}{cand}). Effects smaller than "
                "their detection limits are not ruled out.")
    if v.outcome == "noise_larger":
        return (f"NOISE LARGER THAN DECLARED: the misfit ({glob}) is spread evenly over coordinates and load "
                f"directions (p = {v.homogeneity_p:.2g}) and no candidate effect is significant: the data imply "
                f"noise {v.implied_noise} (sd {v.implied_noise.std:.3g} mm or deg) instead of the declared "
                f"{d.noise}. Check the measurement error; the parameter uncertainties scale with it.")
    best = d.named
    if v.unconfirmed:
        listed = ", ".join(v.unconfirmed[:3]) + (" and more" if len(v.unconfirmed) > 3 else "")
        return (f"NOT ADEQUATE, NOT EXPLAINED: the misfit ({glob}) is real{pattern}. The score tests single out "
                f"{listed}, but no refit with them converged to a better fit, so none is shown to explain any of "
                "it (a one-step estimate is no evidence this far from the data). Look for an effect outside the "
                "library, or several together.")
    if best is None:
        how = (f"has a sign per load direction (mean residuals differ between load directions, p = {v.bias_p:.2g}): "
               "the model's error, not the instrument's noise" if v.bias_p is not None and v.bias_p < v.alpha
               else f"is uneven (p = {v.homogeneity_p:.2g})")
        return (f"MODEL INADEQUATE, NOT EXPLAINED: the misfit ({glob}) {how}, and no candidate effect is "
                f"significant{pattern}. Look for an effect outside the library.")
    others = [n for n in v.significant if n != best.effect]
    listed = ", ".join(others[:3]) + (" and more" if len(others) > 3 else "")
    also = (f" Also significant: {listed} (they partly mimic it with this protocol; the refit prefers "
            f"{best.effect}).") if others else ""
    if not best.refit:
        return (f"MISSING EFFECT?: {best.effect} is significant (Holm-adjusted p = {v.adjusted[best.effect]:.2g}, "
                f"score chi-square drop {best.score_chi2:.1f}); refit to confirm (--refit).{also}")
    ref = best.refit
    explained = (f"explains {100 * ref['excess_explained']:.0f} % of the excess misfit (chi-square drop "
                 f"{ref['chi2_drop']:.1f})" if ref["excess_explained"] is not None and d.p_value < v.alpha
                 else f"lowers the chi-square by {ref['chi2_drop']:.1f} (LR p = {ref['lr_p_value']:.2g})")
    after = (f"RMS after it {ref['rms']:.3f} against {d.expected_rms:.3f} from the noise alone "
             f"(p = {ref['p_value_after']:.2g})")
    if not v.recommended and not v.rivals and (ref["excess_explained"] is None
                                               or ref["excess_explained"] < ADVISE_SHARE):
        # a small, seed-dependent share is no ground for adding it
        return (f"NOT ADEQUATE, NOT EXPLAINED: the best candidate, {best.effect} (Holm-adjusted p = "
                f"{v.adjusted[best.effect]:.2g}), {explained} and leaves {after}{pattern}. That is not the missing "
                "effect, at most a small part of it: do not add it on this evidence. Look for an effect outside the "
                f"library, or several together.{also}")
    est = estimate_words(d.fit, best, d.refits.get(best.effect))
    if v.recommended:
        return (f"MISSING EFFECT: {best.effect} (Holm-adjusted p = {v.adjusted[best.effect]:.2g}) {explained}; "
                f"{after}. Estimate: {est}. Add {best.effect}.{also}")
    if v.rivals:
        return (f"MISSING EFFECT, AMBIGUOUS: {best.effect} (Holm-adjusted p = {v.adjusted[best.effect]:.2g}) "
                f"{explained}; {after}. Estimate: {est}. But {', '.join(v.rivals)} explain the data as well "
                f"(BIC within {AMBIGUOUS_BIC:g}, or not worse in Vuong's non-nested test at one-sided 0.05): this "
                "protocol cannot tell them apart, so none is recommended. "
                "Add trials that separate them (kneenlp design) or knowledge of which is plausible.")
    return (f"NOT ADEQUATE, PARTLY EXPLAINED: {best.effect} (Holm-adjusted p = {v.adjusted[best.effect]:.2g}) "
            f"{explained} but leaves {after}{pattern}. Add it and look for a further effect (outside the library "
            f"or several together).{also}")
