"""The outlier test of a calibration (kneenlp.estimation.outliers) against linear least squares,
where the residuals' distribution is known exactly."""

import numpy as np
import pytest
from scipy import stats

from kneenlp.estimation.outliers import (
    OUTLIER_ALPHA,
    SCREEN_ALPHA,
    HeldOutTrial,
    deletion_test,
    prediction_variance,
    residual_factors,
    screen,
)

LEVELS = np.array([1.0, 2.0, 0.5, 1.5, 3.0])  # noise per coordinate (mm or deg)


def _noise(rng, trials, planted=0.0):
    """Gaussian noise (T x 5) with :data:`LEVELS`, trial 0 shifted by ``planted`` levels in every coordinate."""
    y = rng.normal(size=(trials, 5)) * LEVELS
    y[0] += planted * LEVELS
    return y


def _residuals(J, y):
    return (y.ravel() - J @ np.linalg.lstsq(J, y.ravel(), rcond=None)[0]).reshape(y.shape) if J.shape[1] else y


def _variance(r, n_free):
    return np.broadcast_to(np.sum(r**2, axis=0) / (len(r) - n_free / 5), r.shape)


def _set_aside(J, y):
    """The calibration's procedure (calibrate.without_outliers) on a linear model: the trial set
    aside, or None."""
    n_free = J.shape[1]
    r = _residuals(J, y)
    chi2, p = screen(r, n_free, factors=residual_factors(J, np.ones(r.shape), _variance(r, n_free)))
    worst = int(np.argmax(chi2))
    if not p[worst] < SCREEN_ALPHA:
        return None
    rows = np.repeat(np.arange(len(y)) != worst, 5)
    beta = np.linalg.lstsq(J[rows], y.ravel()[rows], rcond=None)[0]
    kept = (y.ravel()[rows] - J[rows] @ beta).reshape(-1, 5)
    var = _variance(kept, n_free)
    error = y[worst] - J[~rows] @ beta
    held = HeldOutTrial(f"t{worst}", error, var[0], prediction_variance(J[~rows], J[rows], np.ones(kept.shape), var))
    return deletion_test(held, len(kept) - n_free / 5, len(y))


def test_statistic_by_hand():
    """chi2 of a trial is its squared residuals over each coordinate's variance without it."""
    r = np.array([[1.0, 0, 0, 0, 0], [0.5, 1, 1, 1, 1], [-1, 1, -1, 1, -1], [4, 0.5, 0.5, 0.5, 0.5]])
    chi2, p = screen(r, n_free=0)
    dof = 3
    s2 = (np.sum(r**2, axis=0) - r[3] ** 2) / dof
    assert chi2[3] == pytest.approx(np.sum(r[3] ** 2 / s2))
    assert p[3] == pytest.approx(min(1.0, 4 * stats.f.sf(chi2[3] / 5, 5, dof)))
    declared, p_declared = screen(r, 0, variance=0.25)
    assert declared == pytest.approx(np.sum(r**2, axis=1) / 0.25)
    assert p_declared == pytest.approx(np.minimum(1, 4 * stats.chi2.sf(declared, 5)))


def test_residual_factors_are_one_minus_leverage_for_one_coordinate():
    """With one noise level and unit weights the factors are 1 - h (the hat matrix's diagonal)."""
    rng = np.random.default_rng(1)
    J = rng.normal(size=(20, 3))
    h = np.diag(J @ np.linalg.solve(J.T @ J, J.T))
    f = residual_factors(J, np.ones((4, 5)), np.ones((4, 5)))
    assert f.ravel() == pytest.approx(1 - h)


def test_residual_factors_give_the_simulated_variance():
    """Weighted fit, a different noise per coordinate: the factors times the noise variance are the
    residuals' variance over 4000 simulated experiments (within 6 %)."""
    rng = np.random.default_rng(2)
    T, p = 8, 6
    J = rng.normal(size=(T * 5, p))
    w = np.tile(1 / LEVELS, (T, 1))
    sw = np.sqrt(w).ravel()
    var = np.tile(LEVELS**2, (T, 1))
    draws = []
    for _ in range(4000):
        y = rng.normal(size=T * 5) * np.sqrt(var).ravel()
        beta = np.linalg.lstsq(sw[:, None] * J, sw * y, rcond=None)[0]
        draws.append(y - J @ beta)
    simulated = np.var(np.array(draws), axis=0).reshape(T, 5)
    assert simulated / (residual_factors(J, w, var) * var) == pytest.approx(1, abs=0.06)


def test_prediction_variance_is_the_simulated_one():
    """The variance of a left-out trial's prediction by a weighted fit, over 4000 simulations."""
    rng = np.random.default_rng(5)
    T, p = 8, 6
    J, Jt = rng.normal(size=(T * 5, p)), rng.normal(size=(5, p))
    w = np.tile(1 / LEVELS, (T, 1))
    sw = np.sqrt(w).ravel()
    var = np.tile(LEVELS**2, (T, 1))
    draws = [Jt @ np.linalg.lstsq(sw[:, None] * J, sw * rng.normal(size=T * 5) * np.sqrt(var).ravel(),
                                  rcond=None)[0] for _ in range(4000)]
    assert np.var(np.array(draws), axis=0) / prediction_variance(Jt, J, w, var) == pytest.approx(1, abs=0.06)


@pytest.mark.parametrize("trials, n_free", [(25, 0), (25, 24), (12, 12)])
def test_false_alarms_at_most_alpha(trials, n_free):
    """Pure noise: a trial is set aside in at most OUTLIER_ALPHA of 1000 experiments (plus 3 sd)."""
    rng = np.random.default_rng(3)
    flagged = sum(_set_aside(rng.normal(size=(trials * 5, n_free)), _noise(rng, trials)) is not None
                  for _ in range(1000))
    assert flagged / 1000 <= OUTLIER_ALPHA + 3 * np.sqrt(OUTLIER_ALPHA * (1 - OUTLIER_ALPHA) / 1000)


def test_a_planted_outlier_is_found():
    """A trial 5 noise levels off in every coordinate is the one set aside in at least 95 % of
    25-trial experiments with 24 free parameters; the record names it with its prediction error."""
    rng = np.random.default_rng(4)
    found = [_set_aside(rng.normal(size=(125, 24)), _noise(rng, 25, planted=5.0)) for _ in range(200)]
    hits = [o for o in found if o is not None and o.trial == "t0"]
    assert len(hits) >= 190 and len([o for o in found if o is not None]) == len(hits)
    line = hits[0].line()
    assert line.startswith("t0: chi2") and "after Bonferroni" in line and "varus_rotation" in line
    assert hits[0].record()["residual"] == hits[0].residual
