"""Model adequacy: where the model fails, which physical effect is missing, and what adding it does.

``diagnose(fit, noise)`` compares a fit with the noise model:

* goodness of fit: RMS residual vs the noise RMS, ``chi2 = sum r^2 / sigma^2`` on ``N - p`` degrees
  of freedom with its p-value (for uniform noise the statistic is less dispersed than chi-square,
  so the test is conservative), and every residual larger than the noise bound flagged;
* a residual map (trials x coordinates, in units of sigma) with the worst entries in words;
* a ranking of the candidate effects (:mod:`kneenlp.model.effects`) by the score (Lagrange-multiplier)
  test from the base fit's Gauss-Newton sensitivities, no refit needed:
  ``LM = (S' M r)' (S' M S)^-1 (S' M r) / sigma^2`` with ``S = d q / d phi`` of the effect's
  parameters (implicit-function theorem through every trial's equilibrium), ``M`` projecting out
  what the base parameters can absorb, ``r`` the residuals; chi-square with ``dim phi`` degrees of
  freedom.  The one-step estimate ``-(S' M S)^-1 S' M r`` gives the expected RMS after adding it;
* for the best candidates a refit with the effect's parameters free: objective drop, AIC, BIC and
  the likelihood-ratio p-value.  The score test is a linearisation at the neutral value; effects
  that are strongly nonlinear there (a slack bundle switched on) can be under-scored, so the final
  ranking puts the refitted candidates first, ordered by their AIC change.

A stiffness-type effect parameter whose one-step estimate is negative cannot help (its neutral
value is its lower bound) and scores zero.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from kneenlp.conventions import COORDINATE_UNITS, COORDINATES
from kneenlp.experiment.noise import NoiseModel
from kneenlp.inference.fit import Fit
from kneenlp.inference.statistics import chi_square_test
from kneenlp.io.atomic import write_text_atomic

ADEQUATE_P = 0.01


@dataclass
class EffectScore:
    effect: str
    description: str
    parameters: list[str]
    statistic: float
    df: int
    p_value: float
    expected_rms: float
    explained: float  # fraction of the excess misfit it explains (one step)
    one_step: dict[str, float]
    refit: dict | None = None

    def to_dict(self) -> dict:
        d = {"effect": self.effect, "statistic": self.statistic, "df": self.df, "p_value": self.p_value,
             "expected_rms": self.expected_rms, "explained_fraction": self.explained, "one_step": self.one_step,
             "description": self.description}
        if self.refit:
            d["refit"] = self.refit
        return d


@dataclass
class Diagnosis:
    fit: Fit
    noise: NoiseModel
    rms: float
    expected_rms: float
    chi2: float
    dof: int
    p_value: float
    flagged: list[dict]
    residual_map: pd.DataFrame
    worst: list[str]
    ranking: list[EffectScore] = field(default_factory=list)
    verdict: str = ""
    refits: dict[str, Fit] = field(default_factory=dict)  # effect name -> refitted Fit

    @property
    def adequate(self) -> bool:
        return self.p_value >= ADEQUATE_P

    @property
    def recommended(self) -> EffectScore | None:
        """The best candidate if the fit is inadequate and that candidate's refit is adequate."""
        if self.adequate or not self.ranking:
            return None
        best = self.ranking[0]
        if best.refit and best.refit["p_value_after"] >= ADEQUATE_P:
            return best
        return None

    def summary(self) -> dict:
        rec = self.recommended
        return {"adequate": self.adequate, "p_value": self.p_value, "chi2": self.chi2, "dof": self.dof,
                "rms": self.rms, "expected_rms": self.expected_rms, "noise": str(self.noise),
                "flagged": self.flagged, "worst": self.worst,
                "ranking": [s.to_dict() for s in self.ranking],
                "recommended": rec.effect if rec else None, "verdict": self.verdict}

    def to_json(self) -> str:
        from kneenlp.io.serialize import dumps

        return dumps(self.summary())

    def report(self) -> str:
        lines = [f"[[Adequacy]] {self.fit.data.source or 'data'} against noise {self.noise}",
                 f"    RMS residual {self.rms:.3f} (mm, deg); expected from the noise {self.expected_rms:.3f}",
                 f"    chi-square {self.chi2:.1f} on {self.dof} degrees of freedom, p = {self.p_value:.3g} -> "
                 + ("ADEQUATE" if self.adequate else "NOT ADEQUATE"),
                 f"    residuals beyond the noise bound: {len(self.flagged)}"]
        lines += ["[[Where it fails]]"] + [f"    {w}" for w in self.worst]
        if self.ranking:
            lines.append("[[Candidate effects]] score test (no refit); refit for the best")
            for s in self.ranking:
                ref = ""
                if s.refit:
                    ref = (f"; refit: RMS {s.refit['rms']:.3f}, LR p = {s.refit['lr_p_value']:.2g}, "
                           f"dAIC {s.refit['delta_aic']:+.1f}")
                lines.append(f"    {s.effect:18s} LM {s.statistic:9.1f} (df {s.df}) p = {s.p_value:.2g}, explains "
                             f"{100 * s.explained:5.1f} %, expected RMS {s.expected_rms:.3f}{ref}")
        lines.append(f"[[Verdict]] {self.verdict}")
        return "\n".join(lines)

    def write(self, out: str | Path) -> list[Path]:
        """Figures, ``residual_map.csv`` and ``diagnosis.json`` into ``out``; with a recommended
        effect also the refit's figures (``after_<effect>/``) and the parameters before and after
        it (``parameters_before_after_<effect>.csv``, display units)."""
        out = Path(out)
        files = self.figures(out)
        self.residual_map.to_csv(out / "residual_map.csv", float_format="%.6g")
        files += [out / "residual_map.csv", write_text_atomic(out / "diagnosis.json", self.to_json())]
        rec = self.recommended
        if rec is not None:
            after = self.refits[rec.effect]
            files += diagnose(after, self.noise, refit=0).figures(out / f"after_{rec.effect}")
            rows = []
            for n in after.free:
                par = after.model.parameter(n)
                rows.append({"parameter": n, "unit": par.unit,
                             "before": self.fit.params[n] * par.to_user if n in self.fit.params else None,
                             "after": after.params[n] * par.to_user, "after_stderr": after.stderr[n] * par.to_user})
            path = out / f"parameters_before_after_{rec.effect}.csv"
            pd.DataFrame(rows).to_csv(path, index=False, float_format="%.6g")
            files.append(path)
        return files

    def figures(self, out: str | Path) -> list[Path]:
        """Residual heat map and measured vs predicted laxity curves (mm, deg)."""
        from kneenlp.experiment.measured import measured_frame
        from kneenlp.io import plots

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


def _words(trial, coord: str, unit: str, r: float) -> str:
    where = "above" if r > 0 else "below"
    what = trial.describe().replace("no load", "unloaded")
    return f"{coord.replace('_', ' ')} {what}: model {abs(r):.2f} {unit} {where} the measurement"


def diagnose(fit: Fit, noise: str | NoiseModel = "uniform:0.5", *, effects: list[str] | None = None,
             refit: int = 4) -> Diagnosis:
    """Judge ``fit`` against ``noise``; rank candidate effects by the score test, refit the best
    ``refit`` of them and rank those by the refit (AIC)."""
    noise = NoiseModel.parse(noise)
    sigma = noise.std
    r = fit.residuals
    n_obs = r.size
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
    diag = Diagnosis(fit, noise, rms, expected, chi2, dof, p_value, flagged, rmap, worst)
    diag.ranking = rank_effects(fit, sigma, effects)
    if refit:
        for s in diag.ranking[:refit]:
            s.refit, diag.refits[s.effect] = refit_with(fit, s, sigma)
        # the score test is linear in the effect; the refit is not: refitted candidates are ranked
        # by their AIC change, ahead of those only scored
        done = sorted([s for s in diag.ranking if s.refit], key=lambda s: s.refit["delta_aic"])
        diag.ranking = done + [s for s in diag.ranking if not s.refit]
    diag.verdict = _verdict(diag)
    return diag


def rank_effects(fit: Fit, sigma: float, effects: list[str] | None = None) -> list[EffectScore]:
    """Score test of every candidate effect (see module docstring), best first."""
    model = fit.model
    r = fit.residuals.ravel()
    w = np.sqrt(fit.weights.ravel())
    s_base = fit.sensitivity * fit.scales * w[:, None]
    proj = np.eye(len(r)) - s_base @ np.linalg.pinv(s_base)
    rw = w * r
    rss = float(rw @ rw)
    excess = max(rss - sigma**2 * (len(r) - len(fit.free)), 1e-12)
    scores = []
    for e in model.effects:
        if effects is not None and e.name not in effects:
            continue
        names = [n for n in e.free_names() if n not in fit.free]
        if not names:
            continue
        scales = np.array([model.parameter(n).scale for n in names])
        s_e = fit.problem.sensitivities(fit.q_pred, fit.theta, names) * scales * w[:, None]
        a = s_e.T @ proj @ s_e
        g = s_e.T @ proj @ rw
        step = -np.linalg.pinv(a) @ g
        reduction = float(g @ np.linalg.pinv(a) @ g)
        one_sided = model.parameter(names[0]).one_sided
        if len(names) == 1 and one_sided and step[0] < 0:
            reduction, step = 0.0, np.zeros(1)
        stat = reduction / sigma**2
        scores.append(EffectScore(
            e.name, e.description, names, stat, len(names), float(stats.chi2.sf(stat, len(names))),
            float(np.sqrt(max(rss - reduction, 0.0) / len(r))), min(max(reduction / excess, 0.0), 1.0),
            {n: float(v * sc) for n, v, sc in zip(names, step, scales, strict=True)}))
    scores.sort(key=lambda s: (s.p_value, -s.statistic))
    return scores


def refit_with(fit: Fit, score: EffectScore, sigma: float) -> tuple[dict, Fit]:
    """Refit with the effect's parameters free, starting from the base estimate and the one-step
    estimate of the effect (clipped to its bounds)."""
    from kneenlp.inference.identify import identify

    model = fit.model
    start = dict(fit.params)
    for n, v in score.one_step.items():
        par = model.parameter(n)
        base = par.neutral if par.neutral is not None else fit.theta[model.index(n)]
        start[n] = float(np.clip(base + v, *par.bounds))
    free = [*fit.free, *score.parameters]
    fixed = fit.problem.fixed
    new = identify(model, fit.data, free=free, start=start, fixed=fixed)
    if not new.success or new.objective > fit.objective:  # retry from the base fit, effect neutral
        again = identify(model, fit.data, free=free, start=dict(fit.params), fixed=fixed)
        if again.success and (not new.success or again.objective < new.objective):
            new = again
    n_obs = fit.residuals.size
    k0, k1 = len(fit.free), len(new.free)
    rss0, rss1 = float(np.sum(fit.residuals**2)), float(np.sum(new.residuals**2))
    if not new.success or rss1 > rss0:  # no improvement found: report the base fit's numbers
        rss1 = rss0
    lr = max(rss0 - rss1, 0.0) / sigma**2
    dof1 = max(n_obs - k1, 1)
    excess = max(rss0 - sigma**2 * (n_obs - k0), 1e-12)
    return {"success": new.success, "objective": new.objective, "objective_drop": (rss0 - rss1),
            "explained_fraction": min(max((rss0 - rss1) / excess, 0.0), 1.0),
            "rms": float(np.sqrt(rss1 / n_obs)), "lr_statistic": lr, "lr_p_value": float(stats.chi2.sf(lr, k1 - k0)),
            "delta_aic": n_obs * np.log(rss1 / rss0) + 2 * (k1 - k0),
            "delta_bic": n_obs * np.log(rss1 / rss0) + (k1 - k0) * np.log(n_obs),
            "p_value_after": float(stats.chi2.sf(rss1 / sigma**2, dof1)),
            "params": {n: new.params[n] for n in new.free}, "stderr": new.stderr}, new


def _verdict(d: Diagnosis) -> str:
    if d.adequate:
        return (f"The model is adequate: residual RMS {d.rms:.3f} vs {d.expected_rms:.3f} expected from the "
                f"noise (p = {d.p_value:.2g}); no effect is recommended.")
    if not d.ranking:
        return f"The model is NOT adequate (p = {d.p_value:.2g}) and no candidate effect was tested."
    best = d.ranking[0]
    rec = d.recommended
    if rec is not None:
        ref = rec.refit
        return (f"The model is NOT adequate (p = {d.p_value:.2g}). {rec.effect.replace('_', ' ')} explains "
                f"{100 * ref['explained_fraction']:.0f} % of the misfit; expected RMS after adding it "
                f"{ref['rms']:.2f} (noise alone: {d.expected_rms:.2f}; p = {ref['p_value_after']:.2g}). "
                f"Add {rec.effect}.")
    after = best.refit["rms"] if best.refit else best.expected_rms
    return (f"The model is NOT adequate (p = {d.p_value:.2g}) and no candidate explains it well: the best, "
            f"{best.effect}, leaves RMS {after:.2f} against {d.expected_rms:.2f} expected from the noise. "
            "Look for an effect outside the library (e.g. wrong attachments or geometry).")
