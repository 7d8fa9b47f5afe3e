"""The statistics of a fit, each defined once (kneenlp.estimation.statistics): the information
criteria of weighted least squares and the weighted SVD."""

import numpy as np
import pytest

from kneenlp.estimation.identify import identify
from kneenlp.estimation.statistics import information_criteria, weighted_svd


def test_information_criteria_formula():
    aic, bic = information_criteria(12.5, 50, 4)
    assert aic == pytest.approx(50 * np.log(12.5 / 50) + 8)
    assert bic == pytest.approx(50 * np.log(12.5 / 50) + 4 * np.log(50))


def test_information_criteria_differences_do_not_depend_on_a_common_weight():
    """Weights known up to one factor: scaling them all shifts every model's criterion alike."""
    a0, b0 = information_criteria(7.0, 40, 3)
    a1, b1 = information_criteria(5.0, 40, 4)
    c = 1 / 0.5**2
    a0w, b0w = information_criteria(c * 7.0, 40, 3)
    a1w, b1w = information_criteria(c * 5.0, 40, 4)
    assert a1w - a0w == pytest.approx(a1 - a0, abs=1e-12)
    assert b1w - b0w == pytest.approx(b1 - b0, abs=1e-12)


@pytest.fixture(scope="module")
def fits(knee, tmp_path_factory):
    import kneenlp

    path = tmp_path_factory.mktemp("aic") / "set1.csv"
    kneenlp.simulate(knee, "set1").measured("uniform:0.5", seed=4).to_csv(path, index=False)
    plain = identify(knee, path, seed=4, noise="uniform:0.5")
    weighted = identify(knee, path, seed=4, noise="uniform:0.5", weighted=True)
    return plain, weighted


def test_fit_criteria_use_the_weighted_sum(fits):
    """A weighted fit's AIC and BIC are those of its own objective (the weighted sum it minimised),
    not of its unweighted residual sum."""
    plain, weighted = fits
    for fit in fits:
        wrss = float(np.sum(fit.weights * fit.residuals**2))
        assert (fit.aic, fit.bic) == pytest.approx(information_criteria(wrss, fit.residuals.size, len(fit.free)))
    # uniform weights 1/sigma^2: the same estimates, criteria shifted by N ln(1/sigma^2)
    n, w = plain.residuals.size, weighted.weights.flat[0]
    assert weighted.aic - plain.aic == pytest.approx(n * np.log(w), rel=1e-6)


def test_weighted_svd_is_that_of_the_weighted_scaled_matrix(fits):
    fit = fits[1]
    _, sv, _ = weighted_svd(fit.sensitivity, fit.weights, fit.scales)
    m = np.sqrt(fit.weights.ravel())[:, None] * fit.sensitivity * fit.scales
    assert np.allclose(sv, np.linalg.svd(m, compute_uv=False))
    assert fit.rank == len(fit.free)
