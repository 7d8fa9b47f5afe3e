"""Trials a fit cannot be asked to explain: the outlier test of a calibration.

A real experiment can hold a trial that no passive knee produces: S192803's ``valgus_flex60``
rotates the tibia 5.9 deg into *varus* under a 9.6 N m valgus moment, more varus than every trial
at its flexion without a varus moment (docs/real-experiment.md).  Least squares lets such a trial
pull every parameter towards it, and on a lax knee the fit can even follow it onto another
equilibrium branch, so its own residual understates how far off it is.  The test has two steps.

**Screen** (:func:`screen`), from the fit's residuals ``r`` (T x 5, mm and deg) alone:

* per coordinate ``c``, the noise variance without trial ``i``:
  ``s2[c] = (sum_j r[j, c]^2 - r[i, c]^2) / (T - 1 - p / 5)`` (``p`` free parameters shared by
  the five coordinates), or the declared noise's variance;
* each residual's own variance is ``s2[c]`` times its factor (:func:`residual_factors`, from the
  hat matrix): a fit pulls towards the trials it has few others to learn from;
* ``chi2[i] = sum_c r[i, c]^2 / (s2[c] f[i, c])``; ``chi2 / 5`` against the F distribution on 5
  and ``T - 1 - p / 5`` degrees of freedom (a declared noise: ``chi2`` against chi-square on 5),
  the p-value times ``T`` (Bonferroni).
The trial with the largest statistic is the candidate if its adjusted p-value is below
:data:`SCREEN_ALPHA`.

**Deletion test** (:func:`deletion_test`): the fit is repeated without the candidate and the
candidate predicted from it.  Its prediction error ``e`` (5) has the variance of the noise plus
that of the prediction (:func:`prediction_variance`: the refit's parameter covariance through the
candidate's sensitivities); ``sum_c e_c^2 / var_c`` is tested as above, p-value times ``T``.  The
candidate is an outlier if that is below :data:`OUTLIER_ALPHA`: the chance that a well-fitted
experiment loses any trial is at most that.  For a linear model this is the externally studentised
residual test; for the knee it also sees a trial the fit reached only on another branch.

Measured by simulation at ``alpha`` = 5 % (``tests/test_outliers.py``: linear fits, Gaussian
noise with a different level per coordinate): a trial set aside in 0.2-0.7 % of pure-noise
experiments with 25 trials and 24 free parameters (1.8 % with nothing fitted); a trial 4 noise
levels off in every coordinate found in 98.5 % of experiments, 5 levels off in all of 600.
The calibration repeats screen and test on the remaining trials, at most
:data:`MAX_OUTLIER_SHARE` of them (:func:`kneenlp.estimation.calibrate.without_outliers`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from kneenlp.base.conventions import coordinate_columns

#: Family-wise false-alarm rate of the outlier test (Bonferroni over the trials).
OUTLIER_ALPHA = 0.05
#: Adjusted p-value below which the screen's worst trial is refitted without and tested.
SCREEN_ALPHA = 0.5
#: Largest share of a calibration's trials the test may set aside.
MAX_OUTLIER_SHARE = 0.1


@dataclass
class Outlier:
    """A trial set aside: its deletion statistic (:func:`deletion_test`) on ``dof`` degrees of
    freedom, the Bonferroni-adjusted p-value, and its prediction error (measured minus predicted
    by the fit without it, mm and deg)."""

    trial: str
    chi2: float
    dof: int
    p_adjusted: float
    residual: dict[str, float]

    def line(self) -> str:
        res = ", ".join(f"{c.rsplit('_', 1)[0]} {v:+.2f} {c.rsplit('_', 1)[1]}" for c, v in self.residual.items())
        return (f"{self.trial}: chi2 {self.chi2:.1f} on {self.dof} dof, p {self.p_adjusted:.2g} after Bonferroni; "
                f"measured minus predicted without it {res}")

    def record(self) -> dict:
        return {"trial": self.trial, "chi2": self.chi2, "dof": self.dof, "p_adjusted": self.p_adjusted,
                "residual": self.residual}


def residual_factors(sensitivity: np.ndarray, weights: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """Each residual's variance over its observation's noise variance (T x 5, at most 1) in a
    (weighted) least-squares fit linearised at its optimum: ``r = W^-1/2 (I - H) W^1/2 e`` with
    ``H`` the hat matrix of ``W^1/2 J`` (``sensitivity`` J: (T * 5) x p; ``weights`` W and the
    noise ``variance`` per observation: T x 5).  Directions the data do not determine (singular
    values below 1e-8 of the largest) take no degree of freedom."""
    shape = np.shape(weights)
    sw = np.sqrt(np.asarray(weights, float)).ravel()
    var = np.asarray(variance, float).ravel()
    A = sw[:, None] * np.asarray(sensitivity, float)
    if A.size == 0:
        return np.ones(shape)
    U, sv, _ = np.linalg.svd(A, full_matrices=False)
    U = U[:, sv > 1e-8 * sv[0]] if sv.size and sv[0] > 0 else U[:, :0]
    M = np.eye(len(sw)) - U @ U.T
    M = M * (sw[None, :] / sw[:, None])
    return ((M**2) @ var / var).reshape(shape)


def _p_adjusted(chi2, k: int, dof: float | None, n_trials: int):
    """Bonferroni-adjusted p-value of ``chi2`` over ``k`` coordinates: against F(k, dof) on
    ``chi2 / k`` for an estimated variance, chi-square on ``k`` for a declared one (``dof`` None)."""
    p = stats.chi2.sf(chi2, k) if dof is None else stats.f.sf(np.asarray(chi2) / k, k, dof)
    return np.minimum(1.0, n_trials * p)


def screen(residuals: np.ndarray, n_free: int, variance: float | None = None,
           factors: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(chi2, p_adjusted)`` per trial of the residuals (T x 5, mm and deg) of a fit with
    ``n_free`` free parameters; ``variance`` (mm^2 or deg^2): the declared noise's, else each
    coordinate's estimated without the trial (module docstring); ``factors``
    (:func:`residual_factors`, default 1) scale each residual's variance by its leverage."""
    r2 = np.asarray(residuals, float) ** 2
    n, k = r2.shape
    f = np.ones(r2.shape) if factors is None else np.maximum(np.asarray(factors, float), 1e-12)
    if variance is None:
        dof = max(n - 1 - n_free / k, 1.0)
        s2 = (r2.sum(axis=0)[None, :] - r2) / dof
        chi2 = np.sum(r2 / np.maximum(s2 * f, 1e-300), axis=1)
        return chi2, _p_adjusted(chi2, k, dof, n)
    chi2 = np.sum(r2 / (float(variance) * f), axis=1)
    return chi2, _p_adjusted(chi2, k, None, n)


def prediction_variance(sensitivity_trial: np.ndarray, sensitivity: np.ndarray, weights: np.ndarray,
                        variance: np.ndarray) -> np.ndarray:
    """Variance (5, mm^2 or deg^2) of a trial's prediction by a (weighted) least-squares fit
    linearised at its optimum: ``diag(J_t C J_t^T)`` with ``C = A^+ diag(w var) A^+^T`` the
    parameters' covariance, ``A = W^1/2 J`` (``sensitivity`` J: (T * 5) x p of the fitted trials,
    ``weights`` and the noise ``variance``: T x 5; ``sensitivity_trial`` J_t: 5 x p).  Directions
    the data do not determine (singular values below 1e-8 of the largest) are left out."""
    sw = np.sqrt(np.asarray(weights, float)).ravel()
    A = sw[:, None] * np.asarray(sensitivity, float)
    if A.size == 0:
        return np.zeros(np.shape(sensitivity_trial)[0])
    pinv = np.linalg.pinv(A, rcond=1e-8)  # p x (T * 5)
    G = np.asarray(sensitivity_trial, float) @ pinv  # 5 x (T * 5)
    return (G**2) @ (sw**2 * np.asarray(variance, float).ravel())


@dataclass(frozen=True)
class HeldOutTrial:
    """A trial predicted by the fit without it: its ``trial`` id, the prediction ``error`` (5, measured
    minus predicted, mm and deg), and the ``noise_variance`` and ``prediction_variance`` (5, mm^2 or
    deg^2) that add up to the error's variance."""

    trial: str
    error: np.ndarray
    noise_variance: np.ndarray
    prediction_variance: np.ndarray


def deletion_test(held: HeldOutTrial, dof: float | None, n_trials: int,
                  alpha: float = OUTLIER_ALPHA) -> Outlier | None:
    """The ``held`` trial as an :class:`Outlier` if its prediction error is significant at ``alpha``
    after Bonferroni over ``n_trials``, else None; ``dof``: the noise estimate's degrees of freedom
    (None: a declared noise)."""
    error = np.asarray(held.error, float)
    chi2 = float(np.sum(error**2 / (np.asarray(held.noise_variance) + np.asarray(held.prediction_variance))))
    p = float(_p_adjusted(chi2, len(error), dof, n_trials))
    if not p < alpha:
        return None
    return Outlier(held.trial, chi2, len(error), p,
                   dict(zip(coordinate_columns(), map(float, error), strict=True)))
