"""The adequacy verdict: the global test and the targeted tests of every candidate, together.

Tests (one family): the global chi-square test of the base fit against the declared noise, and
one test per candidate effect (its refit's F test if refitted, else its score test's; see
:mod:`kneenlp.adequacy.candidates`).  Holm's step-down procedure over the family keeps the
chance of any false rejection on clean data at most ``alpha`` (default 0.01) whatever the
dependence between the tests; the false-alarm rate actually reached is measured by
``benchmarks/bench_adequacy.py`` (docs/adequacy.md).

Outcomes (:data:`OUTCOMES`):

* ``adequate``: no test rejects; the detection limits say what that rules out;
* ``missing_effect``: a candidate is significant and its refit brings the misfit to the noise
  (chi-square p after it >= alpha): it is recommended, unless another significant candidate's
  refit is as good (BIC within :data:`AMBIGUOUS_BIC`, or not worse in Vuong's non-nested test,
  :func:`closeness_z` below :data:`RIVAL_Z`): then both are named and neither is recommended (the
  protocol cannot tell them apart; nested candidates are compared by their likelihood ratio);
* ``noise_larger``: only the global test rejects, no candidate is significant, the excess is
  spread evenly over coordinates and load directions (Brown-Forsythe tests of equal spread, p >=
  alpha) and the misfit has no sign per load direction (one-way tests of equal mean residual per
  coordinate across load directions, :func:`bias_structure`, p >= alpha): the signature of noise
  larger than declared, reported with the level the data imply.  A declared noise is the user's
  knowledge of the instrument: a misfit of one sign in every trial of a load direction (S192803:
  lateral +2.8 mm in all external-rotation trials) is the model's, never the noise's;
* ``unexplained``: the misfit is real but no candidate removes it (patterns in words say where).
  That includes significant score tests whose refits all failed to lower the misfit (named as
  ``unconfirmed``): the one-step linearisation is no evidence that the effect explains anything.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from kneenlp.experiment.noise import NoiseModel
from kneenlp.experiment.protocol import Trial

#: Family-wise level of the verdict's tests.
ALPHA = 0.01
#: Two significant candidates whose refits differ by less than this in BIC explain the data
#: equally well (Kass & Raftery: "not worth more than a bare mention"): neither is recommended.
AMBIGUOUS_BIC = 2.0
#: The best refit must also beat every other significant refit in Vuong's non-nested test (BIC
#: corrected) at one-sided level 0.05, z > 1.645: with many similar candidates (eight 3-parameter
#: attachment shifts) a BIC lead of a few units is often the noise's choice (docs/adequacy.md).
RIVAL_Z = 1.645
#: Level of the likelihood-ratio test between nested candidates (:func:`nested_p`); Vuong's
#: non-nested statistic does not apply to them (its variance vanishes under the null).
NESTED_ALPHA = 0.05
OUTCOMES = ("adequate", "missing_effect", "noise_larger", "unexplained")


def holm(p_values: Sequence[float]) -> np.ndarray:
    """Holm's step-down adjusted p-values (same order as ``p_values``)."""
    p = np.asarray(p_values, float)
    m = len(p)
    order = np.argsort(p)
    adjusted = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adjusted[i] = running
    return adjusted


def closeness_z(best: np.ndarray, other: np.ndarray, k_best: int, k_other: int) -> float:
    """Vuong's z statistic (Schwarz-corrected) that the model with weighted residuals ``best``
    (``k_best`` parameters) fits better than the non-nested ``other``: the log-likelihood ratio
    ``n/2 ln(RSS_other / RSS_best) - (k_best - k_other) ln(n) / 2`` (half the BIC difference) over
    ``sqrt(n)`` times the spread of the per-observation contributions ``(o_i^2 - b_i^2) / (2 s^2)``
    (``s^2 = RSS_best / n``).  The uncentred spread is used, so that refits with near-identical
    residuals give z near 0 (indistinguishable), never a spurious large z."""
    b, o = np.ravel(best), np.ravel(other)
    n = b.size
    s2 = max(float(b @ b) / n, 1e-300)
    li = (o**2 - b**2) / (2 * s2)
    lr = 0.5 * n * np.log(max(float(o @ o), 1e-300) / max(float(b @ b), 1e-300)) - 0.5 * (k_best - k_other) * np.log(n)
    omega = float(np.sqrt(np.mean(li**2)))
    return float(lr / (np.sqrt(n) * omega)) if omega > 0 else 0.0


def spread_homogeneity(trials: Sequence[Trial], residuals: np.ndarray) -> float:
    """p-value that the residuals (T x 5, mm and deg) spread equally over the five coordinates and
    over the load directions (Brown-Forsythe, Bonferroni over the two groupings)."""
    r = np.asarray(residuals, float)
    p_coord = stats.levene(*r.T, center="median").pvalue
    directions = sorted({t.dominant for t in trials})
    groups = [r[[i for i, t in enumerate(trials) if t.dominant == d]].ravel() for d in directions]
    groups = [g for g in groups if g.size >= 5]
    p_dir = stats.levene(*groups, center="median").pvalue if len(groups) >= 2 else 1.0
    return float(min(1.0, 2 * min(p_coord, p_dir)))


def bias_structure(trials: Sequence[Trial], residuals: np.ndarray) -> float:
    """p-value that the mean residual of each coordinate is the same in every load direction (one-way
    ANOVA F test per coordinate over the directions with at least two trials; Bonferroni over the
    five coordinates): a small p says the misfit has a sign per load direction, a model's error."""
    r = np.asarray(residuals, float)
    directions = sorted({t.dominant for t in trials})
    rows = [[i for i, t in enumerate(trials) if t.dominant == d] for d in directions]
    rows = [g for g in rows if len(g) >= 2]
    if len(rows) < 2:
        return 1.0
    p = [stats.f_oneway(*[r[g, j] for g in rows]).pvalue for j in range(r.shape[1])]
    p = [v for v in p if np.isfinite(v)]
    return float(min(1.0, len(p) * min(p))) if p else 1.0


def implied_noise(declared: NoiseModel, rss: float, dof: int) -> NoiseModel:
    """The noise model of the declared kind whose variance is the residuals' ``rss / dof``."""
    sd = float(np.sqrt(rss / max(dof, 1)))
    if declared.kind == "uniform":
        return NoiseModel("uniform", sd * np.sqrt(3.0))
    return NoiseModel("gaussian", sd)


@dataclass
class Verdict:
    """The outcome of the family of tests, with the numbers behind it."""

    outcome: str
    alpha: float
    adjusted: dict[str, float]  # Holm-adjusted p of every test ("global" and each candidate)
    significant: list[str]  # candidates significant after Holm, best first
    best: str | None = None  # the candidate named (significant, best refit)
    recommended: str | None = None
    implied_noise: NoiseModel | None = None
    homogeneity_p: float | None = None
    #: p that the mean residuals are equal across load directions (:func:`bias_structure`)
    bias_p: float | None = None
    rivals: list[str] = field(default_factory=list)  # candidates as good as ``best`` (:func:`_rival`)
    #: significant by their score tests, but their refits found nothing that lowers the misfit
    unconfirmed: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {"outcome": self.outcome, "alpha": self.alpha, "adjusted_p_values": self.adjusted,
                "significant": self.significant, "named": self.best, "recommended": self.recommended,
                "rivals": self.rivals, "unconfirmed": self.unconfirmed,
                "implied_noise": str(self.implied_noise) if self.implied_noise else None,
                "implied_noise_std": self.implied_noise.std if self.implied_noise else None,
                "homogeneity_p": self.homogeneity_p, "bias_p": self.bias_p}


@dataclass(frozen=True)
class BaseMisfit:
    """The base fit's misfit a verdict reads when no candidate explains it: its ``trials``, its
    ``residuals`` (T x 5, mm and deg), the ``declared`` noise and the fit's ``dof``."""

    trials: Sequence[Trial]
    residuals: np.ndarray
    declared: NoiseModel
    dof: int


def decide(global_p: float, candidates: list, base: BaseMisfit, alpha: float = ALPHA,
           refit_residuals: dict[str, np.ndarray] | None = None) -> Verdict:
    """The outcome of the global test (``global_p``) and the candidates' tests (``candidates``:
    :class:`~kneenlp.adequacy.candidates.EffectScore`, ranked best first) at family level
    ``alpha``; ``base`` the base fit's misfit; ``refit_residuals`` the weighted residuals of each
    refitted candidate (for the non-nested comparison of the best with its rivals, :func:`closeness_z`)."""
    names = ["global", *[c.effect for c in candidates]]
    adj = holm([global_p, *[c.p_value for c in candidates]])
    adjusted = dict(zip(names, (float(a) for a in adj), strict=True))
    sig = [c for c, a in zip(candidates, adj[1:], strict=True) if a < alpha]
    global_sig = adj[0] < alpha
    if not sig and not global_sig:
        return Verdict("adequate", alpha, adjusted, [])
    if sig:
        refitted = [c for c in sig if c.refit and c.refit["success"]]
        if not refitted and sig[0].refit is not None:  # refits tried, none converged: no evidence
            return Verdict("unexplained", alpha, adjusted, [c.effect for c in sig],
                           unconfirmed=[c.effect for c in sig if c.refit is not None])
        # BIC, not the raw drop: a candidate with more parameters always drops the misfit more, and
        # AIC's penalty (2 per parameter) let 3-parameter attachment shifts mimic 1-parameter effects
        best = min(refitted, key=lambda c: c.refit["delta_bic"]) if refitted else sig[0]
        v = Verdict("missing_effect", alpha, adjusted, [c.effect for c in sig], best.effect)
        rivals = [c.effect for c in refitted if c is not best and _rival(best, c, refit_residuals or {})]
        if best.refit and best.refit["success"] and best.refit["p_value_after"] >= alpha:
            if rivals:  # the data cannot tell them apart: naming one would be a guess
                v.rivals = rivals
            else:
                v.recommended = best.effect
        elif best.refit and best.refit["success"]:
            v.outcome = "unexplained"
        return v
    rss = float(np.sum(np.asarray(base.residuals, float) ** 2))
    homog = spread_homogeneity(base.trials, base.residuals)
    bias = bias_structure(base.trials, base.residuals)
    outcome = "noise_larger" if homog >= alpha and bias >= alpha else "unexplained"
    return Verdict(outcome, alpha, adjusted, [], implied_noise=implied_noise(base.declared, rss, base.dof),
                   homogeneity_p=homog, bias_p=bias)


def nested_p(bigger, smaller) -> float:
    """p-value of the likelihood-ratio test that ``bigger``'s refit explains more than the
    ``smaller`` candidate nested in it (its parameters a subset): the difference of their
    chi-square drops (declared noise) against chi-square on the difference of their df."""
    extra = bigger.df - smaller.df
    gain = bigger.refit["chi2_drop"] - smaller.refit["chi2_drop"]
    return float(stats.chi2.sf(max(gain, 0.0), extra)) if extra > 0 else 1.0


def _rival(best, other, refit_residuals: dict[str, np.ndarray]) -> bool:
    """Whether ``other``'s refit explains the data as well as ``best``'s.  Nested candidates
    (one's parameters a subset of the other's, e.g. ``registration_anterior_translation`` in
    ``registration``) are compared by their likelihood ratio (:func:`nested_p`, level
    :data:`NESTED_ALPHA`): the smaller one rivals a bigger best unless the extra parameters are
    needed, a bigger one rivals a smaller best if it is needed.  Other pairs: BIC within
    :data:`AMBIGUOUS_BIC`, or Vuong's non-nested z below :data:`RIVAL_Z`."""
    pb, po = set(best.parameters), set(other.parameters)
    if po < pb:
        return nested_p(best, other) >= NESTED_ALPHA
    if pb < po:
        return nested_p(other, best) < NESTED_ALPHA
    if other.refit["delta_bic"] - best.refit["delta_bic"] < AMBIGUOUS_BIC:
        return True
    rb, ro = refit_residuals.get(best.effect), refit_residuals.get(other.effect)
    if rb is None or ro is None:
        return False
    return closeness_z(rb, ro, best.df, other.df) < RIVAL_Z
