"""Targeted tests of candidate effects: the score test from the base fit and the refit.

For an effect with parameters ``phi`` (neutral in the base model) and the base fit's residuals
``r`` (mm, deg; N observations, p free base parameters):

* **score test** (Lagrange multiplier, no refit): ``S = d y / d phi`` through every trial's
  equilibrium, ``M`` the projection removing what the base parameters absorb; the one-step
  chi-square drop ``D = (S'Mr)'(S'MS)^-1(S'Mr)`` (mm^2 + deg^2) is what adding the effect
  would remove from the residual sum to first order, ``-(S'MS)^-1 S'Mr`` its one-step estimate;
* **refit**: the base fit with ``phi`` free too; its drop ``D = RSS0 - RSS1`` is exact.

Each drop is judged by the extra-sum-of-squares F test, ``F = (D / df) / ((RSS0 - D) / (N - p - df))``
on ``(df, N - p - df)`` degrees of freedom: the residual variance is estimated, not the declared
one, so a noise level declared too small makes the global chi-square test fail but not the
candidates (that is how "noise larger than declared" is told from a missing effect).  With the
declared noise ``sigma`` the same drop is ``D / sigma^2`` in chi-square units (the score and the
likelihood-ratio statistic).

A stiffness-type parameter whose one-step estimate is negative cannot help (its neutral value is
its lower bound): its score drop is zero.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import stats

from kneenlp.estimation.fit import Fit
from kneenlp.estimation.statistics import information_criteria

#: IPOPT iterations allowed to finish a refit whose reduced-space solve failed.
POLISH_ITERATIONS = 40
#: IPOPT iterations of a refit from the base fit (effect neutral) when the reduced solve failed.
WARM_ITERATIONS = 200
#: Relative cost change at which a refit's reduced-space Gauss-Newton stops (see :func:`refit_with`).
REFIT_TOL = 1e-3


@dataclass
class EffectScore:
    """One candidate's targeted tests (drops in mm^2 + deg^2; one-step and refitted values SI)."""

    effect: str
    description: str
    parameters: list[str]
    df: int
    score_drop: float  # one-step drop of the residual sum, mm^2 + deg^2
    score_chi2: float  # score_drop / sigma^2 (declared noise)
    score_p: float  # F test of the score drop
    expected_rms: float  # RMS after adding it, one step (mm, deg)
    one_step: dict[str, float]
    refit: dict | None = None
    detection_limit: dict[str, float] | None = None  # display units, per parameter
    unit: str = ""  # display unit of the (first) parameter
    units: list[str] | None = None  # display unit of every parameter

    @property
    def p_value(self) -> float:
        """The candidate's test: the refit's F test if refitted, else the score's."""
        return self.refit["f_p_value"] if self.refit and self.refit["success"] else self.score_p

    @property
    def chi2_drop(self) -> float:
        """Chi-square drop (declared noise units) of the refit if refitted, else of the score."""
        return self.refit["chi2_drop"] if self.refit and self.refit["success"] else self.score_chi2

    def to_dict(self) -> dict:
        d = {"effect": self.effect, "description": self.description, "df": self.df, "p_value": self.p_value,
             "chi2_drop": self.chi2_drop, "score_chi2_drop": self.score_chi2, "score_p_value": self.score_p,
             "expected_rms": self.expected_rms, "one_step": self.one_step,
             # earlier name of the score statistic, kept for readers of older JSON
             "statistic": self.score_chi2}
        if self.refit:
            d["refit"] = self.refit
        if self.detection_limit:
            d["detection_limit"] = self.detection_limit
        return d


def f_test(drop: float, rss: float, n_obs: int, k0: int, df: int) -> float:
    """p-value of the extra-sum-of-squares F test of a residual-sum drop ``drop`` from ``rss``
    with ``df`` added parameters (``k0`` base parameters, ``n_obs`` observations)."""
    dof = max(n_obs - k0 - df, 1)
    if drop <= 0:
        return 1.0
    f = (drop / df) / max((rss - drop) / dof, 1e-300)
    return float(stats.f.sf(f, df, dof))


def base_projection(fit: Fit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(M, w, rw)``: the projection removing the base parameters' directions from weighted
    observations, the square-root weights and the weighted residuals of ``fit``."""
    r = fit.residuals.ravel()
    w = np.sqrt(fit.weights.ravel())
    s_base = fit.sensitivity * fit.scales * w[:, None]
    proj = np.eye(len(r)) - s_base @ np.linalg.pinv(s_base)
    return proj, w, w * r


def effect_sensitivity(fit: Fit, names: list[str]) -> np.ndarray:
    """Weighted sensitivities (5T x n, mm or deg per SI unit) of ``names`` at the base fit."""
    w = np.sqrt(fit.weights.ravel())
    return fit.sensitivities_of(names) * w[:, None]


def score_effects(fit: Fit, sigma: float, effects: list[str] | None = None) -> list[EffectScore]:
    """Score test of every candidate effect of ``fit``'s model (or of ``effects``), best first."""
    model = fit.model
    proj, _, rw = base_projection(fit)
    rss = float(rw @ rw)
    n_obs, k0 = len(rw), len(fit.free)
    out = []
    for e in model.effects:
        if effects is not None and e.name not in effects:
            continue
        names = [n for n in e.free_names() if n not in fit.free]
        if not names:
            continue
        scales = np.array([model.parameter(n).scale for n in names])
        s_e = effect_sensitivity(fit, names) * scales
        a = s_e.T @ proj @ s_e
        g = s_e.T @ proj @ rw
        step = -np.linalg.pinv(a) @ g
        drop = float(g @ np.linalg.pinv(a) @ g)
        if len(names) == 1 and model.parameter(names[0]).one_sided and step[0] < 0:
            drop, step = 0.0, np.zeros(1)
        out.append(EffectScore(
            e.name, e.description, names, len(names), drop, drop / sigma**2, f_test(drop, rss, n_obs, k0, len(names)),
            float(np.sqrt(max(rss - drop, 0.0) / n_obs)),
            {n: float(v * sc) for n, v, sc in zip(names, step, scales, strict=True)},
            unit=model.parameter(names[0]).unit, units=[model.parameter(n).unit for n in names]))
    out.sort(key=lambda s: (s.score_p, -s.score_chi2))
    return out


def refit_with(fit: Fit, score: EffectScore, sigma: float) -> tuple[dict, Fit]:
    """Refit with the effect's parameters free: reduced-space Gauss-Newton from the base estimate
    (effect neutral; :func:`~kneenlp.estimation.identify.reduced_fit`), finished by the
    simultaneous NLP if it fails; if that fails too or does worse than the base fit, the NLP from
    the base estimate itself, then from the effect's one-step estimate (clipped to its bounds).
    Returns the refit's numbers (drops in mm^2 + deg^2 and chi-square units, F and LR p-values,
    AIC and BIC changes, parameters SI with standard errors) and the refitted :class:`Fit`."""
    from kneenlp.estimation.identify import identify
    from kneenlp.estimation.solve import reduced_fit, solve_simultaneous
    from kneenlp.solvers.nlp import NlpSolver

    model = fit.model
    start = dict(fit.params)
    for n, v in score.one_step.items():
        par = model.parameter(n)
        base = par.neutral if par.neutral is not None else fit.theta[model.index(n)]
        start[n] = float(np.clip(base + v, *par.bounds))
    free = [*fit.free, *score.parameters]
    fixed, noise = fit.problem.fixed, fit.problem.noise
    # reduced-space Gauss-Newton from the base fit (effect neutral, every iterate at equilibrium):
    # robust and about as fast as IPOPT from a good start (IPOPT from the one-step estimate wandered
    # for 150 iterations on cartilage 4x softer); the simultaneous NLP takes over where it fails
    problem = replace(fit.problem, free=free)
    new = reduced_fit(problem, problem.values(fit.theta), q0=fit.q_pred, tol=REFIT_TOL)
    if not new.success:
        polished = solve_simultaneous(problem, dict(new.params),
                                      NlpSolver(options={"ipopt": {"max_iter": POLISH_ITERATIONS}}))
        if polished.success:
            new = polished
    if not new.success or new.objective > fit.objective:
        # IPOPT from the base fit itself (effect neutral): on the real S192803 knee the reduced solve,
        # its polish and the one-step start all failed (~4 min a candidate), while this
        # converged in 50-120 iterations (15-40 s)
        warm = solve_simultaneous(problem, problem.values(fit.theta),
                                  NlpSolver(options={"ipopt": {"max_iter": WARM_ITERATIONS}}))
        if warm.success and (not new.success or warm.objective < new.objective):
            new = warm
    if not new.success or new.objective > fit.objective:
        again = identify(model, fit.data, free=free, start=start, fixed=fixed, noise=noise, restarts=0,
                         solver_options={"ipopt": {"max_iter": WARM_ITERATIONS}}, strategy="scatter")
        if again.success and (not new.success or again.objective < new.objective):
            new = again
    n_obs = fit.residuals.size
    k0, k1 = len(fit.free), len(new.free)
    rss0, rss1 = float(np.sum(fit.residuals**2)), float(np.sum(new.residuals**2))
    wrss0, wrss1 = float(np.sum(fit.weights * fit.residuals**2)), float(np.sum(new.weights * new.residuals**2))
    if not new.success or rss1 > rss0:  # no improvement found: report the base fit's numbers
        rss1, wrss1 = rss0, wrss0
    (aic0, bic0), (aic1, bic1) = information_criteria(wrss0, n_obs, k0), information_criteria(wrss1, n_obs, k1)
    drop = rss0 - rss1
    chi2_0 = rss0 / sigma**2
    excess = chi2_0 - (n_obs - k0)
    return {"success": bool(new.success), "objective": new.objective, "drop": drop, "chi2_drop": drop / sigma**2,
            # share of the base fit's excess chi-square (over its degrees of freedom) the refit removes
            "excess_explained": drop / sigma**2 / excess if excess > 0 else None,
            "rms": float(np.sqrt(rss1 / n_obs)),
            "f_p_value": f_test(drop, rss0, n_obs, k0, k1 - k0),
            "lr_p_value": float(stats.chi2.sf(drop / sigma**2, k1 - k0)),
            "delta_aic": aic1 - aic0, "delta_bic": bic1 - bic0,
            "p_value_after": float(stats.chi2.sf(rss1 / sigma**2, max(n_obs - k1, 1))),
            "params": {n: new.params[n] for n in new.free}, "stderr": new.stderr}, new
